"""Exact nearest neighbours within a distance, from points sorted into cubic cells.

Used where a KD-tree would be built for a few queries (the ICP's samples of each call,
:mod:`ssp.registration`; the label votes' scene points of each frame, :mod:`ssp.segments`;
an object's sample rays in each self-occlusion test, :mod:`ssp.visibility`, in the plane z = 0):
a counting sort of the points into cells of side at least the search distance builds in a
fraction of a tree's time, and a query searches the 27 cells around its own, which hold
every point within that distance of it. Exact: the nearest point closer than the distance
(the first of equals), as a KD-tree query with that strict upper bound finds it.
"""

from __future__ import annotations

import math

import numpy as np

from ssp.jit import kernel_array, njit

__all__ = ["OUTSIDE", "PointCells", "cell_sort", "load_kernels", "nearest_in_cells"]


class PointCells:
    """Points ``(N, 3)`` (m) sorted into cells for :meth:`nearest` queries within ``reach`` (m).

    Args:
        points: the points; only ``live`` (indices) are sorted when given.
        reach: the largest query distance (the cells' side is at least this).
        max_cells: at most this many cells (their side doubles until they fit).
    """

    def __init__(
        self,
        points: np.ndarray,
        reach: float,
        live: np.ndarray | None = None,
        max_cells: int = 1 << 20,
    ) -> None:
        self.points = kernel_array(points)
        live = np.arange(len(self.points)) if live is None else np.asarray(live, np.int64)
        if not len(live):
            raise ValueError("PointCells needs at least one point")
        self.reach = float(reach)
        self._cells = cell_sort(self.points, live, self.reach, int(max_cells))

    def nearest(self, queries: np.ndarray, distance: float) -> np.ndarray:
        """(M,) index of the point nearest each query ``(M, 3)`` closer than ``distance``
        (strictly; at most ``reach``), the smallest index of equals; -1 where none is."""
        if distance > self.reach:
            raise ValueError(f"distance {distance} beyond the cells' reach {self.reach}")
        lo, dims, h, inv_h, start, order = self._cells
        return _nearest_each(
            kernel_array(queries), self.points, lo, inv_h, dims, h * h, float(distance) ** 2,
            start, order,
        )  # fmt: skip


def load_kernels() -> None:
    """Compile :meth:`PointCells.nearest`'s kernels, or load them from numba's cache
    (:func:`ssp.perception.estimator.compile_kernels`: ``make install`` runs it)."""
    PointCells(np.eye(3), 0.1).nearest(np.eye(3), 0.05)


@njit
def _nearest_each(q, pts, lo, inv_h, dims, h2, max2, start, order):
    """:func:`nearest_in_cells` of each query ``q (M, 3)``, -1 for none."""
    out = np.full(q.shape[0], -1, dtype=np.int64)
    for k in range(q.shape[0]):
        j = nearest_in_cells(q[k, 0], q[k, 1], q[k, 2], -1, pts, lo, inv_h, dims, h2, max2,
                             start, order)  # fmt: skip
        if j >= 0:
            out[k] = j
    return out


#: :func:`nearest_in_cells` of a point outside the cells grown by one cell
OUTSIDE = -2


@njit
def cell_sort(pts, live, max_distance, max_cells):
    """The points ``live`` of ``pts`` sorted into cubic cells of side ``h >= max_distance``
    (doubled until at most ``max_cells`` cover them), a counting sort: ``(lo, dims, h, 1 / h,
    start, order)``, the points of cell ``c`` being ``order[start[c]:start[c + 1]]``; cell
    ``(x, y, z)`` is ``(x * dims[1] + y) * dims[2] + z``, its corner ``lo + h (x, y, z)``."""
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = pts[live, a].min()
        hi[a] = pts[live, a].max()
    h = max_distance
    dims = np.empty(3, dtype=np.int64)
    while True:
        for a in range(3):
            dims[a] = int((hi[a] - lo[a]) / h) + 1
        if dims[0] * dims[1] * dims[2] <= max_cells:
            break
        h *= 2.0
    inv_h = 1.0 / h
    n_cells = dims[0] * dims[1] * dims[2]
    cell_of = np.empty(live.shape[0], dtype=np.int64)
    start = np.zeros(n_cells + 1, dtype=np.int64)
    for k in range(live.shape[0]):
        j = live[k]
        c0 = min(int((pts[j, 0] - lo[0]) * inv_h), dims[0] - 1)
        c1 = min(int((pts[j, 1] - lo[1]) * inv_h), dims[1] - 1)
        c2 = min(int((pts[j, 2] - lo[2]) * inv_h), dims[2] - 1)
        cell_of[k] = (c0 * dims[1] + c1) * dims[2] + c2
        start[cell_of[k] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    order = np.empty(live.shape[0], dtype=np.int64)
    fill = start[:-1].copy()
    for k in range(live.shape[0]):
        order[fill[cell_of[k]]] = live[k]
        fill[cell_of[k]] += 1
    return lo, dims, h, inv_h, start, order


@njit
def nearest_in_cells(q0, q1, q2, c, pts, lo, inv_h, dims, h2, max2, start, order):
    """The point of :func:`cell_sort`'s cells nearest to ``(q0, q1, q2)`` (the frame of
    ``pts``) closer than ``sqrt(max2)`` (the first of equals), searched from the point ``c``
    (a guess, e.g. an ICP's last match: taken when within ``sqrt(max2)``; or -1) through the
    27 cells around the query's, skipping the cells farther than the nearest so far; -1 when
    none, :data:`OUTSIDE` when the query lies beyond the cells grown by one cell (``h2``: the
    squared cell side)."""
    w0, w1, w2 = (q0 - lo[0]) * inv_h, (q1 - lo[1]) * inv_h, (q2 - lo[2]) * inv_h
    f0, f1, f2 = math.floor(w0), math.floor(w1), math.floor(w2)
    if f0 < -1 or f1 < -1 or f2 < -1:
        return OUTSIDE
    if f0 > dims[0] or f1 > dims[1] or f2 > dims[2]:
        return OUTSIDE
    i0, i1, i2 = int(f0), int(f1), int(f2)
    r0, r1, r2 = w0 - f0, w1 - f1, w2 - f2  # where in its cell, 0 to 1
    best = max2
    j = -1
    if c >= 0:
        e0, e1, e2 = q0 - pts[c, 0], q1 - pts[c, 1], q2 - pts[c, 2]
        dd = e0 * e0 + e1 * e1 + e2 * e2
        if dd <= max2:
            best = dd
            j = c
    for x in range(max(i0 - 1, 0), min(i0 + 2, dims[0])):
        g0 = 0.0 if x == i0 else (1.0 - r0 if x > i0 else r0)
        for y in range(max(i1 - 1, 0), min(i1 + 2, dims[1])):
            g1 = 0.0 if y == i1 else (1.0 - r1 if y > i1 else r1)
            for z in range(max(i2 - 1, 0), min(i2 + 2, dims[2])):
                g2 = 0.0 if z == i2 else (1.0 - r2 if z > i2 else r2)
                if (g0 * g0 + g1 * g1 + g2 * g2) * h2 > best:
                    continue  # the whole cell is farther than the nearest so far
                cell = (x * dims[1] + y) * dims[2] + z
                for u in range(start[cell], start[cell + 1]):
                    c = order[u]
                    e0, e1, e2 = q0 - pts[c, 0], q1 - pts[c, 1], q2 - pts[c, 2]
                    dd = e0 * e0 + e1 * e1 + e2 * e2
                    if dd < best or (dd == best and j >= 0 and c < j):
                        best = dd
                        j = c
    return j
