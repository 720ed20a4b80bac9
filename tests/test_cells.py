"""Nearest points from cells (ssp.cells): exactly a KD-tree's nearest within a distance."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ssp.cells import PointCells


@pytest.mark.parametrize("max_cells", [1 << 20, 8])
def test_nearest_is_the_kd_trees_nearest_closer_than_the_distance(max_cells):
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.2, 0.2, (5000, 3)) * [1.0, 1.0, 0.2]
    queries = rng.uniform(-0.25, 0.25, (2000, 3)) * [1.0, 1.0, 0.3]
    cells = PointCells(points, 0.02, max_cells=max_cells)
    for distance in (0.02, 0.005):
        dist, idx = cKDTree(points).query(queries, k=1, distance_upper_bound=distance)
        expected = np.where(np.isfinite(dist), idx, -1)
        got = cells.nearest(queries, distance)
        np.testing.assert_array_equal(got, expected)
        assert 0 < np.count_nonzero(got >= 0) < len(queries)  # both outcomes are tested


def test_only_the_live_points_are_found_and_the_bound_is_strict():
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.5, 0.0, 0.0]])
    cells = PointCells(points, 0.01, live=np.array([1, 2]))
    q = np.array([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [0.49, 0.0, 0.0], [5.0, 5.0, 5.0]])
    # point 0 is not live; point 1 lies exactly 0.01 from the first query (not closer)
    np.testing.assert_array_equal(cells.nearest(q, 0.01), [-1, 1, -1, -1])
    np.testing.assert_array_equal(cells.nearest(np.array([[0.495, 0.0, 0.0]]), 0.01), [2])


def test_a_distance_beyond_the_reach_or_no_points_is_refused():
    cells = PointCells(np.zeros((1, 3)), 0.01)
    with pytest.raises(ValueError, match="reach"):
        cells.nearest(np.zeros((1, 3)), 0.02)
    with pytest.raises(ValueError, match="at least one point"):
        PointCells(np.zeros((0, 3)), 0.01)
