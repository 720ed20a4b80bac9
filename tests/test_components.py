"""ssp.components: the compiled connected components, against SciPy's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as scipy_components

from ssp.components import connected_components


def _scipy(n: int, rows: np.ndarray, cols: np.ndarray) -> tuple[int, np.ndarray]:
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    count, labels = scipy_components(graph.tocsr(), directed=False)
    return int(count), labels.astype(np.int64)


@pytest.mark.parametrize("seed", range(8))
def test_the_labels_are_scipys_on_random_graphs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(50):
        n = int(rng.integers(1, 400))
        m = int(rng.integers(0, 2 * n))
        rows, cols = rng.integers(0, n, m), rng.integers(0, n, m)
        count, labels = connected_components(n, rows, cols)
        want_count, want = _scipy(n, rows, cols)
        assert count == want_count
        np.testing.assert_array_equal(labels, want)


def test_chains_joined_from_their_far_ends_keep_the_order_of_their_lowest_nodes() -> None:
    # two chains met edge by edge from the top: the roots must end at each one's lowest node
    n = 10
    rows = np.array([9, 7, 5, 3, 8, 6, 4, 2])
    cols = np.array([7, 5, 3, 1, 6, 4, 2, 0])
    count, labels = connected_components(n, rows, cols)
    assert count == 2
    np.testing.assert_array_equal(labels, [0, 1, 0, 1, 0, 1, 0, 1, 0, 1])
    np.testing.assert_array_equal(labels, _scipy(n, rows, cols)[1])


def test_no_edges_self_loops_and_no_nodes() -> None:
    assert connected_components(0, np.zeros(0, int), np.zeros(0, int))[0] == 0
    count, labels = connected_components(4, np.array([2, 2]), np.array([2, 2]))
    assert count == 4
    np.testing.assert_array_equal(labels, [0, 1, 2, 3])


def test_bad_edges_are_refused() -> None:
    with pytest.raises(ValueError, match="outside"):
        connected_components(3, np.array([0]), np.array([3]))
    with pytest.raises(ValueError, match="outside"):
        connected_components(3, np.array([-1]), np.array([0]))
    with pytest.raises(ValueError, match="edge ends"):
        connected_components(3, np.array([0, 1]), np.array([1]))
