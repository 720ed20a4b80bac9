"""Depth correction before judging (ssp.correction): an RGB estimator's hypothesis that is
centimetres off along the viewing ray is slid to its data's depth, not rejected."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.config import SSPConfig
from ssp.correction import camera_view, correct_hypothesis, ray_shift
from ssp.geometry import make_pose
from ssp.library.library import ObjectLibrary
from ssp.parser import SceneParser
from ssp.probability import pose_change
from ssp.scene import Hypothesis
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at

LIB = ObjectLibrary.builtin()
CAMERA = look_at([-0.45, -0.55, 0.6], [0.0, 0.0, 0.03])
OFF = SSPConfig.model_validate({"correction": {"enabled": False}})


def on_table(cls: str, x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return make_pose(R, [x, y, float(LIB[cls].extents[2]) / 2])


def along_ray(T: np.ndarray, metres: float) -> np.ndarray:
    """``T`` moved ``metres`` along the camera's ray through its origin (away: positive)."""
    u = T[:3, 3] - CAMERA[:3, 3]
    out = T.copy()
    out[:3, 3] += metres * u / np.linalg.norm(u)
    return out


def rgb_frame(gt, shifts, seed=0, segments=False):
    """A rendered frame of ``gt`` whose hypotheses (one per object) are each off by
    ``shifts[oid]`` m along the viewing ray, as an RGB estimator's are."""
    f = synthetic_frame(
        LIB, gt, T_world_cam=CAMERA, rng=np.random.default_rng(seed), k=1, noise=True,
        sigma_t=1e-9, sigma_r_deg=1e-9, stride=2, give_segments=segments,
    )  # fmt: skip
    f.hypotheses = [
        Hypothesis(h.class_name, along_ray(gt[oid][1], shifts[oid]), 0.9, segment=h.segment)
        for h, oid in zip(f.hypotheses, gt, strict=True)
    ]
    return f


def test_ray_shift_finds_the_densest_depth_and_prefers_no_shift_on_ties():
    rng = np.random.default_rng(0)
    on_surface = 0.031 + rng.normal(0, 0.001, 60)
    occluder = -0.05 + rng.normal(0, 0.001, 20)
    shift, count, at_zero = ray_shift(np.r_[on_surface, occluder], 0.005, 0.12)
    assert abs(shift - 0.031) < 0.002 and count == 60 and at_zero == 0
    # nothing beyond max_shift is taken
    shift, count, _ = ray_shift(np.r_[on_surface + 0.2], 0.005, 0.12)
    assert count == 0 and shift == 0.0
    # a tie keeps the smaller shift
    shift, _, _ = ray_shift(np.r_[np.zeros(10), np.full(10, 0.05)], 0.002, 0.12)
    assert shift == 0.0


@pytest.mark.parametrize("metres", [-0.04, -0.025, 0.025, 0.045])
def test_a_hypothesis_off_along_its_ray_is_slid_to_its_data(metres):
    gt = {"a": ("cube", on_table("cube", yaw_deg=15))}
    f = rgb_frame(gt, {"a": metres}).validate(LIB)
    view = camera_view(f, SSPConfig())
    fixed = correct_hypothesis(f.hypotheses[0], LIB["cube"], view, f, SSPConfig())
    assert fixed is not None
    h, fix = fixed
    dt, dth = pose_change(gt["a"][1], h.T_world_obj, LIB["cube"].symmetry)
    assert dt < 0.003 and np.degrees(dth) < 1.0, (dt, np.degrees(dth))
    assert abs(fix.shift + metres) < 0.005 and fix.support_after > fix.support_before + 0.3


def test_a_hypothesis_on_its_data_is_left_alone():
    gt = {"a": ("block", on_table("block", yaw_deg=30))}
    f = rgb_frame(gt, {"a": 0.0}).validate(LIB)
    view = camera_view(f, SSPConfig())
    assert correct_hypothesis(f.hypotheses[0], LIB["block"], view, f, SSPConfig()) is None


def test_the_parser_keeps_and_corrects_what_it_rejected_before():
    """A stack of two blocks whose hypotheses are 3 cm too far and 3 cm too near: without the
    correction both are rejected (their volume is seen empty, or they explain nothing of
    their visible surface); with it both are kept, within millimetres, the reason saying so."""
    h = float(LIB["cube"].extents[2])
    top = on_table("cube", yaw_deg=10)
    top[2, 3] += h
    gt = {"low": ("cube", on_table("cube")), "top": ("cube", top)}
    shifts = {"low": 0.03, "top": -0.03}
    before = SceneParser(LIB, OFF).update(rgb_frame(gt, shifts, segments=True))
    assert len(before.objects) < 2
    est = SceneParser(LIB).update(rgb_frame(gt, shifts, segments=True))
    assert len(est.objects) == 2 and not est.rejected
    for oid, (cls, T) in gt.items():
        o = min(est.objects, key=lambda o: np.linalg.norm(o.T_world_obj[:3, 3] - T[:3, 3]))
        dt, dth = pose_change(T, o.T_world_obj, LIB[cls].symmetry)
        assert dt < 0.003 and np.degrees(dth) < 2.0, (oid, dt, np.degrees(dth))
        assert "corrected" in o.reason and "along the viewing ray" in o.reason


def test_without_a_camera_pose_nothing_is_corrected():
    gt = {"a": ("cube", on_table("cube"))}
    f = rgb_frame(gt, {"a": 0.03})
    f.T_world_cam = None
    est = SceneParser(LIB).update(f)
    assert all("corrected" not in o.reason for o in est.objects)
