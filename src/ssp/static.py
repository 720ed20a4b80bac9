"""Static objects across frames: which objects are where they were, and which of them the
search can leave where they were (issue 19, "caching across frames for static objects").

An object is **unchanged** (:func:`is_unchanged`) when this frame's hypotheses agree with its
previous pose and that pose still fits the data. When every object is unchanged the parser
skips the search altogether (``search.unchanged_shortcut``). Otherwise an unchanged object
whose **neighbourhood is unchanged** too (:func:`settled_objects`: no object that changed
comes within ``search.reach`` of it, at any of that object's candidate poses) keeps its
previous pose without tests (``search.skip_settled``): testing its candidates again would
only repeat the previous frame's search on the same evidence. One that the first-guess settle
moves anyway (:func:`settle_moved`: what held it up is gone, e.g. an undetected block it
leaned on) is searched after all. Objects near a change, and the
objects that hold those up, are searched as usual, so the cost of a frame grows with what
changed in it, not with the size of the scene.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import SSPConfig
from ssp.geometry import hull_box
from ssp.library.model import ObjectModel
from ssp.probability import pose_change
from ssp.scene import Hypothesis
from ssp.scoring import SceneScorer
from ssp.search import CandidateSource

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "SETTLE_MOVED_DEG",
    "SETTLE_MOVED_M",
    "find_static",
    "is_unchanged",
    "keep_unchanged",
    "settle_moved",
    "settled_objects",
]

#: A settled object that the first-guess settle moved more than this (m, deg at the centre of
#: mass) is searched after all.
SETTLE_MOVED_M = 0.001
SETTLE_MOVED_DEG = 1.0


def is_unchanged(
    scorer: SceneScorer,
    i: int,
    T_prev: np.ndarray,
    fit_prev: float,
    hypotheses: Sequence[Hypothesis],
    model: ObjectModel,
    config: SSPConfig,
) -> bool:
    """Is object ``i`` of the scorer's world where it was (``T_prev``, 4x4, m)? Its
    ``hypotheses`` agree (the per-axis median of their centres of mass lies within
    ``temporal.static_translation`` of the previous one) and ``T_prev`` fits this frame's data
    about as well as it fitted the frame that set it: ``c_now >= ratio c_then - tolerance``
    (``search.unchanged_fit_ratio``, ``unchanged_fit_tolerance``; ``fit_prev`` = c_then)."""
    s = config.search
    c = np.asarray(model.center_of_mass, dtype=float)
    at = [h.T_world_obj[:3, :3] @ c + h.T_world_obj[:3, 3] for h in hypotheses]
    centre = np.median(at, axis=0)
    was = T_prev[:3, :3] @ c + T_prev[:3, 3]
    if np.linalg.norm(centre - was) >= config.temporal.static_translation:
        return False
    c_now = scorer.fit_fraction(i, T_prev)
    return c_now >= s.unchanged_fit_ratio * fit_prev - s.unchanged_fit_tolerance


def settled_objects(
    unchanged: Iterable[str],
    poses: Mapping[str, Sequence[np.ndarray]],
    models: Mapping[str, ObjectModel],
    reach: float,
) -> set[str]:
    """The ``unchanged`` objects that no other object comes near: their box at their previous
    pose stays farther than ``reach`` (m, per axis) from the box of every object that is not
    unchanged, over all that object's ``poses`` (``id -> candidate poses``: previous pose,
    hypotheses). Every object of the scene must be in ``poses``; an unchanged object's first
    pose is its previous one."""
    still = set(unchanged)
    moving = [oid for oid in poses if oid not in still]
    if not still:
        return set()
    if not moving:
        return still
    lo_m, hi_m = zip(*(hull_box(models[o].hull_vertices, poses[o]) for o in moving), strict=True)
    lo_m, hi_m = np.array(lo_m) - reach, np.array(hi_m) + reach
    out = set()
    for oid in still:
        lo, hi = hull_box(models[oid].hull_vertices, poses[oid][:1])
        near = np.all((lo[None] <= hi_m) & (hi[None] >= lo_m), axis=1)
        if not near.any():
            out.add(oid)
    return out


def settle_moved(objects: Mapping[str, tuple[np.ndarray, np.ndarray, ObjectModel]]) -> set[str]:
    """The objects (``id -> (previous pose, pose after the first-guess settle, model)``, 4x4,
    m) that the settle moved more than :data:`SETTLE_MOVED_M` or :data:`SETTLE_MOVED_DEG`
    (symmetry-aware, at the centre of mass)."""
    out = set()
    for oid, (T_prev, T_now, model) in objects.items():
        dt, dth = pose_change(T_prev, T_now, model.symmetry, model.center_of_mass)
        if dt > SETTLE_MOVED_M or np.degrees(dth) > SETTLE_MOVED_DEG:
            out.add(oid)
    return out


# ------------------------------------------------------------------ the parser's stages
def find_static(ctx: FrameContext) -> None:
    """Stage *static objects*: the detected known objects that are unchanged
    (:func:`is_unchanged`), and whether the whole frame is (``search.unchanged_shortcut``:
    every known object detected and unchanged, none new, none missing).

    Sets ``static`` and ``unchanged``.
    """
    cfg, known, groups, sim = ctx.config, ctx.known, ctx.groups, ctx.sim
    detected = sorted(groups)
    ctx.static = {
        oid
        for oid in detected
        if oid in known
        and is_unchanged(
            sim.scorer,
            sim.world.index(oid),
            known[oid].T_world_obj,
            known[oid].fit,
            groups[oid],
            ctx.models[oid],
            cfg,
        )  # fmt: skip
    }
    ctx.unchanged = (
        cfg.search.unchanged_shortcut
        and bool(known)
        and not ctx.missing
        and set(detected) == set(known)
        and ctx.static == set(detected)
    )


def keep_unchanged(ctx: FrameContext) -> None:
    """Stage *unchanged shortcut* (run only when nothing changed, instead of the first guess
    and the search): every object back at its previous pose, settled with data forces
    (``search.final_settle``) unless the polish follows.

    Sets ``chosen``.
    """
    sim, ids = ctx.sim, ctx.sim.world.ids
    sim.world.set_poses({oid: ctx.prev_pose[oid] for oid in ids})
    if not ctx.config.forces.final_icp:
        sim.simulator.settle(ctx.config.search.final_settle, with_forces=True)
    ctx.chosen = {oid: CandidateSource.UNCHANGED for oid in ids}
