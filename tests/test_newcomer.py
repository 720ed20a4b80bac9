"""What a newcomer trips on (issue 35): output in a log (not a terminal), and a simulated dataset
that RGB estimators and the BOP toolkit can run on."""

from __future__ import annotations

import json
import logging
import re
from collections import Counter

import numpy as np
import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from ssp.cli import app
from ssp.sim.bop import read_bop, simulate_to_disk

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset(lib, tmp_path_factory):
    """A small simulated dataset: one scene of 2 frames, 4 objects, stride 4."""
    root = tmp_path_factory.mktemp("newcomer")
    (scene,) = simulate_to_disk(
        "structure", 1, 4, out_dir=root, library=lib, stages=2, frames_per_stage=1,
        stride=4, n_objects=4,
    )  # fmt: skip
    return scene


# ------------------------------------------------------------------ output that is not a terminal
def test_run_in_a_log_has_a_line_per_frame_a_warning_summary_and_whole_lines(
    dataset, tmp_path, monkeypatch
):
    """CliRunner's output is not a terminal (as a log file): the transient bar showed nothing
    there; now one plain line per frame (name, objects, seconds). --masks gt warns in every
    frame: the warnings are summarised by kind. Lines are not wrapped at 80 columns."""
    monkeypatch.setenv("COLUMNS", "80")  # what a shell exports
    out = tmp_path / ("a-long-output-folder-name-" * 3) / "out"
    r = runner.invoke(app, ["run", str(dataset), "--masks", "gt", "--out", str(out)])
    assert r.exit_code == 0, r.output
    for k, name in enumerate(("000000", "000001"), start=1):
        assert re.search(rf"^frames {k}/2: {name}: \d+ objects \(\d+\.\d\d s\)$", r.output, re.M), (
            r.output
        )
    assert re.search(
        r"^\d+ warnings of \d+ kinds? \(all of them: summary.json\)$", r.output, re.M
    ), r.output
    assert re.search(
        r"^  2 x segments from the ground-truth masks \(--masks gt\): frames 000000, 000001$",
        r.output,
        re.M,
    ), r.output
    assert f"wrote {out / 'ssp_000000-test.csv'}\n" in r.output  # one line, > 80 characters


def test_a_wide_table_is_not_cut_when_not_a_terminal(monkeypatch):
    from rich.table import Table

    from ssp.cli.common import console

    monkeypatch.setenv("COLUMNS", "80")
    cells = [f"column-{i}-" + "x" * 12 for i in range(8)]  # 8 x 21 characters: > 80

    cmd = typer.Typer()

    @cmd.command()
    def show() -> None:
        table = Table(title="wide")
        for c in cells:
            table.add_column(c)
        table.add_row(*cells)
        console.print(table)

    r = runner.invoke(cmd, [])
    assert r.exit_code == 0, r.output
    rows = [line for line in r.output.splitlines() if "column-0-" in line]
    assert len(rows) == 2  # the header and the row, each on one line ...
    assert all(c in rows[0] and c in rows[1] for c in cells)  # ... with every cell whole
    assert max(len(line) for line in r.output.splitlines()) > 8 * 21


