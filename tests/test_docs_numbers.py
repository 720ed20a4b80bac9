"""The figures the docs quote come from a command that writes them.

``examples/after_your_estimator.sh`` writes ``after-your-estimator.json`` (the BOP19 AR of its
worked example); a copy of it is ``docs/results/after-your-estimator.json``. These tests fail
when README.md or docs/after-your-estimator.md say other figures than that file: rerun the
script after a change that moves them, copy its file, and the tests say which sentence or row
to update.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

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
        ("`--masks gt` (the ground-truth `mask_visib`: an upper bound)", "gt_masks"),
    ):  # fmt: skip
        row = f"| {label} | {_cells(p[key])}"
        assert row in text, row
    gt, ssp = p["gt_masks"]["AR"], RESULTS["structure"]["ssp"]["AR"]
    assert f"({gt:.3f} against {ssp:.3f})" in text
