"""Rigid registration of a model to its segment of the scene cloud (point-to-plane ICP).

Used by the scene parser's final settle (the data forces then pull each object toward its ICP
pose, as the reference code's cached-ICP force mode did) and by the ``icp`` baseline.
"""

from __future__ import annotations

import math

import numpy as np

from ssp.jit import njit
from ssp.kdtree import KDTree
from ssp.library.model import ObjectModel
from ssp.sample_grid import SampleGrid, posed_cell

__all__ = ["even_rows", "facing_mask", "grid_icp", "icp_refine", "point_to_plane_icp"]


def even_rows(n_max: int, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """At most ``n_max`` rows of each array, evenly spaced (the same rows of every array)."""
    n = len(arrays[0])
    if n <= n_max:
        return arrays
    sel = np.linspace(0, n - 1, n_max).astype(int)
    return tuple(a[sel] for a in arrays)


def facing_mask(
    points_w: np.ndarray, normals_w: np.ndarray, camera: np.ndarray | None
) -> np.ndarray:
    """Mask of the samples whose outward normal faces the camera (all when no camera)."""
    if camera is None:
        return np.ones(len(points_w), dtype=bool)
    return ((camera - points_w) * normals_w).sum(axis=1) > 0.0


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


def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of the rotation vector ``w (3,)`` (rad; Rodrigues, in
    scalars: it runs once per ICP step)."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    theta = math.sqrt(x * x + y * y + z * z)
    if theta < 1e-12:
        return np.eye(3)
    x, y, z = x / theta, y / theta, z / theta
    s, c = math.sin(theta), math.cos(theta)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
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
    segment points to the samples facing the camera at ``T_init`` within ``max_distance``
    (m), damped Gauss-Newton steps about the pairs' centroid, at most ``iterations``, until a
    step moves less than 1 um and 1 urad. Returns ``T_world_obj (4, 4)`` (``T_init`` when
    there are fewer than ``min_pairs`` pairs).

    Solved in the model frame, so the samples never move: a pair's Jacobian row
    ``((p - c) x n, n)`` is ``G M`` with the per-sample constants ``G = (p x n, n)`` and a
    ``6 x 6`` matrix ``M`` of the centroid ``c``, so each step gathers ``G`` and forms ``G^T G``.
    """
    T = np.array(T_init, dtype=float)
    seg = np.asarray(segment, dtype=float).reshape(-1, 3)
    if len(seg) < min_pairs:
        return T
    (seg,) = even_rows(n_points, seg)
    keep = facing_mask(pts @ T[:3, :3].T + T[:3, 3], nrm @ T[:3, :3].T, camera)
    pts, nrm = pts[keep], nrm[keep]
    if len(pts) < 3:
        return T
    tree = KDTree(np.ascontiguousarray(pts))
    # per sample: p x n, n, p, p.n; then a zero row, which the misses (index len(pts)) gather
    Z = np.zeros((len(pts) + 1, 10))
    Z[:-1, :3], Z[:-1, 3:6], Z[:-1, 6:9] = np.cross(pts, nrm), nrm, pts
    Z[:-1, 9] = (pts * nrm).sum(1)
    M = np.eye(6)
    tol2 = float(tolerance) ** 2
    for _ in range(int(iterations)):
        R, t = T[:3, :3], T[:3, 3]
        q = (seg - t) @ R  # the segment in the model frame
        _, idx = tree.query(q, k=1, distance_upper_bound=max_distance)
        m = int(np.count_nonzero(idx < len(pts)))
        if m < min_pairs:
            break
        z = Z[idx]  # misses are zero rows: they add nothing below
        G, n = z[:, :6], z[:, 3:6]
        c = (np.ones(len(z)) @ z[:, 6:9]) / m  # centroid of the matched samples
        b = np.einsum("ij,ij->i", q, n) - z[:, 9]  # n . (q - p)
        # (p - c) x n = p x n - c x n = p x n + n [c]_x:  M = [[I, 0], [[c]_x, I]]
        M[3:, :3] = [[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]]
        H = M.T @ (G.T @ G) @ M
        H.flat[::7] += 1e-6 * np.trace(H) / 6.0 + 1e-12
        x = np.linalg.solve(H, M.T @ (G.T @ b))
        omega, v = x[:3], x[3:]
        Rd = _rotvec_matrix(omega)
        # about the pairs' centroid, then shifted (model frame): T <- T [Rd, c - Rd c + v]
        T[:3, 3] += R @ (c - Rd @ c + v)
        T[:3, :3] = R @ Rd
        if v @ v < tol2 and omega @ omega < tol2:  # moved less than the tolerance
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
        np.ascontiguousarray(seg),
        np.zeros(3) if camera is None else np.ascontiguousarray(camera, dtype=float),
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
    R = T[:3, :3].copy()
    t = T[:3, 3].copy()
    # the samples facing the camera at T_init: n . (R^T (cam - t)) > n . p
    keep = np.ones(miss, dtype=np.bool_)
    if use_cam:
        lc = R.T @ (cam - t)
        for j in range(miss):
            keep[j] = (
                nrm[j, 0] * (lc[0] - pts[j, 0])
                + nrm[j, 1] * (lc[1] - pts[j, 1])
                + nrm[j, 2] * (lc[2] - pts[j, 2])
                > 0.0
            )
    if keep.sum() < 3:
        return T
    n_bins = bin_index.shape[1]
    live = np.zeros(n_bins, dtype=np.bool_)  # directions with a facing sample
    for j in range(miss):
        if keep[j]:
            live[bins[j]] = True
    for _ in range(iterations):
        R = T[:3, :3].copy()
        t = T[:3, 3].copy()
        GtG = np.zeros((6, 6))
        Gtb = np.zeros(6)
        csum = np.zeros(3)
        g = np.zeros(6)
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
            p0, p1, p2 = pts[j, 0], pts[j, 1], pts[j, 2]
            e0, e1, e2 = q0 - p0, q1 - p1, q2 - p2
            a0, a1, a2 = nrm[j, 0], nrm[j, 1], nrm[j, 2]
            g[0], g[1], g[2] = p1 * a2 - p2 * a1, p2 * a0 - p0 * a2, p0 * a1 - p1 * a0
            g[3], g[4], g[5] = a0, a1, a2
            b = a0 * e0 + a1 * e1 + a2 * e2  # n . (q - p)
            for r in range(6):
                Gtb[r] += g[r] * b
                for q in range(r, 6):
                    GtG[r, q] += g[r] * g[q]
            csum[0] += p0
            csum[1] += p1
            csum[2] += p2
            m += 1
        if m < min_pairs:
            break
        for r in range(6):
            for q in range(r):
                GtG[r, q] = GtG[q, r]
        cx, cy, cz = csum[0] / m, csum[1] / m, csum[2] / m
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
        if theta >= 1e-12:
            ux, uy, uz = w0 / theta, w1 / theta, w2 / theta
            s, co = math.sin(theta), math.cos(theta)
            C = 1.0 - co
            Rd[0, 0], Rd[0, 1], Rd[0, 2] = (
                co + ux * ux * C,
                ux * uy * C - uz * s,
                ux * uz * C + uy * s,
            )
            Rd[1, 0], Rd[1, 1], Rd[1, 2] = (
                uy * ux * C + uz * s,
                co + uy * uy * C,
                uy * uz * C - ux * s,
            )
            Rd[2, 0], Rd[2, 1], Rd[2, 2] = (
                uz * ux * C - uy * s,
                uz * uy * C + ux * s,
                co + uz * uz * C,
            )
        cen = np.array([cx, cy, cz])
        shift = cen - Rd @ cen + np.array([v0, v1, v2])
        T[:3, 3] = t + R @ shift
        T[:3, :3] = R @ Rd
        if v0 * v0 + v1 * v1 + v2 * v2 < tol2 and theta * theta < tol2:
            break
    return T
