"""Rigid registration of a model to its segment of the scene cloud (point-to-plane ICP).

Used by the scene parser's final settle (the data forces then pull each object toward its ICP
pose, as the reference code's cached-ICP force mode did) and by the ``icp`` baseline.
"""

from __future__ import annotations

import math

import numpy as np

from ssp.cells import OUTSIDE, cell_sort, nearest_in_cells
from ssp.config import SSPConfig
from ssp.jit import kernel_array, njit
from ssp.library.model import ObjectModel
from ssp.probability import pose_change
from ssp.sample_grid import SampleGrid, posed_cell

__all__ = [
    "REFIT_ITERATIONS", "REFIT_MAX_JUMP_DEG", "REFIT_MAX_JUMP_M", "REFIT_MIN_POINTS",
    "REFIT_TOLERANCE", "bounded_refit", "even_rows", "facing_mask", "grid_icp", "icp_refine",
    "load_kernels", "point_to_plane_icp",
]  # fmt: skip

#: :func:`bounded_refit`: a result that moves the object more than this (m, deg at its centre
#: of mass) is a wrong local minimum, and ignored.
REFIT_MAX_JUMP_M = 0.02
REFIT_MAX_JUMP_DEG = 20.0

#: :func:`bounded_refit`: segments with fewer points are not registered.
REFIT_MIN_POINTS = 30

#: :func:`bounded_refit`: ICP steps at most, and the step (m and rad) below which it stops:
#: the polish's spring target need not be finer than 10 um. At most 8 steps left a carton of a
#: real capture (``examples/real_dev.py``, the milk scene) where it would fall.
REFIT_ITERATIONS = 20
REFIT_TOLERANCE = 1e-5


