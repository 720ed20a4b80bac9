"""Pose hypotheses from point pairs, and the perception pipeline, on rendered noisy depth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.camera import Camera
from ssp.errors import PerceptionError, TableNotFoundError, UnknownObjectError
from ssp.eval.metrics import pose_error
from ssp.geometry import invert
from ssp.perception.estimator import HypothesisEstimator, ModelPairs
from ssp.perception.normals import estimate_normals
from ssp.perception.pipeline import Perception
from ssp.sim.render import add_depth_noise, look_at, render

CAMERA = Camera.default()
T_WC = look_at([0.0, -0.7, 0.7], [0.0, 0.0, 0.03])


def _pose(x, y, z, yaw_deg=0.0, roll_deg=0.0):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zx", [yaw_deg, roll_deg], degrees=True).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


@pytest.fixture(scope="module")
def scene(lib):
    """A cube, a block lying apart, and two touching cubes (one on the other)."""
    h = lib["cube"].extents[2] / 2
    hb = lib["block"].extents[2] / 2
    gt = {
        "cube_a": ("cube", _pose(-0.12, 0.02, h, 20)),
        "block_b": ("block", _pose(0.0, -0.05, hb, -35)),
        "cube_c": ("cube", _pose(0.13, 0.05, h, 10)),
        "cube_d": ("cube", _pose(0.13, 0.05, 3 * h, 35)),
    }
    objects = [(k, lib[c].mesh, T) for k, (c, T) in gt.items()]
    res = render(objects, T_WC, CAMERA, stride=1)
    depth = add_depth_noise(res.depth, np.random.default_rng(3))
    return gt, depth, np.asarray(res.instance).astype(np.int64)


def _segment(scene, k):
    gt, depth, inst = scene
    z = depth.reshape(-1) > 0
    p_cam = CAMERA.backproject(depth).reshape(-1, 3)
    pts = p_cam @ T_WC[:3, :3].T + T_WC[:3, 3]
    return pts[z & (inst.reshape(-1) == k)]


def test_model_pair_table(lib):
    from ssp.config import PerceptionConfig

    table = ModelPairs.build(lib["cube"], PerceptionConfig())
    assert len(table.points) <= PerceptionConfig().max_model_points
    assert np.all(np.diff(table.keys) >= 0)
    d = np.linalg.norm(table.points[table.first] - table.points[table.second], axis=1)
    assert d.min() >= table.min_dist - 1e-12 and d.max() <= table.max_dist + 1e-12
    assert len(table.symmetries) > 1  # the cube is symmetric


def test_table_lookup_matches_a_search_of_the_sorted_keys(lib):
    from ssp.config import PerceptionConfig

    table = ModelPairs.build(lib["block"], PerceptionConfig())
    rng = np.random.default_rng(0)
    keys = np.concatenate([rng.choice(table.keys, 300), rng.integers(0, table.keys.max() + 9, 300)])
    first, count = table.lookup(keys)
    lo = np.searchsorted(table.keys, keys, side="left")
    hi = np.searchsorted(table.keys, keys, side="right")
    np.testing.assert_array_equal(count, hi - lo)
    np.testing.assert_array_equal(first[count > 0], lo[count > 0])
    assert (count == 0).any() and (count > 0).any()


def test_coarse_hits_equal_the_pointwise_test():
    """The compiled coarse score counts what the occupancy grid and the facing test say of
    every posed sample, including samples that land outside the grid on every side."""
    from ssp.perception.estimator import _coarse_hits, _Occupancy

    rng = np.random.default_rng(1)
    occ = _Occupancy(rng.random((800, 3)) * 0.1, 0.004)
    R = Rotation.random(50, random_state=2).as_matrix()
    t = rng.normal(0.05, 0.08, (50, 3))
    v = rng.normal(0.0, 0.04, (40, 3))
    nv = v / np.linalg.norm(v, axis=1, keepdims=True)
    cam = np.array([0.3, -0.2, 0.9])
    world = np.einsum("mij,pj->mpi", R, v) + t[:, None, :]
    normals = np.einsum("mij,pj->mpi", R, nv)
    face = ((cam - world) * normals).sum(-1) > 0
    hit = occ(world)
    hits, facing = _coarse_hits(R, t, v, nv, cam, occ)
    np.testing.assert_array_equal(facing, face.sum(1))
    np.testing.assert_array_equal(hits, (hit & face).sum(1))
    hits_all, facing_all = _coarse_hits(R, t, v, nv, None, occ)
    np.testing.assert_array_equal(hits_all, hit.sum(1))
    assert (facing_all == len(v)).all() and hit.any() and not hit.all()


def test_pair_poses_map_the_model_pair_onto_the_scene_pair():
    """A pair of model samples seen through a rigid motion gives back that motion."""
    from ssp.perception.estimator import _pair_poses

    rng = np.random.default_rng(3)
    p = rng.normal(0.0, 0.05, (30, 3))
    n = rng.normal(0.0, 1.0, (30, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    R = Rotation.random(1, random_state=4).as_matrix()[0]
    t = np.array([0.4, -0.1, 0.2])
    i, j = rng.integers(0, 30, 20), rng.integers(0, 30, 20)
    keep = i != j
    i, j = i[keep], j[keep]
    Rs, ts = _pair_poses(p @ R.T + t, n @ R.T, i, j, p, n, i, j)
    np.testing.assert_allclose(Rs, np.broadcast_to(R, Rs.shape), atol=1e-9)
    np.testing.assert_allclose(ts, np.broadcast_to(t, ts.shape), atol=1e-9)


def test_pair_features_are_the_point_pair_feature():
    """The compiled features: distance, the three angles quantised, the coplanar flag as the
    lowest bit (checked against the formula, away from the bin edges)."""
    from ssp.perception.estimator import _features

    rng = np.random.default_rng(5)
    p = rng.normal(0.0, 0.05, (200, 3))
    n = rng.normal(0.0, 1.0, (200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    i, j = rng.integers(0, 200, 2000), rng.integers(0, 200, 2000)
    i, j = i[i != j], j[i != j]
    step_d, step_a = 0.004, np.radians(12.0)
    keys, coplanar, dist = _features(p, n, i, j, step_d, step_a)
    d = p[j] - p[i]
    r = np.linalg.norm(d, axis=1)
    u = d / r[:, None]
    a = [np.arccos(np.clip(x, -1, 1)) for x in ((n[i] * u).sum(1), (n[j] * u).sum(1),
                                                 (n[i] * n[j]).sum(1))]  # fmt: skip
    flat = (a[2] < np.radians(20)) & (np.abs(a[0] - np.pi / 2) < np.radians(20))
    nb = int(np.ceil(np.pi / step_a)) + 1
    q = [np.floor(x / step_a).astype(int) for x in a]
    ref = (((np.floor(r / step_d).astype(int) * nb + q[0]) * nb + q[1]) * nb + q[2]) * 2 + flat
    edge = np.zeros(len(r), bool)
    for x, s in [(r, step_d)] + [(x, step_a) for x in a]:
        frac = x / s - np.floor(x / s)
        edge |= (frac < 1e-9) | (frac > 1 - 1e-9)
    np.testing.assert_allclose(dist, r, rtol=1e-12)
    np.testing.assert_array_equal(coplanar, flat)
    np.testing.assert_array_equal(keys[~edge], ref[~edge])
    assert (~edge).sum() > 0.99 * len(r)


def _world_frame_icp(pts, nrm, T, seg, cam, max_distance, iterations, n_points, grid=None):
    """Reference: point-to-plane Gauss-Newton in the world frame, samples moved every step
    (the algorithm as first written, before it was solved in the model frame). Each point is
    matched to the nearest facing sample (scipy's tree), or with ``grid`` (a
    :class:`ssp.sample_grid.SampleGrid` of ``pts`` with normals) to the nearest facing one
    of its voxel's per-direction samples, if within ``max_distance``."""
    from scipy.spatial import cKDTree

    from ssp.registration import even_rows, facing_mask

    T = T.copy()
    (seg,) = even_rows(n_points, seg)
    keep = facing_mask(pts @ T[:3, :3].T + T[:3, 3], nrm @ T[:3, :3].T, cam)
    kept = np.flatnonzero(keep)
    tree = cKDTree(pts[kept])
    for _ in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        local = (seg - t) @ R
        if grid is None:
            dist, j = tree.query(local, k=1, distance_upper_bound=max_distance)
            ok = np.isfinite(dist)
            idx = np.where(ok, kept[np.minimum(j, len(kept) - 1)], 0)
        else:
            idx = grid.nearest(local, keep)
            ok = idx != grid.miss
            idx = np.where(ok, idx, 0)
            ok &= np.linalg.norm(local - pts[idx], axis=1) <= max_distance
        q, p, n = seg[ok], pts[idx[ok]] @ R.T + t, nrm[idx[ok]] @ R.T
        c = p.mean(axis=0)
        A = np.hstack([np.cross(p - c, n), n])
        H = A.T @ A
        H += np.eye(6) * (1e-6 * np.trace(H) / 6.0 + 1e-12)
        x = np.linalg.solve(H, A.T @ -((p - q) * n).sum(axis=1))
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
        D[:3, 3] = c - D[:3, :3] @ c + x[3:]
        T = D @ T
        if np.linalg.norm(x[3:]) < 1e-6 and np.linalg.norm(x[:3]) < 1e-6:
            break
    return T


