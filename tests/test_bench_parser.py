"""``ssp.eval.bench_parser`` on a tiny setting: the report has what issue 3 asks for."""

from __future__ import annotations

import json

import numpy as np

from ssp.eval.bench_parser import FRAMES, STAGES, bench_parser, stacks, write_report
from ssp.library import ObjectLibrary


def test_stacks_have_the_requested_size_and_rest_on_each_other():
    lib = ObjectLibrary.builtin()
    gt = stacks(lib, 7, seed=3)
    assert len(gt) == 7
    for cls, T in gt.values():
        bottom = T[2, 3] + lib[cls].mesh.bounds[0, 2]
        assert bottom > -1e-9  # nothing below the table


def test_bench_parser_reports_every_frame_kind(tmp_path):
    result = bench_parser(sizes=(2, 3), k=2, repeats=1)
    assert [r["objects"] for r in result["rows"]] == [2, 3]
    for row in result["rows"]:
        for name in FRAMES:
            d = row[name]
            assert d["sec_per_frame_mean"] > 0
            assert set(d["stage_share"]) == {*STAGES, "other"}
            assert abs(sum(d["stage_share"].values()) - 1.0) < 1e-6
            sec = d["stage_seconds"]
            assert {"total", "segments", "association"} <= set(sec)
            assert 0 < sec["segments"] < sec["total"] <= d["sec_per_frame_max"] + 1e-9
            err = d["error"]  # the worst object beside the mean
            assert (
                err["ssp_mm_max"] >= err["ssp_mm_mean"]
                and err["ssp_deg_max"] >= err["ssp_deg_mean"]
            )
        assert row["added"]["hypotheses_tested_mean"] >= row["objects"] * 2
        assert all(isinstance(u, bool) for u in row["unchanged"]["unchanged_shortcut"])
    j, m = write_report(result, tmp_path)
    assert json.loads(j.read_text())["protocol"] == "parser-timing"
    assert "| 3 | unchanged |" in m.read_text() and "ssp worst" in m.read_text()


def test_link_node_structure_puts_every_link_end_on_a_node_face():
    from ssp.eval.bench_parser import links_structure

    lib = ObjectLibrary.builtin()  # a block plays the link, a cube the node
    gt = links_structure(lib, link="block", node="cube")
    assert len(gt) == 6
    for cls, T in gt.values():
        assert T[2, 3] + (lib[cls].mesh.vertices @ T[:3, :3].T)[:, 2].min() > -1e-9
    size = float(lib["cube"].extents[0])
    (_, a), (_, b), (_, c) = gt["node_a"], gt["node_b"], gt["node_c"]
    long_side = float(lib["block"].extents[2])  # the link's own z axis is laid along x, y
    assert abs(b[0, 3] - a[0, 3] - (size + long_side)) < 1e-9
    assert abs(c[1, 3] - b[1, 3] - (size + long_side)) < 1e-9


def test_targets_are_checked_against_the_rows_measured():
    from ssp.eval.bench_parser import _checks

    def row(n, changed, scene="stacks"):
        frames = {f: {"sec_per_frame_mean": changed} for f in FRAMES}
        return {"scene": scene, "objects": n, **frames}

    checks = {c["what"]: c for c in _checks([row(10, 0.2), row(20, 0.5), row(6, 0.3, "links")])}
    assert checks["changed frame, N = 10 (s)"]["met"]
    assert not checks["changed frame, N = 20 / N = 10"]["met"]  # 2.5 > 2.1
    assert checks["link/node structure, added frame (s)"]["met"]
    assert _checks([row(5, 0.1)]) == []


def test_compare_times_another_checkout_beside_this_code(tmp_path):
    from pathlib import Path

    import ssp
    from ssp.eval.bench_parser import compare_parser, write_compare

    root = Path(ssp.__file__).resolve().parents[2]  # this checkout, as "another" one
    result = compare_parser(str(root), sizes=(2,), k=2, repeats=1, rounds=1)
    assert [r["frame"] for r in result["rows"]] == list(FRAMES)
    for r in result["rows"]:
        assert r["rev_s"] > 0 and r["this_s"] > 0 and r["speedup"] > 0
        assert r["rev_tested"] == r["this_tested"]  # the same code decides the same
        assert r["rev_error"] == r["this_error"]
    _, m = write_compare(result, tmp_path)
    assert "| 2 | changed |" in m.read_text()


def test_compare_with_an_unknown_revision_says_so():
    import pytest

    from ssp.errors import ArgumentError
    from ssp.eval.bench_parser import compare_parser

    with pytest.raises(ArgumentError, match="no-such-revision"):
        compare_parser("no-such-revision", sizes=(2,), k=2, repeats=1, rounds=1)


def _interpenetrating(scene: dict, lib) -> list[tuple[str, str]]:
    """Pairs of objects whose hull boxes overlap by more than 0.1 mm on every axis."""
    from ssp.geometry import hull_box

    ids = list(scene)
    boxes = {o: hull_box(lib[scene[o][0]].hull_vertices, [scene[o][1]]) for o in ids}
    out = []
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            overlap = np.minimum(boxes[a][1], boxes[b][1]) - np.maximum(boxes[a][0], boxes[b][0])
            if (overlap > 1e-4).all():
                out.append((a, b))
    return out


def test_changed_frames_are_scenes_physics_allows():
    """The changed frame moves the first stack; it must not push it into a neighbour (the
    link/node structure's node a is flush against link 1's end on +x, so it moves to -x)."""
    from ssp.eval.bench_parser import SLIDE, _slide, links_structure, stacks

    lib = ObjectLibrary.builtin()
    for n in (5, 10, 20):
        gt = stacks(lib, n, seed=n * 10)
        assert _interpenetrating(_slide(gt, SLIDE), lib) == []
    links = links_structure(lib, link="block", node="cube")
    assert _interpenetrating(links, lib) == []
    assert _interpenetrating(_slide(links, -SLIDE), lib) == []
    assert _interpenetrating(_slide(links, SLIDE), lib) == [("node_a", "link_1")]
