"""Euclidean clustering and segment labels (ssp.perception.segmentation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ssp.errors import PerceptionError
from ssp.geometry import make_pose
from ssp.perception.depth import cloud_from_depth
from ssp.perception.segmentation import Segmentation, euclidean_clusters, segment_cloud
from ssp.sim.render import add_depth_noise, look_at, render

EDGE = 0.0508
T_CAM = look_at([0.0, -math.sqrt(0.5), math.sqrt(0.5)], [0.0, 0.0, 0.0])


def _world_cloud(cube_model, xs):
    """Noisy world cloud and instance labels of cubes at ``x`` positions on the table."""
    objects = [
        (f"c{i}", cube_model.mesh, make_pose(None, [x, 0.0, EDGE / 2])) for i, x in enumerate(xs)
    ]
    r = render(objects, T_CAM)
    depth = add_depth_noise(r.depth, np.random.default_rng(0))
    return cloud_from_depth(depth, r.camera, mask=r.instance, T_world_cam=T_CAM)


@pytest.fixture(scope="module")
def separated(cube_model):
    return _world_cloud(cube_model, [-0.06, 0.06])


@pytest.fixture(scope="module")
def touching(cube_model):
    return _world_cloud(cube_model, [-EDGE / 2, EDGE / 2])


def _purity(seg_labels: np.ndarray, truth: np.ndarray, label: int) -> tuple[int, float]:
    """Majority true label of a segment and the fraction of its points that have it."""
    values, counts = np.unique(truth[seg_labels == label], return_counts=True)
    return int(values[np.argmax(counts)]), counts.max() / counts.sum()


def test_separated_cubes_are_two_segments(separated):
    seg = segment_cloud(separated.points)
    assert isinstance(seg, Segmentation)
    assert seg.classes == {0: None, 1: None}
    assert seg.labels.dtype == np.int64 and seg.labels.shape == separated.labels.shape
    majority = set()
    for label in (0, 1):
        truth, purity = _purity(seg.labels, separated.labels, label)
        assert truth >= 0 and purity > 0.99
        majority.add(truth)
        own = (separated.labels == truth).sum()
        assert (seg.labels == label).sum() > 0.85 * own  # all but the bottom rim
    assert majority == {0, 1}
    assert (seg.labels[separated.labels < 0] >= 0).mean() < 0.001  # table stays background


def test_touching_cubes_are_one_segment(touching):
    seg = segment_cloud(touching.points)
    assert seg.classes == {0: None}
    objects = touching.labels >= 0
    assert (seg.labels[objects] == 0).mean() > 0.85


def test_given_instance_labels_are_kept(separated):
    labels = separated.labels.copy()
    labels[labels == 1] = 7
    labels[:5] = 3  # a tiny segment
    seg = segment_cloud(separated.points, labels, min_points=30)
    assert seg.classes == {0: None, 7: None}
    np.testing.assert_array_equal(seg.labels == 7, labels == 7)
    assert (seg.labels[:5] == -1).all()
    assert (seg.labels[labels < 0] == -1).all()


def test_class_labels_are_split_into_instances(touching, separated):
    # both cubes carry one colour class (label 4): separated ones become two segments
    cls = np.where(separated.labels >= 0, 4, -1)
    seg = segment_cloud(separated.points, cls, {4: "cube"})
    assert seg.classes == {0: "cube", 1: "cube"}
    truths = {_purity(seg.labels, separated.labels, lab)[0] for lab in (0, 1)}
    assert truths == {0, 1}
    # touching ones cannot be told apart
    cls = np.where(touching.labels >= 0, 4, -1)
    seg = segment_cloud(touching.points, cls, {4: "cube"})
    assert seg.classes == {0: "cube"}
    # two classes, one instance each; a label without a class gets None
    cls = separated.labels.copy()
    seg = segment_cloud(separated.points, cls, {0: "cube", 5: "block"})
    assert sorted(seg.classes.values(), key=str) == [None, "cube"]
    for label, name in seg.classes.items():
        truth, purity = _purity(seg.labels, separated.labels, label)
        assert purity == 1.0 and name == ("cube" if truth == 0 else None)


def test_deterministic(separated):
    a = segment_cloud(separated.points)
    b = segment_cloud(separated.points.copy())
    np.testing.assert_array_equal(a.labels, b.labels)
    cls = np.where(separated.labels >= 0, 0, -1)
    c = segment_cloud(separated.points, cls, {0: "cube"})
    d = segment_cloud(separated.points, cls, {0: "cube"})
    np.testing.assert_array_equal(c.labels, d.labels)
    assert c.classes == d.classes


def test_cluster_numbering_by_size_then_index():
    rng = np.random.default_rng(0)

    def blob(centre, n):
        return np.asarray(centre) + rng.uniform(-0.005, 0.005, (n, 3))

    # sizes 40 (first), 60, 40, 10: expect 60 -> 0, first 40 -> 1, second 40 -> 2, 10 -> -1
    pts = np.vstack(
        [blob([0, 0, 0], 40), blob([1, 0, 0], 60), blob([2, 0, 0], 40), blob([3, 0, 0], 10)]
    )
    labels = euclidean_clusters(pts, tolerance=0.02, min_points=30)
    assert labels.dtype == np.int64
    np.testing.assert_array_equal(labels, np.repeat([1, 0, 2, -1], [40, 60, 40, 10]))
    # a permutation of the points gives the same partition
    perm = rng.permutation(len(pts))
    permuted = euclidean_clusters(pts[perm], tolerance=0.02, min_points=30)
    np.testing.assert_array_equal(permuted, labels[perm])


def test_chain_links_and_tolerance():
    line = np.column_stack([np.arange(50) * 0.005, np.zeros(50), np.zeros(50)])
    assert set(euclidean_clusters(line, tolerance=0.006, min_points=1)) == {0}
    assert len(set(euclidean_clusters(line, tolerance=0.004, min_points=1))) == 50


def test_edge_cases():
    assert euclidean_clusters(np.zeros((0, 3))).shape == (0,)
    pts = np.zeros((40, 3))
    pts[3] = np.nan
    labels = euclidean_clusters(pts, min_points=30)
    assert labels[3] == -1 and (np.delete(labels, 3) == 0).all()
    with pytest.raises(PerceptionError, match=r"\(N, 3\)"):
        segment_cloud(np.zeros((5, 2)))
    with pytest.raises(PerceptionError, match="labels must have shape"):
        segment_cloud(np.zeros((5, 3)), np.zeros(4, dtype=int))
    with pytest.raises(PerceptionError, match="integers"):
        segment_cloud(np.zeros((5, 3)), np.full(5, 0.5))
    empty = segment_cloud(np.zeros((0, 3)))
    assert empty.labels.shape == (0,) and empty.classes == {}


def test_pair_bound_is_an_upper_bound_of_the_pairs():
    """The grid bound that lets the clustering skip its exact pair count is never below the
    count (random clouds, dense and sparse, and a surface)."""
    from scipy.spatial import cKDTree

    from ssp.perception.segmentation import pair_bound

    rng = np.random.default_rng(0)
    clouds = [rng.normal(size=(int(rng.integers(2, 800)), 3)) * rng.uniform(0.001, 0.05)
              for _ in range(60)]  # fmt: skip
    u, v = np.meshgrid(np.linspace(0, 0.2, 120), np.linspace(0, 0.1, 60))
    clouds.append(np.column_stack([u.ravel(), v.ravel(), 0.01 * np.sin(20 * u.ravel())]))
    clouds.append(np.zeros((50, 3)))  # all one point
    clouds.append(rng.normal(size=(6000, 3)) * 0.02)  # above the trivial bound
    for p in clouds:
        for tol in (0.001, 0.006, 0.02):
            tree = cKDTree(p)
            exact = (int(tree.count_neighbors(tree, tol)) - len(p)) // 2
            assert pair_bound(p, tol) >= exact


def test_clusters_unchanged_when_the_pair_count_is_skipped(monkeypatch):
    """A cloud within the budget by the bound clusters as with the exact count."""
    import ssp.perception.segmentation as seg

    rng = np.random.default_rng(1)
    p = np.concatenate([rng.normal(c, 0.01, size=(400, 3)) for c in ((0, 0, 0), (0.1, 0, 0))])
    fast = euclidean_clusters(p, tolerance=0.006, min_points=5)
    monkeypatch.setattr(seg, "pair_bound", lambda *a: seg.MAX_PAIRS + 1)  # always count
    assert np.array_equal(fast, euclidean_clusters(p, tolerance=0.006, min_points=5))