def test_model_frame_icp_is_point_to_plane_gauss_newton(lib, scene):
    """ssp.registration.point_to_plane_icp (the estimator's and the parser's polish's ICP)
    solves in the model frame what a world-frame point-to-plane Gauss-Newton does: the same
    pose from the same start."""
    from ssp.registration import even_rows, icp_refine, point_to_plane_icp

    model = lib["block"]
    T_gt = scene[0]["block_b"][1]
    seg = _segment(scene, 1)
    T0 = T_gt.copy()
    T0[:3, :3] = Rotation.from_rotvec([0.05, -0.04, 0.08]).as_matrix() @ T0[:3, :3]
    T0[:3, 3] += [0.004, -0.003, 0.002]
    cam = T_WC[:3, 3]
    pts, nrm = even_rows(400, np.asarray(model.surface_points), np.asarray(model.surface_normals))
    ours = point_to_plane_icp(
        pts, nrm, T0, seg, cam, max_distance=0.012, iterations=8, n_points=500
    )
    ref = _world_frame_icp(pts, nrm, T0, seg, cam, 0.012, 8, 500)
    np.testing.assert_allclose(ours, ref, atol=1e-9)
    assert np.abs(ours - T0).max() > 1e-3  # it moved
    np.testing.assert_array_equal(
        icp_refine(model, T0, seg, cam, max_distance=0.012, iterations=8, n_samples=400,
                   n_points=500),
        ours,
    )  # fmt: skip


