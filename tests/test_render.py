"""Ray-cast depth rendering, the camera model and the depth noise model (ssp.sim.render)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.geometry import invert, make_pose, transform_points
from ssp.library.builtin import builtin_specs
from ssp.sim.render import (
    NO_HIT,
    TABLE,
    Camera,
    add_depth_noise,
    cloud,
    look_at,
    render,
)

EDGE = 0.0508  # built-in cube edge, m
SMALL = Camera(101, 101, 200.0, 200.0, 50.0, 50.0)  # principal point on pixel (50, 50)


@pytest.fixture(scope="module")
def lib() -> dict:
    """The built-in models' specs by name: the same meshes as ``ObjectLibrary.builtin()``
    without building the models (rendering needs only ``.mesh``; saves ~1 s)."""
    return {spec.name: spec for spec in builtin_specs()}


def _on_table(x=0.0, y=0.0, yaw_deg=0.0, half_height=EDGE / 2) -> np.ndarray:
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return make_pose(R, [x, y, half_height])


def _box_surface_distance(points_obj: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Signed distance-like residual of points near an axis-aligned box surface (0 on it)."""
    return np.max(np.abs(points_obj) - half, axis=1)


# ------------------------------------------------------------------------------------------
# camera


def test_default_camera_and_rays():
    cam = Camera.default()
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (
        640,
        480,
        554.25,
        554.25,
        320.5,
        240.5,
    )
    rays = SMALL.rays()
    assert rays.shape == (101 * 101, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    np.testing.assert_allclose(rays[50 * 101 + 50], [0.0, 0.0, 1.0])  # row-major, centre
    # pixel (u=100, v=50) looks to the right (+x), pixel (u=50, v=0) up (-y)
    assert rays[50 * 101 + 100][0] > 0 and rays[50][1] < 0


def test_project_inverts_backproject():
    cam = Camera(40, 30, 50.0, 60.0, 19.5, 14.5)
    depth = np.random.default_rng(0).uniform(0.5, 2.0, cam.shape)
    pts = cam.backproject(depth).reshape(-1, 3)
    uv = cam.project(pts)
    v, u = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(uv, np.column_stack([u.ravel(), v.ravel()]), atol=1e-9)
    assert np.all(np.isnan(cam.project(np.array([[0.0, 0.0, -1.0]]))))


def test_subsample_samples_every_nth_pixel():
    cam = Camera.default()
    sub = cam.subsample(3)
    assert sub.shape == (160, 214)
    full = cam.rays().reshape(480, 640, 3)
    np.testing.assert_allclose(sub.rays().reshape(160, 214, 3), full[::3, ::3], atol=1e-12)


def test_look_at_axes():
    T = look_at([1.0, 0.0, 0.5], [0.0, 0.0, 0.5])  # horizontal view along -x
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [-1.0, 0.0, 0.0], atol=1e-12)  # z toward target
    np.testing.assert_allclose(R[:, 1], [0.0, 0.0, -1.0], atol=1e-12)  # y down
    np.testing.assert_allclose(T[:3, 3], [1.0, 0.0, 0.5])
    down = look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])  # degenerate with up = z
    np.testing.assert_allclose(down[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


# ------------------------------------------------------------------------------------------
# rendering


def test_cube_top_depth_from_above(lib):
    h = 1.0
    T_wc = look_at([0.0, 0.0, h], [0.0, 0.0, 0.0])
    res = render([("c", lib["cube"].mesh, _on_table())], T_wc, SMALL)
    assert res.depth.shape == res.instance.shape == (101, 101)
    assert res.instance[50, 50] == 0
    assert abs(res.depth[50, 50] - (h - EDGE)) < 1e-6
    # seen from straight above, only the top face of the centred cube is visible
    assert np.all(np.abs(res.depth[res.instance == 0] - (h - EDGE)) < 1e-9)
    # everything else in view is the table at depth h
    assert np.all(res.instance != NO_HIT)
    assert np.all(np.abs(res.depth[res.instance == TABLE] - h) < 1e-9)


def test_instance_area_matches_projected_square(lib):
    h = 0.5
    cam = Camera.default()
    T_wc = look_at([0.0, 0.0, h], [0.0, 0.0, 0.0])
    res = render([("c", lib["cube"].mesh, _on_table(yaw_deg=30.0))], T_wc, cam)
    side_px = cam.fx * EDGE / (h - EDGE)
    area = res.pixel_counts()["c"]
    assert area == pytest.approx(side_px**2, rel=0.02)
    # stride 2: a quarter of the pixels
    res2 = render([("c", lib["cube"].mesh, _on_table(yaw_deg=30.0))], T_wc, cam, stride=2)
    assert res2.depth.shape == (240, 320)
    assert res2.pixel_counts()["c"] == pytest.approx(side_px**2 / 4, rel=0.04)


def test_table_points_lie_on_z0_and_table_is_finite():
    T_wc = look_at([0.6, -0.4, 0.7], [0.0, 0.0, 0.0])
    res = render([], T_wc, Camera.default(), stride=4, table_size=0.6)
    table = res.instance == TABLE
    assert table.sum() > 100
    pts = res.points_world(mask=table)
    assert np.max(np.abs(pts[:, 2])) < 1e-9
    assert np.max(np.abs(pts[:, :2])) <= 0.3 + 1e-9
    # beyond the 0.6 m table there is nothing: depth 0, no points
    nothing = res.instance == NO_HIT
    assert nothing.any() and np.all(res.depth[nothing] == 0)
    assert len(res.points_world()) == int((res.depth > 0).sum())
    no_table = render([], T_wc, Camera.default(), stride=4, table=False)
    assert np.all(no_table.instance == NO_HIT) and np.all(no_table.depth == 0)


def test_occlusion(lib):
    cube = lib["cube"].mesh
    # camera at cube-centre height, looking along +x at cube "a"; "b" is right behind it
    T_wc = look_at([-0.5, 0.0, EDGE / 2], [0.0, 0.0, EDGE / 2])
    front, behind = ("a", cube, _on_table(0.0)), ("b", cube, _on_table(0.15))
    alone = render([behind], T_wc, Camera.default(), stride=2).pixel_counts()["b"]
    assert alone > 100
    both = render([front, behind], T_wc, Camera.default(), stride=2).pixel_counts()
    assert both["b"] == 0 and both["a"] > alone  # the nearer cube looks bigger
    # shifted sideways by half an edge: "b" is partly visible
    half = render(
        [("a", cube, _on_table(0.0, EDGE / 2)), behind], T_wc, Camera.default(), stride=2
    ).pixel_counts()["b"]
    assert 0 < half < alone


def test_cloud_points_lie_on_cube_surface(lib):
    T_wo = make_pose(
        Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix(), [0.05, -0.02, 0.06]
    )
    T_wc = look_at([0.4, 0.3, 0.5], [0.0, 0.0, 0.0])
    res = render([("c", lib["cube"].mesh, T_wo)], T_wc, Camera.default(), stride=2)
    pts, labels = cloud(res, T_wc, Camera.default())
    assert len(pts) == len(labels) == int((res.depth > 0).sum())
    mine = pts[labels == 0]
    assert len(mine) > 200
    local = transform_points(invert(T_wo), mine)
    assert np.max(np.abs(_box_surface_distance(local, np.full(3, EDGE / 2)))) < 1e-6
    # seen obliquely, points lie on more than one face: (axis, sign) of the face per point
    axis = np.argmax(np.abs(local), axis=1)
    face = axis * 2 + (local[np.arange(len(local)), axis] > 0)
    assert len(np.unique(face)) >= 2
    with pytest.raises(ValueError):
        cloud(res, look_at([1.0, 0.0, 1.0], [0.0, 0.0, 0.0]))


def test_cloud_points_lie_on_concave_mesh(lib):
    model = lib["claw_hammer"]
    T_wo = _on_table(0.0, 0.0, 40.0, half_height=model.mesh.extents[2] / 2)
    T_wc = look_at([0.3, -0.3, 0.45], [0.0, 0.0, 0.0])
    res = render([("h", model.mesh, T_wo)], T_wc, Camera.default(), stride=3)
    mine = res.points_world(mask=res.mask("h"))
    assert len(mine) > 200
    local = transform_points(invert(T_wo), mine)
    _, dist, _ = trimesh.proximity.closest_point(model.mesh, local)
    assert np.max(dist) < 1e-6


def test_projected_object_centre_sees_the_object(lib):
    T_wo = _on_table(0.1, 0.05, 10.0)
    T_wc = look_at([0.5, 0.4, 0.4], [0.0, 0.0, 0.0])
    res = render([("x", lib["cube"].mesh, T_wo)], T_wc, Camera.default(), stride=2)
    top = transform_points(invert(T_wc), np.array([[0.1, 0.05, EDGE]]))  # top-face centre
    u, v = np.round(res.camera.project(top)[0]).astype(int)
    assert res.instance[v, u] == 0


def test_render_rejects_duplicate_ids(lib):
    cube = lib["cube"].mesh
    with pytest.raises(ValueError, match="unique"):
        render([("a", cube, np.eye(4)), ("a", cube, np.eye(4))], np.eye(4), SMALL)


# ------------------------------------------------------------------------------------------
# noise


def _plane_depth(z: float) -> np.ndarray:
    T_wc = look_at([0.0, 0.0, z], [0.0, 0.0, 0.0])
    res = render([], T_wc, Camera.default(), stride=4, table_size=4.0 * z)
    assert np.all(res.instance == TABLE)
    return res.depth


@pytest.mark.parametrize("z", [1.0, 2.0])
def test_noise_std_matches_kinect_model(z):
    depth = _plane_depth(z)
    np.testing.assert_allclose(depth, z, atol=1e-9)
    noisy = add_depth_noise(depth, np.random.default_rng(1), dropout_edges=False)
    expected = 0.0012 + 0.0019 * (z - 0.4) ** 2
    err = noisy - depth
    assert np.std(err) == pytest.approx(expected, rel=0.1)
    assert abs(np.mean(err)) < 6 * expected / np.sqrt(err.size)  # unbiased


def test_noise_is_deterministic_with_a_seed(lib):
    T_wc = look_at([0.4, 0.0, 0.5], [0.0, 0.0, 0.0])
    depth = render([("c", lib["cube"].mesh, _on_table())], T_wc, SMALL).depth
    a = add_depth_noise(depth, np.random.default_rng(7), quantum=0.003)
    b = add_depth_noise(depth, np.random.default_rng(7), quantum=0.003)
    c = add_depth_noise(depth, np.random.default_rng(8), quantum=0.003)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_quantisation_and_edge_dropout(lib):
    T_wc = look_at([0.0, 0.0, 0.6], [0.0, 0.0, 0.0])
    res = render([("c", lib["cube"].mesh, _on_table())], T_wc, Camera.default(), stride=2)
    q = 0.003
    noisy = add_depth_noise(res.depth, np.random.default_rng(3), quantum=q, edge_dropout=0.5)
    valid = noisy > 0
    steps = 1.0 / (noisy[valid] * q)  # 1/z on a grid of step q
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    # the cube's silhouette (a 50 mm depth jump) loses about half its pixels, nothing else does
    inside = res.instance == 0
    edge = np.zeros_like(inside)
    edge[1:, :] |= inside[1:, :] != inside[:-1, :]
    edge[:-1, :] |= inside[1:, :] != inside[:-1, :]
    edge[:, 1:] |= inside[:, 1:] != inside[:, :-1]
    edge[:, :-1] |= inside[:, 1:] != inside[:, :-1]
    assert np.all(valid[~edge])
    assert 0.3 < 1.0 - valid[edge].mean() < 0.7
    clean = add_depth_noise(res.depth, np.random.default_rng(3), dropout_edges=False)
    assert np.all(clean > 0)
