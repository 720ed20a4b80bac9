"""The figures the docs quote come from a command that writes them.

Every marked table of README.md and docs/*.md and the README's sentences with figures are
rendered from ``docs/results/`` (``ssp.eval.docs_figures``, ``examples/docs_figures.sh``).

``examples/after_your_estimator.sh`` writes ``after-your-estimator.json`` (the BOP19 AR of its
worked example); a copy of it is ``docs/results/after-your-estimator.json``. These tests fail
when README.md or docs/after-your-estimator.md say other figures than that file: rerun the
script after a change that moves them, copy its file, and the tests say which sentence or row
to update.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from ssp.errors import SSPError
from ssp.eval.docs_figures import FIGURES, SOURCES, blocks, check, doc_files, load, write

ROOT = Path(__file__).resolve().parents[1]
RESULTS = json.loads((ROOT / "docs/results/after-your-estimator.json").read_text())


def _text(name: str) -> str:
    """The file's text with every run of whitespace one space (sentences wrap anywhere)."""
    return re.sub(r"\s+", " ", (ROOT / name).read_text(encoding="utf-8"))


def _cells(r: dict, bold: bool = False) -> str:
    ar = f"**{r['AR']:.3f}**" if bold else f"{r['AR']:.3f}"
    return f"{ar} | {r['AR_VSD']:.3f} | {r['AR_MSSD']:.3f} | {r['AR_MSPD']:.3f} |"


def test_the_readme_quotes_the_worked_example():
    s, i, p = RESULTS["structure"], RESULTS["isolated"], RESULTS["published"]
    text = _text("README.md")
    assert (
        f"from {s['estimator']['AR']:.3f} to {s['ssp']['AR']:.3f} on block structures and from "
        f"{i['estimator']['AR']:.3f} to {i['ssp']['AR']:.3f} on tools"
    ) in text
    assert f"from {p['estimator']['AR']:.3f} to {p['no_masks']['AR']:.3f}" in text
    rs, ri = RESULTS["rgb_structure"], RESULTS["rgb_isolated"]
    assert (
        f"from {rs['estimator']['AR']:.3f} to {rs['ssp']['AR']:.3f} on block structures and from "
        f"{ri['estimator']['AR']:.3f} to {ri['ssp']['AR']:.3f} on tools"
    ) in text


def test_the_guide_quotes_the_worked_example():
    text = _text("docs/after-your-estimator.md")
    labels = {"structure": "structure (stacks)", "isolated": "isolated (tools)"}
    for exp, label in labels.items():
        r = RESULTS[exp]
        row = (
            f"| {label} | {r['targets']} | estimator | {_cells(r['estimator'])} "
            f"| | | **ssp refine** | {_cells(r['ssp'], bold=True)}"
        )
        assert row in text, row
    p = RESULTS["published"]
    for label, key in (
        ("estimator (the CSV)", "estimator"),
        ("none: the cloud above the table is clustered (the default for a published scene)",
         "no_masks"),
        ("`--masks silhouettes`: the hypotheses' rendered silhouettes", "silhouettes"),
        ("`--masks gt` (the ground-truth `mask_visib`: an upper bound)", "gt_masks"),
    ):  # fmt: skip
        row = f"| {label} | {_cells(p[key])}"
        assert row in text, row
    gt, ssp = p["gt_masks"]["AR"], RESULTS["structure"]["ssp"]["AR"]
    assert f"({gt:.3f} against {ssp:.3f})" in text


def test_the_guide_quotes_the_rgb_rows():
    text = _text("docs/after-your-estimator.md")
    labels = {"structure": "structure (stacks)", "isolated": "isolated (tools)"}
    for exp, label in labels.items():
        r = RESULTS[f"rgb_{exp}"]
        row = (
            f"| {label} | {r['targets']} | RGB estimator | {_cells(r['estimator'])} "
            f"| | | **ssp refine** | {_cells(r['ssp'], bold=True)} "
            f"| | | ssp refine, kept objects only | {_cells(r['ssp_kept_only'])}"
        )
        assert row in text, row
    p = RESULTS["rgb_published"]
    for label, key in (
        ("RGB estimator (the CSV)", "estimator"),
        ("none: the cloud above the table is clustered (the default)", "no_masks"),
        ("`--masks silhouettes`: the hypotheses' rendered silhouettes", "silhouettes"),
        ("`--masks detections.json`: a detector's masks", "detector_masks"),
    ):
        row = f"| {label} | {_cells(p[key])}"
        assert row in text, row
    s, i = RESULTS["rgb_structure"], RESULTS["rgb_isolated"]
    gain = (s["ssp"]["AR"] - s["ssp_kept_only"]["AR"], i["ssp"]["AR"] - i["ssp_kept_only"]["AR"])
    assert f"the rule is worth {gain[0]:.3f} and {gain[1]:.3f} AR here" in text


