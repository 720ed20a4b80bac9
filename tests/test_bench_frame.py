"""``ssp bench frame`` (issue 34): its numbers, its targets, its side-by-side comparison.

The latency figures themselves are the benchmark's (results in files, never asserted here);
these tests check that what it reports is computed right from what the runs wrote.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from ssp.eval.bench_frame import (
    _in_process,
    check_targets,
    markdown_report,
    same_results,
    summarize,
    time_scenarios,
)
from ssp.sim.bop import simulate_to_disk


def _frame(wall, objects=3, status="done", stages=True):
    doc = {"wall": wall, "status": status, "objects": objects, "seconds": wall}
    if stages:
        doc.update(
            frame_timings={"perception": 0.4 * wall, "parser": 0.5 * wall,
                           "results": 0.05 * wall, "other": 0.0, "total": 0.95 * wall},
            perception={"read": 0.1 * wall, "cleaning": 0.3 * wall, "total": 0.4 * wall},
            parser={"search": 0.5 * wall, "total": 0.5 * wall, "lanes": 9.0},
        )  # fmt: skip
    return doc


def test_summarize_leaves_each_runs_first_frame_apart():
    walls = [5.0, 0.1, 0.2, 0.3, 0.4, 1.0]
    rounds = [{"runs": [{"scenario": "sim structure: masks, hypotheses given",
                         "frames": [_frame(w) for w in walls]}]}]  # fmt: skip
    (row,) = summarize(rounds)
    rest = walls[1:]
    assert row["frames"] == 5 and row["first_median"] == 5.0
    assert row["median"] == pytest.approx(np.median(rest))
    assert row["p95"] == pytest.approx(np.percentile(rest, 95))
    assert row["max"] == 1.0 and row["mean"] == pytest.approx(np.mean(rest))
    shares = row["shares"]
    # exclusive stages as shares of the frames' wall time; lanes (CPU) never counted
    assert shares["parser/search"] == pytest.approx(0.5)
    assert shares["perception/cleaning"] == pytest.approx(0.3)
    assert "parser/lanes" not in shares
    assert sum(shares.values()) == pytest.approx(1.0)
    assert shares["writing and other"] == pytest.approx(0.05)


def test_failed_frames_are_counted_not_timed():
    frames = [_frame(1.0), _frame(0.2), _frame(9.0, status="failed"), _frame(0.4)]
    (row,) = summarize([{"runs": [{"scenario": "s", "frames": frames}]}])
    assert row["failed"] == 1 and row["frames"] == 2 and row["max"] == 0.4


def test_an_old_revision_without_stage_timings_has_no_shares():
    frames = [_frame(w, stages=False) for w in (1.0, 0.2, 0.3)]
    (row,) = summarize([{"runs": [{"scenario": "s", "frames": frames}]}])
    assert row["shares"] == {} and row["median"] == pytest.approx(0.25)


def test_targets_per_experiment():
    rows = [
        {"scenario": "sim structure: masks, hypotheses given", "median": 0.25, "p95": 0.6},
        {"scenario": "sim isolated: masks, hypotheses given", "median": 0.35, "p95": 0.45},
        {"scenario": "sim isolated: no masks, built-in estimator", "median": 0.9, "p95": 2.0},
        {
            "scenario": "sim structure: no masks, built-in estimator",
            "median": 0.5,
            "p95": 0.6,
            "failed": 1,
        },  # fast, but a frame raised
        {"scenario": "real: test16 labels", "median": 9.0, "p95": 9.0},
    ]
    rows = [{"failed": 0, **r} for r in rows]
    got = {(t["scenario"], t["statistic"]): t["met"] for t in check_targets(rows)}
    assert got == {
        ("sim structure: masks, hypotheses given", "median"): True,
        ("sim structure: masks, hypotheses given", "p95"): False,
        ("sim isolated: masks, hypotheses given", "median"): False,
        ("sim isolated: masks, hypotheses given", "p95"): True,
        ("sim isolated: no masks, built-in estimator", "median"): True,
        ("sim structure: no masks, built-in estimator", "median"): False,
    }


def _write_run(folder: Path, frames: dict[str, dict], rows: list[str]) -> None:
    (folder / "frames").mkdir(parents=True)
    for name, doc in frames.items():
        (folder / "frames" / f"{name}.json").write_text(json.dumps(doc))
    (folder / "ssp_x-test.csv").write_text("\n".join(rows) + "\n")


def test_same_results_ignores_wall_times_only(tmp_path):
    runs = [{"scenario": "a", "input": "/x/000000"}, {"scenario": "b", "input": "/x/000001"}]
    doc = {"name": "000000", "objects": [{"id": "cube_0", "T": [1, 2]}], "seconds": 0.3,
           "timings": {"total": 0.2}, "perception": {"timings": {"total": 0.1}}}  # fmt: skip
    slower = {**doc, "seconds": 0.9, "timings": {"total": 0.8}, "frame_timings": {"total": 1}}
    moved = {**doc, "objects": [{"id": "cube_0", "T": [1, 3]}]}
    _write_run(tmp_path / "rev" / "000", {"000000": doc}, ["1,0,1,0.9,R,t,0.3"])
    _write_run(tmp_path / "this" / "000", {"000000": slower}, ["1,0,1,0.9,R,t,0.8"])
    _write_run(tmp_path / "rev" / "001", {"000000": doc}, ["1,0,1,0.9,R,t,0.3"])
    _write_run(tmp_path / "this" / "001", {"000000": moved}, ["1,0,1,0.9,R,t,0.3"])
    got = same_results(runs, tmp_path / "rev", tmp_path / "this")
    assert got["a"] == "identical"
    assert got["b"].startswith("1 frame(s) differ") and "000001/000000" in got["b"]


def test_markdown_side_by_side():
    row = {"scenario": "sim structure: masks, hypotheses given", "frames": 5, "failed": 0,
           "objects": [3, 8], "median": 0.2, "p95": 0.4, "max": 0.5, "mean": 0.25,
           "first_median": 1.0, "shares": {"parser/search": 0.5}}  # fmt: skip
    old = {**row, "median": 0.4, "p95": 0.6}
    result = {"machine": {"cpus": 2, "python": "3.11"}, "sequences": 1, "seed": 1000,
              "rounds": 1, "compare": "abc123", "this": [row], "rev": [old],
              "same_results": {row["scenario"]: "identical"},
              "targets": check_targets([row])}  # fmt: skip
    text = markdown_report(result)
    assert "| 0 / 0 | 400 | 200 | 2.00x | 600 | 400 | 1.50x | identical |" in text
    assert "| sim structure: masks, hypotheses given | median | 300 | 200 | 0 | yes |" in text


@pytest.fixture(scope="module")
def small_scene(lib, tmp_path_factory):
    root = tmp_path_factory.mktemp("benchframe")
    (scene,) = simulate_to_disk("structure", 1, 11, out_dir=root, library=lib, stages=2,
                                frames_per_stage=2, stride=4, n_objects=3)  # fmt: skip
    return scene


def test_time_scenarios_reads_what_the_run_wrote(small_scene, tmp_path):
    runs = [{"scenario": "s", "input": str(small_scene), "models": None, "masks": "auto",
             "hypotheses": "given", "kind": "sim"}]  # fmt: skip
    res = time_scenarios({"runs": runs, "out": str(tmp_path / "runs")})
    (run,) = res["runs"]
    frames = run["frames"]
    assert len(frames) == 4 and all(f["status"] == "done" for f in frames)
    for f in frames:
        # the wall time between two frames' ends holds the frame's own time and its writing
        assert f["wall"] >= f["seconds"] > 0
        assert math.isclose(f["frame_timings"]["total"], f["seconds"])
        assert f["perception"]["total"] > 0 and f["parser"]["total"] > 0


def test_another_code_is_timed_in_its_own_process(small_scene, tmp_path):
    """The driver runs a checkout's ssp (here this one's ``src``) in a fresh process."""
    tree = str(Path(__file__).resolve().parents[1] / "src")
    runs = [{"scenario": "s", "input": str(small_scene), "models": None, "masks": "none",
             "hypotheses": "given", "kind": "sim"}]  # fmt: skip
    res = _in_process(tree, {"runs": runs, "out": str(tmp_path / "runs")}, "this code")
    (run,) = res["runs"]
    assert len(run["frames"]) == 4 and res["machine"]["cpus"] >= 1
    assert (tmp_path / "runs" / "000" / "summary.json").exists()


def test_a_wrong_real_dev_folder_is_named(tmp_path):
    from ssp.errors import ArgumentError
    from ssp.eval.bench_frame import _real_runs

    with pytest.raises(ArgumentError, match="real captures"):
        _real_runs(tmp_path / "nowhere", tmp_path / "work", 3)
