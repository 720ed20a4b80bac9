"""The cleaning's pieces (issue 34's speed-up): the same partition as Euclidean clustering."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.kdtree import KDTree
from ssp.perception.cleaning import clean_segment, pieces
from ssp.perception.segmentation import euclidean_clusters


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Two labelings of the same points split them alike (up to the labels' names)."""
    pairs = np.unique(np.column_stack([a, b]), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def _clouds(seed: int = 0):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        m = int(rng.integers(20, 2500))
        p = rng.normal(size=(m, 3)) * rng.uniform(0.002, 0.05)
        if rng.random() < 0.3:
            p = np.concatenate([p, p[: m // 3]])  # exact duplicates
        yield p
    # two patches and a thin bridge, a ring of sparse points: chains the k neighbours miss
    u = np.linspace(0, 0.05, 40)
    patch = np.stack(np.meshgrid(u, u), -1).reshape(-1, 2)
    bridge = np.column_stack([np.linspace(0.05, 0.06, 3), [0.02] * 3, [0] * 3])
    flat = np.zeros((len(patch), 1))
    yield np.concatenate([np.hstack([patch, flat]), np.hstack([patch + [0.06, 0], flat]), bridge])
    angle = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    yield np.column_stack([0.18 * np.cos(angle), 0.18 * np.sin(angle), np.zeros(200)])


@pytest.mark.parametrize("k", [2, 8])
def test_pieces_partition_equals_euclidean_clusters(k):
    for p in _clouds():
        d, nn = KDTree(p).query(p, k=k + 1)
        keep = np.random.default_rng(len(p)).random(len(p)) > 0.1  # some points left out
        idx = np.flatnonzero(keep)
        for tol in (0.003, 0.006):
            got = pieces(p, idx, nn[:, 1:], d[:, 1:], tol)
            want = euclidean_clusters(p[idx], tolerance=tol, min_points=1)
            assert _same_partition(got, want), (len(p), tol)


def test_clean_segment_drops_a_flying_line_and_a_stray_piece():
    rng = np.random.default_rng(3)
    u = np.linspace(0, 0.1, 60)
    face = np.stack(np.meshgrid(u, u), -1).reshape(-1, 2)
    face = np.column_stack([face, 0.5 + 0.0005 * rng.standard_normal(len(face))])
    flying = np.column_stack([np.full(12, 0.05), np.full(12, 0.05), np.linspace(0.52, 0.7, 12)])
    stray = np.column_stack([np.full(40, 0.3), np.linspace(0, 0.01, 40), np.full(40, 0.5)])
    res = clean_segment(np.concatenate([face, flying, stray]))
    n = len(face)
    assert res.keep[:n].all()
    assert not res.keep[n : n + 12].any() and res.flying >= 12
    assert not res.keep[n + 12 :].any() and res.stray + res.flying == 52
