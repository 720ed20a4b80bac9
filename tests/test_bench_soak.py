"""``ssp bench soak`` on a tiny setting: per-frame time and memory, parser alone and runner."""

from __future__ import annotations

import json

from ssp.eval.bench_soak import bench_soak, rss_mib, summarize, write_report


def test_bench_soak_reports_time_and_memory_per_frame(tmp_path):
    assert rss_mib() > 10  # this process, MiB
    for runner in (False, True):
        r = bench_soak(3, stride=8, runner=runner, work_dir=tmp_path / str(runner))
        rows = r["per_frame"]
        assert [row["frame"] for row in rows] == [0, 1, 2] and not any(x["failed"] for x in rows)
        assert all(row["seconds"] > 0 and row["rss_mib"] > 10 for row in rows)
        assert rows[0]["objects"] >= 1
        s = r["summary"]
        assert s["frames"] == 3 and s["rss_mib_end"] == rows[-1]["rss_mib"]
        assert s["first_3"]["mean"] == s["last_3"]["mean"] > 0
    assert (tmp_path / "True" / "run" / "summary.json").exists()  # kept: work_dir was given
    assert json.loads(write_report(r, tmp_path / "out").read_text())["protocol"] == "soak"


def test_summary_windows_and_growth():
    rows = [{"seconds": 1.0 if k < 100 else 2.0, "rss_mib": 100.0 + 0.01 * k} for k in range(300)]
    s = summarize(rows)
    assert s["first_100"]["mean"] == 1.0 and s["last_100"]["mean"] == 2.0
    assert abs(s["rss_growth_mib_after_100"] - 0.01 * 200) < 1e-9
    assert abs(s["rss_slope_mib_per_1000_frames"] - 10.0) < 1e-6