def even_rows(n_max: int, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """At most ``n_max`` rows of each array, evenly spaced (the same rows of every array)."""
    n = len(arrays[0])
    if n <= n_max:
        return arrays
    sel = np.linspace(0, n - 1, n_max).astype(int)
    return tuple(a[sel] for a in arrays)


def load_kernels() -> None:
    """Compile :func:`point_to_plane_icp`'s kernel, or load it from numba's cache (some 0.2 s;
    :class:`ssp.parser.SceneParser` does it when built, not in its first frame)."""
    p = np.eye(3) * 0.01
    point_to_plane_icp(p, np.eye(3), np.eye(4), p, None, max_distance=0.01, iterations=1,
                       n_points=3, min_pairs=1)  # fmt: skip


def facing_mask(
    points_w: np.ndarray, normals_w: np.ndarray, camera: np.ndarray | None
) -> np.ndarray:
    """Mask of the samples whose outward normal faces the camera (all when no camera)."""
    if camera is None:
        return np.ones(len(points_w), dtype=bool)
    return ((camera - points_w) * normals_w).sum(axis=1) > 0.0


def bounded_refit(
    model: ObjectModel,
    T_world_obj: np.ndarray,
    segment: np.ndarray,
    camera_position: np.ndarray | None,
    config: SSPConfig,
) -> np.ndarray | None:
    """:func:`icp_refine` of ``model`` from ``T_world_obj`` (4x4, m) onto its ``segment``
    (K, 3; world, m) with the polish's settings (``forces.icp_max_distance``,
    :data:`REFIT_ITERATIONS`): the refined pose, or None when the segment has fewer than
    :data:`REFIT_MIN_POINTS` points or the result moves the object :data:`REFIT_MAX_JUMP_M` /
    :data:`REFIT_MAX_JUMP_DEG` or more (a wrong local minimum). ``camera_position``: (3,)
    world, m, or None (every model sample may match)."""
    if len(segment) < REFIT_MIN_POINTS:
        return None
    T = np.asarray(T_world_obj, dtype=float)
    T_icp = icp_refine(
        model,
        T,
        segment,
        camera_position,
        max_distance=config.forces.icp_max_distance,
        iterations=REFIT_ITERATIONS,
        tolerance=REFIT_TOLERANCE,
    )
    dt, dth = pose_change(T, T_icp, None, model.center_of_mass)
    if dt < REFIT_MAX_JUMP_M and dth < math.radians(REFIT_MAX_JUMP_DEG):
        return T_icp
    return None


def icp_refine(
    model: ObjectModel,
    T_init: np.ndarray,
    segment: np.ndarray,
    camera_position: np.ndarray | None = None,
    *,
    max_distance: float = 0.01,
    iterations: int = 20,
    n_samples: int = 1000,
    n_points: int = 2000,
    min_pairs: int = 10,
    tolerance: float = 1e-6,
) -> np.ndarray:
    """Point-to-plane ICP of ``model`` onto its ``segment`` (K, 3), world frame; returns the
    refined pose (``T_init`` unchanged when fewer than ``min_pairs`` pairs are found).

    Correspondences are searched from each segment point to the nearest camera-facing model
    surface sample (facing at ``T_init``) within ``max_distance``, and the model moves to put
    the sample planes (the model's exact normals) through the points: a damped Gauss-Newton
    step of the linearised point-to-plane cost, ``iterations`` at most, stopping when a step
    moves less than 1 um and 1 urad.

    Why not :func:`trimesh.registration.icp`: it matches every point with no maximum
    correspondence distance, so model samples of parts hidden by other objects (no segment
    points there) would pull the pose towards the visible edge, and it is point-to-point on
    sparse samples (about 4 mm apart on a cube), which biases the fit by the sample spacing.
    Searching from the observed points keeps only what the camera saw, and the plane of each
    sample interpolates between samples.
    """
    pts, nrm = even_rows(
        n_samples,
        np.asarray(model.surface_points, dtype=float),
        np.asarray(model.surface_normals, dtype=float),
    )
    return point_to_plane_icp(
        pts,
        nrm,
        T_init,
        segment,
        camera_position,
        max_distance=max_distance,
        iterations=iterations,
        n_points=n_points,
        min_pairs=min_pairs,
        tolerance=tolerance,
    )


def point_to_plane_icp(
    pts: np.ndarray,
    nrm: np.ndarray,
    T_init: np.ndarray,
    segment: np.ndarray,
    camera: np.ndarray | None,
    *,
    max_distance: float,
    iterations: int,
    n_points: int,
    min_pairs: int = 10,
    tolerance: float = 1e-6,
) -> np.ndarray:
    """Point-to-plane ICP of model samples ``pts, nrm (S, 3)`` (model frame) onto ``segment
    (K, 3)`` (world, m), from ``T_init`` (4, 4): correspondences from at most ``n_points``
    segment points, evenly spaced, to the nearest sample facing the camera at ``T_init``
    within ``max_distance`` (m, exact), damped Gauss-Newton steps about the pairs' centroid,
    at most ``iterations``, until a step moves less than ``tolerance`` (m and rad). Returns
    ``T_world_obj (4, 4)`` (``T_init`` when there are fewer than ``min_pairs`` pairs).

    Solved in the model frame, so the samples never move: a pair's Jacobian row
    ``((p - c) x n, n)`` is ``G M`` with the per-sample constants ``G = (p x n, n)`` and a
    ``6 x 6`` matrix ``M`` of the centroid ``c``, so each step accumulates ``G^T G``.
    Compiled (:func:`_exact_icp`): the facing samples are binned in cubic cells of side
    ``max_distance`` once, and each point searches the 27 cells around its own, which hold
    every sample within ``max_distance`` of it (2.2-2.6x faster than a KD-tree and numpy's
    algebra per step, measured on the built-in models).
    """
    T = np.array(T_init, dtype=float)
    seg = np.asarray(segment, dtype=float).reshape(-1, 3)
    if len(seg) < min_pairs:
        return T
    (seg,) = even_rows(n_points, seg)
    return _exact_icp(
        kernel_array(pts),
        kernel_array(nrm),
        T,
        kernel_array(seg),
        np.zeros(3) if camera is None else kernel_array(camera),
        camera is not None,
        float(max_distance),
        int(iterations),
        int(min_pairs),
        float(tolerance) ** 2,
        MAX_CELLS,
    )


#: :func:`_exact_icp` bins its samples in at most this many cells (larger cells beyond).
MAX_CELLS = 1 << 18


@njit
def _facing(pts, nrm, T, cam, use_cam):
    """Mask ``(S,)`` of the samples ``pts, nrm`` (model frame) facing ``cam`` (world) at pose
    ``T``: ``n . (R^T (cam - t) - p) > 0``; all when not ``use_cam``."""
    keep = np.ones(pts.shape[0], dtype=np.bool_)
    if use_cam:
        d = cam - T[:3, 3]
        lc = np.zeros(3)
        for a in range(3):
            lc[a] = T[0, a] * d[0] + T[1, a] * d[1] + T[2, a] * d[2]
        for j in range(pts.shape[0]):
            keep[j] = (
                nrm[j, 0] * (lc[0] - pts[j, 0])
                + nrm[j, 1] * (lc[1] - pts[j, 1])
                + nrm[j, 2] * (lc[2] - pts[j, 2])
                > 0.0
            )
    return keep


@njit
def _gauss_newton_step(T, GtG, Gtb, csum, m, tol2):
    """One damped Gauss-Newton step of the point-to-plane cost from the upper triangle of
    ``G^T G (6, 6)``, ``G^T b (6,)`` and the sum of the ``m`` matched samples ``csum (3,)``
    (model frame), about their centroid: ``T <- T [Rd, c - Rd c + v]``, in place. Returns
    whether the step moved less than ``sqrt(tol2)`` (m and rad)."""
    for r in range(6):
        for q in range(r):
            GtG[r, q] = GtG[q, r]
    cx, cy, cz = csum[0] / m, csum[1] / m, csum[2] / m
    # (p - c) x n = p x n + n [c]_x:  M = [[I, 0], [[c]_x, I]]
    M = np.eye(6)
    M[3, 1], M[3, 2] = -cz, cy
    M[4, 0], M[4, 2] = cz, -cx
    M[5, 0], M[5, 1] = -cy, cx
    H = M.T @ GtG @ M
    damp = 1e-6 * np.trace(H) / 6.0 + 1e-12
    for r in range(6):
        H[r, r] += damp
    x = np.linalg.solve(H, M.T @ Gtb)
    w0, w1, w2, v0, v1, v2 = x[0], x[1], x[2], x[3], x[4], x[5]
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    Rd = np.eye(3)
    if theta >= 1e-12:  # Rodrigues
        ux, uy, uz = w0 / theta, w1 / theta, w2 / theta
        s, co = math.sin(theta), math.cos(theta)
        C = 1.0 - co
        Rd[0, 0], Rd[0, 1], Rd[0, 2] = co + ux * ux * C, ux * uy * C - uz * s, ux * uz * C + uy * s
        Rd[1, 0], Rd[1, 1], Rd[1, 2] = uy * ux * C + uz * s, co + uy * uy * C, uy * uz * C - ux * s
        Rd[2, 0], Rd[2, 1], Rd[2, 2] = uz * ux * C - uy * s, uz * uy * C + ux * s, co + uz * uz * C
    R = T[:3, :3].copy()
    t = T[:3, 3].copy()
    cen = np.array([cx, cy, cz])
    shift = cen - Rd @ cen + np.array([v0, v1, v2])
    T[:3, 3] = t + R @ shift
    T[:3, :3] = R @ Rd
    return v0 * v0 + v1 * v1 + v2 * v2 < tol2 and theta * theta < tol2


@njit
def _accumulate(GtG, Gtb, csum, p0, p1, p2, a0, a1, a2, e0, e1, e2):
    """Add the pair of sample ``p`` (normal ``a``) and point ``p + e`` (model frame) to the
    upper triangle of ``G^T G``, ``G^T b`` and the samples' sum (the row ``g = (p x a, a)``,
    ``b = a . e``)."""
    g0, g1, g2 = p1 * a2 - p2 * a1, p2 * a0 - p0 * a2, p0 * a1 - p1 * a0
    g = (g0, g1, g2, a0, a1, a2)
    b = a0 * e0 + a1 * e1 + a2 * e2
    for r in range(6):
        Gtb[r] += g[r] * b
        for q in range(r, 6):
            GtG[r, q] += g[r] * g[q]
    csum[0] += p0
    csum[1] += p1
    csum[2] += p2


@njit
def _exact_icp(pts, nrm, T_init, seg, cam, use_cam, max_distance, iterations, min_pairs, tol2,
               max_cells):  # fmt: skip
    """:func:`point_to_plane_icp`, compiled. The samples facing ``cam`` at ``T_init`` are
    sorted into cubic cells of side ``h >= max_distance`` (doubled until at most
    ``max_cells`` cover them; a counting sort). A point's nearest
    facing sample within ``max_distance`` (the first of equals) lies in the 27 cells around
    the point's own; the search starts from the point's match of the last step and skips the
    cells farther than the nearest found so far."""
    T = T_init.copy()
    keep = _facing(pts, nrm, T, cam, use_cam)
    live = np.flatnonzero(keep)
    if live.shape[0] < 3:
        return T
    lo, dims, h, inv_h, start, order = cell_sort(pts, live, max_distance, max_cells)
    max2 = max_distance * max_distance
    h2 = h * h
    prev = np.full(seg.shape[0], -1, dtype=np.int64)  # each point's match of the last step
    GtG = np.zeros((6, 6))
    Gtb = np.zeros(6)
    csum = np.zeros(3)
    for _ in range(iterations):
        R = T[:3, :3].copy()
        t = T[:3, 3].copy()
        GtG[:] = 0.0
        Gtb[:] = 0.0
        csum[:] = 0.0
        m = 0
        for k in range(seg.shape[0]):
            # the point in the model frame, R^T (s - t)
            d0, d1, d2 = seg[k, 0] - t[0], seg[k, 1] - t[1], seg[k, 2] - t[2]
            q0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
            q1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
            q2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
            j = nearest_in_cells(q0, q1, q2, prev[k], pts, lo, inv_h, dims, h2, max2, start, order)
            if j == OUTSIDE:
                continue  # no sample within h (the last step's match is kept)
            prev[k] = j
            if j < 0:
                continue
            _accumulate(GtG, Gtb, csum, pts[j, 0], pts[j, 1], pts[j, 2],
                        nrm[j, 0], nrm[j, 1], nrm[j, 2],
                        q0 - pts[j, 0], q1 - pts[j, 1], q2 - pts[j, 2])  # fmt: skip
            m += 1
        if m < min_pairs:
            break
        if _gauss_newton_step(T, GtG, Gtb, csum, m, tol2):
            break
    return T


def grid_icp(
    grid: SampleGrid,
    T_init: np.ndarray,
    segment: np.ndarray,
    camera: np.ndarray | None,
    *,
    max_distance: float,
    iterations: int,
    n_points: int,
    min_pairs: int = 10,
    tolerance: float = 1e-6,
) -> np.ndarray:
    """:func:`point_to_plane_icp` of the samples of ``grid`` (built with their normals, model
    frame) onto ``segment (K, 3)`` (world, m), with constant-time lookups: at most
    ``n_points`` of the segment points, evenly spaced, each matched to the nearest camera-facing
    (at ``T_init``) of its voxel's nearest samples of every normal direction
    (:meth:`SampleGrid.nearest` with ``keep``) within ``max_distance``, instead of the exact
    nearest facing sample. Returns ``T_world_obj (4, 4)`` (``T_init`` when there are fewer
    than ``min_pairs`` points or fewer than 3 facing samples).
    """
    if max_distance > grid.reach:
        raise ValueError(f"max_distance must be within the grid's reach {grid.reach} m")
    if grid.normals is None:
        raise ValueError("grid_icp needs a grid built with the samples' normals")
    T = np.array(T_init, dtype=float)
    seg = np.asarray(segment, dtype=float).reshape(-1, 3)
    if len(seg) < min_pairs:
        return T
    (seg,) = even_rows(n_points, seg)
    return _grid_icp(
        grid.points,
        grid.normals,
        grid.bins,
        grid.bin_index,
        grid.lo,
        1.0 / grid.voxel,
        grid.shape,
        T,
        kernel_array(seg),
        np.zeros(3) if camera is None else kernel_array(camera),
        camera is not None,
        float(max_distance) ** 2,
        int(iterations),
        int(min_pairs),
        float(tolerance) ** 2,
    )


@njit
def _grid_icp(pts, nrm, bins, bin_index, lo, inv_voxel, shape, T_init, seg, cam, use_cam, max2,
              iterations, min_pairs, tol2):  # fmt: skip
    """:func:`grid_icp`, compiled (the grid as its samples' ``bins``, ``bin_index``, ``lo``,
    ``inv_voxel`` and ``shape``); each step is one pass over the points ``seg`` that
    accumulates ``G^T G``, ``G^T b`` and the matched samples' sum."""
    T = T_init.copy()
    miss = pts.shape[0]
    keep = _facing(pts, nrm, T, cam, use_cam)
    if keep.sum() < 3:
        return T
    n_bins = bin_index.shape[1]
    live = np.zeros(n_bins, dtype=np.bool_)  # directions with a facing sample
    for j in range(miss):
        if keep[j]:
            live[bins[j]] = True
    GtG = np.zeros((6, 6))
    Gtb = np.zeros(6)
    csum = np.zeros(3)
    for _ in range(iterations):
        R = T[:3, :3].copy()
        t = T[:3, 3].copy()
        GtG[:] = 0.0
        Gtb[:] = 0.0
        csum[:] = 0.0
        m = 0
        for k in range(seg.shape[0]):
            cell, q0, q1, q2 = posed_cell(R, t, seg[k, 0], seg[k, 1], seg[k, 2], lo,
                                          inv_voxel, shape)  # fmt: skip
            if cell < 0:
                continue
            j = miss
            best = np.inf
            for bb in range(n_bins):  # the nearest facing of the directions' nearest samples
                if not live[bb]:
                    continue
                c = bin_index[cell, bb]
                if c == miss or not keep[c]:
                    continue
                f0, f1, f2 = q0 - pts[c, 0], q1 - pts[c, 1], q2 - pts[c, 2]
                d2 = f0 * f0 + f1 * f1 + f2 * f2
                if d2 < best:  # the first of equals
                    best = d2
                    j = c
            if best > max2:
                continue
            _accumulate(GtG, Gtb, csum, pts[j, 0], pts[j, 1], pts[j, 2],
                        nrm[j, 0], nrm[j, 1], nrm[j, 2],
                        q0 - pts[j, 0], q1 - pts[j, 1], q2 - pts[j, 2])  # fmt: skip
            m += 1
        if m < min_pairs:
            break
        if _gauss_newton_step(T, GtG, Gtb, csum, m, tol2):
            break
    return T
