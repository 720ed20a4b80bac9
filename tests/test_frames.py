"""Synthetic frames from a ground-truth scene (ssp.sim.frames)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.geometry import invert, make_pose, rotation_angle, transform_points
from ssp.sim.frames import perturb_pose, synthetic_frame, visible_fractions
from ssp.sim.render import Camera, look_at

EDGE = 0.0508
CAM = Camera.default()
T_WC = look_at([0.45, -0.35, 0.5], [0.0, 0.0, 0.03])


def _pose(x, y, z, yaw_deg=0.0) -> np.ndarray:
    return make_pose(Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), [x, y, z])


@pytest.fixture(scope="module")
def gt() -> dict:
    """A cube with a block on top, and a drill lying beside them."""
    return {
        "cube_1": ("cube", _pose(0.0, 0.0, EDGE / 2, 15.0)),
        "block_1": ("block", _pose(0.0, 0.0, EDGE + 0.0127, -20.0)),
        "drill_1": (
            "drill",
            make_pose(Rotation.from_euler("x", 90, degrees=True).as_matrix(), [0.0, 0.16, 0.039]),
        ),
    }


def _surface_distance(lib, gt, iid, points) -> np.ndarray:
    cls, T = gt[iid]
    local = transform_points(invert(T), points)
    return trimesh.proximity.closest_point(lib[cls].mesh, local)[1]


def test_labels_line_up_with_points(lib, gt):
    frame = synthetic_frame(lib, gt, T_world_cam=T_WC, rng=0, noise=False, stride=3)
    assert frame.points.shape == (len(frame.labels), 3)
    assert set(np.unique(frame.labels)) == {-1, 0, 1, 2}
    np.testing.assert_array_equal(frame.T_world_cam, T_WC)
    for i, iid in enumerate(gt):
        pts = frame.points[frame.labels == i]
        assert len(pts) > 30
        assert np.max(_surface_distance(lib, gt, iid, pts)) < 1e-6
    assert np.max(np.abs(frame.points[frame.labels == -1][:, 2])) < 1e-9
    frame.validate(lib)  # a valid frame for the parser


def test_noisy_points_stay_near_their_surface(lib, gt):
    frame = synthetic_frame(lib, gt, T_world_cam=T_WC, rng=1, stride=3)
    clean = synthetic_frame(lib, gt, T_world_cam=T_WC, rng=1, stride=3, noise=False)
    assert len(frame.points) < len(clean.points)  # some edge pixels dropped
    pts = frame.points[frame.labels == 0]
    dist = _surface_distance(lib, gt, "cube_1", pts)
    assert np.median(dist) > 1e-4  # noise is there (~1.5 mm at 0.7 m)
    assert np.max(dist) < 0.015  # and bounded (~ 8 sigma)
    table = frame.points[frame.labels == -1][:, 2]
    assert 0.5e-3 < np.std(table) < 5e-3


def test_hypotheses_follow_the_stated_noise(lib, gt):
    sigma_t, sigma_r = 0.004, 6.0
    frame = synthetic_frame(
        lib,
        gt,
        T_world_cam=T_WC,
        rng=2,
        k=300,
        sigma_t=sigma_t,
        sigma_r_deg=sigma_r,
        stride=8,
        detect={"cube_1"},
        give_ids=True,
    )
    hyps = frame.hypotheses
    assert len(hyps) == 300
    assert all(h.class_name == "cube" and h.instance_id == "cube_1" for h in hyps)
    scores = [h.score for h in hyps]
    assert scores[0] == max(scores) and np.all(np.diff(scores) < 0)
    T_gt = gt["cube_1"][1]
    dt = np.array([np.linalg.norm(h.T_world_obj[:3, 3] - T_gt[:3, 3]) for h in hyps])
    dr = np.degrees([rotation_angle(h.T_world_obj[:3, :3] @ T_gt[:3, :3].T) for h in hyps])
    assert np.sqrt(np.mean(dt**2)) == pytest.approx(sigma_t, rel=0.15)
    assert np.sqrt(np.mean(dr**2)) == pytest.approx(sigma_r, rel=0.15)
    assert np.max(dt) < 5 * sigma_t and np.max(dr) < 5 * sigma_r
    for h in hyps[:5]:  # rigid
        R = h.T_world_obj[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_undetected_objects_get_no_hypotheses(lib, gt):
    frame = synthetic_frame(
        lib, gt, T_world_cam=T_WC, rng=3, k=4, stride=8, detect=["block_1", "drill_1"]
    )
    assert [h.class_name for h in frame.hypotheses] == ["block"] * 4 + ["drill"] * 4
    assert all(h.instance_id is None for h in frame.hypotheses)
    assert np.any(frame.labels == 0)  # the undetected cube is still in the cloud
    with pytest.raises(ValueError, match="not in the ground truth"):
        synthetic_frame(lib, gt, T_world_cam=T_WC, rng=0, stride=8, detect=["nope"])


def test_same_seed_same_frame(lib, gt):
    a = synthetic_frame(lib, gt, T_world_cam=T_WC, rng=np.random.default_rng(5), stride=4)
    b = synthetic_frame(lib, gt, T_world_cam=T_WC, rng=np.random.default_rng(5), stride=4)
    c = synthetic_frame(lib, gt, T_world_cam=T_WC, rng=np.random.default_rng(6), stride=4)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.labels, b.labels)
    for ha, hb in zip(a.hypotheses, b.hypotheses, strict=True):
        np.testing.assert_array_equal(ha.T_world_obj, hb.T_world_obj)
    assert not np.array_equal(a.hypotheses[0].T_world_obj, c.hypotheses[0].T_world_obj)


def test_segments_hold_each_objects_points(lib, gt):
    frame = synthetic_frame(
        lib, gt, T_world_cam=T_WC, rng=0, stride=4, give_segments=True, stamp=2.5
    )
    assert frame.stamp == 2.5
    assert list(frame.segments) == list(gt)
    for i, iid in enumerate(gt):
        np.testing.assert_array_equal(frame.segments[iid], frame.points[frame.labels == i])


def test_perturb_pose_zero_noise_is_identity():
    T = _pose(0.1, 0.2, 0.3, 40.0)
    np.testing.assert_allclose(perturb_pose(T, np.random.default_rng(0), 0.0, 0.0), T)


def test_visible_fractions(lib):
    # seen from the side, the second cube hides behind the first
    T_wc = look_at([-0.5, 0.0, EDGE / 2], [0.0, 0.0, EDGE / 2])
    scene = {
        "front": ("cube", _pose(0.0, 0.0, EDGE / 2)),
        "back": ("cube", _pose(0.1, EDGE / 2, EDGE / 2)),
        "away": ("cube", _pose(0.05, -0.15, EDGE / 2)),
    }
    frac = visible_fractions(lib, scene, T_world_cam=T_wc, camera=CAM, stride=4)
    assert frac["front"] == 1.0 and frac["away"] == 1.0
    assert 0.2 < frac["back"] < 0.8