@pytest.mark.parametrize("max_distance", [0.002, 0.004, 0.03])
def test_exact_icp_matches_are_the_kd_trees(lib, scene, monkeypatch, max_distance):
    """The compiled ICP's cell search finds each point's nearest facing sample exactly: with
    a cut-off below the sample spacing (about 3 mm), near it and far above it, and with its
    cells grown until at most 8 cover the model, it gives the reference's pose (scipy's
    tree)."""
    from ssp import registration
    from ssp.registration import even_rows, point_to_plane_icp

    model = lib["cube"]
    T_gt = scene[0]["cube_a"][1]
    seg = _segment(scene, 0)
    T0 = T_gt.copy()
    T0[:3, :3] = Rotation.from_rotvec([-0.03, 0.05, 0.02]).as_matrix() @ T0[:3, :3]
    T0[:3, 3] += [-0.002, 0.003, 0.001]
    cam = T_WC[:3, 3]
    pts, nrm = even_rows(600, np.asarray(model.surface_points), np.asarray(model.surface_normals))
    ref = _world_frame_icp(pts, nrm, T0, seg, cam, max_distance, 6, 800)
    for cells in (registration.MAX_CELLS, 8):
        monkeypatch.setattr(registration, "MAX_CELLS", cells)  # read at each call
        ours = point_to_plane_icp(
            pts, nrm, T0, seg, cam, max_distance=max_distance, iterations=6, n_points=800
        )
        np.testing.assert_allclose(ours, ref, atol=1e-9)


