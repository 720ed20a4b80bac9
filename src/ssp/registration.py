"""Rigid registration of a model to its segment of the scene cloud (point-to-plane ICP).

Used by the scene parser's final settle (the data forces then pull each object toward its ICP
pose, as the reference code's cached-ICP force mode did) and by the ``icp`` baseline.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ssp.library.model import ObjectModel

__all__ = ["even_rows", "facing_mask", "icp_refine"]


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
    T = np.array(T_init, dtype=float)
    seg = np.asarray(segment, dtype=float).reshape(-1, 3)
    if len(seg) < min_pairs:
        return T
    (seg,) = even_rows(n_points, seg)
    pts, nrm = even_rows(
        n_samples,
        np.asarray(model.surface_points, dtype=float),
        np.asarray(model.surface_normals, dtype=float),
    )
    keep = facing_mask(pts @ T[:3, :3].T + T[:3, 3], nrm @ T[:3, :3].T, camera_position)
    pts, nrm = pts[keep], nrm[keep]
    if len(pts) < 3:
        return T
    tree = cKDTree(pts)  # model frame: the segment is moved into it instead
    for _ in range(int(iterations)):
        R, t = T[:3, :3], T[:3, 3]
        q_model = (seg - t) @ R  # R^T (q - t)
        dist, idx = tree.query(q_model, k=1, distance_upper_bound=max_distance)
        ok = np.isfinite(dist)
        if ok.sum() < min_pairs:
            break
        q = seg[ok]
        p = pts[idx[ok]] @ R.T + t
        n = nrm[idx[ok]] @ R.T
        c = p.mean(axis=0)
        A = np.hstack([np.cross(p - c, n), n])  # d/d(omega, v) of n . (p' - q)
        b = -((p - q) * n).sum(axis=1)
        H = A.T @ A
        H += np.eye(6) * (1e-6 * np.trace(H) / 6.0 + 1e-12)
        x = np.linalg.solve(H, A.T @ b)
        omega, v = x[:3], x[3:]
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(omega).as_matrix()
        D[:3, 3] = c - D[:3, :3] @ c + v  # rotate about the centroid of the pairs, then shift
        T = D @ T
        if np.linalg.norm(v) < 1e-6 and np.linalg.norm(omega) < 1e-6:
            break
    return T
