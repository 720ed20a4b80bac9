"""Orientations the view cannot decide (issue 33; DESIGN "Ambiguity is state, not noise").

A mug seen from the side opposite its handle is a cylinder: every yaw explains the view, and
an estimator proposes several. The parser's memory keeps the first orientation it chose; the
data term (paper eq. 10: the fraction of the model's visible surface explained) cannot undo
that, because a handle put behind the body is not visible and so costs nothing, even when the
camera sees the real handle elsewhere. This stage looks at each object's distinct candidate
orientations with the data of its instance segment:

* **candidates**: this frame's hypotheses of the object and the alternatives it kept from the
  previous frames (:attr:`ssp.frame_context.Known.alternatives`), turned by at least
  :data:`DISTINCT_TURN` from its pose after the search (symmetry-aware; closer ones are copies
  of it), one per orientation, each aligned to the segment by ICP
  (:func:`ssp.registration.icp_refine`) and kept only if still distinct from the pose (ICP
  can bring one back to it);
* **rank** (:func:`orientation_rank`): the F1 of the visible surface explained
  (:func:`ssp.verification.evidence`'s ``fit``; a face the camera sees through counts against
  it) and of the instance segment explained (``explained``: the segment's points near the
  model, where the hidden-handle pose leaves the seen handle's points unexplained);
* **the data decides** (:func:`decides`): a candidate that passes the new-object check
  (:func:`ssp.verification.check_new`), ranks higher than the pose by more than
  :data:`DECIDE_MARGIN`, and beats it by more than sampling noise (:data:`DECIDE_Z` standard
  errors of its fit or explained fraction) replaces it: the object is turned there, in the
  world too. The pose is ranked at its best, as it is or aligned by ICP as the candidates
  are, so that the millimetres the physics' settle put it off its data do not count as a
  worse orientation;
* **tied**: the other candidates within :data:`DECIDE_MARGIN` of the pose (or above it) are
  its alternatives: the output says the orientation is undecided and lists them
  (``ObjectEstimate.orientation``), and the next frame remembers them, so a later view can
  decide between them even when the estimator no longer proposes them; one ranked lower by
  more than the margin is dropped (the data decided against it). The pose stays while the
  evidence is tied.

Only with instance masks (``Frame.instance_masks``): without them an object's points are a
cluster's, which need not all be its own, and ``explained`` would count its neighbours.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ssp.errors import PhysicsError
from ssp.geometry import validate_pose
from ssp.library.model import ObjectModel
from ssp.probability import pose_change
from ssp.registration import icp_refine
from ssp.static import RANKED_TURN
from ssp.verification import Evidence, check_new, evidence

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "DECIDE_MARGIN",
    "DECIDE_Z",
    "DISTINCT_TURN",
    "Alternative",
    "Orientation",
    "alternatives_from_state",
    "alternatives_state",
    "decide_orientations",
    "decides",
    "distinct_orientations",
    "orientation_rank",
]

log = logging.getLogger(__name__)

#: Candidates turned less than this (rad, symmetry-aware) from a pose are copies of it: the
#: unchanged test's (an estimator's distinct orientations differ by more).
DISTINCT_TURN = RANKED_TURN

#: A candidate replaces the pose when its rank is higher by more than this; within it, the
#: two are tied (the class margin of the association, ``ssp.temporal.CLASS_MARGIN``).
DECIDE_MARGIN = 0.05

#: ... and by this many standard errors of its fit or explained fraction (:func:`decides`).
DECIDE_Z = 3.0


@dataclass(frozen=True)
class Alternative:
    """An orientation the data allow as well as the output pose.

    Attributes:
        T_world_obj: (4, 4) pose, m. turn_deg: its turn from the output pose, deg
            (symmetry-aware). rank: its :func:`orientation_rank`.
    """

    T_world_obj: np.ndarray
    turn_deg: float
    rank: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "T_world_obj": np.asarray(self.T_world_obj).tolist(),
            "turn_deg": round(self.turn_deg, 2),
            "rank": round(self.rank, 4),
        }


@dataclass(frozen=True)
class Orientation:
    """Whether an object's orientation is decided (``ObjectEstimate.orientation``).

    Attributes:
        decided: no other orientation explains the data as well (within
            :data:`DECIDE_MARGIN`). rank: the output pose's :func:`orientation_rank`.
        alternatives: the tied orientations, best first. turned_deg: how far this frame's data
            turned the object from its pose after the search (0: not turned).
    """

    decided: bool
    rank: float
    alternatives: tuple[Alternative, ...] = ()
    turned_deg: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "decided": self.decided,
            "rank": round(self.rank, 4),
            "alternatives": [a.as_dict() for a in self.alternatives],
            "turned_deg": round(self.turned_deg, 2),
        }


def orientation_rank(ev: Evidence) -> float:
    """F1 of ``ev.fit`` (visible surface explained) and ``ev.explained`` (instance segment
    explained; ``fit`` alone when the evidence has none)."""
    if ev.explained is None:
        return float(ev.fit)
    s = ev.fit + ev.explained
    return 0.0 if s <= 0 else float(2 * ev.fit * ev.explained / s)


def decides(new: Evidence, old: Evidence, segment_points: int) -> bool:
    """Whether evidence ``new`` (a candidate's) decides against ``old`` (the pose's) on an
    instance segment of ``segment_points`` points: its :func:`orientation_rank` is higher by
    more than :data:`DECIDE_MARGIN`, and by more than sampling noise: its fit (a fraction of
    the visible samples) or its explained fraction (of the segment's points) is higher by at
    least :data:`DECIDE_Z` standard errors of the difference of two proportions. A heavily
    occluded object shows a few dozen samples, where a pose that hides a few more of them
    behind the occluder gains 0.05 by chance."""
    if orientation_rank(new) <= orientation_rank(old) + DECIDE_MARGIN:
        return False
    if _z(new.fit, new.visible, old.fit, old.visible) >= DECIDE_Z:
        return True
    if new.explained is None or old.explained is None:
        return False
    return _z(new.explained, segment_points, old.explained, segment_points) >= DECIDE_Z


def _z(p1: float, n1: int, p2: float, n2: int) -> float:
    """Two-proportion z statistic of ``p1 - p2`` (fractions of ``n1`` and ``n2`` trials;
    pooled; infinite for a gain with no variance, 0 without trials)."""
    if n1 <= 0 or n2 <= 0:
        return 0.0
    pooled = (p1 * n1 + p2 * n2) / (n1 + n2)
    var = pooled * (1.0 - pooled) * (1.0 / n1 + 1.0 / n2)
    if var <= 0.0:
        return float("inf") if p1 > p2 else 0.0
    return float((p1 - p2) / np.sqrt(var))


def distinct_orientations(
    T: np.ndarray, candidates: list[np.ndarray], model: ObjectModel
) -> list[tuple[np.ndarray, float]]:
    """``[(pose, turn rad)]`` of ``candidates`` (4x4, best first) turned at least
    :data:`DISTINCT_TURN` from ``T`` and from every earlier one kept (one per orientation)."""
    out: list[tuple[np.ndarray, float]] = []
    for U in candidates:
        turn = pose_change(T, U, model.symmetry, model.center_of_mass)[1]
        if turn < DISTINCT_TURN:
            continue
        if any(
            pose_change(V, U, model.symmetry, model.center_of_mass)[1] < DISTINCT_TURN
            for V, _ in out
        ):
            continue
        out.append((np.asarray(U, dtype=float), float(turn)))
    return out


def decide_orientations(ctx: FrameContext) -> None:
    """Stage *orientations* (module docstring): each object with an instance segment turned
    to a distinct candidate orientation its data rank higher, or told undecided between the
    tied ones.

    Sets ``orientations``; updates ``score`` and ``evidence`` (the turned objects').
    """
    if not ctx.frame.instance_masks:
        return
    cfg, sim = ctx.config, ctx.sim
    world, score = sim.world, ctx.scene_score
    # id -> (pose, turn deg, rank where it is, what to say if it stays there)
    turns: dict[str, tuple[np.ndarray, float, float, Orientation]] = {}
    for oid in world.ids:
        label = ctx.owner.get(oid)
        if oid in ctx.removed or label is None:
            continue
        model = ctx.models[oid]
        T = np.asarray(score.poses[world.index(oid)], dtype=float)
        known = ctx.known.get(oid)
        candidates = [h.T_world_obj for h in ctx.groups.get(oid, [])]
        candidates += list(known.alternatives) if known is not None else []
        ev = ctx.evidence.get(oid) or _judged(ctx, oid, label, T)
        rank = bar = orientation_rank(ev)
        bar_ev = ev
        distinct = distinct_orientations(T, candidates, model)
        if distinct:
            # what a candidate must beat: the pose aligned as the candidates are (a candidate
            # decides an orientation, not the millimetres the settle put the pose off its data)
            ev_aligned = _judged(ctx, oid, label, _aligned(ctx, oid, T))
            if orientation_rank(ev_aligned) > bar:
                bar, bar_ev = orientation_rank(ev_aligned), ev_aligned
            aligned = [_aligned(ctx, oid, U) for U, _ in distinct]
            distinct = distinct_orientations(T, aligned, model)  # ICP may bring one back to T
        if not distinct:
            ctx.orientations[oid] = Orientation(True, rank)
            continue
        ranked = [
            (orientation_rank(e), U, e) for U, _ in distinct for e in [_judged(ctx, oid, label, U)]
        ]
        ranked.sort(key=lambda r: -r[0])
        best_rank, best, best_ev = ranked[0]
        if decides(best_ev, bar_ev, _points(ctx, oid)) and check_new(best_ev, cfg).keep:
            turn = pose_change(T, best, model.symmetry, model.center_of_mass)[1]
            stay = _said(ranked, T, rank, model, bar)
            turns[oid] = (best, float(np.degrees(turn)), bar, stay)
            ranked = [(bar, T, ev)] + ranked[1:]  # the pose it leaves is a candidate now
            T, rank = best, best_rank
            bar = rank
        ctx.orientations[oid] = _said(ranked, T, rank, model, bar)
    if turns:
        _turn(ctx, turns)


def _said(ranked: list, T: np.ndarray, rank: float, model: ObjectModel, bar: float) -> Orientation:
    """The :class:`Orientation` of an object at ``T`` (its rank ``rank``; ``bar``: the rank
    its candidates are compared with, ``rank`` or more) among its other ``ranked``
    candidates (``(rank, pose, evidence)``, ``T`` not among them)."""
    tied = []
    for r, U, _ in ranked:
        turn = np.degrees(pose_change(T, U, model.symmetry, model.center_of_mass)[1])
        if r >= bar - DECIDE_MARGIN and turn >= np.degrees(DISTINCT_TURN):
            tied.append(Alternative(U, float(turn), r))
    return Orientation(not tied, rank, tuple(tied))


def _turn(
    ctx: FrameContext, turns: dict[str, tuple[np.ndarray, float, float, Orientation]]
) -> None:
    """Turn the objects ``turns`` (id -> (pose, turn deg, rank where it was, its
    :class:`Orientation` there)) and settle the scene (the search's window: with data forces,
    then without), so the turned poses rest on what holds them and touch nothing; if a turned
    object then ranks no higher than where it was by :data:`DECIDE_MARGIN` (physics took it
    off its data), or the world fails, nothing is turned (and each says what it would have
    said where it stays)."""
    sim = ctx.sim
    world = sim.world
    saved = world.save_state()

    def undo(why: str) -> None:
        log.info("orientations: %s: none turned", why)
        world.restore_state(saved)
        for oid, (*_, stay) in turns.items():
            ctx.orientations[oid] = stay

    try:
        for oid, (T, *_) in turns.items():
            world.set_pose(oid, T)
        sim.simulator.window()
    except PhysicsError as exc:
        undo(f"settling the turned objects failed ({exc})")
        return
    settled = {}
    for oid, (_, turn, old, _) in turns.items():
        T = np.asarray(world.get_pose(oid), dtype=float)
        ev = _judged(ctx, oid, ctx.owner[oid], T)
        if orientation_rank(ev) <= old + DECIDE_MARGIN:
            undo(f"{oid} no better once settled")
            return
        settled[oid] = (ev, turn)
    for oid, (ev, turn) in settled.items():
        log.info("%s turned %.0f deg: its data rank %.2f there", oid, turn, orientation_rank(ev))
        o = ctx.orientations[oid]
        ctx.orientations[oid] = Orientation(
            o.decided, orientation_rank(ev), o.alternatives, turn
        )  # fmt: skip
    ctx.score = sim.scorer.evaluate(world, ctx.timer)
    for oid in world.ids:  # every object's evidence at its settled pose
        if oid in ctx.evidence:
            ctx.evidence[oid] = _judged(ctx, oid, ctx.owner.get(oid), world.get_pose(oid))


def alternatives_state(alternatives: tuple[np.ndarray, ...]) -> dict[str, Any]:
    """A scene state object's ``alternatives`` entry (none when it has none)."""
    return {"alternatives": [U.tolist() for U in alternatives]} if alternatives else {}


def alternatives_from_state(entry: Mapping[str, Any]) -> tuple[np.ndarray, ...]:
    """The remembered alternatives of a scene state object ``entry`` (none in older states).

    Raises:
        InvalidPoseError: one is not a rigid pose.
    """
    return tuple(
        validate_pose(np.asarray(U, dtype=float), f"object {entry['id']!r}: an alternative")
        for U in entry.get("alternatives", [])
    )


def _points(ctx: FrameContext, oid: str) -> int:
    """The number of points of object ``oid``'s instance segment."""
    segment = ctx.segments.get(oid)
    return 0 if segment is None else len(segment)


def _aligned(ctx: FrameContext, oid: str, U: np.ndarray) -> np.ndarray:
    """Candidate ``U`` of object ``oid`` aligned to its segment (point-to-plane ICP, as the
    polish aligns the pose it is compared with): an estimator's alternative is often some
    millimetres off, and a thin part (a handle) a few degrees off is seen through."""
    segment = ctx.segments.get(oid)
    if segment is None or not len(segment):
        return np.asarray(U, dtype=float)
    return icp_refine(ctx.models[oid], U, segment, ctx.sim.camera_position)


def _judged(ctx: FrameContext, oid: str, label: int | None, T: np.ndarray) -> Evidence:
    """:func:`ssp.verification.evidence` of object ``oid`` at ``T`` on its instance segment
    (label ``label``)."""
    trees = ctx.segment_trees
    return evidence(
        ctx.models[oid], T, trees.tree(oid), ctx.view, ctx.config, own_label=label,
        segment_spacing=trees.spacing(oid),
    )  # fmt: skip