@pytest.mark.parametrize("k, cls", [(0, "cube"), (1, "block")])
def test_single_object_pose_and_class(lib, scene, k, cls):
    gt = scene[0]
    T_gt = list(gt.values())[k][1]
    seg = _segment(scene, k)
    est = HypothesisEstimator(lib)
    nrm = estimate_normals(seg, viewpoint=T_WC[:3, 3])
    res = est.estimate(seg, nrm, ["cube", "block"], T_WC[:3, 3], single_object=True)
    assert len(res.objects) == 1
    best = res.objects[0][0]
    assert best.class_name == cls
    dt, dr = pose_error(T_gt, best.T_world_obj, lib[cls].symmetry)
    assert dt < 3.0 and dr < 3.0, (dt, dr)
    scores = [h.score for h in res.objects[0]]
    assert scores == sorted(scores, reverse=True) and 0 < scores[0] <= 1
    assert len(res.objects[0]) <= est.cfg.hypotheses_per_object


def test_touching_objects_in_one_segment(lib, scene):
    gt = scene[0]
    seg = np.vstack([_segment(scene, 2), _segment(scene, 3)])
    est = HypothesisEstimator(lib)
    nrm = estimate_normals(seg, viewpoint=T_WC[:3, 3])
    res = est.estimate(seg, nrm, ["cube", "block"], T_WC[:3, 3])
    found = [obj[0] for obj in res.objects]
    for gid in ("cube_c", "cube_d"):
        errs = [
            pose_error(gt[gid][1], h.T_world_obj, lib["cube"].symmetry)
            for h in found
            if h.class_name == "cube"
        ]
        assert errs and min(e[0] for e in errs) < 5.0, (gid, errs)


def test_diverse_keeps_other_orientations_that_explain_the_segment():
    from ssp.config import PerceptionConfig
    from ssp.perception.estimator import _diverse

    def turned(deg, axis="z"):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler(axis, deg, degrees=True).as_matrix()
        return T

    sym = np.eye(3)[None]
    found = [  # (score, T, coverage), best score first
        (0.9, turned(0), 1.0),
        (0.85, turned(5), 1.0),  # a near-duplicate of the best
        (0.6, turned(90), 0.99),  # another orientation that explains the points
        (0.5, turned(90, "x"), 0.8),  # another that does not
    ]
    cfg = PerceptionConfig()
    kept = _diverse(found, 2, cfg, sym)
    assert [s for s, _, _ in kept] == [0.9, 0.6]
    assert [s for s, _, _ in _diverse(found, 3, cfg, sym)] == [0.9, 0.85, 0.6]
    assert [s for s, _, _ in _diverse(found, 4, cfg, sym)] == [0.9, 0.85, 0.6, 0.5]
    off = PerceptionConfig(alternatives=0, alternative_coverage=0.0)
    assert [s for s, _, _ in _diverse(found, 2, off, sym)] == [0.9, 0.85]
    assert _diverse([], 3, cfg, sym) == []


def test_partly_hidden_block_gets_both_orientations(lib):
    """A block behind a cube shows one end: the seen part fits it lying along x or along y.
    Both orientations are among the hypotheses (the scene parser chooses); without
    alternatives only the best-fitting one is."""
    h, hb = lib["cube"].extents[2] / 2, lib["block"].extents[2] / 2
    gt = {"cube": ("cube", _pose(0.0, -0.03, h)), "block": ("block", _pose(0.03, 0.03, hb))}
    res = render([(k, lib[c].mesh, T) for k, (c, T) in gt.items()], T_WC, CAMERA, stride=1)
    depth = add_depth_noise(res.depth, np.random.default_rng(0))
    seg = _segment((gt, depth, np.asarray(res.instance).astype(np.int64)), 1)
    nrm = estimate_normals(seg, viewpoint=T_WC[:3, 3])
    sym = lib["block"].symmetry
    T_gt = gt["block"][1]
    from ssp.config import PerceptionConfig

    for alternatives in (0, 4):
        est = HypothesisEstimator(lib, PerceptionConfig(alternatives=alternatives))
        res = est.estimate(seg, nrm, ["block"], T_WC[:3, 3], single_object=True)
        errs = [pose_error(T_gt, hyp.T_world_obj, sym) for hyp in res.hypotheses]
        assert min(dt for dt, dr in errs if dr <= 10) <= 5.0
        turned = [dr for _, dr in errs if dr > 30]
        assert (len(turned) > 0) == (alternatives > 0)


