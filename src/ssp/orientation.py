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
* **closer**: among the candidates tied with the pose, one whose instance segment's points
  lie decidedly closer to its surface (:func:`closer`: truncated squared distances, paired
  over the same points, lower by :data:`CLOSER_GAIN` and :data:`DECIDE_Z` standard errors)
  replaces it as well, and a tied candidate the pose is decidedly closer than is dropped. The
  ranks count points within the inlier radius (3.7 mm): a nearly square tin turned a quarter
  leaves its sides 3 mm off and ranks as high; the distances tell them apart;
* **tied**: the other candidates within :data:`DECIDE_MARGIN` of the pose (or above it) are
  its alternatives: the output says the orientation is undecided and lists them
  (``ObjectEstimate.orientation``), and the next frame remembers them, so a later view can
  decide between them even when the estimator no longer proposes them; one ranked lower by
  more than the margin is dropped (the data decided against it). The pose stays while the
  evidence is tied.

**The same view decides the same** (:class:`Ranking`, :func:`same_view`): an object whose
orientation was decided, seen again unchanged (``FrameContext.static``) from the same camera
pose with about as many segment points, whose candidates are all copies of those its data
ruled out then, keeps that verdict (``Orientation.repeated``) without aligning and ranking
them again: the same data up to sensor noise, which can only flip a verdict by chance. A new
orientation, a moved object or camera, or a segment that gained or lost
:data:`SAME_VIEW_POINTS` of its points (an occluder moved) ranks them again.

**Whose points** (:class:`OwnPoints`): an object's instance segment (``Frame.instance_masks``).
Without masks an object's points are a crop of the cloud, which may hold a neighbour's, and
``explained`` would count them: an object is ranked there only when it lies alone in its
cluster (``Frame.label_kind == "cluster"``; no other object of the scene in it), on that
cluster's points within its bounding sphere (grown by ``forces.max_distance``), and ties are
not decided by distance there (:func:`_decided`). Without the stage a mug's memory held the
yaw it first chose without masks: development seeds 0-1 (the view-ambiguous protocol, the
built-in estimator) its mean rotation error 106 deg against the memoryless parser's 67.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ssp.errors import PhysicsError
from ssp.geometry import same_camera_pose, squared_distances, validate_pose
from ssp.library.model import ObjectModel
from ssp.probability import pose_change
from ssp.registration import icp_refine
from ssp.segments import SegmentTrees, indices_by_label
from ssp.static import RANKED_TURN
from ssp.threads import thread_map
from ssp.verification import Evidence, check_new, evidence

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "DECIDE_MARGIN",
    "DECIDE_Z",
    "CLOSER_GAIN",
    "CLOSER_RADII",
    "MAX_RULED_OUT",
    "MIN_CLOSER_POINTS",
    "OwnPoints",
    "DISTINCT_TURN",
    "SAME_VIEW_POINTS",
    "Alternative",
    "Orientation",
    "Ranking",
    "Residuals",
    "closer",
    "decide_orientations",
    "decides",
    "distinct_orientations",
    "orientation_rank",
    "orientations_from_state",
    "orientations_state",
    "residual_costs",
    "same_view",
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

#: Tied candidates are compared by their segment's distances, truncated at this many inlier
#: radii (``data.inlier_radius``; :func:`closer`) ...
CLOSER_RADII = 2.0

#: ... one decides when its mean truncated cost is lower by this (of 1) and by DECIDE_Z
#: standard errors: a side 3 mm off at 7.4 mm costs 0.16 a point, and a tin seen from above
#: shows its sides in a few percent of its points (development seeds 4-9: gains of 0.005-0.013
#: over 880 points; 0.02 left a tin a quarter turn off for a whole sequence).
CLOSER_GAIN = 0.005

#: Fewer segment points than this never decide by distance.
MIN_CLOSER_POINTS = 30

#: An instance segment whose point count changed by less than this fraction (of the count
#: then), seen from the same camera pose, shows the same part of the object (a handle coming
#: into view adds more).
SAME_VIEW_POINTS = 0.05

