"""``ssp.eval.bench_parser`` on a tiny setting: the report has what issue 3 asks for."""

from __future__ import annotations

import json

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
        assert row["added"]["hypotheses_tested_mean"] >= row["objects"] * 2
        assert all(isinstance(u, bool) for u in row["unchanged"]["unchanged_shortcut"])
    j, m = write_report(result, tmp_path)
    assert json.loads(j.read_text())["protocol"] == "parser-timing"
    assert "| 3 | unchanged |" in m.read_text()