def test_deterministic(lib, scene):
    seg = _segment(scene, 1)
    nrm = estimate_normals(seg, viewpoint=T_WC[:3, 3])
    a = HypothesisEstimator(lib, seed=4).estimate(seg, nrm, ["cube", "block"], T_WC[:3, 3])
    b = HypothesisEstimator(lib, seed=4).estimate(seg, nrm, ["cube", "block"], T_WC[:3, 3])
    assert len(a.hypotheses) == len(b.hypotheses)
    for ha, hb in zip(a.hypotheses, b.hypotheses, strict=True):
        assert ha.class_name == hb.class_name and ha.score == hb.score
        np.testing.assert_array_equal(ha.T_world_obj, hb.T_world_obj)


def test_bad_calls(lib):
    est = HypothesisEstimator(lib)
    pts = np.zeros((10, 3))
    with pytest.raises(PerceptionError):
        est.estimate(pts, pts, [])
    with pytest.raises(PerceptionError):
        est.estimate(pts, pts[:5], ["cube"])
    with pytest.raises(UnknownObjectError):
        est.estimate(np.random.default_rng(0).random((50, 3)) * 0.05, np.ones((50, 3)), ["nope"])
    with pytest.raises(UnknownObjectError):
        Perception(lib, classes=["cube", "nope"])


def test_pipeline_from_depth_without_pose_or_labels(lib, scene):
    """Table fit + clustering + estimator: every object found, in the camera frame."""
    gt, depth, _ = scene
    res = Perception(lib, classes=["cube", "block"]).from_depth(depth, CAMERA)
    frame = res.frame
    assert frame.T_world_cam is not None
    # the fitted world frame differs from the true one by a yaw and an in-plane shift: compare
    # poses in the camera frame
    T_cw_est = invert(frame.T_world_cam)
    for gid, (cls, T) in gt.items():
        T_cam_gt = invert(T_WC) @ T
        errs = [
            pose_error(T_cam_gt, T_cw_est @ h.T_world_obj, lib[cls].symmetry)
            for h in frame.hypotheses
            if h.class_name == cls
        ]
        assert errs and min(e[0] for e in errs) < 5.0, (gid, errs)
    # the world z of the points: table near 0, objects above
    assert abs(np.median(frame.points[frame.labels < 0][:, 2])) < 0.002
    assert set(res.timings) >= {"table", "segmentation", "normals", "hypotheses", "total"}
    # a cluster may hold several objects: its hypotheses carry no instance segment
    assert all(h.segment is None for h in frame.hypotheses)


def test_pipeline_instance_labels_tag_hypotheses_with_their_segment(lib, scene):
    """With an instance mask a segment is one object: each hypothesis names its segment, so
    that association never groups two segments' hypotheses as one object."""
    gt, depth, inst = scene
    res = Perception(lib, classes=["cube", "block"]).from_depth(
        depth, CAMERA, T_world_cam=T_WC, mask=inst
    )
    hyps = res.frame.hypotheses
    assert hyps and len(res.segments) == len(gt)
    for label, seg in res.segments.items():
        tagged = [h for h in hyps if h.segment == label]
        assert len(tagged) == len(seg.hypotheses) > 0
        assert [h.score for h in tagged] == [h.score for h in seg.hypotheses]
    assert {h.segment for h in hyps} == set(res.segments)


