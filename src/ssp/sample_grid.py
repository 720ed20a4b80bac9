"""A voxel grid of the nearest model sample: constant-time neighbour lookups in the model frame.

The estimator's refinement runs some twenty ICPs per segment, each a few hundred to a thousand
nearest-neighbour queries per step, always against the same model samples in the model frame.
:class:`SampleGrid` answers them from a grid built once per model: every voxel within
``reach`` of the samples holds its centre's nearest sample and that distance.

* :meth:`SampleGrid.nearest` is approximate: a query takes the nearest sample of its voxel's
  centre, at most a voxel diagonal (``voxel * sqrt(3)``) farther from it than the true nearest
  sample. A grid built with normals also holds each voxel's nearest sample of six normal
  directions, and ``nearest(q, keep)`` returns the nearest kept (facing) one of them: the two
  faces of a thin part never share a direction, so a point on the seen face is not matched to
  the hidden one.
* :meth:`SampleGrid.within` is exact: the centre's distance bounds the query's to within that
  half-diagonal; a query in that uncertain band is inside when one of its voxel's stored
  samples is within the radius, and only the rest go to the KD-tree.
* :meth:`SampleGrid.nearest_within` is exact too: the nearest sample of any point of a voxel
  lies within the centre's distance plus a voxel diagonal of the centre, so each voxel lists
  those samples (built at the first call), and a query compares its voxel's few (some 15 at a
  3 mm voxel) instead of descending a KD-tree: the nearest sample closer than a radius and
  that distance, as a KD-tree query with that (strict) upper bound returns them.
"""

from __future__ import annotations

import math

import numpy as np

from ssp.jit import kernel_array, njit
from ssp.kdtree import KDTree

__all__ = ["N_BINS", "SampleGrid", "normal_bins", "posed_cell", "voxel_of"]

#: The grid holds at most about this many voxels (the voxel grows for large models).
MAX_VOXELS = 1_500_000

#: m: more than the float32 rounding of the stored distances.
_ROUNDING = 1e-6


#: Normal directions of the per-direction grids: the sample's normal's dominant axis and its
#: sign (+x, -x, +y, -y, +z, -z). Opposite normals never share one, so the two faces of a
#: thin part keep their own nearest samples.
N_BINS = 6


def normal_bins(normals: np.ndarray) -> np.ndarray:
    """The direction bin ``(S,)`` int8 of each unit normal ``(S, 3)`` (:data:`N_BINS`)."""
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    axis = np.argmax(np.abs(n), axis=1)
    negative = n[np.arange(len(n)), axis] < 0
    return (2 * axis + negative).astype(np.int8)


