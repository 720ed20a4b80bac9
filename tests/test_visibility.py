"""Visibility of an object at a pose, against synthetic scene clouds (no renderer library).

The scene clouds come from a tiny pinhole ray caster (one depth per pixel, like a depth camera)
over a table plane z = 0 and axis-aligned boxes, seen from a camera at (0, -0.6, 0.5) looking at
the origin. Layout (m):

* box A, extents (0.08, 0.06, 0.10), centre (0, -0.05, 0.05): in plain view;
* occluder, extents (0.16, 0.04, 0.25), centre (-0.2, -0.1, 0.125): a tall board ...
* hidden box, extents 0.06, centre (-0.2, 0.05, 0.03): ... completely hiding this box;
* free spot (0.2, 0.1): bare table, in view.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ssp import visibility as vis
from ssp.geometry import make_pose
from ssp.visibility import (
    FALLBACK_ANGULAR_RESOLUTION,
    CameraView,
    VisibilityReport,
)

EYE = np.array([0.0, -0.6, 0.5])
FOCAL = 300.0  # px
WIDTH, HEIGHT = 320, 240  # px
TABLE_HALF = 0.5  # m, the table spans |x|, |y| <= TABLE_HALF

BOX_A = ((0.08, 0.06, 0.10), (0.0, -0.05, 0.05))
OCCLUDER = ((0.16, 0.04, 0.25), (-0.2, -0.1, 0.125))
HIDDEN = ((0.06, 0.06, 0.06), (-0.2, 0.05, 0.03))
FREE_SPOT = (0.2, 0.1)


def look_at(eye, target) -> np.ndarray:
    """T_world_cam of an OpenCV camera at ``eye`` looking at ``target`` (world up = +z)."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.column_stack([x, y, z]), eye)


def render(T_world_cam, boxes, noise: float = 0.0) -> np.ndarray:
    """World points (n, 3) seen by a pinhole camera: the nearest hit per pixel, or nothing.

    ``boxes``: ((extents), (centre)) axis-aligned boxes; the table is the square z = 0,
    |x|, |y| <= TABLE_HALF. ``noise``: std (m) of Gaussian depth noise (seeded).
    """
    u, v = np.meshgrid(np.arange(WIDTH) - (WIDTH - 1) / 2, np.arange(HEIGHT) - (HEIGHT - 1) / 2)
    d_cam = np.column_stack([u.ravel() / FOCAL, v.ravel() / FOCAL, np.ones(u.size)])
    d = d_cam @ T_world_cam[:3, :3].T  # camera z component 1: the ray parameter is the depth
    o = T_world_cam[:3, 3]
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = -o[2] / d[:, 2]
        hit = o + t_table[:, None] * d
        ok = (t_table > 0) & (np.abs(hit[:, 0]) <= TABLE_HALF) & (np.abs(hit[:, 1]) <= TABLE_HALF)
        t[ok] = t_table[ok]
        for extents, centre in boxes:
            lo = np.asarray(centre) - np.asarray(extents) / 2
            hi = np.asarray(centre) + np.asarray(extents) / 2
            t1, t2 = (lo - o) / d, (hi - o) / d
            t_near = np.minimum(t1, t2).max(axis=1)
            t_far = np.maximum(t1, t2).min(axis=1)
            ok = (t_far >= t_near) & (t_near > 0)
            t[ok] = np.minimum(t[ok], t_near[ok])
    keep = np.isfinite(t)
    t = t[keep]
    if noise:
        t = t + np.random.default_rng(0).normal(0.0, noise, size=t.shape)
    return o + t[:, None] * d[keep]


def box_samples(extents, n: int = 600):
    """(points, normals) (n, 3) on the surface of a box centred at its origin."""
    mesh = trimesh.creation.box(extents=extents)
    pts, faces = trimesh.sample.sample_surface(mesh, n, seed=0)
    return np.asarray(pts), np.asarray(mesh.face_normals[faces])


def at(centre) -> np.ndarray:
    return make_pose(t=np.asarray(centre, dtype=float))


def assert_consistent(rep: VisibilityReport) -> None:
    fractions = (rep.seen, rep.occluded, rep.seen_through, rep.unknown)
    assert all(0.0 <= f <= 1.0 for f in fractions)
    assert sum(fractions) == pytest.approx(1.0 if rep.n_facing else 0.0)