def test_pipeline_given_hypotheses_in_camera_frame(lib, scene):
    from ssp.scene import Hypothesis

    gt, depth, inst = scene
    T_cam_obj = invert(T_WC) @ gt["cube_a"][1]
    res = Perception(lib).from_depth(
        depth,
        CAMERA,
        T_world_cam=T_WC,
        mask=inst,
        hypotheses=[Hypothesis("cube", T_cam_obj)],
        hypotheses_frame="camera",
    )
    assert res.segments == {}
    assert len(res.frame.hypotheses) == 1
    np.testing.assert_allclose(res.frame.hypotheses[0].T_world_obj, gt["cube_a"][1], atol=1e-9)
    # hypotheses in the camera frame need the camera pose
    with pytest.raises(PerceptionError):
        Perception(lib).from_points(
            np.zeros((5, 3)) + [0, 0, 0.1],
            frame="world",
            hypotheses=[Hypothesis("cube", T_cam_obj)],
            hypotheses_frame="camera",
        )


def test_pipeline_without_table(lib):
    """Only an object in view: no table, a clear error."""
    T = _pose(0, 0, 0.03)
    res = render([("c", lib["cube"].mesh, T)], T_WC, CAMERA, table=False, stride=2)
    with pytest.raises(TableNotFoundError):
        Perception(lib).from_depth(res.depth, CAMERA.subsample(2))


def test_segments_survive_real_mask_defects(lib, scene):
    """Issue 15, item 2: 0.5-2 % stray pixels (edge bleeding, flying pixels) made a segment's
    max-min extent larger than every model and the estimator skipped it without a word."""
    from ssp.perception.cleaning import clean_segment, robust_extent
    from ssp.sim.masks import add_mask_defects

    gt, depth, inst = scene
    d2, i2, counts = add_mask_defects(
        depth, inst, np.random.default_rng(5), fraction=(0.02, 0.02), bleed_share=0.3
    )
    assert all(counts.values())
    res = Perception(lib, classes=["cube", "block"]).from_depth(
        d2, CAMERA, T_world_cam=T_WC, mask=i2
    )
    for k, (gid, (cls, T)) in enumerate(gt.items()):
        seg = res.segments[k]
        assert seg.objects, (gid, res.verdicts[k])
        best = seg.objects[0][0]
        if gid != "cube_c":  # the lower of the two touching cubes is mostly hidden
            assert best.class_name == cls
            mm, deg = pose_error(T, best.T_world_obj, lib[cls].symmetry)
            assert mm < 5.0 and deg < 10.0, (gid, mm, deg)
        assert res.verdicts[k].startswith("removed ") and "hypotheses of" in res.verdicts[k]
    # the cleaning itself: flying pixels far behind a cube's points are dropped, and the
    # robust extent ignores the few that remain
    pts = _segment(scene, 0)
    rng = np.random.default_rng(1)
    flying = pts[rng.choice(len(pts), 20)] + np.array([0.0, 0.25, -0.25]) * rng.random((20, 1))
    both = np.concatenate([pts, flying])
    kept = clean_segment(both)
    assert kept.keep[: len(pts)].mean() > 0.97 and kept.keep[len(pts) :].mean() < 0.2
    assert robust_extent(both) < 1.15 * robust_extent(pts)
    assert "flying" in kept.describe() or "stray" in kept.describe()


def test_a_segment_larger_than_every_model_says_so(lib):
    est = HypothesisEstimator(lib)
    g = np.linspace(0.0, 0.6, 40)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pts = np.column_stack([pts, np.full(len(pts), 0.05)])  # a 60 cm plate
    res = est.estimate(pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1)), ["cube"], single_object=True)
    assert not res.objects and res.stopped.startswith("larger than every candidate class")


