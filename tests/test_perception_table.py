"""Support-plane detection and the world frame it defines (ssp.perception.table)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.errors import PerceptionError, TableNotFoundError
from ssp.geometry import invert, make_pose, transform_points
from ssp.perception.depth import cloud_from_depth
from ssp.perception.table import Plane, T_world_cam_from_plane, fit_plane, table_frame
from ssp.sim.render import TABLE, add_depth_noise, look_at, render

EDGE = 0.0508
#: 1 m from the table centre, 45 deg down, looking along world +y.
T_TRUE = look_at([0.0, -math.sqrt(0.5), math.sqrt(0.5)], [0.0, 0.0, 0.0])
UP_CAM = T_TRUE[:3, :3].T @ [0.0, 0.0, 1.0]  # true table normal in the camera frame


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, abs(c))))


def _noisy_cloud(objects, *, table: bool = True, stride: int = 1, seed: int = 0):
    """Camera-frame cloud and labels (object index, TABLE) of a noisy render."""
    r = render(objects, T_TRUE, table=table, stride=stride)
    depth = add_depth_noise(r.depth, np.random.default_rng(seed))
    return cloud_from_depth(depth, r.camera, mask=r.instance)


@pytest.fixture(scope="module")
def two_cubes(cube_model):
    yaw = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    objects = [
        ("a", cube_model.mesh, make_pose(None, [0.0, 0.0, EDGE / 2])),
        ("b", cube_model.mesh, make_pose(yaw, [0.12, 0.05, EDGE / 2])),
    ]
    return _noisy_cloud(objects)


def test_table_frame_matches_truth(two_cubes):
    T_est, plane = table_frame(two_cubes.points)
    assert _angle_deg(plane.normal, UP_CAM) < 1.0
    assert plane.normal @ UP_CAM > 0  # oriented toward the camera
    # world z axis (in camera coordinates) and camera height
    assert _angle_deg(T_est[2, :3], T_TRUE[2, :3]) < 1.0
    assert abs(T_est[2, 3] - T_TRUE[2, 3]) < 0.002
    # the two frames differ only by a rotation about z and an in-plane shift
    T_rel = T_est @ invert(T_TRUE)
    assert _angle_deg(T_rel[:3, 2], [0, 0, 1]) < 1.0
    assert abs(T_rel[2, 3]) < 0.002
    # world x is the viewing direction projected onto the table
    view = T_est[:3, :3] @ [0.0, 0.0, 1.0]
    assert abs(view[1]) < 1e-9 and view[0] > 0.5
    np.testing.assert_allclose(T_est[:3, :3] @ T_est[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.linalg.det(T_est[:3, :3]) == pytest.approx(1.0)
    # objects stand on the table: (almost) nothing below it
    z = transform_points(T_est, two_cubes.points)[:, 2]
    on_objects = two_cubes.labels >= 0
    assert np.percentile(z[on_objects], 1) > -0.003
    assert z[on_objects].max() == pytest.approx(EDGE, abs=0.006)


def test_inliers_are_the_table(two_cubes):
    plane = fit_plane(two_cubes.points)
    table = two_cubes.labels == TABLE
    assert plane.inliers.shape == table.shape
    assert plane.inliers[table].mean() > 0.95
    assert plane.inliers[~table].mean() < 0.2  # only the cubes' bottom rims
    assert plane.n_inliers == int(plane.inliers.sum())
    d = plane.signed_distance(two_cubes.points[plane.inliers])
    assert np.abs(d).max() < 0.006


def test_deterministic_for_a_seed(two_cubes):
    a = fit_plane(two_cubes.points, seed=3)
    b = fit_plane(two_cubes.points, seed=3)
    np.testing.assert_array_equal(a.normal, b.normal)
    assert a.offset == b.offset
    np.testing.assert_array_equal(a.inliers, b.inliers)
    c = fit_plane(two_cubes.points, seed=4)
    assert _angle_deg(a.normal, c.normal) < 0.05
    assert abs(a.offset - c.offset) < 1e-4


def test_non_finite_points_are_never_inliers(two_cubes):
    pts = two_cubes.points.copy()
    pts[::7] = np.nan
    plane = fit_plane(pts)
    assert not plane.inliers[::7].any()
    assert _angle_deg(plane.normal, UP_CAM) < 1.0


def test_only_an_object_raises():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    cloud = _noisy_cloud([("s", sphere, make_pose(None, [0, 0, 0.05]))], table=False)
    with pytest.raises(TableNotFoundError, match=r"inliers.*needs at least 500"):
        fit_plane(cloud.points)


def test_single_cube_without_table_raises(cube_model):
    """A cube face is a plane with enough inliers, but far too small for a table."""
    cloud = _noisy_cloud([("c", cube_model.mesh, make_pose(None, [0, 0, EDGE / 2]))], table=False)
    with pytest.raises(TableNotFoundError, match="wide"):
        fit_plane(cloud.points)


def test_too_few_points_raises():
    pts = np.random.default_rng(0).random((100, 3))
    with pytest.raises(TableNotFoundError, match="too few points"):
        fit_plane(pts)
    with pytest.raises(PerceptionError, match=r"\(N, 3\)"):
        fit_plane(np.zeros((10, 2)))


def test_wall_rejected_with_up_hint():
    """A wall with more points than the visible table wins without a hint, not with one."""
    wall = trimesh.creation.box(extents=(2.0, 0.02, 1.5))
    cloud = _noisy_cloud([("wall", wall, make_pose(None, [0, 0, 0.75]))], stride=2)
    assert (cloud.labels == 0).sum() > (cloud.labels == TABLE).sum()
    assert _angle_deg(fit_plane(cloud.points).normal, UP_CAM) > 80  # documented limitation
    rough = Rotation.from_rotvec([0.3, 0.0, 0.0]).apply(UP_CAM)  # ~17 deg off
    plane = fit_plane(cloud.points, up_hint=rough)
    assert _angle_deg(plane.normal, UP_CAM) < 1.0
    assert plane.normal @ rough > 0  # oriented along the hint
    with pytest.raises(TableNotFoundError, match="up_hint"):
        fit_plane(cloud.points, up_hint=[1.0, 0.0, 0.0], max_tilt_deg=10)  # parallel to both


def test_large_box_top_is_not_the_support():
    """The top of a big box has more inliers than the table around it, but stands on it."""
    box = trimesh.creation.box(extents=(0.8, 0.8, 0.1))
    cloud = _noisy_cloud([("box", box, make_pose(None, [0, 0, 0.05]))], stride=2)
    T_est, plane = table_frame(cloud.points)
    assert _angle_deg(plane.normal, UP_CAM) < 1.0
    assert abs(T_est[2, 3] - T_TRUE[2, 3]) < 0.002  # the table, not the box top 0.1 m higher
    assert plane.inliers[cloud.labels == TABLE].mean() > 0.95


def test_straight_down_uses_camera_x():
    """Camera 1 m above a plane, looking straight down: world x is the camera's x axis."""
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.5, 0.5, 4000), rng.uniform(-0.4, 0.4, 4000)])
    pts = np.column_stack([pts, 1.0 + rng.normal(0, 0.001, len(pts))])
    T, plane = table_frame(pts)
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=0.01)
    assert plane.offset == pytest.approx(1.0, abs=0.002)
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=0.01)  # camera x -> world x
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=0.01)  # looks down
    assert T[2, 3] == pytest.approx(1.0, abs=0.002)
    np.testing.assert_allclose(T[:2, 3], -pts[:, :2].mean(axis=0) @ np.diag([1, -1]), atol=0.01)


def test_frame_from_a_plane_facing_away():
    """The normal is flipped toward the camera whatever the plane's sign convention."""
    pts = np.array([[x, y, 2.0] for x in (-1, 0, 1) for y in (-1, 0, 1)], dtype=float)
    plane = Plane(np.array([0.0, 0.0, 1.0]), -2.0, np.ones(len(pts), dtype=bool))
    T = T_world_cam_from_plane(plane, pts)
    assert T[2, 3] == pytest.approx(2.0)
    with pytest.raises(PerceptionError, match="shape"):
        T_world_cam_from_plane(plane, pts[:-1])
