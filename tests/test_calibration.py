"""Calibration of the stability and collision constants (``ssp bench calibrate``).

A tiny run (one seed, a few resting families, one bad scene per kind and parameter) checks
that the measurement sees what the terms must judge (resting objects nearly still, hovering
ones in free fall, overlaps at their set depth), that the chosen constants separate the
classes when fed through the real probability functions, and that the report and the command
line write what they promise.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ssp.cli import app
from ssp.config import SSPConfig
from ssp.eval.calibrate import (
    GT_REST_BETA,
    TARGET_BAD,
    TARGET_REST,
    _noisy,
    calibrate,
    choose_logistic,
    write_report,
)
from ssp.geometry import make_pose, rotation_angle
from ssp.probability import log_collision, log_stability

TINY = {
    "seeds": [0],
    "families": ("tower", "bridge", "tool_scatter"),
    "tower_sizes": (2, 4),
    "quick_bad": True,
}


@pytest.fixture(scope="module")
def tiny() -> dict:
    return calibrate(**TINY)


def _rows(result, cls=None, stage=None, family=None):
    return [
        r
        for r in result["records"]
        if (cls is None or r["cls"] == cls)
        and (stage is None or r["stage"] == stage)
        and (family is None or r["family"] == family)
    ]


def _p_b(rows, cfg) -> np.ndarray:
    """P_B through the scorer's function: beta_t g as |a|, beta_R as |alpha| with alpha_max 1."""
    lin = np.array([[r["beta_t"] * cfg.physics.gravity, 0, 0] for r in rows])
    ang = np.array([[r["beta_r"], 0, 0] for r in rows])
    return np.exp(log_stability(lin, ang, 1.0, cfg.physics.gravity, cfg.stability))


def _chosen_config(result) -> SSPConfig:
    ch = result["summary"]["chosen"]
    return SSPConfig.from_dict(
        {
            "stability": {
                "steepness": ch["stability"]["steepness"],
                "midpoint": ch["stability"]["midpoint"],
            },
            "collision": {
                "steepness": ch["collision"]["steepness"],
                "midpoint": ch["collision"]["midpoint"],
            },
        }
    )


def test_choose_logistic_meets_both_targets():
    for rest, bad in ((0.005, 0.097), (0.0, 3.3e-4), (0.02, 0.5)):
        ch = choose_logistic(rest, bad, rest_factors=2)
        assert ch["achievable"] and rest < ch["midpoint"] < bad
        s, a = ch["steepness"], ch["midpoint"]
        p_rest = (1 / (1 + math.exp(s * (rest - a)))) ** 2
        p_bad = 1 / (1 + math.exp(s * (bad - a)))
        assert p_rest >= TARGET_REST and p_bad <= TARGET_BAD
    assert not choose_logistic(0.2, 0.1)["achievable"]


def test_noise_stays_within_its_bounds(cube_model):
    rng = np.random.default_rng(0)
    T0 = make_pose(t=[0.1, 0.0, 0.0254])
    com0 = T0[:3, :3] @ cube_model.center_of_mass + T0[:3, 3]
    for _ in range(50):
        T = _noisy({"a": T0}, {"a": cube_model}, rng, 0.002, 2.0)["a"]
        com = T[:3, :3] @ cube_model.center_of_mass + T[:3, 3]
        assert np.linalg.norm(com - com0) <= 0.002 + 1e-12
        assert math.degrees(rotation_angle(T0[:3, :3].T @ T[:3, :3])) <= 2.0 + 1e-9


def test_ground_truth_is_at_rest_and_contact_free(tiny):
    exact = _rows(tiny, "resting", "exact")
    assert len(exact) == 2 + 4 + 2 * 3 + 8  # towers 2 and 4, two bridges, 8 tools
    assert max(max(r["beta_t"], r["beta_r"]) for r in exact) <= GT_REST_BETA
    assert max(r["depth_mm"] for r in exact) < 0.2
    assert tiny["rejected_scenes"] == []


def test_resting_below_midpoint_and_bad_above(tiny):
    mid = tiny["summary"]["chosen"]["stability"]["midpoint"]
    for r in _rows(tiny, "resting", "search"):
        assert max(r["beta_t"], r["beta_r"]) < mid, r
    hover = _rows(tiny, "bad", "set", "hover")
    assert len(hover) == 4
    for r in hover:  # free fall from rest: |a| = g exactly
        assert r["beta_t"] == pytest.approx(1.0, abs=1e-3) and r["depth_mm"] == 0.0
    for kind in ("overhang", "tilted"):
        rows = [r for r in _rows(tiny, "bad", "set", kind) if r["param"] >= 5]
        assert rows and all(max(r["beta_t"], r["beta_r"]) > mid for r in rows)
    # a 2 mm overhang tips, but slowly: its beta is the smallest bad one
    ch = tiny["summary"]["chosen"]["stability"]
    assert ch["smallest_bad_case"] == "overhang_block_2mm"