def test_estimating_compiles_nothing_beyond_compile_kernels(lib, scene):
    """Every kernel call uses the argument types that :func:`compile_kernels` compiles (and
    ``make install`` caches): a camera position or a segment that is a strided view, float32
    or a list must not make numba compile another specialisation in the middle of a run."""
    from ssp import forces, jit, registration, sample_grid
    from ssp.perception import estimator
    from ssp.registration import icp_refine

    estimator.compile_kernels()
    kernels = [
        estimator._features, estimator._pair_poses, estimator._pair_frame,
        estimator._coarse_kernel, registration._grid_icp, registration._exact_icp,
        registration._facing, registration._gauss_newton_step, registration._accumulate,
        sample_grid._fill,
        sample_grid._within_kernel, sample_grid.posed_cell,
        forces._wrenches, jit.pairwise_sum, jit._pairwise, jit._block,
    ]  # fmt: skip
    before = [len(k.signatures) for k in kernels]
    seg = _segment(scene, 1)
    T_gt = scene[0]["block_b"][1]
    nrm = estimate_normals(seg, viewpoint=T_WC[:3, 3])
    est = HypothesisEstimator(lib)
    for points, normals, camera in (
        (seg, nrm, T_WC[:3, 3]),  # a column of the camera pose: strided
        (np.asfortranarray(seg), np.asfortranarray(nrm), list(T_WC[:3, 3])),
        (seg.astype(np.float32), nrm.astype(np.float32), T_WC[:3, 3].astype(np.float32)),
    ):
        res = est.estimate(points, normals, ["cube", "block"], camera, single_object=True)
        assert res.objects and res.objects[0]
    # the exact ICP (the parser's polish): read-only model samples and segment, strided camera
    model = lib["block"]
    frozen = seg.copy()
    frozen.flags.writeable = False
    icp_refine(model, T_gt, frozen, T_WC[:3, 3], max_distance=0.01, iterations=3)
    icp_refine(model, T_gt, seg[::2], list(T_WC[:3, 3]), max_distance=0.01, iterations=3)
    # the data forces (the parser's search): float32 poses, a list of enabled flags
    df = forces.DataForces([model, lib["cube"]], [forces.SegmentField(seg), None])
    poses = np.stack([T_gt, np.eye(4)]).astype(np.float32)
    df.compute(poses, 9.81, [True, True])
    df.compute(poses[:, :, :], 9.81, [False, True])
    assert [len(k.signatures) for k in kernels] == before


def test_a_frame_compiles_no_kernel_that_compile_kernels_leaves_out(lib):
    """The kernels a frame meets beyond the estimator's (the cleaning's components, the label
    votes' cells, the self-occlusion test, the volume test) are compiled by
    :func:`compile_kernels` too, which ``make install`` runs: left out, each compiled in the
    first frame of a user's first run (3.1 s against 0.3 s on the tools of ``ssp bench
    frame``)."""
    from ssp import cells, components, overlap, sample_grid, visibility
    from ssp.parser import SceneParser
    from ssp.perception import estimator
    from ssp.sim.generate import generate_sequence

    estimator.compile_kernels()
    kernels = [  # those called from Python (the others compile inside them)
        cells._nearest_each, cells.cell_sort, components._components, overlap._contains,
        visibility._self_hidden_kernel, sample_grid._voxel_lists, sample_grid._nearest_within,
    ]  # fmt: skip
    before = [len(k.signatures) for k in kernels]
    assert all(before)
    seq = generate_sequence("structure", 3, lib, stages=1, frames_per_stage=1, stride=2,
                            n_objects=4)  # fmt: skip
    f = seq.frames[0]
    res = Perception(lib).from_depth(f.depth, seq.camera, mask=f.instance,
                                     T_world_cam=seq.T_world_cam)  # fmt: skip
    est = SceneParser(lib).update(res.frame)
    assert est.objects
    assert [len(k.signatures) for k in kernels] == before


@pytest.mark.parametrize("voxel, dilate", [(0.004, 1), (0.003, 2), (0.005, 0)])
def test_occupancy_is_the_dilated_voxel_grid(scene, voxel, dilate):
    """The coarse score's occupancy grid is scipy's binary dilation (3^3 structure, `dilate`
    iterations) of the segment's voxels."""
    from scipy import ndimage

    from ssp.perception.estimator import _Occupancy

    p = _segment(scene, 2)
    occ = _Occupancy(p, voxel, dilate)
    idx = np.floor((p - occ.lo) / voxel).astype(np.int64)
    grid = np.zeros(tuple(occ.shape), dtype=bool)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    if dilate:
        grid = ndimage.binary_dilation(grid, np.ones((3, 3, 3), bool), iterations=dilate)
    np.testing.assert_array_equal(occ.grid, grid)
    n_voxels = len(np.unique(idx, axis=0))
    assert (occ.grid.sum() > 2 * n_voxels) if dilate else (occ.grid.sum() == n_voxels)
