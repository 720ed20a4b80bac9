"""Motion in the world (ssp.motion): a changed estimate is motion only when the data left the
old pose, or a correction; the running mean of a static object's estimates; what a scene state
keeps of them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.config import SSPConfig
from ssp.errors import SSPError
from ssp.geometry import make_pose, rotation_angle
from ssp.motion import (
    FUSION_CORRECTION,
    explains_before,
    fuse_static,
    moved_in_world,
    points_residual,
    prefers_estimate,
    seen_from_state,
    seen_points,
    seen_state,
)
from ssp.verification import Evidence

NAN = float("nan")


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def pose(x=0.0, y=0.0, z=0.0254, R=None) -> np.ndarray:
    return make_pose(R, [x, y, z])


def _ev(
    fit: float, visible: int = 60, seen_through: float = 0.0, residual: float = NAN
) -> tuple[Evidence, float]:
    """The evidence at the previous pose now, and the residual there."""
    return Evidence(visible, visible, fit, None, seen_through, 0.0, 0.0), residual


def test_a_changed_estimate_is_motion_only_when_the_data_left_where_it_was():
    cfg = SSPConfig()
    drop = cfg.temporal.moved_fit_drop
    # the data at the previous pose as it was (within the drop): a correction, not motion
    assert not moved_in_world(0.9, NAN, *_ev(0.9), cfg)
    assert not moved_in_world(0.9, NAN, *_ev(0.9 - drop + 0.01), cfg)
    assert not moved_in_world(0.4, NAN, *_ev(0.5), cfg)  # a wrong pose then, as wrong now
    # the data left it: explained much less, or its volume seen empty
    assert moved_in_world(0.9, NAN, *_ev(0.9 - drop - 0.01), cfg)
    assert moved_in_world(0.9, NAN, *_ev(0.9, seen_through=cfg.temporal.seen_through_fraction), cfg)
    # too little seen, now or then: the data cannot say, the estimate's change decides
    few = cfg.verification.min_visible_samples - 1
    assert moved_in_world(0.9, NAN, *_ev(0.9, visible=few), cfg)
    assert moved_in_world(None, NAN, *_ev(0.9), cfg)
    # a turn in place: the fit as it was, the points farther from its surface there
    rise = cfg.temporal.moved_residual_rise
    assert moved_in_world(0.9, 0.001, *_ev(0.9, residual=0.001 + rise + 1e-5), cfg)
    assert not moved_in_world(0.9, 0.001, *_ev(0.9, residual=0.001 + rise - 1e-5), cfg)
    assert not moved_in_world(0.9, NAN, *_ev(0.9, residual=0.005), cfg)  # not known then


def test_a_changed_estimate_is_motion_only_when_this_frames_data_prefer_it():
    # the data at the previous pose changed against the frame that set it (a new view), yet
    # this frame's data fit the estimate no better there: no motion; the estimate explains
    # more of the visible surface, its segment lies closer to it, or the old place is seen
    # empty: the data prefer it
    cfg = SSPConfig()
    gain, closer = cfg.temporal.moved_fit_gain, FUSION_CORRECTION
    old, r_old = _ev(0.8, residual=0.002)
    assert not prefers_estimate(old, r_old, _ev(0.8)[0], 0.002, cfg)
    assert not prefers_estimate(old, r_old, _ev(0.8 + gain - 0.01)[0], r_old - closer + 1e-5, cfg)
    assert prefers_estimate(old, r_old, _ev(0.8 + gain + 0.01)[0], 0.002, cfg)
    assert prefers_estimate(old, r_old, _ev(0.8)[0], r_old - closer - 1e-5, cfg)
    empty = _ev(0.8, seen_through=cfg.temporal.seen_through_fraction)[0]
    assert prefers_estimate(empty, r_old, _ev(0.8)[0], 0.002, cfg)
    # too little seen at either pose, or no evidence at the estimate: the data cannot say
    few = cfg.verification.min_visible_samples - 1
    assert prefers_estimate(_ev(0.8, visible=few)[0], r_old, _ev(0.8)[0], 0.002, cfg)
    assert prefers_estimate(old, r_old, _ev(0.8, visible=few)[0], 0.002, cfg)
    assert prefers_estimate(old, r_old, None, 0.002, cfg)
    assert not prefers_estimate(old, NAN, _ev(0.8)[0], 0.002, cfg)  # residual not known


def test_a_static_objects_output_is_the_running_mean_of_its_estimates():
    a, b = pose(0.0, R=rot("z", 0)), pose(0.004, R=rot("z", 4))
    # at rest for 0 frames before this one: this frame's estimate as it is
    np.testing.assert_allclose(fuse_static(a, b, 0, 4), b)
    # one frame before: the mean of the two (translation and turn halfway)
    half = fuse_static(a, b, 1, 4)
    assert half[0, 3] == pytest.approx(0.002)
    assert math.degrees(rotation_angle(half[:3, :3])) == pytest.approx(2.0)
    # three or more before: at least a quarter (about four frames' memory)
    assert fuse_static(a, b, 3, 4)[0, 3] == pytest.approx(0.001)
    assert fuse_static(a, b, 30, 4)[0, 3] == pytest.approx(0.001)
    # one frame: no memory
    np.testing.assert_allclose(fuse_static(a, b, 30, 1), b)
    assert np.allclose(half[:3, :3] @ half[:3, :3].T, np.eye(3))  # a rotation


# ----------------------------------------------------------------------------- snap_symmetric


def _seen_of(model, T: np.ndarray, camera=(0.0, -0.6, 0.5)) -> np.ndarray:
    """The points a camera at ``camera`` sees of ``model`` at ``T`` (its facing samples)."""
    p = model.surface_points @ T[:3, :3].T + T[:3, 3]
    n = model.surface_normals @ T[:3, :3].T
    return p[np.einsum("ij,ij->i", n, np.asarray(camera) - p) > 0.0]


def test_an_estimate_that_explains_the_points_seen_before_is_a_correction_not_a_motion(lib):
    """Issue 32: a moving camera's new view shows that the previous estimate was off (a cube
    estimated 8 deg off from one side) though nothing moved: the new estimate explains the
    points seen of it before as well as the old one did, or better. An object that moved
    (slid 10 mm, turned 10 deg) has left those points."""
    cfg = SSPConfig()
    block = lib["block"]
    T_true = pose(R=rot("z", 20))
    seen = seen_points(_seen_of(block, T_true))
    assert len(seen_points(np.zeros((1000, 3)))) == 128  # at most so many, evenly strided
    off = T_true @ make_pose(rot("z", 8))  # the estimate the old view allowed
    assert explains_before(seen, block, off, T_true, cfg)
    assert explains_before(seen, block, T_true, T_true, cfg)
    slid, turned = T_true.copy(), T_true @ make_pose(rot("z", 10))
    slid[:3, 3] += [0.010, 0.0, 0.0]
    assert not explains_before(seen, block, T_true, slid, cfg)
    assert not explains_before(seen, block, T_true, turned, cfg)
    far = T_true.copy()
    far[:3, 3] += [0.2, 0.0, 0.0]  # none of the points near it: each counts the cap
    cap = 2.0 * cfg.data.inlier_radius
    assert points_residual(seen, block, far, cap) == pytest.approx(cap)
    assert not explains_before(seen, block, T_true, far, cfg)
    assert not explains_before(None, block, off, T_true, cfg)  # nothing known: cannot say
    assert math.isnan(points_residual(np.zeros((0, 3)), block, T_true, cap))


def test_seen_points_go_through_the_scene_state():
    pts = np.arange(12.0).reshape(4, 3) * 0.01
    entry = json.loads(json.dumps(seen_state(0.9, 0.001, 3, pts)))
    back = seen_from_state(entry)
    np.testing.assert_array_equal(back["seen_points"], pts)
    assert (back["seen_fit"], back["seen_residual"], back["still"]) == (0.9, 0.001, 3)
    assert seen_from_state({})["seen_points"] is None  # an older state
    with pytest.raises(SSPError, match="seen_points"):
        seen_from_state({"seen_points": [[0.0, 1.0]]})
    with pytest.raises(SSPError, match="NaN"):
        seen_from_state({"seen_points": [[0.0, float("nan"), 1.0]]})
