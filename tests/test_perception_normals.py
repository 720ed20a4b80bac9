"""Normals by PCA of nearest neighbours (ssp.perception.normals)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.errors import PerceptionError
from ssp.geometry import invert, make_pose, transform_points
from ssp.perception.depth import cloud_from_depth
from ssp.perception.normals import estimate_normals
from ssp.sim.render import add_depth_noise, look_at, render

EDGE = 0.0508
HALF = EDGE / 2


@pytest.fixture(scope="module")
def cube_view(cube_model):
    """A cube (yawed 30 deg) seen from 0.7 m: render, camera pose and cube pose."""
    T_wo = make_pose(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [0, 0, HALF])
    T_wc = look_at([0.0, -0.5, 0.5], [0.0, 0.0, 0.0])
    return render([("c", cube_model.mesh, T_wo)], T_wc), T_wc, T_wo


def _face_errors_deg(cube_view, depth, k):
    """Angle errors (deg) of the normals of the top and front faces' interiors."""
    r, T_wc, T_wo = cube_view
    cloud = cloud_from_depth(depth, r.camera, mask=r.instance, T_world_cam=T_wc)
    pts = cloud.points[cloud.labels == 0]
    normals = estimate_normals(pts, k=k, viewpoint=T_wc[:3, 3])
    p_obj = transform_points(invert(T_wo), pts)
    n_obj = normals @ T_wo[:3, :3]
    inner = HALF - 0.008
    top = (p_obj[:, 2] > HALF - 0.004) & (np.abs(p_obj[:, :2]) < inner).all(axis=1)
    front = (p_obj[:, 1] < -HALF + 0.004) & (np.abs(p_obj[:, [0, 2]]) < inner).all(axis=1)
    assert top.sum() > 300 and front.sum() > 300
    err_top = np.degrees(np.arccos(np.clip(n_obj[top, 2], -1, 1)))
    err_front = np.degrees(np.arccos(np.clip(-n_obj[front, 1], -1, 1)))
    return np.concatenate([err_top, err_front])


def test_rendered_cube_faces(cube_view):
    errors = _face_errors_deg(cube_view, cube_view[0].depth, k=16)
    assert errors.max() < 5.0


def test_rendered_cube_faces_with_noise(cube_view):
    noisy = add_depth_noise(cube_view[0].depth, np.random.default_rng(0))
    errors = _face_errors_deg(cube_view, noisy, k=64)  # ~2 mm noise: a wider neighbourhood
    assert np.median(errors) < 5.0
    assert np.percentile(errors, 90) < 10.0


def test_oriented_toward_viewpoint(cube_view):
    r, T_wc, _ = cube_view
    pts = r.points_world()[::29]
    normals = estimate_normals(pts, viewpoint=T_wc[:3, 3])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert (np.einsum("ij,ij->i", normals, T_wc[:3, 3] - pts) >= 0).all()


def test_away_from_centroid_without_viewpoint():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    pts = np.asarray(sphere.vertices) + [0.3, -0.2, 0.1]
    normals = estimate_normals(pts, k=12)
    radial = (pts - [0.3, -0.2, 0.1]) / 0.05
    assert np.einsum("ij,ij->i", normals, radial).min() > np.cos(np.radians(5))


def test_few_points():
    assert estimate_normals(np.zeros((0, 3))).shape == (0, 3)
    square = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1.0], [0.5, 0.5, 1]])
    normals = estimate_normals(square, k=16, viewpoint=[0, 0, 0])  # N < k: all points used
    np.testing.assert_allclose(normals, np.tile([0, 0, -1.0], (5, 1)), atol=1e-12)
    for n in (1, 2):
        out = estimate_normals(np.random.default_rng(0).random((n, 3)))
        assert out.shape == (n, 3)
        np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0)


def test_bad_input():
    with pytest.raises(PerceptionError, match=r"\(N, 3\)"):
        estimate_normals(np.zeros((4, 2)))
    with pytest.raises(PerceptionError, match="NaN"):
        estimate_normals(np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]]))
