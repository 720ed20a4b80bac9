"""Connected components of an undirected graph given by its edges, compiled (issue 34).

The cleaning of each instance segment (:mod:`ssp.perception.cleaning`) and the Euclidean
clusters of a cloud without masks (:mod:`ssp.perception.segmentation`) join points into
pieces through their neighbour pairs. SciPy's ``connected_components`` needs the pairs as a
sparse matrix first (a COO to CSR conversion, an index sort and a CSC copy), a third of a
segment's cleaning on the tools' 640 x 480 frames (docs/benchmarks.md, "Whole-frame
latency"). :func:`connected_components` is
a union-find over the edges themselves (path halving, the smaller node the root), with the
same labels as SciPy's: each component numbered by the order of its lowest node
(tests/test_components.py compares them on random graphs).
"""

from __future__ import annotations

import numpy as np

from ssp.jit import njit

__all__ = ["connected_components", "load_kernels"]


def connected_components(n: int, rows: np.ndarray, cols: np.ndarray) -> tuple[int, np.ndarray]:
    """``(count, labels (n,) int64)``: the connected components of the undirected graph on
    nodes ``0 .. n - 1`` with the edges ``rows[i] -- cols[i]`` (int arrays of one length, each
    in ``[0, n)``), numbered 0, 1, ... in the order of each component's lowest node, as
    ``scipy.sparse.csgraph.connected_components(..., directed=False)`` numbers them."""
    r = np.ascontiguousarray(rows, dtype=np.int64).reshape(-1)
    c = np.ascontiguousarray(cols, dtype=np.int64).reshape(-1)
    if len(r) != len(c):
        raise ValueError(f"{len(r)} edge starts but {len(c)} edge ends")
    n = int(n)
    if n < 0:
        raise ValueError(f"the node count must be >= 0, got {n}")
    if len(r) and (min(r.min(), c.min()) < 0 or max(r.max(), c.max()) >= n):
        raise ValueError(f"an edge names a node outside 0 .. {n - 1}")
    count, labels = _components(n, r, c)
    return int(count), labels


def load_kernels() -> None:
    """Compile the union-find, or load it from numba's cache
    (:func:`ssp.perception.estimator.compile_kernels`: ``make install`` runs it)."""
    connected_components(2, np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64))


@njit
def _root(parent, i):
    """The root of node ``i``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit
def _components(n, rows, cols):
    """:func:`connected_components`' union-find: every root is its component's lowest node, so
    a node's root is labelled before the node (the labels' order)."""
    parent = np.arange(n)
    for e in range(rows.shape[0]):
        a = _root(parent, rows[e])
        b = _root(parent, cols[e])
        if a < b:
            parent[b] = a
        elif b < a:
            parent[a] = b
    labels = np.empty(n, dtype=np.int64)
    count = 0
    for i in range(n):
        r = _root(parent, i)
        if r == i:
            labels[i] = count
            count += 1
        else:
            labels[i] = labels[r]
    return count, labels
