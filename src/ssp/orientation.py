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
  (:func:`ssp.registration.icp_refine`; the pose was, by the polish);
* **rank** (:func:`orientation_rank`): the F1 of the visible surface explained
  (:func:`ssp.verification.evidence`'s ``fit``; a face the camera sees through counts against
  it) and of the instance segment explained (``explained``: the segment's points near the
  model, where the hidden-handle pose leaves the seen handle's points unexplained);
* **the data decides**: a candidate that passes the new-object check
  (:func:`ssp.verification.check_new`) and ranks higher than the pose by more than
  :data:`DECIDE_MARGIN` replaces it (the object is turned there, in the world too);
* **tied**: the candidates within :data:`DECIDE_MARGIN` of the pose are its alternatives: the
  output says the orientation is undecided and lists them (``ObjectEstimate.orientation``),
  and the next frame remembers them, so a later view can decide between them even when the
  estimator no longer proposes them; one ranked lower by more than the margin is dropped (the
  data decided against it). The pose stays while the evidence is tied.

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
    "DISTINCT_TURN",
    "Alternative",
    "Orientation",
    "alternatives_from_state",
    "alternatives_state",
    "decide_orientations",
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
        distinct = distinct_orientations(T, candidates, model)
        distinct = [(_aligned(ctx, oid, U), turn) for U, turn in distinct]
        ev = ctx.evidence.get(oid) or _judged(ctx, oid, label, T)
        rank = orientation_rank(ev)
        if not distinct:
            ctx.orientations[oid] = Orientation(True, rank)
            continue
        ranked = [
            (orientation_rank(e), U, e) for U, _ in distinct for e in [_judged(ctx, oid, label, U)]
        ]
        ranked.sort(key=lambda r: -r[0])
        best_rank, best, best_ev = ranked[0]
        if best_rank > rank + DECIDE_MARGIN and check_new(best_ev, cfg).keep:
            turn = pose_change(T, best, model.symmetry, model.center_of_mass)[1]
            stay = _said(ranked, T, rank, model)
            turns[oid] = (best, float(np.degrees(turn)), rank, stay)
            ranked = [(rank, T, ev)] + ranked[1:]  # the pose it leaves is a candidate now
            T, rank = best, best_rank
        ctx.orientations[oid] = _said(ranked, T, rank, model)
    if turns:
        _turn(ctx, turns)


def _said(ranked: list, T: np.ndarray, rank: float, model: ObjectModel) -> Orientation:
    """The :class:`Orientation` of an object at ``T`` (its rank ``rank``) among its other
    ``ranked`` candidates (``(rank, pose, evidence)``, ``T`` not among them)."""
    tied = []
    for r, U, _ in ranked:
        turn = np.degrees(pose_change(T, U, model.symmetry, model.center_of_mass)[1])
        if r >= rank - DECIDE_MARGIN and turn >= np.degrees(DISTINCT_TURN):
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
