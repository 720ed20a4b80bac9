"""Where objects can go: in the camera's view, clear of each other on the table, at rest.

Shared by the synthetic scene builders (:mod:`ssp.sim.generate`, :mod:`ssp.sim.events`). Units:
metres; poses ``T_world_obj`` (4, 4), world z up, table top at z = 0.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from ssp.camera import Camera
from ssp.geometry import yaw_pose
from ssp.library.model import ObjectModel

__all__ = [
    "VIEW_MARGIN_PX",
    "footprint",
    "hull_world",
    "in_view",
    "poly_distance",
    "random_resting",
    "stable_poses",
]

#: Objects must project at least this far (full-resolution pixels) inside the image border.
VIEW_MARGIN_PX = 8.0


def hull_world(model: ObjectModel, T: np.ndarray) -> np.ndarray:
    """World positions ``(V, 3)`` of the model's convex hull vertices at pose ``T``."""
    return model.hull_vertices @ T[:3, :3].T + T[:3, 3]


def in_view(model: ObjectModel, T: np.ndarray, T_wc: np.ndarray, camera: Camera) -> bool:
    """Every hull vertex in front of the camera and :data:`VIEW_MARGIN_PX` inside the image."""
    p = (hull_world(model, T) - T_wc[:3, 3]) @ T_wc[:3, :3]
    if not (p[:, 2] > 0.05).all():
        return False
    uv = camera.project(p)
    m = VIEW_MARGIN_PX
    return bool(
        (uv[:, 0] >= m).all()
        and (uv[:, 0] <= camera.width - 1 - m).all()
        and (uv[:, 1] >= m).all()
        and (uv[:, 1] <= camera.height - 1 - m).all()
    )


def footprint(model: ObjectModel, T: np.ndarray) -> np.ndarray:
    """Convex hull (CCW, (P, 2)) of the object's projection on the table, m."""
    xy = hull_world(model, T)[:, :2]
    return xy[ConvexHull(xy).vertices]


def _separated(P: np.ndarray, Q: np.ndarray) -> bool:
    """Separating-axis test for two convex polygons (True: they do not overlap)."""
    for A in (P, Q):
        e = np.roll(A, -1, axis=0) - A
        normals = np.column_stack([e[:, 1], -e[:, 0]])
        pa = P @ normals.T
        qa = Q @ normals.T
        if ((pa.max(0) < qa.min(0)) | (qa.max(0) < pa.min(0))).any():
            return True
    return False


def _points_to_segments(P: np.ndarray, Q: np.ndarray) -> float:
    """Smallest distance from the points ``P`` to the edges of polygon ``Q``."""
    a = Q
    d = np.roll(Q, -1, axis=0) - Q
    ap = P[:, None, :] - a[None]
    t = np.clip((ap * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-18)[None], 0.0, 1.0)
    diff = ap - t[..., None] * d[None]
    return float(np.sqrt((diff * diff).sum(-1).min()))


def poly_distance(P: np.ndarray, Q: np.ndarray) -> float:
    """Distance between two convex polygons (0 if they overlap), m."""
    if not _separated(P, Q):
        return 0.0
    return min(_points_to_segments(P, Q), _points_to_segments(Q, P))


@lru_cache(maxsize=128)
def stable_poses(model: ObjectModel, min_prob: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Stable resting transforms of ``model`` (lowest point at z = 0) and their probabilities
    (those above ``min_prob``, renormalised; at least the most probable one)."""
    transforms, probs = trimesh.poses.compute_stable_poses(model.mesh, n_samples=1, threshold=0.0)
    transforms = np.asarray(transforms, dtype=float)
    probs = np.asarray(probs, dtype=float)
    if len(transforms) == 0:
        T = np.eye(4)
        T[2, 3] = -model.mesh.bounds[0, 2]
        return T[None], np.ones(1)
    order = np.argsort(-probs, kind="stable")
    transforms, probs = transforms[order], probs[order]
    keep = probs >= min_prob
    keep[0] = True
    return transforms[keep], probs[keep] / probs[keep].sum()


def random_resting(model: ObjectModel, rng: np.random.Generator, region) -> np.ndarray:
    """A random stable resting pose (by probability), random yaw, its box centre at a uniform
    spot of ``region`` ``((x0, x1), (y0, y1))``."""
    transforms, probs = stable_poses(model)
    j = int(rng.choice(len(probs), p=probs))
    yaw = float(rng.uniform(-np.pi, np.pi))
    x = float(rng.uniform(*region[0]))
    y = float(rng.uniform(*region[1]))
    T = yaw_pose(yaw) @ transforms[j]
    centre = model.mesh.bounds.mean(axis=0) @ T[:3, :3].T + T[:3, 3]
    T[:2, 3] += np.array([x, y]) - centre[:2]
    return T
