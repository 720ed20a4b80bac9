"""``ssp bench estimator`` on one short sequence: alone, and beside a checkout (this one)."""

from __future__ import annotations

from pathlib import Path

import pytest

from ssp.eval.bench_estimator import bench_estimator, compare_estimator, write_report


@pytest.fixture(scope="module")
def result():
    return bench_estimator("structure", sequences=1, seed=1000, stages=1)


def test_bench_estimator_times_and_scores_every_segment(result, tmp_path):
    this = result["this"]
    assert this["segments"] > 5
    assert 0 < this["sec_per_segment_median"] <= this["sec_per_segment_p95"]
    assert 0.5 <= this["recall"] <= 1.0  # four frames of a block structure: most are found
    json_path, md_path = write_report(result, tmp_path)
    text = md_path.read_text()
    assert "s per segment, mean" in text and "Target (issue 19)" in text
    assert json_path.name == "results.json"


def test_compare_with_the_same_code_recalls_the_same(tmp_path):
    """Beside itself (this checkout as the other side): the same hypotheses, so the same
    recall and no segment recalled by one side only; the times are both positive."""
    here = Path(__file__).resolve().parents[1]
    res = compare_estimator(str(here), "structure", sequences=1, seed=1000, stages=1)
    assert res["rev_summary"]["recall"] == res["this"]["recall"]
    assert res["recalled_by_rev_only"] == [] and res["recalled_by_this_only"] == []
    assert res["speedup"] > 0
    _, md = write_report(res, tmp_path)
    assert "Speed-up" in md.read_text()