def test_the_window_lets_hovering_objects_land(tiny):
    """Quasi-static steps fall g dt^2 = 0.245 mm per step: 5 mm lands within 0.25 s, 10 mm
    does not land within 0.1 s."""
    by = {(r["scene"], r["stage"]): r for r in _rows(tiny, "bad", family="hover")}
    assert by[("hover_cube_table_5mm", "0.25s")]["beta_t"] < 0.01
    assert by[("hover_cube_table_10mm", "0.10s")]["beta_t"] == pytest.approx(1.0, abs=1e-3)


def test_overlaps_are_measured_at_their_set_depth(tiny):
    rows = _rows(tiny, "bad", "set", "overlap")
    assert {r["param"] for r in rows} == {1.0, 2.0, 5.0, 10.0}
    for r in rows:
        assert r["depth_mm"] == pytest.approx(r["param"], abs=0.05)
    deep = [r for r in rows if r["param"] >= 5]
    assert all(r["e_c"] > 0 for r in deep)
    # solver residue: no resting object gets an overlap volume
    assert max(r["e_c"] for r in _rows(tiny, "resting")) == 0.0


def test_chosen_constants_separate_the_classes(tiny):
    cfg = _chosen_config(tiny)
    ch = tiny["summary"]["chosen"]
    assert ch["stability"]["achievable"] and ch["collision"]["achievable"]
    rest = _rows(tiny, "resting", "search")
    assert _p_b(rest, cfg).min() >= TARGET_REST
    e_rest = np.array([r["e_c"] for r in rest])
    assert np.exp(log_collision(e_rest, cfg.collision)).min() >= TARGET_REST
    stab_bad = [
        r for r in _rows(tiny, "bad", "set") if r["family"] in ("hover", "overhang", "tilted")
    ]
    assert _p_b(stab_bad, cfg).max() <= TARGET_BAD
    used = ch["collision"]["bad_overlap_mm_used"]
    coll_bad = [r for r in _rows(tiny, "bad", "set", "overlap") if r["param"] >= used]
    e_bad = np.array([r["e_c"] for r in coll_bad])
    assert coll_bad and np.exp(log_collision(e_bad, cfg.collision)).max() <= TARGET_BAD
    # the summary's table agrees with the functions
    p = tiny["summary"]["probabilities"]["chosen"]
    assert p["resting@search"]["P_B_min"] >= TARGET_REST
    assert p["hover_5@set"]["P_B_max"] <= TARGET_BAD


def test_min_depth_suggestion_is_above_resting_penetration(tiny):
    ch = tiny["summary"]["chosen"]
    d_rest = max(r["depth_mm"] for r in _rows(tiny, "resting"))
    assert d_rest / 1000 < ch["min_depth_m"] < 0.001  # below the 1 mm overlaps


def test_deterministic():
    kw = {"seeds": [3], "families": ("tower",), "tower_sizes": (3,), "quick_bad": True}
    a, b = calibrate(**kw), calibrate(**kw)
    assert a["records"] == b["records"]
    assert a["summary"]["chosen"] == b["summary"]["chosen"]


def test_report_files(tiny, tmp_path):
    paths = write_report(tiny, tmp_path / "cal")
    assert [p.name for p in paths] == ["calibration.json", "calibration.png"]
    data = json.loads(paths[0].read_text())
    for key in ("protocol", "mujoco_version", "machine", "settings", "summary", "records"):
        assert key in data
    s = data["summary"]
    for key in ("resting", "bad", "chosen", "probabilities", "stability_by_stage"):
        assert key in s
    assert set(s["resting"]) == {"exact", "0.10s", "0.25s", "search"}
    for term in ("stability", "collision"):
        assert {"steepness", "midpoint", "achievable"} <= set(s["chosen"][term])
    assert {"median", "p95", "p99", "max"} <= set(s["resting"]["search"]["beta"])
    assert data["records"] == tiny["records"]
    assert paths[1].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bench_calibrate(tmp_path):
    out = tmp_path / "cal"
    r = CliRunner().invoke(
        app, ["bench", "calibrate", "--quick", "--seeds", "1", "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert (out / "calibration.json").exists() and (out / "calibration.png").exists()
    assert "chosen constants" in r.output and "stability" in r.output
    data = json.loads((out / "calibration.json").read_text())
    assert data["settings"]["seeds"] == [0]
