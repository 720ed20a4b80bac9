"""Distractors: objects in the scene that are not in the object library.

Real tables hold things the robot has no model of; an estimator still proposes library objects
on them (a can taken for a cube, a box for a block). These simple convex shapes are physical
objects of the synthetic scenes (settled by MuJoCo, ray cast into the depth, given their own
instance mask) but never part of the ground truth the methods are scored against. Each is
convex, so its single convex part is exact (no decomposition).
"""

from __future__ import annotations

from functools import lru_cache

import trimesh

from ssp.config import LibraryConfig
from ssp.library.build import build_model
from ssp.library.model import ObjectModel

__all__ = ["DISTRACTOR_SHAPES", "distractor_models"]

#: name -> (how it is made, size in m): a soda can, a ball, a flat box, a tall bottle.
DISTRACTOR_SHAPES = {
    "can": ("cylinder", (0.033, 0.12)),
    "ball": ("sphere", (0.035,)),
    "flat_box": ("box", (0.12, 0.08, 0.03)),
    "bottle": ("cylinder", (0.035, 0.21)),
}


def _mesh(kind: str, size: tuple[float, ...]) -> trimesh.Trimesh:
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=size[0], height=size[1], sections=32)
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=3, radius=size[0])
    return trimesh.creation.box(size)


@lru_cache(maxsize=1)
def _models() -> tuple[ObjectModel, ...]:
    cfg = LibraryConfig()
    out = []
    for name, (kind, size) in DISTRACTOR_SHAPES.items():
        mesh = _mesh(kind, size)
        out.append(
            build_model(f"distractor_{name}", mesh, config=cfg, density=400.0, convex_parts=[mesh])
        )
    return tuple(out)


def distractor_models() -> dict[str, ObjectModel]:
    """Name -> model of every distractor (built once per process)."""
    return {m.name: m for m in _models()}
