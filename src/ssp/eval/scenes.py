"""Small deterministic physical scenes built from library models (benchmarks, demo, tests).

Every builder returns ``(instances, poses)``: object instances and their initial ``T_world_obj``
(table top at z = 0). Objects are placed resting on the table in a stable orientation found by
trimesh (``compute_stable_poses``), so a scene settles quickly.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import trimesh

from ssp.geometry import make_pose
from ssp.library.model import ObjectInstance, ObjectModel


@lru_cache(maxsize=64)
def _resting_rotation(model_id: int, mesh: trimesh.Trimesh) -> np.ndarray:
    """Most probable stable resting transform of ``mesh`` (4x4, lowest point at z = 0)."""
    transforms, probs = trimesh.poses.compute_stable_poses(mesh, n_samples=1, threshold=0.0)
    if len(transforms) == 0:
        T = np.eye(4)
        T[2, 3] = -mesh.bounds[0, 2]
        return T
    return np.asarray(transforms[int(np.argmax(probs))], dtype=float)


def resting_pose(model: ObjectModel, x: float, y: float, yaw: float = 0.0) -> np.ndarray:
    """``T_world_obj`` of ``model`` resting on the table at (x, y), turned by ``yaw`` (rad)."""
    T_rest = _resting_rotation(id(model), model.mesh)
    c, s = np.cos(yaw), np.sin(yaw)
    T_yaw = make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), [x, y, 0.0])
    T = T_yaw @ T_rest
    # centre the footprint on (x, y)
    centre = (model.mesh.bounds.mean(axis=0) @ T[:3, :3].T) + T[:3, 3]
    T[:2, 3] += np.array([x, y]) - centre[:2]
    return T


def scatter(models: Sequence[ObjectModel], n: int, spacing: float, seed: int = 0):
    """``n`` objects (cycling through ``models``) resting on a square grid ``spacing`` m apart."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    instances, poses = [], {}
    for i in range(n):
        model = models[i % len(models)]
        ix, iy = i % side, i // side
        x, y = (ix - (side - 1) / 2) * spacing, (iy - (side - 1) / 2) * spacing
        inst = ObjectInstance(f"{model.name}_{i}", model)
        instances.append(inst)
        poses[inst.id] = resting_pose(model, x, y, yaw=float(rng.uniform(-np.pi, np.pi)))
    return instances, poses


def tower(model: ObjectModel, n: int, gap: float = 0.0):
    """``n`` copies of a box-like ``model`` stacked at x = y = 0, faces in contact (+``gap``)."""
    h = float(model.extents[2])
    z0 = -float(model.mesh.bounds[0, 2])
    instances, poses = [], {}
    for i in range(n):
        inst = ObjectInstance(f"{model.name}_{i}", model)
        instances.append(inst)
        poses[inst.id] = make_pose(t=[0.0, 0.0, z0 + i * (h + gap)])
    return instances, poses


def pile(models: Sequence[ObjectModel], n: int, seed: int = 0, spread: float = 0.06):
    """``n`` objects dropped in a column inside +-``spread`` m: they land on each other."""
    rng = np.random.default_rng(seed)
    instances, poses = [], {}
    z = 0.0
    for i in range(n):
        model = models[i % len(models)]
        x, y = rng.uniform(-spread, spread, size=2)
        T = resting_pose(model, float(x), float(y), yaw=float(rng.uniform(-np.pi, np.pi)))
        T[2, 3] += z + 0.005
        z += float(model.extents.min()) + 0.01
        inst = ObjectInstance(f"{model.name}_{i}", model)
        instances.append(inst)
        poses[inst.id] = T
    return instances, poses