def test_demo_in_a_log_has_a_line_per_frame(monkeypatch, tmp_path):
    """``ssp demo`` printed nothing for a minute (a transient spinner): now a line per frame
    with ssp's objects and seconds."""
    import ssp.eval.sequence_demo as sd

    real = sd.run_sequence_demo

    def small(out, config=None, **kw):
        return real(out, config, stages=2, frames_per_stage=1, stride=4, record=False, **kw)

    monkeypatch.setattr(sd, "run_sequence_demo", small)
    r = runner.invoke(app, ["demo", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    for k in (1, 2):
        assert re.search(rf"frame {k}/2: ssp kept \d+ objects \(\d+\.\d\d s\)", r.output), r.output
    assert (tmp_path / "report.html").exists()


def test_plain_progress_of_a_long_input_prints_every_n_steps(capsys):
    from ssp.cli.common import PlainProgress

    with PlainProgress() as p:
        task = p.add_task("frames", total=1000)
        for i in range(1000):
            p.update(task, completed=i + 1, description=f"{i:06d}: 3 objects")
    lines = capsys.readouterr().err.splitlines()
    assert 10 <= len(lines) <= 101
    assert lines[-1].startswith("frames 1000/1000: 000999: 3 objects (")
    assert "s each, 10 steps)" in lines[0]


def test_repeated_log_warnings_are_capped_and_counted(capsys):
    from ssp.cli.common import log_digest

    log = logging.getLogger("ssp.test_newcomer")
    seen: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            seen.append(record.getMessage())

    handler = Keep()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with log_digest(examples=3):
            for i in range(40):
                log.warning("frame %d: cube_%d: would fall (stability term %.1f)", i, i, -i)
            log.warning("something else")
    finally:
        root.removeHandler(handler)
    assert len(seen) == 4 and seen[-1] == "something else"
    err = capsys.readouterr().err
    assert "37 more warnings like" in err and "(40 in all)" in err


# ------------------------------------------------------------------ ssp simulate for the toolkit
def _targets_from_gt(scene, scene_id: int) -> list[dict]:
    """The BOP19 targets of the ground truth (the toolkit's get_im_targets, visib >= 0.1)."""
    seq = read_bop(scene, _Classes())
    ids = {c: int(i) for i, c in json.loads((scene / "models.json").read_text())["obj_ids"].items()}
    out = []
    for f in seq.frames:
        n = Counter(ids[cls] for iid, (cls, _) in f.gt.items() if f.visib_fract[iid] >= 0.1)
        out += [
            {"scene_id": scene_id, "im_id": f.index, "obj_id": o, "inst_count": c}
            for o, c in sorted(n.items())
        ]
    return out


class _Classes(dict):
    """A library that knows every class (read_bop only checks the names)."""

    def __contains__(self, name) -> bool:
        return True


def test_simulate_writes_test_targets_matching_the_ground_truth(dataset):
    root = dataset.parent.parent
    targets = json.loads((root / "test_targets_bop19.json").read_text())
    assert targets and all(set(t) == {"scene_id", "im_id", "obj_id", "inst_count"} for t in targets)
    assert all(isinstance(v, int) for t in targets for v in t.values())
    assert targets == _targets_from_gt(dataset, 0)
    # and as the toolkit counts them from scene_gt.json and scene_gt_info.json
    gt = json.loads((dataset / "scene_gt.json").read_text())
    info = json.loads((dataset / "scene_gt_info.json").read_text())
    for im, objs in gt.items():
        counts = Counter(
            g["obj_id"] for g, i in zip(objs, info[im], strict=True) if i["visib_fract"] >= 0.1
        )
        mine = {t["obj_id"]: t["inst_count"] for t in targets if t["im_id"] == int(im)}
        assert mine == dict(counts)
    from ssp.eval.bop_metrics import MIN_VISIB
    from ssp.sim.bop import TARGET_MIN_VISIB

    assert TARGET_MIN_VISIB == MIN_VISIB  # the threshold of ssp evaluate


def test_simulate_writes_models_eval(dataset):
    root = dataset.parent.parent
    ev, models = root / "models_eval", root / "models"
    assert sorted(p.name for p in ev.iterdir()) == sorted(p.name for p in models.iterdir())
    for p in models.iterdir():
        assert (ev / p.name).read_bytes() == p.read_bytes()
    info = json.loads((ev / "models_info.json").read_text())
    obj_ids = json.loads((root / "models.json").read_text())["obj_ids"]
    assert set(info) == set(obj_ids)
    cube = next(i for i, c in obj_ids.items() if c == "cube")
    assert info[cube]["size_x"] == pytest.approx(50.8, abs=0.01)  # mm, as the toolkit reads


def test_simulate_writes_a_shaded_rgb_image_per_frame(dataset):
    depths = sorted(p.name for p in (dataset / "depth").iterdir())
    assert (dataset / "rgb").is_dir()
    assert sorted(p.name for p in (dataset / "rgb").iterdir()) == depths
    from ssp.sim.bop import CLASS_COLORS, TABLE_COLOR

    gt = json.loads((dataset / "scene_gt.json").read_text())
    for name in depths:
        rgb_img = Image.open(dataset / "rgb" / name)
        assert rgb_img.mode == "RGB"
        rgb = np.asarray(rgb_img).astype(float)
        depth = np.asarray(Image.open(dataset / "depth" / name))
        inst = np.asarray(Image.open(dataset / "instance" / name)).astype(int) - 2
        assert rgb.shape == (*depth.shape, 3)
        assert (rgb[inst == -2] == 0).all()  # nothing: black
        for value, color in [(-1, TABLE_COLOR)] + [
            (k, CLASS_COLORS[(g["obj_id"] - 1) % len(CLASS_COLORS)])
            for k, g in enumerate(gt[str(int(name[:6]))])
        ]:
            px = rgb[inst == value]
            if not len(px):
                continue
            color = np.asarray(color)
            assert (px[:, color == 0] == 0).all()
            ch = color >= 0.1  # the same shading on every channel (up to rounding)
            light = px[:, ch] / (color[ch] * 255.0)
            assert np.allclose(light, light.mean(axis=1, keepdims=True), atol=0.03)
            assert 0.29 <= light.min() and light.max() <= 1.01
            if value == -1:
                assert light.std() > 0.01  # shaded, not flat
