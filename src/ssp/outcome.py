"""The frame's outcome: each object's transition mode and reason, and the scene estimate.

The last stages of :meth:`ssp.parser.SceneParser.update`. :func:`fuse_at_rest` gives each
object at rest the mean of its estimates since it came to rest (:func:`ssp.motion.at_rest`)
where that mean stays clear of its neighbours; :func:`transition_modes` gives every
object that stays its output pose (the symmetric equivalent closest to its previous one,
:func:`ssp.temporal.snap_symmetric`), its transition mode (paper section IV-C:
:func:`ssp.temporal.classify`), its reason in words and the frame's per-object warnings;
:func:`scene_estimate` adds the removed objects, the support edges and every segment's
verdict, and builds the :class:`~ssp.estimate.SceneEstimate`. What the next frame remembers
(:attr:`FrameContext.next_known`) is committed by the parser.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ssp.correction import correction_note, correction_of
from ssp.estimate import ObjectEstimate, SceneEstimate, SupportEdge
from ssp.frame_context import Known
from ssp.motion import (
    at_rest,
    explains_before,
    moved_in_world,
    object_residual,
    prefers_estimate,
    seen_points,
)
from ssp.orientation import Orientation, Ranking
from ssp.probability import pose_change
from ssp.retention import TriageState
from ssp.scene import TransitionMode
from ssp.search import CandidateSource
from ssp.segments import segment_verdicts
from ssp.support import GROUND
from ssp.temporal import classify, snap_symmetric
from ssp.verification import evidence

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "FUSION_DEPTH_SLACK",
    "KEEP_FIT_MARGIN",
    "KEEP_STILL_FRAMES",
    "TABLE",
    "fuse_at_rest",
    "report_moved",
    "scene_estimate",
    "transition_modes",
]

log = logging.getLogger(__name__)

#: Name of the ground in support edges.
TABLE = "table"


#: An object static in the world (the data where it was is as it was) whose new estimate
#: explains this much less of its visible surface than its previous pose does in the same frame
#: keeps the previous pose (:func:`_kept_where_it_was`) ...
KEEP_FIT_MARGIN = 0.1
#: ... when it was at rest the frame before (:attr:`ssp.frame_context.Known.still`). The
#: search can land on a worse hypothesis of an object at rest (issue 32: a block reported
#: static drifted 7 -> 36 mm over four frames of a moving camera, each estimate explaining
#: 4-42 % of it where its old pose explained 78 %); an object not yet at rest may be kept at a
#: wrong pose its few visible points fit as well (development seeds: a block 16 % visible kept
#: 19 mm off for 8 frames), so only a pose already established is kept.
KEEP_STILL_FRAMES = 1

#: A fused pose may not push an object deeper into another (or the table) than its estimate
#: by more than this, m.
FUSION_DEPTH_SLACK = 1e-4


def fuse_at_rest(ctx: FrameContext) -> None:
    """Stage *static fusion*: every known object at rest (:func:`ssp.motion.at_rest`) is output
    at the mean of its estimates since it came to rest, unless that mean would push it into another
    object or the table (its deepest contact more than :data:`FUSION_DEPTH_SLACK` deeper than
    at its estimate; tested in the frame's world, left as it was): output means of stacked
    blocks put them up to 1.2 mm into each other on development seeds.

    Sets ``fused``.
    """
    ctx.fused = {}
    if ctx.config.temporal.static_fusion_frames <= 1:
        return
    score, world = ctx.scene_score, ctx.sim.world
    fused, estimate = {}, {}
    for i, oid in enumerate(score.ids):
        if oid in ctx.gone or oid in ctx.placed or oid in ctx.old_of:
            continue
        T = at_rest(ctx, oid, score.poses[i])
        if T is not None:
            fused[oid], estimate[oid] = T, score.poses[i]
    if not fused:
        return
    before = _deepest(world)
    state = world.save_state()
    try:
        for _ in range(3):  # an object put back may free another
            world.set_poses(fused)
            deeper = _deepest(world) > before + FUSION_DEPTH_SLACK
            back = [oid for oid in fused if deeper[world.index(oid)]]
            if not back:
                break
            for oid in back:
                world.set_pose(oid, estimate[oid])
                del fused[oid]
    finally:
        world.restore_state(state)
    ctx.fused = fused


def _deepest(world, skip: Sequence[int] = ()) -> np.ndarray:
    """Each object's deepest contact in ``world`` now (m; 0 without one), world order, with
    the table or an object whose index is not in ``skip``."""
    c = world.contacts()
    out = np.zeros(len(world.ids))
    skipped_a, skipped_b = np.isin(c.obj_a, skip), np.isin(c.obj_b, skip)
    for side, other_skipped in ((c.obj_a, skipped_b), (c.obj_b, skipped_a)):
        ok = (side >= 0) & ~other_skipped
        np.maximum.at(out, side[ok], np.maximum(c.depth[ok], 0.0))
    return out


def transition_modes(ctx: FrameContext) -> None:
    """Stage *transition modes*: every object that stays, at its output pose, with its mode,
    reason and terms; a warning for each one the camera sees through (not placed by its data)
    or that would fall (``verification.fall_stability``).

    Sets ``objects`` and ``next_known``; updates ``warnings``.
    """
    cfg, score, models = ctx.config, ctx.scene_score, ctx.models
    for i, oid in enumerate(score.ids):
        if oid in ctx.gone:
            continue
        model = models[oid]
        T = ctx.placed.get(oid, score.poses[i])
        out_id = ctx.old_of.get(oid, oid)
        prev = ctx.prev_pose.get(out_id)
        if prev is not None:
            T = snap_symmetric(prev, T, model.symmetry)
        v = ctx.verdicts.get(oid)
        ephemeral = v is not None and v.state == TriageState.EPHEMERAL
        retained = oid in ctx.retained or (ephemeral and bool(score.graph.children(i)))
        mode = classify(prev, T, model.symmetry, cfg.temporal, retained, model.center_of_mass)
        corrected, still, kept_fit = None, 0, None
        if mode == TransitionMode.PERTURBED and oid not in ctx.old_of:
            assert prev is not None, "a perturbed object has a previous pose"
            corrected, fit_there = _corrected(ctx, oid, prev, T)
            mode = TransitionMode.PERTURBED if corrected is None else TransitionMode.STATIC
            kept = _kept_where_it_was(ctx, oid, prev, fit_there)
            if kept is not None:  # at rest where it was, as the data there say
                T, corrected = prev, kept
                still, kept_fit = ctx.known[oid].still + 1, fit_there
        if mode == TransitionMode.STATIC and oid in ctx.fused and kept_fit is None:
            T, still = ctx.fused[oid], ctx.known[oid].still + 1
        terms = score.object_terms(i)
        ev = ctx.evidence.get(oid)
        if oid not in ctx.placed and ev is not None and ev.seen_empty(cfg):
            ctx.warnings.append(
                f"{out_id}: the camera sees through {100 * ev.seen_through:.0f} % of it"
            )
        if terms.stability < cfg.verification.fall_stability:
            ctx.warnings.append(f"{out_id}: would fall (stability term {terms.stability:.1f})")
        verdict = ctx.final_verdicts.get(oid)
        orientation = ctx.orientations.get(oid)
        ctx.objects.append(
            ObjectEstimate(
                out_id,
                model.name,
                T,
                mode,
                ephemeral=ephemeral,
                terms=terms,
                source=ctx.chosen.get(oid, CandidateSource.CURRENT),
                fit=float(score.fit[i]),
                reason=_with_correction(ctx, oid, _reason(ctx, oid, T, prev), corrected),
                evidence=verdict.judged.as_dict() if verdict is not None else None,
                orientation=orientation,
            )
        )
        ctx.next_known[out_id] = Known(
            model.name, T, ephemeral, float(score.fit[i]), held=oid in ctx.fallbacks,
            doubt=ctx.doubts.get(oid),
            alternatives=_alternatives(ctx, out_id, orientation),
            ranking=_ranking(ctx, oid, out_id, orientation),
            still=still,
            **_seen(ctx, oid, T, kept_fit),
        )  # fmt: skip


def _alternatives(
    ctx: FrameContext, out_id: str, orientation: Orientation | None
) -> tuple[np.ndarray, ...]:
    """The orientations the next frame remembers for ``out_id``: this frame's tied ones, or,
    when this frame did not look (no instance segment of it), those it remembered."""
    if orientation is not None:
        return tuple(a.T_world_obj for a in orientation.alternatives)
    known = ctx.known.get(out_id)
    return () if known is None else known.alternatives


def _ranking(
    ctx: FrameContext, oid: str, out_id: str, orientation: Orientation | None
) -> Ranking | None:
    """The decided ranking the next frame remembers for ``out_id``: this frame's, or, when
    this frame did not look, the one it remembered."""
    if orientation is not None:
        return ctx.rankings.get(oid)
    known = ctx.known.get(out_id)
    return None if known is None else known.ranking


def _with_correction(ctx: FrameContext, oid: str, reason: str, corrected: str | None = None) -> str:
    """``reason`` with the depth correction of the object's hypothesis said, when it had one,
    and ``corrected``, why its changed estimate is no motion in the world (:func:`_corrected`)."""
    fix = correction_of(ctx, oid)
    out = reason if fix is None else f"{reason}; {correction_note(fix)}"
    return out if corrected is None else f"{out}; {corrected}"


def _corrected(
    ctx: FrameContext, oid: str, prev: np.ndarray, T: np.ndarray
) -> tuple[str | None, float | None]:
    """``(why, fit)``: why known object ``oid``, whose estimate changed from ``prev`` to ``T``
    (4x4, m) beyond the static thresholds, did not move in the world, in words (None: it
    moved, or the data cannot say), and, when the data at ``prev`` is as it was
    (:func:`ssp.motion.moved_in_world`) or this frame's data do not prefer ``T`` to it
    (:func:`ssp.motion.prefers_estimate`), the fraction of its visible surface ``prev``
    explains in this frame (None otherwise)."""
    known = ctx.known.get(oid)
    if known is None or known.seen_fit is None:
        return None, None
    trees, model = ctx.segment_trees, ctx.models[oid]
    now = evidence(
        model, prev, trees.tree(oid), ctx.view, ctx.config, own_label=ctx.owner.get(oid),
        segment_spacing=trees.spacing(oid),
    )  # fmt: skip
    residual = object_residual(ctx, oid, prev)
    dt, dr = pose_change(prev, T, model.symmetry, model.center_of_mass)
    change = f"static in the world, its estimate corrected by {1000 * dt:.0f} mm / "
    change += f"{np.degrees(dr):.0f} deg: "
    if not moved_in_world(known.seen_fit, known.seen_residual, now, residual, ctx.config):
        return change + (
            f"the data where it was is as it was (explains {100 * now.fit:.0f} % of its "
            f"visible surface there, {100 * known.seen_fit:.0f} % in the frame before)"
        ), float(now.fit)
    est = ctx.evidence.get(oid)
    if not prefers_estimate(now, residual, est, object_residual(ctx, oid, T), ctx.config):
        assert est is not None
        return change + (
            f"this frame's data do not prefer the new estimate (it explains {100 * est.fit:.0f} "
            f"% of its visible surface, where it was {100 * now.fit:.0f} %)"
        ), float(now.fit)
    if explains_before(known.seen_points, model, prev, T, ctx.config):
        return change + "the new estimate explains the points seen of it before as well", None
    return None, None


def _kept_where_it_was(
    ctx: FrameContext, oid: str, prev: np.ndarray, fit_there: float | None
) -> str | None:
    """Why known object ``oid``, static in the world (the data at its previous pose ``prev``
    (4x4, m) is as it was: :func:`_corrected`, whose evidence there explains ``fit_there`` of
    its visible surface; None: not found static that way), keeps its previous pose over the
    frame's estimate, in words; None: the estimate stands. It keeps it when it was at rest the
    frame before (``still >=`` :data:`KEEP_STILL_FRAMES`), the estimate explains at least
    :data:`KEEP_FIT_MARGIN` less of its visible surface than the previous pose does now, and
    the previous pose is clear of the others as they are now (:func:`_clear_at`)."""
    known, ev = ctx.known.get(oid), ctx.evidence.get(oid)
    if fit_there is None or known is None or ev is None or known.still < KEEP_STILL_FRAMES:
        return None
    if ev.fit >= fit_there - KEEP_FIT_MARGIN:
        return None
    if not _clear_at(ctx, oid, prev):
        return None
    return (
        f"static in the world: kept where it was (the new estimate explains "
        f"{100 * ev.fit:.0f} % of its visible surface, where it was {100 * fit_there:.0f} %)"
    )


def _clear_at(ctx: FrameContext, oid: str, T: np.ndarray) -> bool:
    """Whether object ``oid`` at pose ``T`` (4x4, m) lies no deeper in the table or another
    object that stays (not in ``ctx.gone``) than at its estimate, by more than
    :data:`FUSION_DEPTH_SLACK` (the frame's world, the others at their estimates; left as it
    was). A previous pose kept where a neighbour's estimate has since moved into it put a tin
    25 mm into a mug (Table I's mug without masks, report seed 1007). Objects the frame
    removes are still in the world here; counting them refused the keeps that helped the
    tools without masks (their Table I AR 0.978 -> 0.970)."""
    world = ctx.sim.world
    k = world.index(oid)
    skip = sorted(world.index(g) for g in ctx.gone if g in world.ids)
    before = _deepest(world, skip)[k]
    state = world.save_state()
    try:
        world.set_pose(oid, T)
        return bool(_deepest(world, skip)[k] <= before + FUSION_DEPTH_SLACK)
    finally:
        world.restore_state(state)


def _seen(
    ctx: FrameContext, oid: str, T: np.ndarray, kept_fit: float | None = None
) -> dict[str, Any]:
    """:attr:`Known.seen_fit` (from the object's evidence at its final pose, or ``kept_fit``,
    the fraction its previous pose explains, when it keeps that pose:
    :func:`_kept_where_it_was`) and ``seen_residual`` (at its output pose ``T``); none when
    too little of it is visible."""
    ev = ctx.evidence.get(oid)
    if ev is None or ev.visible < ctx.config.verification.min_visible_samples:
        return {}
    seen: dict[str, Any] = {
        "seen_fit": float(ev.fit) if kept_fit is None else kept_fit,
        "seen_residual": object_residual(ctx, oid, T),
    }
    tree = ctx.segment_trees.tree(oid)
    if tree is not None:
        seen["seen_points"] = seen_points(tree.data)
    return seen


def _reason(ctx: FrameContext, oid: str, T: np.ndarray, prev: np.ndarray | None) -> str:
    """Why object ``oid`` (at its output pose ``T``; ``prev``: its previous pose) is in the
    scene, in words."""
    out_id = ctx.old_of.get(oid, oid)
    if oid in ctx.old_of and out_id in ctx.superseded:
        return (
            f"found again where the depth puts it (re-identified: {oid} is {out_id}, "
            "whose pose the camera saw through)"
        )
    if oid in ctx.old_of:
        assert prev is not None, "a re-identified object has a previous pose"
        dist = np.linalg.norm(T[:3, 3] - prev[:3, 3])
        return f"moved {1000 * dist:.0f} mm (re-identified: {oid} is {out_id})"
    if oid in ctx.retained:
        return f"support-retained: holds up {', '.join(ctx.retained[oid])}"
    v = ctx.verdicts.get(oid)
    if v is not None:
        return v.reason
    if oid in ctx.reasons:
        return ctx.reasons[oid]
    src = ctx.chosen.get(oid, CandidateSource.CURRENT)
    return f"detected; the search kept its {src} pose"


def scene_estimate(ctx: FrameContext) -> None:
    """Stage *outcome*: the :class:`~ssp.estimate.SceneEstimate`: the objects, the removed
    ones (not found again elsewhere) with their reasons, the rejected ones, every segment's
    verdict (:func:`ssp.segments.segment_verdicts`), the warnings (also logged), the support
    edges among what stays and the scene's log-probability.

    Sets ``estimate``.
    """
    score, models = ctx.scene_score, ctx.models
    removed = tuple(
        ObjectEstimate(
            oid,
            models[oid].name,
            ctx.prev_pose[oid],
            TransitionMode.REMOVED,
            source="removed",
            reason=ctx.verdicts[oid].reason if oid in ctx.verdicts else ctx.doubted.get(oid, ""),
        )  # fmt: skip
        for oid in sorted(ctx.removed)
        if oid not in ctx.moved_away
    )
    ids, old_of, g = score.ids, ctx.old_of, score.graph
    support = []
    for a, b, f in zip(g.supporter, g.supported, g.edge_fraction, strict=True):
        if ids[b] in ctx.gone or (a != GROUND and ids[a] in ctx.gone):
            continue
        sup = TABLE if a == GROUND else old_of.get(ids[a], ids[a])
        support.append(SupportEdge(sup, old_of.get(ids[b], ids[b]), float(f)))
    objects = tuple(ctx.objects)
    ctx.estimate = SceneEstimate(
        stamp=ctx.frame.stamp,
        frame_index=ctx.frame_index,
        objects=objects,
        removed=removed,
        rejected=tuple(
            replace(r, reason=_with_correction(ctx, k, r.reason))
            for k, r in sorted(ctx.rejected.items())
        ),
        segments=segment_verdicts(ctx, {o.id for o in objects}),
        warnings=tuple(ctx.warnings),
        support=tuple(support),
        log_prob=float(sum(o.log_prob for o in objects)),
        hypotheses_tested=ctx.tested,
        unchanged=ctx.unchanged,
    )
    for w in ctx.warnings:
        log.warning("frame %d: %s", ctx.frame_index, w)


def report_moved(
    estimate: SceneEstimate, moved: Mapping[str, np.ndarray | None], gone: Mapping[str, Known]
) -> SceneEstimate:
    """The estimate with :attr:`Frame.moved` said: a moved object that is still in the scene
    is ``perturbed``, with the reason; one that left is among the removed objects."""
    note = "moved by the caller (Frame.moved)"
    objects = tuple(
        replace(o, mode=TransitionMode.PERTURBED, reason=f"{o.reason}; {note}")
        if o.id in moved and o.mode == TransitionMode.STATIC
        else replace(o, reason=f"{o.reason}; {note}")
        if o.id in moved
        else o
        for o in estimate.objects
    )
    removed = estimate.removed + tuple(
        ObjectEstimate(
            oid,
            k.class_name,
            k.T_world_obj.copy(),
            TransitionMode.REMOVED,
            source="removed",
            reason="left the scene (Frame.moved: None)",
        )  # fmt: skip
        for oid, k in sorted(gone.items())
    )
    return replace(estimate, objects=objects, removed=removed)