# ------------------------------------------------------------------ every other figure block
# ``ssp.eval.docs_figures`` renders the docs' marked tables (``<!-- figures: NAME -->``) and the
# README's sentences from ``docs/results/<run>/results.json``; ``examples/docs_figures.sh``
# reruns every bench command and copies their files there.


def test_every_figure_block_and_sentence_says_its_results():
    problems = check(ROOT)
    wrong = [str(p) for p in problems if p.kind != "incomplete"]
    assert not wrong, "\n".join(wrong)
    # the blocks are marked: every figure the module knows is in the docs
    marked = {n for f in doc_files(ROOT) for n, *_ in blocks(f.read_text(), f.name)}
    assert marked == set(FIGURES)


def test_the_script_runs_every_source():
    script = (ROOT / "examples/docs_figures.sh").read_text()
    for s in SOURCES.values():
        assert f"run {s.name} {s.file} $SSP {s.command.removeprefix('ssp ')}\n" in script, s.name
    assert "bench docs-figures --collect" in script


def _options(command: str) -> dict[str, str]:
    words = command.split()
    return {w[2:]: v for w, v in zip(words, words[1:], strict=False) if w.startswith("--")}


def test_each_results_file_is_of_its_command():
    for name, result in load(ROOT).items():
        recorded = result.get("command") or {}
        for key, value in _options(SOURCES[name].command).items():
            if key in recorded:
                got = recorded[key]
                got = ",".join(got) if isinstance(got, list) else str(got)
                assert got == value, (name, key, got, value)


def _copy_docs(tmp: Path, with_baselines: bool) -> Path:
    (tmp / "docs").mkdir()
    shutil.copy(ROOT / "README.md", tmp / "README.md")
    for f in (ROOT / "docs").glob("*.md"):
        shutil.copy(f, tmp / "docs" / f.name)
    shutil.copytree(ROOT / "docs/results", tmp / "docs/results")
    if with_baselines:  # the block complete: a stand-in for the baselines' run
        shutil.copytree(
            tmp / "docs/results/t1-structure-paper-ssp",
            tmp / "docs/results/t1-structure-paper-baselines",
        )
    return tmp


def test_a_changed_figure_is_named_and_write_restores_it(tmp_path):
    root = _copy_docs(tmp_path, with_baselines=True)
    assert "table1-paper-structure" in write(root)
    assert not [p for p in check(root) if p.kind == "differs"]
    bench = root / "docs/benchmarks.md"
    text = bench.read_text()
    bench.write_text(text.replace("| **0.992** |", "| **0.993** |", 1))
    differs = [p for p in check(root) if p.kind == "differs"]
    assert len(differs) == 1 and "table1-paper-structure" in str(differs[0])
    write(root)
    assert bench.read_text() == text


def test_a_wrong_row_of_an_incomplete_block_is_named(tmp_path):
    root = _copy_docs(tmp_path, with_baselines=False)
    bench = root / "docs/benchmarks.md"
    bench.write_text(bench.read_text().replace("| **8 / 36** |", "| **9 / 36** |", 1))
    differs = [str(p) for p in check(root) if p.kind == "differs"]
    assert len(differs) == 1 and "realistic-conditions-structure" in differs[0]
    readme = root / "README.md"
    readme.write_text(readme.read_text().replace("0.56 mm / 0.35 deg", "0.57 mm / 0.35 deg"))
    assert any("readme-paper" in str(p) for p in check(root) if p.kind == "differs")


def test_a_marker_left_open_is_an_error():
    with pytest.raises(SSPError, match="never closed"):
        blocks("<!-- figures: tower-realistic -->\n| a |\n", "x.md")