class SampleGrid:
    """Nearest sample and its distance for every voxel within ``reach`` of ``points``.

    Args:
        points: ``(S, 3)`` samples (model frame, m), ``S < 2**31``.
        reach: m; queries farther than this from every sample are misses.
        voxel: voxel side, m (grown until the grid has at most :data:`MAX_VOXELS`).
        normals: ``(S, 3)`` unit normals, or None. With them the grid also holds, per
            voxel, the nearest sample of each normal direction (:data:`N_BINS`), so that
            :meth:`nearest` can return the nearest *facing* one (the ICP's matches).

    Attributes: ``points``; ``normals`` (or None); ``bins`` (each sample's direction);
    ``tree`` (KD-tree of the points); ``voxel``; ``half_diagonal`` (m); ``miss`` (the index
    of a miss: ``S``); ``index``, ``distance`` (per voxel, flat); ``bin_index`` (``(voxels,
    N_BINS)``, with normals).
    """

    def __init__(
        self, points: np.ndarray, reach: float, voxel: float, normals: np.ndarray | None = None
    ) -> None:
        self.points = np.array(points, dtype=float, order="C").reshape(-1, 3)  # a copy
        if len(self.points) == 0:
            raise ValueError("a sample grid needs at least one sample")
        self.tree = KDTree(self.points)
        self.reach = float(reach)
        self.miss = len(self.points)
        lo_pts, hi_pts = self.points.min(0), self.points.max(0)
        while True:
            # a border of at least reach + voxel: its voxels are misses, and out-of-grid
            # queries are clipped onto it
            margin = self.reach + 2.0 * voxel
            shape = np.ceil((hi_pts - lo_pts + 2 * margin) / voxel).astype(np.int64) + 1
            if int(np.prod(shape)) <= MAX_VOXELS:
                break
            voxel *= 1.25
        self.voxel = float(voxel)
        self.half_diagonal = 0.5 * math.sqrt(3.0) * self.voxel
        self.lo = lo_pts - margin
        self.shape = shape
        index, distance = _fill(self.points, self.lo, self.voxel, shape,
                                self.reach + self.half_diagonal)  # fmt: skip
        itype = np.int16 if self.miss < 2**15 else np.int32
        self.index = index.astype(itype)
        self.distance = distance.astype(np.float32)
        self._scale = np.array(shape[1:], dtype=np.uint32)
        self._lists: tuple[np.ndarray, np.ndarray] | None = None  # nearest_within's
        self.normals = None
        self.bins = np.zeros(0, dtype=np.int8)
        self.bin_index = np.zeros((0, 0), dtype=itype)
        if normals is not None:
            self.normals = np.array(normals, dtype=float, order="C").reshape(-1, 3)
            if self.normals.shape != self.points.shape:
                raise ValueError(f"{len(self.normals)} normals for {len(self.points)} samples")
            self.bins = normal_bins(self.normals)
            # (voxels, N_BINS): a voxel's candidates side by side, in one cache line
            self.bin_index = np.full((int(np.prod(shape)), N_BINS), self.miss, dtype=itype)
            for b in range(N_BINS):
                members = np.flatnonzero(self.bins == b)
                if len(members) == 0:
                    continue
                sub, _ = _fill(kernel_array(self.points[members]), self.lo, self.voxel,
                               shape, self.reach + self.half_diagonal)  # fmt: skip
                found = sub < len(members)
                self.bin_index[found, b] = members[sub[found]]

    def cells(self, q: np.ndarray) -> np.ndarray:
        """Flat voxel indices ``(N,)`` of queries ``q (N, 3)`` (model frame); queries outside
        the grid land on its border voxels, which are misses."""
        w = (q - self.lo) * (1.0 / self.voxel)
        # negative coordinates wrap to huge unsigned ones, clipped onto the far border
        i = w.astype(np.int32).view(np.uint32)
        np.minimum(i, (self.shape - 1).astype(np.uint32), out=i)
        flat = i[:, 0] * self._scale[0]
        flat += i[:, 1]
        flat *= self._scale[1]
        flat += i[:, 2]
        return flat

    def nearest(self, q: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
        """Approximate nearest sample of each query ``q (N, 3)``: the nearest of its voxel's
        centre, or :attr:`miss` beyond ``reach`` (plus at most the half-diagonal).

        ``keep``: ``(S,)`` mask of the samples that may be matched (the facing ones; needs
        the grid's normals): of the voxel's nearest sample of each direction, the kept one
        nearest to the query (the first direction of equals), or :attr:`miss`.
        """
        cells = self.cells(q)
        if keep is None:
            return self.index[cells]
        if self.normals is None:
            raise ValueError("nearest(keep=...) needs a grid built with normals")
        cand = self.bin_index[cells].T.astype(np.int64)  # (N_BINS, N)
        ok = cand != self.miss
        ok[ok] = np.asarray(keep, dtype=bool)[cand[ok]]
        pts = np.vstack([self.points, np.zeros((1, 3))])
        d2 = ((pts[cand] - q[None]) ** 2).sum(-1)
        d2[~ok] = np.inf
        best = np.argmin(d2, axis=0)
        out = cand[best, np.arange(len(q))]
        return np.where(np.isfinite(d2[best, np.arange(len(q))]), out, self.miss)

    def within(self, q: np.ndarray, radius: float, T: np.ndarray | None = None) -> np.ndarray:
        """Exact mask ``(N,)`` of the queries ``q (N, 3)`` with a sample within ``radius``
        (m, at most ``reach``). ``T``: the grid's pose ``(4, 4)``, the queries then in that
        pose's parent frame (a model's samples at ``T_world_obj`` and world points)."""
        if radius > self.reach:
            raise ValueError(f"radius {radius} m is beyond the grid's reach {self.reach} m")
        q = kernel_array(np.asarray(q, dtype=float).reshape(-1, 3))
        if len(q) == 0:
            return np.zeros(0, dtype=bool)
        T = np.eye(4) if T is None else np.asarray(T, dtype=float)
        band = self.half_diagonal + _ROUNDING
        status = _within_kernel(
            q, kernel_array(T[:3, :3]), kernel_array(T[:3, 3]),
            self.distance, self.lo, 1.0 / self.voxel, self.shape, radius - band, radius + band,
            self.points, self.index, self.bin_index, float(radius),
        )  # fmt: skip
        inside = status == 1
        unsure = np.flatnonzero(status == 2)
        if len(unsure):
            local = (q[unsure] - T[:3, 3]) @ T[:3, :3]
            dq, _ = self.tree.query(local, k=1, distance_upper_bound=radius)
            inside[unsure] = np.isfinite(dq)
        return inside

    def nearest_within(self, q: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact ``(distance (N,), index (N,) int64)`` of the sample nearest each query ``q
        (N, 3)`` closer than ``radius`` (m, strictly; at most ``reach``): ``(inf,`` :attr:`miss`
        ``)`` where none is; the first of equals. The same as ``tree.query(q, k=1,
        distance_upper_bound=radius)``, from the lists of the samples each voxel's points can
        have nearest (module docstring), made at the first call."""
        if radius > self.reach:
            raise ValueError(f"radius {radius} m is beyond the grid's reach {self.reach} m")
        if self._lists is None:
            slack = 2.0 * self.half_diagonal + _ROUNDING
            self._lists = _voxel_lists(self.points, self.lo, self.voxel, self.shape,
                                       self.distance.astype(np.float64), slack)  # fmt: skip
        start, members = self._lists
        return _nearest_within(
            kernel_array(np.asarray(q, dtype=float).reshape(-1, 3)), self.points, self.lo,
            1.0 / self.voxel, self.shape, start, members, float(radius) ** 2,
        )  # fmt: skip


@njit
def _voxel_lists(points, lo, voxel, shape, centre_distance, slack):
    """``(start, members)``: the samples within ``centre_distance + slack`` (m) of each
    voxel's centre, voxel ``v``'s being ``members[start[v]:start[v + 1]]`` in the samples'
    order (none for a voxel whose centre is farther than the grid's bound from every sample,
    ``centre_distance`` inf). Two passes over each sample's cube of voxels: count, then fill."""
    n0, n1, n2 = shape[0], shape[1], shape[2]
    nv = n0 * n1 * n2
    bound = 0.0
    for v in range(nv):
        if np.isfinite(centre_distance[v]) and centre_distance[v] + slack > bound:
            bound = centre_distance[v] + slack
    start = np.zeros(nv + 1, dtype=np.int64)
    members = np.empty(0, dtype=np.int32)
    fill = np.empty(0, dtype=np.int64)
    for fill_pass in range(2):
        if fill_pass == 1:
            for v in range(nv):
                start[v + 1] += start[v]
            members = np.empty(start[nv], dtype=np.int32)
            fill = start[:-1].copy()
        for s in range(points.shape[0]):
            x, y, z = points[s, 0], points[s, 1], points[s, 2]
            lo0, lo1, lo2, hi0, hi1, hi2 = _cube(x, y, z, bound, lo, voxel, shape)
            for i in range(lo0, hi0 + 1):
                dx = lo[0] + (i + 0.5) * voxel - x
                for j in range(lo1, hi1 + 1):
                    dy = lo[1] + (j + 0.5) * voxel - y
                    base = (i * n1 + j) * n2
                    for k in range(lo2, hi2 + 1):
                        v = base + k
                        r = centre_distance[v] + slack
                        if not np.isfinite(r):
                            continue
                        dz = lo[2] + (k + 0.5) * voxel - z
                        if dx * dx + dy * dy + dz * dz <= r * r:
                            if fill_pass == 0:
                                start[v + 1] += 1
                            else:
                                members[fill[v]] = s
                                fill[v] += 1
    return start, members


@njit
def _nearest_within(q, points, lo, inv_voxel, shape, start, members, max2):
    """:meth:`SampleGrid.nearest_within` of each query: its voxel's listed samples compared
    (out-of-grid queries are misses)."""
    n = q.shape[0]
    dist = np.full(n, np.inf)
    index = np.full(n, points.shape[0], dtype=np.int64)
    for k in range(n):
        v = voxel_of(q[k, 0], q[k, 1], q[k, 2], lo, inv_voxel, shape)
        if v < 0:
            continue
        best = max2
        j = -1
        for u in range(start[v], start[v + 1]):
            s = members[u]
            e0, e1, e2 = q[k, 0] - points[s, 0], q[k, 1] - points[s, 1], q[k, 2] - points[s, 2]
            d = e0 * e0 + e1 * e1 + e2 * e2
            if d < best:
                best = d
                j = s
        if j >= 0:
            dist[k] = np.sqrt(best)
            index[k] = j
    return dist, index


@njit
def posed_cell(R, t, x, y, z, lo, inv_voxel, shape):
    """``(flat, q0, q1, q2)``: the point ``(x, y, z)`` moved into a grid's frame, ``q = R^T
    ((x, y, z) - t)``, and the flat index of its voxel (-1 outside the grid: corner ``lo``,
    ``1 / voxel`` = ``inv_voxel``, ``shape``). Compiled, for the kernels."""
    d0, d1, d2 = x - t[0], y - t[1], z - t[2]
    q0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
    q1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
    q2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
    return voxel_of(q0, q1, q2, lo, inv_voxel, shape), q0, q1, q2


@njit
def voxel_of(q0, q1, q2, lo, inv_voxel, shape):
    """The flat index of the voxel holding the point ``(q0, q1, q2)`` (the grid's frame;
    corner ``lo``, ``1 / voxel`` = ``inv_voxel``, ``shape``), -1 outside the grid."""
    w0, w1, w2 = (q0 - lo[0]) * inv_voxel, (q1 - lo[1]) * inv_voxel, (q2 - lo[2]) * inv_voxel
    if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
        return -1
    i0, i1, i2 = int(w0), int(w1), int(w2)
    if i0 >= shape[0] or i1 >= shape[1] or i2 >= shape[2]:
        return -1
    return (i0 * shape[1] + i1) * shape[2] + i2


@njit
def _within_kernel(q, R, t, distance, lo, inv_voxel, shape, sure, maybe, points, index,
                   bin_index, radius):  # fmt: skip
    """Per query of ``q (N, 3)`` moved into the grid's frame (``R^T (q - t)``): 1 when its
    voxel centre's distance is at most ``sure`` or one of the voxel's stored samples (its
    nearest, ``index``, and those of ``bin_index``'s directions) lies within ``radius`` of
    it, else 2 when the centre's distance is at most ``maybe``, else 0."""
    out = np.zeros(q.shape[0], dtype=np.int8)
    n_bins = bin_index.shape[1]
    for k in range(q.shape[0]):
        cell, q0, q1, q2 = posed_cell(R, t, q[k, 0], q[k, 1], q[k, 2], lo, inv_voxel, shape)
        if cell < 0:
            continue
        d = distance[cell]
        if d <= sure:
            out[k] = 1
        elif d <= maybe:
            out[k] = 2
            for b in range(-1, n_bins):  # the stored samples settle most of the band
                j = index[cell] if b < 0 else bin_index[cell, b]
                if j >= points.shape[0]:
                    continue
                e0, e1, e2 = q0 - points[j, 0], q1 - points[j, 1], q2 - points[j, 2]
                if e0 * e0 + e1 * e1 + e2 * e2 <= radius * radius:
                    out[k] = 1
                    break
    return out


@njit
def _cube(x, y, z, bound, lo, voxel, shape):
    """The voxel ranges ``(lo0, lo1, lo2, hi0, hi1, hi2)`` (inclusive, clipped to the grid of
    corner ``lo``, side ``voxel``, ``shape``) of the voxels whose centres may lie within
    ``bound`` of the point ``(x, y, z)``."""
    lo0 = max(int(np.floor((x - bound - lo[0]) / voxel - 0.5)), 0)
    lo1 = max(int(np.floor((y - bound - lo[1]) / voxel - 0.5)), 0)
    lo2 = max(int(np.floor((z - bound - lo[2]) / voxel - 0.5)), 0)
    hi0 = min(int(np.ceil((x + bound - lo[0]) / voxel - 0.5)), shape[0] - 1)
    hi1 = min(int(np.ceil((y + bound - lo[1]) / voxel - 0.5)), shape[1] - 1)
    hi2 = min(int(np.ceil((z + bound - lo[2]) / voxel - 0.5)), shape[2] - 1)
    return lo0, lo1, lo2, hi0, hi1, hi2


@njit
def _fill(points, lo, voxel, shape, bound):
    """Per voxel of the grid (corner ``lo``, side ``voxel``, ``shape``), flat: the index of
    the sample nearest to its centre (the first of equals) and that distance, for centres
    within ``bound`` of a sample; ``len(points)`` and inf elsewhere. Each sample visits the
    voxels of its ``bound`` cube, so the cost is the samples times that cube's voxels."""
    n0, n1, n2 = shape[0], shape[1], shape[2]
    S = points.shape[0]
    best = np.full(n0 * n1 * n2, np.inf)
    index = np.full(n0 * n1 * n2, S, dtype=np.int64)
    b2 = bound * bound
    for s in range(S):
        x, y, z = points[s, 0], points[s, 1], points[s, 2]
        lo0, lo1, lo2, hi0, hi1, hi2 = _cube(x, y, z, bound, lo, voxel, shape)
        for i in range(lo0, hi0 + 1):
            dx = lo[0] + (i + 0.5) * voxel - x
            for j in range(lo1, hi1 + 1):
                dy = lo[1] + (j + 0.5) * voxel - y
                dxy = dx * dx + dy * dy
                if dxy > b2:
                    continue
                base = (i * n1 + j) * n2
                for k in range(lo2, hi2 + 1):
                    dz = lo[2] + (k + 0.5) * voxel - z
                    d2 = dxy + dz * dz
                    if d2 <= b2 and d2 < best[base + k]:
                        best[base + k] = d2
                        index[base + k] = s
    return index, np.sqrt(best)
