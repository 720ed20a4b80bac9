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

import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import SSPConfig
from ssp.estimate import Rejected
from ssp.geometry import hull_box
from ssp.library.model import ObjectModel
from ssp.probability import pose_change
from ssp.scene import Hypothesis
from ssp.scoring import SceneScorer
from ssp.search import CandidateSource, prepare_world
from ssp.verification import verify_new

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

log = logging.getLogger(__name__)

__all__ = [
    "RANKED_FIT_SLACK",
    "RANKED_TURN",
    "REPEATED",
    "SETTLE_MOVED_DEG",
    "SETTLE_MOVED_M",
    "find_static",
    "is_unchanged",
    "keep_unchanged",
    "repeated_rejections",
    "settle_moved",
    "settled_objects",
]

#: Added to the reason of an object rejected again (:func:`repeated_rejections`).
REPEATED = "; rejected there in the previous frame too, and nothing else changed"

#: A settled object that the first-guess settle moved more than this (m, deg at the centre of
#: mass) is searched after all.
SETTLE_MOVED_M = 0.001
SETTLE_MOVED_DEG = 1.0


#: An object whose hypotheses agree with its previous pose only through the best-scored one
#: (:func:`is_unchanged`) is unchanged when its previous pose fits this frame's data within
#: this much (fraction of the fit c) of every hypothesis.
RANKED_FIT_SLACK = 0.05

#: ... and hypotheses turned less than this (rad) from the best one are copies of it (an
#: estimator's distinct orientations differ by more: its refinement keeps candidates turned
#: by over 15 deg).
RANKED_TURN = np.radians(15.0)


def _centres(poses: Sequence[np.ndarray], model: ObjectModel) -> np.ndarray:
    """``(n, 3)`` centres of mass of ``model`` at ``poses`` (4x4, m)."""
    c = np.asarray(model.center_of_mass, dtype=float)
    return np.array([T[:3, :3] @ c + T[:3, 3] for T in poses]).reshape(-1, 3)


def is_unchanged(
    scorer: SceneScorer,
    i: int,
    T_prev: np.ndarray,
    fit_prev: float,
    hypotheses: Sequence[Hypothesis],
    model: ObjectModel,
    config: SSPConfig,
) -> bool:
    """Is object ``i`` of the scorer's world where it was (``T_prev``, 4x4, m)?

    ``T_prev`` fits this frame's data about as well as it fitted the frame that set it
    (``c_now >= ratio c_then - tolerance``: ``search.unchanged_fit_ratio``,
    ``unchanged_fit_tolerance``; ``fit_prev`` = c_then), and its ``hypotheses`` (best first)
    agree: the per-axis median of their centres of mass lies within
    ``temporal.static_translation`` of ``T_prev``'s (noisy copies of one pose, some of them
    outliers), or, when their scores rank them, the median of the best one and those turned
    less than :data:`RANKED_TURN` from it (symmetry-aware) does, and ``T_prev`` fits the data
    within :data:`RANKED_FIT_SLACK` of every hypothesis. An estimator proposes its best pose
    and the other orientations a partial view allows, whose median lies anywhere between them;
    noisy copies of one pose are alike, and the best of them alone does not decide (its score
    may say nothing); had the object moved, one of its poses would fit better than where it
    was.
    """
    s, near = config.search, config.temporal.static_translation
    at = _centres([h.T_world_obj for h in hypotheses], model)
    was = _centres([T_prev], model)[0]
    agree = bool(np.linalg.norm(np.median(at, axis=0) - was) < near)
    if not agree:
        if len({h.score for h in hypotheses}) < 2:
            return False
        best = hypotheses[0].T_world_obj
        alike = [
            k
            for k, h in enumerate(hypotheses)
            if pose_change(best, h.T_world_obj, model.symmetry, model.center_of_mass)[1]
            < RANKED_TURN
        ]
        if np.linalg.norm(np.median(at[alike], axis=0) - was) >= near:
            return False
    c_now = scorer.fit_fraction(i, T_prev)
    if c_now < s.unchanged_fit_ratio * fit_prev - s.unchanged_fit_tolerance:
        return False
    if agree:
        return True
    best_fit = max(scorer.fit_fraction(i, h.T_world_obj) for h in hypotheses)
    return c_now >= best_fit - RANKED_FIT_SLACK


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
def repeated_rejections(ctx: FrameContext, new: Iterable[str]) -> dict[str, Rejected]:
    """The ``new`` objects (ids) that the previous frame rejected already: one of its rejected
    objects (:attr:`FrameContext.remembered`) of the same class lies where one of this
    object's hypotheses puts it (centres of mass within ``temporal.association_distance``, as
    the association matches an object across frames: an estimator's poses of a thing it does
    not know wander), and the data supports the object at none of its hypotheses
    (:func:`ssp.verification.verify_new` with the check after the search). Each is rejected
    for what the data says at its best hypothesis, said to be repeated (:data:`REPEATED`): an
    unknown thing on the table (a distractor) is then not a change of the scene, frame after
    frame."""
    cfg = ctx.config
    seen_before = []
    for oid in new:
        model = ctx.models[oid]
        at = _centres([h.T_world_obj for h in ctx.groups[oid]], model)
        was = _centres([r.T_world_obj for r in ctx.remembered if r.class_name == model.name],
                       model)  # fmt: skip
        gap = np.linalg.norm(at[:, None, :] - was[None, :, :], axis=2)
        if (gap < cfg.temporal.association_distance).any():
            seen_before.append(oid)
    rejected = verify_new(seen_before, ctx.groups, ctx.models, ctx.segment_trees, ctx.owner,
                          ctx.view, cfg, loose=False)  # fmt: skip
    return {oid: replace(r, reason=r.reason + REPEATED) for oid, r in rejected.items()}


def find_static(ctx: FrameContext) -> None:
    """Stage *static objects*: the detected known objects that are unchanged
    (:func:`is_unchanged`), and whether the whole frame is (``search.unchanged_shortcut``:
    every known object detected and unchanged, none missing, and every new one rejected in the
    previous frame already: :func:`repeated_rejections`, which then leave the frame as
    rejected, and the world is prepared again without them).

    Sets ``static`` and ``unchanged``; may update ``rejected``, ``groups``, ``first``,
    ``classes`` and ``simulation``.
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
    new = [oid for oid in detected if oid not in known]
    ctx.unchanged = (
        cfg.search.unchanged_shortcut
        and bool(known)
        and not ctx.missing
        and ctx.static == set(known)
    )
    if ctx.unchanged and new:
        repeated = repeated_rejections(ctx, new)
        ctx.unchanged = len(repeated) == len(new)
        if ctx.unchanged:
            for oid, r in repeated.items():
                log.info("%s (%s) rejected again: %s", oid, r.class_name, r.reason)
                del ctx.groups[oid], ctx.first[oid], ctx.classes[oid]
            ctx.rejected.update(repeated)
            with ctx.timer("world"):
                prepare_world(ctx)  # the world without them


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