@pytest.fixture(scope="module")
def T_cam() -> np.ndarray:
    return look_at(EYE, (0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def cloud(T_cam) -> np.ndarray:
    return render(T_cam, [BOX_A, OCCLUDER, HIDDEN], noise=0.001)


@pytest.fixture(scope="module")
def view(cloud, T_cam) -> CameraView:
    return CameraView(cloud, T_cam)


def test_look_at_is_opencv(T_cam):
    R = T_cam[:3, :3]
    assert np.allclose(R[:, 0], [1, 0, 0])  # x right
    assert R[2, 1] < 0  # y down (world z)
    assert np.allclose(R[:, 2], -EYE / np.linalg.norm(EYE))  # z toward the target


def test_estimated_resolution_is_about_one_and_a_half_pixels(view, cloud, T_cam):
    # The cloud is a pixel grid: nearest rays are 1/f apart.
    assert view.angular_resolution == pytest.approx(1.5 / FOCAL, rel=0.02)
    doubled = CameraView(np.vstack([cloud, cloud]), T_cam)  # duplicates do not shrink it
    assert doubled.angular_resolution == pytest.approx(view.angular_resolution)
    assert CameraView(cloud[:1], T_cam).angular_resolution == FALLBACK_ANGULAR_RESOLUTION
    assert CameraView(cloud, T_cam, angular_resolution=0.01).angular_resolution == 0.01


def test_object_on_observed_surface_is_seen(view):
    pts, nrm = box_samples(BOX_A[0])
    rep = view.report_pose(pts, nrm, at(BOX_A[1]))
    assert_consistent(rep)
    assert rep.seen > 0.8
    assert rep.occluded < 0.1 and rep.seen_through < 0.1 and rep.unknown == 0.0


def test_object_behind_another_is_occluded(view):
    pts, nrm = box_samples(HIDDEN[0])
    rep = view.report_pose(pts, nrm, at(HIDDEN[1]))
    assert_consistent(rep)
    assert rep.occluded > 0.8
    assert rep.seen < 0.05 and rep.seen_through < 0.05


def test_object_where_the_table_is_seen_is_seen_through(view):
    pts, nrm = box_samples((0.06, 0.06, 0.06))
    rep = view.report_pose(pts, nrm, at((*FREE_SPOT, 0.03)))  # resting on the bare table
    assert_consistent(rep)
    assert rep.seen_through > 0.8
    assert rep.occluded < 0.05
    # Same box floating above the table: all of its facing samples look through to the table.
    rep_up = view.report_pose(pts, nrm, at((*FREE_SPOT, 0.1)))
    assert rep_up.seen_through > 0.95


def test_object_outside_the_view_is_unknown(view):
    pts, nrm = box_samples((0.06, 0.06, 0.06))
    rep = view.report_pose(pts, nrm, at((1.5, 0.0, 0.03)))  # far right of the image
    assert_consistent(rep)
    assert rep.n_facing > 0
    assert rep.unknown > 0.95


def test_object_behind_the_camera_has_no_facing_samples(view):
    pts, nrm = box_samples((0.06, 0.06, 0.06))
    rep = view.report_pose(pts, nrm, at(2 * EYE))  # beyond the camera, away from the scene
    assert rep == VisibilityReport(0, 0.0, 0.0, 0.0, 0.0)


def test_empty_or_unusable_cloud_gives_unknown(T_cam):
    pts, nrm = box_samples(BOX_A[0])
    for scene in (np.empty((0, 3)), np.array([[0.0, -2.0, 1.0]])):  # none / behind the camera
        view = CameraView(scene, T_cam)
        assert view.n_points == 0
        rep = view.report_pose(pts, nrm, at(BOX_A[1]))
        assert rep.n_facing > 0 and rep.unknown == 1.0
        assert_consistent(rep)


def test_back_facing_samples_are_not_counted(view):
    pts, nrm = box_samples(BOX_A[0])
    # Box A sits at x = 0 below and in front of the camera: only its -y and +z faces face it.
    front_or_top = np.isclose(nrm @ [0, -1, 0], 1.0) | np.isclose(nrm @ [0, 0, 1], 1.0)
    rep = view.report_pose(pts, nrm, at(BOX_A[1]))
    assert rep.n_facing == int(front_or_top.sum())
    assert 0 < rep.n_facing < len(pts)

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    s_pts, s_nrm = np.asarray(sphere.vertices), np.asarray(sphere.vertex_normals)
    centre = at((*FREE_SPOT, 0.05))
    n = view.report_pose(s_pts, s_nrm, centre).n_facing
    assert 0.4 * len(s_pts) < n < 0.55 * len(s_pts)  # a bit less than half: (1 - r/d) / 2
    n_flipped = view.report_pose(s_pts, -s_nrm, centre).n_facing
    assert n + n_flipped <= len(s_pts)
    assert n_flipped > n  # inward normals: the far side "faces" the camera


def _axis_view(points, **kw) -> CameraView:
    """Camera at the world origin with the world axes (world = camera frame)."""
    return CameraView(np.asarray(points, dtype=float), np.eye(4), **kw)


def test_nearest_ray_in_angle_is_used_not_the_nearest_depth():
    # On the sample's ray: a surface at 1.0 m; 0.4 px away in angle: something at 0.5 m.
    view = _axis_view([[0.0, 0.0, 1.0], [0.0008 * 0.5, 0.0, 0.5]], angular_resolution=0.002)
    normal = [[0.0, 0.0, -1.0]]
    assert view.report([[0.0, 0.0, 1.0]], normal).seen == 1.0
    assert view.report([[0.0007, 0.0, 1.0]], normal).occluded == 1.0  # nearer to the 2nd ray
    assert view.report([[-0.0025, 0.0, 1.0]], normal).unknown == 1.0  # beyond the radius


def test_depth_tolerance_decides_between_classes():
    view = _axis_view([[0.0, 0.0, 1.0]], angular_resolution=0.002, depth_tolerance=0.005)
    strict = _axis_view([[0.0, 0.0, 1.0]], angular_resolution=0.002, depth_tolerance=0.002)
    normal = [[0.0, 0.0, -1.0]]
    assert view.report([[0.0, 0.0, 1.004]], normal).seen == 1.0
    assert strict.report([[0.0, 0.0, 1.004]], normal).occluded == 1.0
    assert view.report([[0.0, 0.0, 0.996]], normal).seen == 1.0
    assert strict.report([[0.0, 0.0, 0.996]], normal).seen_through == 1.0
    # Depth is compared along the optical axis: an off-axis sample on the same ray agrees.
    off_axis = _axis_view([[0.3, 0.0, 1.0]], angular_resolution=0.002, depth_tolerance=0.001)
    assert off_axis.report([[0.6, 0.0, 2.0]], normal).occluded == 1.0
    assert off_axis.report([[0.15, 0.0, 0.5]], normal).seen_through == 1.0
    assert off_axis.report([[0.3003, 0.0, 1.001]], normal).seen == 1.0


def test_fractions_over_mixed_samples():
    view = _axis_view([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.2, 0.0, 1.0]], angular_resolution=0.01)
    # seen, occluded (behind the observed point), seen through (in front of it), unknown
    pts = [[0.0, 0, 1.0], [0.15, 0, 1.5], [0.1, 0, 0.5], [0.3, 0, 1.0], [0.0, 0, 1.0]]
    nrm = [[0, 0, -1]] * 4 + [[0, 0, 1]]  # the last one faces away
    assert view.report(pts, nrm) == VisibilityReport(4, 0.25, 0.25, 0.25, 0.25)


@pytest.mark.parametrize(
    "points, T, kwargs, match",
    [
        (np.zeros((4, 2)), np.eye(4), {}, r"points_world: expected shape \(n, 3\)"),
        (np.zeros(3), np.eye(4), {}, r"points_world: expected shape"),
        (np.array([[0.0, 0.0, np.nan]]), np.eye(4), {}, "NaN or infinite"),
        ([["a", "b", "c"]], np.eye(4), {}, "not a numeric"),
        (np.zeros((1, 3)), np.eye(3), {}, r"T_world_cam: expected shape \(4, 4\)"),
        (np.zeros((1, 3)), 2 * np.eye(4), {}, "T_world_cam"),
        (np.zeros((1, 3)), np.diag([1.0, 1.0, -1.0, 1.0]), {}, "orthonormal"),
        (np.zeros((1, 3)), np.eye(4), {"depth_tolerance": -0.001}, "depth_tolerance"),
        (np.zeros((1, 3)), np.eye(4), {"depth_tolerance": np.inf}, "depth_tolerance"),
        (np.zeros((1, 3)), np.eye(4), {"angular_resolution": 0.0}, "angular_resolution"),
        (np.zeros((1, 3)), np.eye(4), {"angular_resolution": np.nan}, "angular_resolution"),
    ],
)
def test_constructor_validation(points, T, kwargs, match):
    with pytest.raises(ValueError, match=match):
        CameraView(points, T, **kwargs)


def test_report_validation():
    view = _axis_view([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="does not match"):
        view.report(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"normals_world: expected shape"):
        view.report(np.zeros((3, 3)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="points_world: contains NaN"):
        view.report(np.full((1, 3), np.inf), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="model_normals"):
        view.report_pose(np.zeros((3, 3)), np.zeros((2, 3)), np.eye(4))
    with pytest.raises(ValueError, match="T_world_obj"):
        view.report_pose(np.zeros((1, 3)), np.zeros((1, 3)), np.ones((4, 4)))
    # No samples at all is not an error.
    assert view.report(np.empty((0, 3)), np.empty((0, 3))).n_facing == 0


def test_report_pose_matches_report_on_transformed_samples(view):
    pts, nrm = box_samples(BOX_A[0])
    R = trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])[:3, :3]
    T = make_pose(R, BOX_A[1])
    direct = view.report(pts @ R.T + T[:3, 3], nrm @ R.T)
    assert view.report_pose(pts, nrm, T) == direct
    assert direct.n_facing > 0


def test_deterministic(cloud, T_cam):
    pts, nrm = box_samples((0.06, 0.06, 0.06))
    poses = [at(BOX_A[1]), at(HIDDEN[1]), at((*FREE_SPOT, 0.03)), at((1.5, 0.0, 0.03))]
    a, b = CameraView(cloud, T_cam), CameraView(cloud, T_cam)
    first = [a.report_pose(pts, nrm, T) for T in poses]
    assert [a.report_pose(pts, nrm, T) for T in poses] == first
    assert [b.report_pose(pts, nrm, T) for T in poses] == first
    # The order of the samples or of the scene points does not matter.
    order = np.random.default_rng(1).permutation(len(pts))
    assert [a.report_pose(pts[order], nrm[order], T) for T in poses] == first
    perm = np.random.default_rng(2).permutation(len(cloud))
    assert CameraView(cloud[perm], T_cam).angular_resolution == pytest.approx(a.angular_resolution)
    shuffled = CameraView(cloud[perm], T_cam, angular_resolution=a.angular_resolution)
    assert [shuffled.report_pose(pts, nrm, T) for T in poses] == first


def _union_samples(boxes, n: int = 2000):
    """(points, normals, spacing) on the surface of a union of disjoint boxes (one object)."""
    mesh = trimesh.util.concatenate(
        [trimesh.creation.box(extents=e, transform=at(c)) for e, c in boxes]
    )
    pts, faces = trimesh.sample.sample_surface_even(mesh, n, seed=0)
    return np.asarray(pts), np.asarray(mesh.face_normals[faces]), float(np.sqrt(mesh.area / n))


def test_an_objects_own_parts_hide_what_lies_behind_them(T_cam):
    """Issue 15, item 5: a concave object's facing samples behind its own other parts are not
    part of what the camera could see (they were scored as unexplained surface)."""
    front, back = ((0.10, 0.02, 0.10), (0.0, -0.1, 0.05)), ((0.10, 0.02, 0.10), (0.0, 0.0, 0.05))
    pts, nrm, spacing = _union_samples([front, back])
    view = CameraView(render(T_cam, [front, back], noise=0.001), T_cam)
    state = view.classify(pts, nrm, self_spacing=spacing)
    # the back plate's face towards the camera (-y) below z = 0.037 m (the front plate's top
    # edge as seen from the camera) is hidden by the front plate
    back_face = np.isclose(nrm @ [0, -1, 0], 1.0) & np.isclose(pts[:, 1], -0.01)
    low = back_face & (pts[:, 2] < 0.03)
    assert low.sum() > 20
    assert np.mean(state[low] == vis.SELF_HIDDEN) > 0.9
    # without the test they are classified against the front plate's points in front of them
    assert np.all(view.classify(pts, nrm)[low] != vis.SELF_HIDDEN)
    assert np.mean(view.classify(pts, nrm)[low] == vis.OCCLUDED) > 0.9
    # the front plate and the top of both are not hidden by anything
    seen_parts = (np.isclose(pts[:, 1], -0.11) & np.isclose(nrm @ [0, -1, 0], 1.0)) | np.isclose(
        nrm @ [0, 0, 1], 1.0
    )
    assert np.mean(state[seen_parts] == vis.SELF_HIDDEN) < 0.02


@pytest.mark.parametrize("eye", [EYE, (0.5, -0.1, 0.12), (0.02, 0.0, 0.6)])
def test_a_convex_object_never_hides_itself(eye):
    """A sphere and a box, seen from above and at grazing angles: no sample is self-hidden
    (neighbours on one smooth face are not occluders)."""
    T = look_at(eye, (0.0, 0.0, 0.05))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    sphere.apply_translation([0.0, 0.0, 0.05])
    box = trimesh.creation.box(extents=(0.12, 0.05, 0.08), transform=at((0, 0, 0.04)))
    for mesh in (sphere, box):
        pts, faces = trimesh.sample.sample_surface_even(mesh, 1000, seed=1)
        nrm = mesh.face_normals[faces]
        view = CameraView(render(T, [], noise=0.0), T)
        state = view.classify(np.asarray(pts), nrm, self_spacing=float(np.sqrt(mesh.area / 1000)))
        assert np.count_nonzero(state == vis.SELF_HIDDEN) == 0


def test_least_depth_sees_the_edge_of_a_silhouette_and_past_a_floating_point(view, T_cam):
    """The least depth among the rays around a point: a point on box A's far top edge (its
    silhouette against the table behind) has the box's own rays around it, so the least
    depth is not behind it, though its nearest ray may pass beside the box; a point floating
    above the bare table has only the table around it, behind it."""
    x = np.linspace(-0.035, 0.035, 15)
    edge = np.column_stack([x, np.full_like(x, -0.05 + 0.03), np.full_like(x, 0.10)])
    floating = np.array([[*FREE_SPOT, 0.05]])
    T_cam_world = np.linalg.inv(T_cam)
    depth = lambda p: (p @ T_cam_world[:3, :3].T + T_cam_world[:3, 3])[:, 2]  # noqa: E731
    least = view.least_depth(edge, 8, 2.0)
    assert np.all(least - depth(edge) < 0.005)
    assert view.least_depth(floating, 8, 2.0)[0] - depth(floating)[0] > 0.03
    assert np.isinf(view.least_depth(np.array([[0.0, -2.0, 0.5]]), 8, 2.0)).all()  # behind


def _self_hidden_by_tree(p_cam, p_world, n_world, spacing, tol):
    """The self-occlusion test as a KD-tree states it (the implementation before the compiled
    one): each sample's SELF_NEIGHBOURS + 1 nearest rays closer than the largest footprint."""
    from scipy.spatial import cKDTree

    n = len(p_cam)
    depth = p_cam[:, 2]
    rays = p_cam[:, :2] / depth[:, None]
    cover = vis.SELF_COVER * spacing / depth
    k = min(vis.SELF_NEIGHBOURS + 1, n)
    dist, idx = cKDTree(rays).query(rays, k=k, distance_upper_bound=float(cover.max()))
    dist, idx = dist.reshape(n, k), idx.reshape(n, k)
    ok = np.isfinite(dist)
    j = np.where(ok, idx, 0)
    ok &= dist <= cover[j]
    ok &= depth[j] < depth[:, None] - tol
    nrm = n_world / np.maximum(np.linalg.norm(n_world, axis=1, keepdims=True), 1e-12)
    off_plane = np.einsum("ikd,id->ik", p_world[j] - p_world[:, None, :], nrm)
    ok &= off_plane > tol
    return ok.any(axis=1)


@pytest.mark.parametrize("max_cells", [vis.SELF_MAX_CELLS, 4])
def test_self_occlusion_is_what_the_k_nearest_rays_decide(T_cam, max_cells, monkeypatch):
    """The compiled self-occlusion test (rays in cells) gives every verdict of the KD-tree's
    k-nearest formulation, on a concave object seen from several sides (with 4 cells too:
    the cells grow until they fit)."""
    monkeypatch.setattr(vis, "SELF_MAX_CELLS", max_cells)
    front, back = ((0.10, 0.02, 0.10), (0.0, -0.1, 0.05)), ((0.10, 0.02, 0.10), (0.0, 0.0, 0.05))
    pts, nrm, spacing = _union_samples([front, back], n=1500)
    hidden = 0
    for eye in (EYE, (0.5, -0.1, 0.12), (0.3, -0.5, 0.3), (0.02, 0.0, 0.6)):
        T = look_at(eye, (0.0, -0.05, 0.05))
        p_cam = (pts - T[:3, 3]) @ T[:3, :3]
        facing = np.einsum("ij,ij->i", nrm, T[:3, 3] - pts) > 0.0
        args = (p_cam[facing], pts[facing], nrm[facing], spacing, 0.005)
        expected = _self_hidden_by_tree(*args)
        np.testing.assert_array_equal(vis._self_hidden(*args), expected)
        hidden += int(expected.sum())
    assert hidden > 50  # the test has hidden samples to find
