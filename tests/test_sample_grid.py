"""ssp.sample_grid: the nearest-sample grid, and ssp.registration.grid_icp on it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ssp.registration import even_rows, facing_mask, grid_icp
from ssp.sample_grid import SampleGrid


@pytest.fixture(scope="module")
def samples():
    """Samples of a 60 x 30 x 20 mm box surface with outward normals, model frame."""
    rng = np.random.default_rng(0)
    half = np.array([0.03, 0.015, 0.01])
    p = rng.uniform(-half, half, (3000, 3))
    axis = rng.integers(0, 3, 3000)
    sign = rng.choice([-1.0, 1.0], 3000)
    p[np.arange(3000), axis] = sign * half[axis]
    n = np.zeros_like(p)
    n[np.arange(3000), axis] = sign
    return even_rows(800, p, n)


def _centres(grid):
    axes = [grid.lo[a] + (np.arange(grid.shape[a]) + 0.5) * grid.voxel for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_grid_holds_each_centres_nearest_sample(samples):
    grid = SampleGrid(samples[0], reach=0.012, voxel=0.002)
    d, idx = cKDTree(samples[0]).query(
        _centres(grid), distance_upper_bound=0.012 + grid.half_diagonal
    )
    found = np.isfinite(d)
    np.testing.assert_array_equal(np.isfinite(grid.distance), found)
    np.testing.assert_allclose(grid.distance[found], d[found], atol=1e-6)
    # the nearest sample, or one as near (ties)
    chosen = np.linalg.norm(samples[0][grid.index[found]] - _centres(grid)[found], axis=1)
    np.testing.assert_allclose(chosen, d[found], atol=1e-9)
    assert (grid.index[~found] == grid.miss).all()


@pytest.mark.parametrize("radius", [0.002, 0.005, 0.008, 0.012])
def test_within_is_exact(samples, radius):
    """The mask equals a KD-tree's answer, for queries all around the box and far outside the
    grid, in the model frame and through a pose."""
    grid = SampleGrid(samples[0], reach=0.012, voxel=0.002)
    rng = np.random.default_rng(1)
    q = np.vstack([rng.uniform(-0.05, 0.05, (20000, 3)), rng.uniform(-2, 2, (500, 3))])
    truth = np.isfinite(cKDTree(samples[0]).query(q, distance_upper_bound=radius)[0])
    np.testing.assert_array_equal(grid.within(q, radius), truth)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    T[:3, 3] = [0.5, -0.2, 0.9]
    np.testing.assert_array_equal(grid.within(q @ T[:3, :3].T + T[:3, 3], radius, T), truth)
    assert truth.any() and not truth.all()


@pytest.mark.parametrize("voxel", [0.002, 0.003, 0.005])
def test_nearest_within_is_a_kd_trees_query(samples, voxel):
    """The nearest sample closer than each radius and its distance: a KD-tree query with that
    upper bound, bit for bit, for queries on and off the surface, outside the grid, and on
    voxel faces."""
    from ssp.kdtree import KDTree

    grid = SampleGrid(samples[0], reach=0.0075, voxel=voxel)
    rng = np.random.default_rng(3)
    on = samples[0][rng.integers(0, len(samples[0]), 5000)] + rng.normal(0, 0.002, (5000, 3))
    faces = grid.lo + voxel * rng.integers(0, grid.shape, (2000, 3))  # voxel corners
    q = np.vstack([on, rng.uniform(-0.05, 0.05, (5000, 3)), rng.uniform(-2, 2, (300, 3)), faces])
    tree = KDTree(samples[0])
    for radius in (0.0075, 0.0067, 0.003):
        d_ref, i_ref = tree.query(q, k=1, distance_upper_bound=radius)
        d, i = grid.nearest_within(q, radius)
        hit = np.isfinite(d_ref)
        assert hit.any() and not hit.all()
        np.testing.assert_array_equal(d, d_ref)
        np.testing.assert_array_equal(i[hit], i_ref[hit])
        assert (i[~hit] == grid.miss).all()
    with pytest.raises(ValueError, match="reach"):
        grid.nearest_within(q, 0.008)


def test_nearest_is_within_a_voxel_diagonal_of_the_nearest(samples):
    grid = SampleGrid(samples[0], reach=0.012, voxel=0.002)
    rng = np.random.default_rng(2)
    q = rng.uniform(-0.045, 0.045, (20000, 3))
    d, _ = cKDTree(samples[0]).query(q)
    idx = grid.nearest(q)
    hit = idx != grid.miss
    got = np.linalg.norm(samples[0][idx[hit]] - q[hit], axis=1)
    assert (got <= d[hit] + 2 * grid.half_diagonal + 1e-12).all()
    # a miss only beyond reach; every query within reach less a diagonal has a sample
    assert (d[~hit] > 0.012 - 2 * grid.half_diagonal).all()
    assert hit[d <= 0.012 - 2 * grid.half_diagonal].all()


def test_grid_bad_arguments(samples):
    grid = SampleGrid(samples[0], reach=0.008, voxel=0.002)
    with pytest.raises(ValueError, match="reach"):
        grid.within(samples[0], 0.01)
    with pytest.raises(ValueError, match="at least one sample"):
        SampleGrid(np.zeros((0, 3)), reach=0.01, voxel=0.002)
    with pytest.raises(ValueError, match="normals"):
        grid_icp(grid, np.eye(4), samples[0], None, max_distance=0.005, iterations=3,
                 n_points=100)  # fmt: skip
    with_normals = SampleGrid(samples[0], reach=0.008, voxel=0.002, normals=samples[1])
    with pytest.raises(ValueError, match="reach"):
        grid_icp(with_normals, np.eye(4), samples[0], None, max_distance=0.01, iterations=3,
                 n_points=100)  # fmt: skip
    with pytest.raises(ValueError, match="normals for"):
        SampleGrid(samples[0], reach=0.008, voxel=0.002, normals=samples[1][:5])
    with pytest.raises(ValueError, match="normals"):
        grid.nearest(samples[0], keep=np.ones(len(samples[0]), bool))


def test_a_large_model_gets_a_coarser_voxel():
    from ssp.sample_grid import MAX_VOXELS

    p = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    grid = SampleGrid(p, reach=0.01, voxel=0.002)
    assert grid.voxel > 0.002 and np.prod(grid.shape) <= MAX_VOXELS


def test_grid_icp_is_point_to_plane_gauss_newton_and_finds_the_pose(samples):
    pts, nrm = samples
    grid = SampleGrid(pts, reach=0.012, voxel=0.002, normals=nrm)
    T_gt = np.eye(4)
    T_gt[:3, :3] = Rotation.from_rotvec([0.2, 0.5, -0.3]).as_matrix()
    T_gt[:3, 3] = [0.1, 0.05, 0.6]
    cam = np.array([0.0, 0.0, 1.5])
    world, world_n = pts @ T_gt[:3, :3].T + T_gt[:3, 3], nrm @ T_gt[:3, :3].T
    rng = np.random.default_rng(3)
    seen = world[facing_mask(world, world_n, cam)]
    seen = seen + rng.normal(0, 0.0005, seen.shape)
    T0 = T_gt.copy()
    T0[:3, :3] = Rotation.from_rotvec([0.04, -0.05, 0.06]).as_matrix() @ T0[:3, :3]
    T0[:3, 3] += [0.003, -0.002, 0.002]
    from test_perception_estimator import _world_frame_icp

    ours = grid_icp(grid, T0, seen, cam, max_distance=0.012, iterations=8, n_points=500)
    ref = _world_frame_icp(pts, nrm, T0, seen, cam, 0.012, 8, 500, grid=grid)
    np.testing.assert_allclose(ours, ref, atol=1e-9)
    fine = grid_icp(grid, ours, seen, cam, max_distance=0.005, iterations=20, n_points=1000)
    assert np.abs(ours - T0).max() > 1e-3  # it moved
    assert np.linalg.norm(fine[:3, 3] - T_gt[:3, 3]) < 0.001
    dR = Rotation.from_matrix(fine[:3, :3] @ T_gt[:3, :3].T).magnitude()
    assert np.degrees(dR) < 1.0
    # no sample within reach of the points: the start comes back
    far = T0.copy()
    far[:3, 3] += 0.5
    np.testing.assert_array_equal(
        grid_icp(grid, far, seen, cam, max_distance=0.012, iterations=8, n_points=500),
        far,
    )


def test_nearest_facing_keeps_a_thin_parts_faces_apart():
    """A 4 mm plate seen from above: a point on its top face takes a top sample even where a
    bottom sample is nearer, once the bottom ones are not kept (they face away)."""
    rng = np.random.default_rng(4)
    top = np.c_[rng.uniform(-0.05, 0.05, (400, 2)), np.full(400, 0.002)]
    bottom = np.c_[rng.uniform(-0.05, 0.05, (400, 2)), np.full(400, -0.002)]
    pts = np.vstack([top, bottom])
    nrm = np.vstack([np.tile([0, 0, 1.0], (400, 1)), np.tile([0, 0, -1.0], (400, 1))])
    grid = SampleGrid(pts, reach=0.012, voxel=0.002, normals=nrm)
    q = np.c_[rng.uniform(-0.04, 0.04, (2000, 2)), np.full(2000, 0.0015)]
    keep = nrm[:, 2] > 0
    idx = grid.nearest(q, keep)
    assert (idx != grid.miss).all() and keep[idx].all()
    d_top, _ = cKDTree(top).query(q)
    got = np.linalg.norm(pts[idx] - q, axis=1)
    assert (got <= d_top + 2 * grid.half_diagonal + 1e-12).all()
    assert (~keep[grid.nearest(q)]).any()  # without the faces apart, some take the bottom