#: A :class:`Ranking` remembers at most this many ruled-out orientations.
MAX_RULED_OUT = 16


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
        repeated: decided in an earlier frame from the same view, its candidates not ranked
            again (:func:`same_view`).
    """

    decided: bool
    rank: float
    alternatives: tuple[Alternative, ...] = ()
    turned_deg: float = 0.0
    repeated: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {
            "decided": self.decided,
            "rank": round(self.rank, 4),
            "alternatives": [a.as_dict() for a in self.alternatives],
            "turned_deg": round(self.turned_deg, 2),
            "repeated": self.repeated,
        }


@dataclass(frozen=True)
class Ranking:
    """An object's decided orientation ranking, remembered for the next frames
    (``Known.ranking``; :func:`same_view`).

    Attributes:
        T_world_cam: (4, 4) the camera pose it was ranked from, m. points: its instance
            segment's points then. ruled_out: the candidate orientations (poses, 4x4, m, as
            proposed) its data ruled out then.
    """

    T_world_cam: np.ndarray
    points: int
    ruled_out: tuple[np.ndarray, ...] = ()


def same_view(
    ranking: Ranking | None, T_world_cam: np.ndarray | None, points: int,
    candidates: list[np.ndarray] | None = None, model: ObjectModel | None = None,
) -> bool:  # fmt: skip
    """Whether ``ranking`` was made from this view: the camera ``T_world_cam`` the one it was
    ranked from (:func:`ssp.geometry.same_camera_pose`) and the instance segment's ``points``
    within :data:`SAME_VIEW_POINTS` of its count then; with
    ``candidates`` (this frame's distinct ones, 4x4, of ``model``), also whether each lies
    within :data:`DISTINCT_TURN` of an orientation it ruled out (symmetry-aware): then it
    decides them again."""
    if ranking is None or ranking.points <= 0:
        return False
    if not same_camera_pose(ranking.T_world_cam, T_world_cam):
        return False
    if abs(points - ranking.points) >= SAME_VIEW_POINTS * ranking.points:
        return False
    if candidates is None or model is None:
        return True
    return all(_copy_of(U, ranking.ruled_out, model) for U in candidates)


def _copy_of(U: np.ndarray, poses: tuple[np.ndarray, ...], model: ObjectModel) -> bool:
    """Whether pose ``U`` is turned less than :data:`DISTINCT_TURN` from one of ``poses``."""
    return any(
        pose_change(V, U, model.symmetry, model.center_of_mass)[1] < DISTINCT_TURN for V in poses
    )


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
    """Stage *orientations* (module docstring): each object with points of its own
    (:class:`OwnPoints`) turned to a distinct candidate orientation its data rank higher, or
    told undecided between the tied ones; an unchanged object seen from the same view keeps
    its decided verdict (:func:`same_view`).

    Sets ``orientations`` and ``rankings``; updates ``score`` and ``evidence`` (the turned
    objects').
    """
    own = OwnPoints.of(ctx)
    if not own.labels:
        return
    cfg, sim = ctx.config, ctx.sim
    world, score = sim.world, ctx.scene_score
    cam = ctx.frame.T_world_cam
    # id -> (pose, turn deg, the settle's check, what to say if it stays there)
    turns: dict[str, tuple[np.ndarray, float, Any, Orientation]] = {}
    for oid in world.ids:
        if oid not in own.labels:
            continue
        model = ctx.models[oid]
        T = np.asarray(score.poses[world.index(oid)], dtype=float)
        known = ctx.known.get(oid)
        candidates = [h.T_world_obj for h in ctx.groups.get(oid, [])]
        candidates += list(known.alternatives) if known is not None else []
        ev = (ctx.evidence.get(oid) if own.shared else None) or own.judged(oid, T)
        rank = bar = orientation_rank(ev)
        bar_ev = ev
        distinct = distinct_orientations(T, candidates, model)
        segment = own.segments.get(oid)
        points = 0 if segment is None else len(segment)
        proposed = tuple(U for U, _ in distinct)
        if (
            distinct
            and known is not None
            and oid in ctx.static
            and same_view(known.ranking, cam, points, list(proposed), model)
        ):
            ctx.orientations[oid] = Orientation(True, rank, repeated=True)
            ctx.rankings[oid] = known.ranking
            continue
        T_fit = T  # the pose as the candidates are compared with it
        if distinct:
            # what a candidate must beat: the pose aligned as the candidates are (a candidate
            # decides an orientation, not the millimetres the settle put the pose off its data)
            T_fit, *aligned = own.aligned(oid, [T, *(U for U, _ in distinct)])
            ev_aligned = own.judged(oid, T_fit)
            if orientation_rank(ev_aligned) > bar:
                bar, bar_ev = orientation_rank(ev_aligned), ev_aligned
            distinct = distinct_orientations(T, aligned, model)  # ICP may bring one back to T
        if not distinct:
            ctx.orientations[oid] = Orientation(True, rank)
            _remember(ctx, oid, cam, points, proposed)
            continue
        ranked = [(orientation_rank(e), U, e) for U, _ in distinct for e in [own.judged(oid, U)]]
        ranked.sort(key=lambda r: -r[0])
        residuals = Residuals(segment, model, CLOSER_RADII * cfg.data.inlier_radius)
        chosen = _decided(ranked, bar, bar_ev, residuals, T_fit, cfg, by_distance=own.shared)
        if chosen is not None:
            k, by_rank = chosen
            best_rank, best, _ = ranked[k]
            turn = pose_change(T, best, model.symmetry, model.center_of_mass)[1]
            stay = _said(ranked, T, rank, model, bar, residuals, T_fit)
            if by_rank:
                check = _ranks_higher(bar)
            else:
                check = _fits_closer(bar, residuals, T_fit)
            turns[oid] = (best, float(np.degrees(turn)), check, stay)
            # the pose it leaves is a candidate now
            ranked = [(bar, T_fit, bar_ev)] + ranked[:k] + ranked[k + 1 :]
            T, rank = best, best_rank
            T_fit, bar = best, rank
        ctx.orientations[oid] = _said(ranked, T, rank, model, bar, residuals, T_fit)
        if chosen is None and ctx.orientations[oid].decided:
            _remember(ctx, oid, cam, points, proposed)
    if turns:
        _turn(ctx, own, turns)


def _remember(
    ctx: FrameContext, oid: str, cam: np.ndarray | None, points: int,
    ruled_out: tuple[np.ndarray, ...],
) -> None:  # fmt: skip
    """Remember object ``oid``'s decided ranking (:class:`Ranking`) from camera ``cam`` on a
    segment of ``points`` points, ``ruled_out`` its distinct candidates: added to those it
    ruled out from the same view before (:func:`same_view`; an estimator proposes a few of
    the orientations a view allows each frame, not always the same), at most
    :data:`MAX_RULED_OUT`; nothing without a camera or points."""
    if cam is None or points <= 0:
        return
    known = ctx.known.get(oid)
    before = None if known is None else known.ranking
    if oid in ctx.static and same_view(before, cam, points):
        assert before is not None
        model = ctx.models[oid]
        new = [U for U in ruled_out if not _copy_of(U, before.ruled_out, model)]
        merged = (*before.ruled_out, *new)[:MAX_RULED_OUT]
        ctx.rankings[oid] = Ranking(before.T_world_cam, before.points, merged)
    else:
        ctx.rankings[oid] = Ranking(np.asarray(cam, dtype=float), points, ruled_out)


def _decided(
    ranked, bar, bar_ev, residuals, T_fit, cfg, *, by_distance: bool
) -> tuple[int, bool] | None:  # fmt: skip
    """The candidate of ``ranked`` the data decide for, as ``(its index, by rank)``, or None:
    the best-ranked one when it :func:`decides` against the pose; else, ``by_distance``, among
    those tied with the pose (within :data:`DECIDE_MARGIN` of ``bar``), the one whose segment
    points lie closer to its surface by the most (:func:`closer`); either must pass the
    new-object check. Not by distance on a cluster's points (:class:`OwnPoints`, no masks): a
    tin's quarter turns tied in rank were decided one way and back again frame after frame
    there (report seed 1005 of the view-ambiguous protocol, the built-in estimator: the
    cluster's points all explained by either, gains of a few thousandths either way)."""
    if decides(ranked[0][2], bar_ev, residuals.n):
        return (0, True) if check_new(ranked[0][2], cfg).keep else None
    if not by_distance:
        return None
    gains = []
    for k, (r, U, e) in enumerate(ranked):
        if r < bar - DECIDE_MARGIN:
            continue
        gain = residuals.closer(U, T_fit)
        if gain is not None and check_new(e, cfg).keep:
            gains.append((gain, k))
    return (max(gains)[1], False) if gains else None


def _ranks_higher(bar: float):
    """The settle's check of a turn the ranks decided: it still ranks higher than ``bar`` by
    more than :data:`DECIDE_MARGIN`."""
    return lambda T, ev: orientation_rank(ev) > bar + DECIDE_MARGIN


def _fits_closer(bar: float, residuals: Residuals, T_old: np.ndarray):
    """The settle's check of a turn the closeness decided: still tied in rank or better, and
    still :func:`closer` than the pose ``T_old`` it left."""

    def check(T: np.ndarray, ev: Evidence) -> bool:
        if orientation_rank(ev) < bar - DECIDE_MARGIN:
            return False
        return residuals.closer(T, T_old) is not None

    return check


def residual_costs(
    points: np.ndarray, model: ObjectModel, T_world_obj: np.ndarray, tau: float
) -> np.ndarray:
    """Per point of ``points`` ``(K, 3)`` (world, m): ``min(d, tau)^2 / tau^2``, ``d`` its
    distance to the model's nearest surface sample at ``T_world_obj`` (a truncated quadratic:
    a point farther than ``tau`` m costs 1)."""
    R, t = T_world_obj[:3, :3], T_world_obj[:3, 3]
    local = (np.asarray(points, dtype=float).reshape(-1, 3) - t) @ R
    d, _ = model.surface_tree.query(local, k=1, distance_upper_bound=tau)
    return np.where(np.isfinite(d), (np.minimum(d, tau) / tau) ** 2, 1.0)


def closer(
    segment: np.ndarray | None, model: ObjectModel, T_new: np.ndarray, T_old: np.ndarray,
    tau: float,
) -> float | None:  # fmt: skip
    """How much closer (mean :func:`residual_costs` gain) the instance ``segment``'s points
    lie to the model at ``T_new`` than at ``T_old``, when that is decided: a gain of at least
    :data:`CLOSER_GAIN` and :data:`DECIDE_Z` standard errors of the paired differences (the
    same points under both poses); else None. A nearly square tin turned a quarter leaves
    the points of its sides 3 mm off, inside the data term's inlier radius: the ranks tie,
    the distances do not."""
    return Residuals(segment, model, tau).closer(T_new, T_old)


class Residuals:
    """:func:`residual_costs` of one instance segment ``(K, 3)`` (or None) and its model,
    ``tau`` m, computed once per pose: the stage compares each candidate with the same pose,
    both ways (:func:`closer`), and the cost of a pose is a KD-tree query of every segment
    point (about 5 ms for a real capture's box)."""

    def __init__(self, segment: np.ndarray | None, model: ObjectModel, tau: float) -> None:
        self.segment, self.model, self.tau = segment, model, float(tau)
        self.n = 0 if segment is None else len(segment)
        self._costs: dict[bytes, np.ndarray] = {}

    def costs(self, T_world_obj: np.ndarray) -> np.ndarray:
        """:func:`residual_costs` of the segment at ``T_world_obj`` (4x4, m), ``(K,)``."""
        T = np.asarray(T_world_obj, dtype=float)
        key = T.tobytes()
        if key not in self._costs:
            assert self.segment is not None
            self._costs[key] = residual_costs(self.segment, self.model, T, self.tau)
        return self._costs[key]

    def closer(self, T_new: np.ndarray, T_old: np.ndarray) -> float | None:
        """:func:`closer`: the decided gain of ``T_new`` over ``T_old``, or None."""
        if self.n < MIN_CLOSER_POINTS:
            return None
        diff = self.costs(T_old) - self.costs(T_new)
        gain = float(diff.mean())
        if gain < CLOSER_GAIN:
            return None
        sd = float(diff.std(ddof=1))
        if sd > 0 and gain / (sd / np.sqrt(len(diff))) < DECIDE_Z:
            return None
        return gain


def _said(
    ranked: list, T: np.ndarray, rank: float, model: ObjectModel, bar: float,
    residuals: Residuals, T_fit: np.ndarray,
) -> Orientation:  # fmt: skip
    """The :class:`Orientation` of an object at ``T`` (its rank ``rank``; ``bar``: the rank
    its candidates are compared with, ``rank`` or more) among its other ``ranked``
    candidates (``(rank, pose, evidence)``, ``T`` not among them): those within
    :data:`DECIDE_MARGIN` of ``bar`` are tied, unless the segment's points lie decidedly
    closer to the pose (at ``T_fit``, as compared) than to them (:func:`closer`)."""
    tied = []
    for r, U, _ in ranked:
        turn = np.degrees(pose_change(T, U, model.symmetry, model.center_of_mass)[1])
        if r < bar - DECIDE_MARGIN or turn < np.degrees(DISTINCT_TURN):
            continue
        if residuals.closer(T_fit, U) is not None:
            continue  # the data decided against it
        tied.append(Alternative(U, float(turn), r))
    return Orientation(not tied, rank, tuple(tied))


def _turn(
    ctx: FrameContext, own: OwnPoints,
    turns: dict[str, tuple[np.ndarray, float, Any, Orientation]],
) -> None:  # fmt: skip
    """Turn the objects ``turns`` (id -> (pose, turn deg, ``check(T, evidence)`` on ``own``
    points: whether a settled pose still beats the one left, its :class:`Orientation`
    there)) and settle the scene (the search's window: with data forces, then without), so
    the turned poses rest on what holds them and touch nothing; if a turned object then fails
    its check (physics took it off its data), or the world fails, nothing is turned (and each
    says what it would have said where it stays)."""
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
    for oid, (_, turn, check, _) in turns.items():
        T = np.asarray(world.get_pose(oid), dtype=float)
        ev = own.judged(oid, T)
        if not check(T, ev):
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
    stages = OwnPoints.stages(ctx)
    for oid in world.ids:  # every object's evidence at its settled pose, as the stages judge it
        if oid in ctx.evidence:
            ctx.evidence[oid] = stages.judged(oid, world.get_pose(oid))


def orientations_state(
    alternatives: tuple[np.ndarray, ...], ranking: Ranking | None
) -> dict[str, Any]:
    """A scene state object's ``alternatives`` and ``ranking`` entries (none when it has
    none)."""
    out: dict[str, Any] = {}
    if alternatives:
        out["alternatives"] = [U.tolist() for U in alternatives]
    if ranking is not None:
        out["ranking"] = {
            "T_world_cam": np.asarray(ranking.T_world_cam).tolist(),
            "points": int(ranking.points),
            "ruled_out": [U.tolist() for U in ranking.ruled_out],
        }
    return out


def orientations_from_state(
    entry: Mapping[str, Any],
) -> tuple[tuple[np.ndarray, ...], Ranking | None]:
    """The remembered alternatives and :class:`Ranking` of a scene state object ``entry``
    (none in older states).

    Raises:
        InvalidPoseError: a pose that is not rigid.
    """
    what = f"object {entry['id']!r}"
    alternatives = tuple(
        validate_pose(np.asarray(U, dtype=float), f"{what}: an alternative")
        for U in entry.get("alternatives", [])
    )
    r = entry.get("ranking")
    if r is None:
        return alternatives, None
    ranking = Ranking(
        validate_pose(np.asarray(r["T_world_cam"], dtype=float), f"{what}: its ranking's camera"),
        int(r["points"]),
        tuple(
            validate_pose(np.asarray(U, dtype=float), f"{what}: a ruled-out orientation")
            for U in r["ruled_out"]
        ),
    )
    return alternatives, ranking


class OwnPoints:
    """The points each object is ranked on (module docstring, "Whose points"), with their
    labels and KD-trees: ``labels`` id -> its instance segment's label, or, without masks,
    the cluster's it lies in alone; ``segments`` id -> ``(K, 3)`` points (world, m);
    ``shared``: they are the frame's segments (``FrameContext.segments``; instance masks),
    so the stages' evidence is the ranking's."""

    def __init__(
        self, ctx: FrameContext, labels: dict[str, int], segments: Mapping[str, np.ndarray],
        trees: SegmentTrees, shared: bool,
    ) -> None:  # fmt: skip
        self.ctx, self.labels, self.segments = ctx, labels, segments
        self.trees, self.shared = trees, shared

    @classmethod
    def stages(cls, ctx: FrameContext) -> OwnPoints:
        """The frame's segments, as the other stages judge every object (owned when it is
        its instance segment)."""
        return cls(ctx, ctx.owner, ctx.segments, ctx.segment_trees, True)

    @classmethod
    def of(cls, ctx: FrameContext) -> OwnPoints:
        """The objects of ``ctx``'s scene (not removed) with points of their own."""
        frame = ctx.frame
        live = [oid for oid in ctx.sim.world.ids if oid not in ctx.removed]
        if frame.instance_masks:
            labels = {oid: ctx.owner[oid] for oid in live if oid in ctx.owner}
            return cls(ctx, labels, ctx.segments, ctx.segment_trees, True)
        if frame.labels is None or frame.label_kind != "cluster":
            return cls(ctx, {}, {}, SegmentTrees({}), False)
        in_cluster: dict[int, list[str]] = {}
        for oid in live:
            if oid in ctx.members:
                in_cluster.setdefault(int(ctx.members[oid]), []).append(oid)
        # a cluster of several objects: whose point is whose is not known
        alone = {ids[0]: label for label, ids in in_cluster.items() if len(ids) == 1}
        of_label = indices_by_label(frame.labels) if alone else {}
        segments = {}
        reach = ctx.config.forces.max_distance
        for oid, label in alone.items():
            pts = frame.points[of_label[label]]
            model, T = ctx.models[oid], np.asarray(ctx.sim.world.get_pose(oid), dtype=float)
            centre = T[:3, :3] @ np.asarray(model.center_of_mass, dtype=float) + T[:3, 3]
            near = squared_distances(pts, centre) <= (model.d_max + reach) ** 2
            segments[oid] = pts[near]
        return cls(ctx, alone, segments, SegmentTrees(segments), False)

    def aligned(self, oid: str, poses: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Poses ``(4, 4)`` of object ``oid`` aligned to its points (point-to-plane ICP, as the
        polish aligns the pose they are compared with; in threads,
        :func:`ssp.threads.thread_map`): an estimator's alternative is often some millimetres
        off, and a thin part (a handle) a few degrees off is seen through."""
        segment = self.segments.get(oid)
        if segment is None or not len(segment):
            return [np.asarray(U, dtype=float) for U in poses]
        model, camera = self.ctx.models[oid], self.ctx.sim.camera_position
        return thread_map(
            lambda U: icp_refine(model, U, segment, camera), list(poses), name="ssp-icp"
        )

    def judged(self, oid: str, T: np.ndarray) -> Evidence:
        """:func:`ssp.verification.evidence` of object ``oid`` at ``T`` on its points."""
        ctx, trees = self.ctx, self.trees
        return evidence(
            ctx.models[oid], T, trees.tree(oid), ctx.view, ctx.config,
            own_label=self.labels.get(oid), segment_spacing=trees.spacing(oid),
        )  # fmt: skip
