"""Hypothesis verification: does an object explain its data, and is its volume not seen empty?

The role of global hypothesis verification (Aldoma et al., ECCV 2012; DESIGN section 6): a pose
estimator proposes objects; only those the data supports become part of the scene. Per object
at a pose, :func:`evidence` compares the model's surface samples with the frame:

* the camera classifies every camera-facing sample that the object's own other parts do not
  hide (:meth:`ssp.visibility.CameraView.classify` with the samples' spacing: the inner wall
  of a clamp behind its jaw is not part of what the camera could see):
  *seen* (observed depth at the sample), *occluded* (another object observed in front of it:
  the data says nothing about it), *behind its own surface* (the object's own segment observed
  in front of it: the model is too small there, or inside what was seen), *seen through*
  (observed depth behind it: that space is empty), or *unknown* (no depth along its ray);
* ``fit``: of the samples the camera could have seen (seen, seen through, or behind its own
  surface), the fraction with a point of the object's segment within the inlier radius, or
  within 0.75 point spacings of a sparser cloud (model to data; Eq. 12's ``c`` on the visible
  surface only, so a cube in full view scores near 1 and a half-hidden one too, and a cube
  proposed inside a ball does not);
* ``explained``: the fraction of the segment's points within the inlier radius plus the sample
  spacing of the model surface (data to model), when the segment is the object's own instance
  segment;
* ``seen_through``: the fraction of the camera-facing samples whose ray sees past them.

Without a camera pose every sample counts as visible and nothing is seen through.
:func:`check_new` turns the evidence into a verdict for an object the parser has not seen
before; :func:`still_visible` decides whether an undetected known object is still where it was.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ssp.config import SSPConfig
from ssp.estimate import Rejected
from ssp.geometry import transform_points
from ssp.holders import nothing_holds
from ssp.library.model import ObjectModel
from ssp.registration import bounded_refit
from ssp.scene import Hypothesis
from ssp.scoring import Term
from ssp.segments import SegmentTrees, explained_fraction, point_spacing
from ssp.visibility import (
    BEHIND_OWN,
    NOT_FACING,
    OCCLUDED,
    SEEN,
    SEEN_THROUGH,
    SELF_HIDDEN,
    CameraView,
)

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

log = logging.getLogger(__name__)

__all__ = [
    "Evidence",
    "Verdict",
    "check_new",
    "data_fallbacks",
    "evidence",
    "fall_back_to_data",
    "held_up",
    "judge_final",
    "may_hold_up",
    "place_new",
    "still_visible",
    "verify_and_place",
    "verify_final",
    "verify_new",
    "verify_new_objects",
]


@dataclass(frozen=True)
class Evidence:
    """What the frame says about an object at one pose (module docstring).

    Attributes:
        facing: camera-facing samples not hidden by the object itself (all samples without a
            camera).
        visible: facing samples the camera could have seen (seen or seen through).
        fit: fraction of the visible samples with a segment point within the inlier radius.
        explained: fraction of the instance segment's points the model accounts for, or None.
        seen_through: fraction of the facing samples whose ray sees past them.
        occluded: fraction of the facing samples hidden behind observed points.
        outside: fraction of all its samples outside the camera's field of view
            (:meth:`~ssp.visibility.CameraView.in_view`; 0.0 without a camera).
    """

    facing: int
    visible: int
    fit: float
    explained: float | None
    seen_through: float
    occluded: float
    outside: float = 0.0

    def seen_empty(self, config: SSPConfig) -> bool:
        """The camera sees through at least ``temporal.seen_through_fraction`` of the facing
        surface: the object's volume is observed empty."""
        return self.facing > 0 and self.seen_through >= config.temporal.seen_through_fraction

    def as_dict(self) -> dict:
        return {
            "facing": self.facing,
            "visible": self.visible,
            "fit": round(self.fit, 4),
            "explained": None if self.explained is None else round(self.explained, 4),
            "seen_through": round(self.seen_through, 4),
            "occluded": round(self.occluded, 4),
            "outside": round(self.outside, 4),
        }


@dataclass(frozen=True)
class Verdict:
    """Whether an object is kept, and why (a short sentence for people); ``T_world_obj``:
    the pose to keep it at when that is not the pose it was judged for (:func:`verify_final`),
    else None; ``searched``: then, the failed verdict at the pose it was judged for;
    ``unheld``: rejected because it would fall and nothing was shown to hold it up (weak data,
    or data that rules a holder out), why."""

    keep: bool
    reason: str
    evidence: Evidence | None = None
    T_world_obj: np.ndarray | None = None
    searched: Verdict | None = None
    unheld: str | None = None

    @property
    def judged(self) -> Evidence:
        """The evidence the verdict was reached on (:func:`check_new` and :func:`verify_final`
        always give it)."""
        if self.evidence is None:
            raise ValueError(f"a verdict without evidence: {self.reason}")
        return self.evidence


#: A surface sample counts as explained within this many point spacings of the segment (at
#: least the inlier radius): a grid of spacing s leaves no surface point farther than 0.71 s.
SPACING_COVER = 0.75


def _samples(model: ObjectModel, n: int) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(model.surface_points, dtype=float)
    nrm = np.asarray(model.surface_normals, dtype=float)
    if len(p) > n:
        sel = np.linspace(0, len(p) - 1, n).astype(int)
        p, nrm = p[sel], nrm[sel]
    return p, nrm


def evidence(
    model: ObjectModel,
    T_world_obj: np.ndarray,
    segment: np.ndarray | cKDTree | None,
    view: CameraView | None,
    config: SSPConfig,
    *,
    own_label: int | None = None,
    segment_spacing: float | None = None,
) -> Evidence:
    """The :class:`Evidence` for ``model`` at ``T_world_obj`` (4x4, m): ``segment`` ``(K, 3)``
    (or its KD-tree) is the object's part of the cloud, ``own_label`` the instance label it
    came from when it is the object's instance segment (then ``explained`` is computed).
    ``segment_spacing``: the segment's :func:`point_spacing` when already known (several
    poses of one object)."""
    own_segment = own_label is not None
    pts, nrm = _samples(model, int(config.search.fit_samples))
    T = np.asarray(T_world_obj, dtype=float)
    pw = transform_points(T, pts)
    if view is not None:
        spacing = float(np.sqrt(model.mesh.area / len(pts))) if len(pts) else None
        if model.convexity_excess <= view.depth_tolerance:
            spacing = None  # a (nearly) convex object cannot hide its own facing samples
        state = view.classify(pw, nrm @ T[:3, :3].T, own_label, self_spacing=spacing)
        facing = (state != NOT_FACING) & (state != SELF_HIDDEN)
        visible = (state == SEEN) | (state == SEEN_THROUGH) | (state == BEHIND_OWN)
        n_facing = int(np.count_nonzero(facing))
        through = int(np.count_nonzero(state == SEEN_THROUGH)) / n_facing if n_facing else 0.0
        occluded = int(np.count_nonzero(state == OCCLUDED)) / n_facing if n_facing else 0.0
        outside = 1.0 - float(np.mean(view.in_view(pw))) if len(pw) else 0.0
    else:
        facing = visible = np.ones(len(pw), dtype=bool)
        n_facing, through, occluded, outside = len(pw), 0.0, 0.0, 0.0
    n_visible = int(np.count_nonzero(visible))
    fit = 0.0
    tree = None
    if segment is not None:
        tree = segment if isinstance(segment, cKDTree) else None
        if tree is None and len(segment):
            tree = cKDTree(np.asarray(segment, dtype=float))
    if tree is not None and n_visible:
        if segment_spacing is None:
            segment_spacing = point_spacing(tree)
        radius = max(config.data.inlier_radius, SPACING_COVER * segment_spacing)
        d, _ = tree.query(pw[visible], k=1, distance_upper_bound=radius)
        fit = float(np.count_nonzero(np.isfinite(d))) / n_visible
    explained = None
    if own_segment and tree is not None:
        radius = config.data.inlier_radius + config.library.surface_spacing
        explained = explained_fraction(tree.data, model, T, radius)
    return Evidence(n_facing, n_visible, fit, explained, through, occluded, outside)


#: Loose check (raw hypotheses, before the search): the seen-through limit is at least this,
#: and the fit limit this fraction of ``verification.min_fit``.
LOOSE_SEEN_THROUGH = 0.6
LOOSE_FIT = 1.0 / 3.0


def check_new(
    ev: Evidence, config: SSPConfig, *, loose: bool = False, counted: bool = True
) -> Verdict:
    """Verdict on an object not seen before, at its best pose: kept only if the camera could
    see enough of it (``verification.min_visible_samples``), its visible surface is explained
    (``fit >= verification.min_fit``) by at least as many samples (a new object almost
    hidden, 3 of its 10 visible samples explained, kept a ghost on the wrist-camera tower's
    table: development seed 11, trial 2), it explains its instance segment
    (``explained >= verification.min_explained``) and its volume is not seen empty
    (``seen_through < temporal.seen_through_fraction``).

    ``loose``: the check of a raw hypothesis, which may be a few millimetres off (a face 5 mm
    too close to the camera is seen through): the seen-through limit is at least
    :data:`LOOSE_SEEN_THROUGH`, the fit limit :data:`LOOSE_FIT` of ``min_fit``, and the
    segment is not checked. ``counted``: the explained samples are counted (not for a known
    object, :func:`doubt`: one mostly hidden is not doubted for it)."""
    v = config.verification
    through = config.temporal.seen_through_fraction
    min_fit = v.min_fit
    if loose:
        through, min_fit = max(through, LOOSE_SEEN_THROUGH), LOOSE_FIT * min_fit
    if ev.visible < v.min_visible_samples:
        if ev.facing == 0:
            return Verdict(False, "not in the camera's view: no data to support it", ev)
        return Verdict(False, "nothing of it is visible: no data to support it", ev)
    if ev.seen_through >= through:
        return Verdict(
            False, f"its volume is seen empty ({100 * ev.seen_through:.0f} % seen through)", ev
        )
    if ev.fit < min_fit:
        pct, lim = 100 * ev.fit, 100 * min_fit
        return Verdict(False, f"explains {pct:.0f} % of its visible surface (< {lim:.0f})", ev)
    if loose:
        return Verdict(True, "plausible", ev)
    if counted and ev.fit * ev.visible < v.min_visible_samples:  # what the data shows of it
        return Verdict(
            False,
            f"only {ev.fit * ev.visible:.0f} samples of its surface are explained by the data "
            f"(< {v.min_visible_samples}): too little to verify it by",
            ev,
        )
    if ev.explained is not None and ev.explained < v.min_explained:
        return Verdict(
            False,
            f"accounts for {100 * ev.explained:.0f} % of its segment "
            f"(< {100 * v.min_explained:.0f})",
            ev,
        )
    text = f"verified: explains {100 * ev.fit:.0f} % of its visible surface"
    if ev.explained is not None:
        text += f" and accounts for {100 * ev.explained:.0f} % of its segment"
    return Verdict(True, text, ev)


def verify_new(
    new: Sequence[str],
    groups: Mapping[str, Sequence[Hypothesis]],
    models: Mapping[str, ObjectModel],
    segments: SegmentTrees,
    owner: Mapping[str, int],
    view: CameraView | None,
    config: SSPConfig,
    *,
    loose: bool = True,
) -> dict[str, Rejected]:
    """Parser stage 4: the ``new`` objects (ids) that the data supports at none of their
    hypotheses (``groups``; :func:`check_new` with ``loose``: the raw hypotheses may be a few
    millimetres off), by id, each with the evidence of its best hypothesis. ``segments``: the
    frame's segment trees; ``owner``: the instance label of each object's segment. ``loose``
    False: the check after the search (:func:`ssp.static.repeated_rejections`)."""
    out: dict[str, Rejected] = {}
    for oid in new:
        best: tuple[tuple, Evidence, Hypothesis] | None = None
        tree, spacing = segments.tree(oid), segments.spacing(oid)
        for h in groups[oid]:
            ev = evidence(
                models[oid], h.T_world_obj, tree, view, config,
                own_label=owner.get(oid), segment_spacing=spacing,
            )  # fmt: skip
            key = (check_new(ev, config, loose=loose).keep, ev.fit, -ev.seen_through)
            if best is None or key > best[0]:
                best = (key, ev, h)
            if key[0]:  # one hypothesis the data supports keeps the object
                break
        assert best is not None, "every group has a hypothesis"
        _, ev, h = best
        verdict = check_new(ev, config, loose=loose)
        if not verdict.keep:
            out[oid] = Rejected(
                oid, h.class_name, np.array(h.T_world_obj), verdict.reason, ev.as_dict(),
                h.segment,
            )  # fmt: skip
            log.info("%s (%s) rejected: %s", oid, h.class_name, verdict.reason)
    return out


def verify_final(
    model: ObjectModel,
    T_final: np.ndarray,
    hypotheses: Sequence[np.ndarray],
    segment: np.ndarray | cKDTree | None,
    view: CameraView | None,
    config: SSPConfig,
    *,
    own_label: int | None,
    stability: float,
    segment_spacing: float | None = None,
    before: Sequence[Rejected] = (),
) -> Verdict:
    """The verdict on a new object after the search: :func:`check_new` at its final pose
    ``T_final``. An object is never reported at a pose its data does not support: when the
    final pose fails (physics moved it off its data: what holds it is undetected, or its
    hypothesis interpenetrates another object, so the data fallbacks could not put it back)
    but one of its ``hypotheses`` passes, it is kept at the best such hypothesis
    (:attr:`Verdict.T_world_obj`; the data decides whether and where it is; the reason
    says so), unless nothing undetected can hold it up there
    (:func:`~ssp.holders.nothing_holds`). When its ``stability`` term at the final pose says
    it would fall (below ``verification.fall_stability``), it is kept only if its data is
    strong and does not rule out a holder (:func:`_falls`: a cube proposed on a ball
    explains half of the ball and cannot rest on it; a cube fitted to a can's top has the
    can's side under it). ``segment``:
    ``(K, 3)`` points or their KD-tree;
    ``segment_spacing``: their :func:`~ssp.segments.point_spacing` when known; ``before``: the
    previous frame's rejections (where nothing held an object up then)."""
    tree = segment if isinstance(segment, cKDTree) else None
    if tree is None and segment is not None and len(segment):
        tree = cKDTree(np.asarray(segment, dtype=float))
    spacing = segment_spacing
    if spacing is None and tree is not None:
        spacing = point_spacing(tree)
    ev = evidence(model, T_final, tree, view, config, own_label=own_label, segment_spacing=spacing)
    verdict = check_new(ev, config)
    if not verdict.keep:
        best: tuple[float, np.ndarray, Verdict] | None = None
        unheld = None
        for T in hypotheses:
            ev_h = evidence(
                model, T, tree, view, config, own_label=own_label, segment_spacing=spacing
            )
            hv = check_new(ev_h, config)
            e = hv.judged
            strength = e.fit if e.explained is None else e.explained
            if hv.keep and (why := _unheld(model, T, tree, own_label, view, config, before)):
                unheld = unheld or why
                continue  # held there by nothing under it
            if hv.keep and (best is None or strength > best[0]):
                best = (strength, np.asarray(T, dtype=float), hv)
        if best is None:
            return replace(verdict, unheld=unheld)
        _, T, hv = best
        return Verdict(
            True,
            f"{hv.reason}, kept at its hypothesis: the searched scene could not hold it where "
            f"its data puts it ({verdict.reason} there)",
            hv.evidence,
            T.copy(),
            verdict,
        )
    why = _falls(model, T_final, stability, ev, tree, view, config, own_label, before)
    if why is not None:
        return Verdict(
            False,
            f"would fall where the data puts it (stability term {stability:.0f}) and {why}",
            ev,
            unheld=why,
        )
    return verdict


def _place(oid, verdict: Verdict, world, scorer, model, segments, own_label, view, config,
           timer, before) -> Verdict:  # fmt: skip
    """:func:`verify_and_place` of one object kept at a hypothesis (``verdict.T_world_obj``):
    put there in ``world`` and its verdict, or put back where the search left it (disabled)
    with the failed one: it would fall there with nothing shown to hold it (:func:`_falls`),
    or be inside another object without its own instance segment saying it is there."""
    searched = world.get_pose(oid)
    target = verdict.T_world_obj
    assert target is not None, "a verdict kept at a hypothesis has its pose"
    world.set_enabled(oid, True)
    world.set_pose(oid, target)
    terms = scorer.evaluate(world, timer).terms[world.index(oid)]
    collision, stability = float(terms[Term.COLLISION]), float(terms[Term.STABILITY])
    own = verdict.judged.explained is not None  # it accounts for its segment
    falls = None  # with its own instance segment: without masks a cluster says less
    if own:
        falls = _falls(model, target, stability, verdict.judged, segments.tree(oid), view,
                       config, own_label, before)  # fmt: skip
    failed = verdict.searched if verdict.searched is not None else verdict
    if falls is None and (collision >= config.verification.fallback_collision or own):
        if collision < config.verification.fallback_collision:
            # its own instance segment says it is there: kept, with the doubt said
            return replace(verdict, reason=(
                f"{verdict.reason}; there it is inside another object (collision term "
                f"{collision:.1f}): its model or a neighbour's may not match the data"
            ))  # fmt: skip
        return verdict
    world.set_pose(oid, searched)
    world.set_enabled(oid, False)
    if falls is not None:  # held there by nothing: the rule of a final pose
        why = f"would fall (stability term {stability:.0f}) and {falls}"
    else:
        why = f"would be inside another object (collision term {collision:.1f})"
    return Verdict(False, f"{failed.reason}; at its best hypothesis it {why}", failed.evidence,
                   unheld=falls)  # fmt: skip


def _weak(ev: Evidence, config: SSPConfig) -> str | None:
    """Why ``ev`` is not strong enough to keep an object that would fall (held by something
    undetected), or None: it explains ``verification.stand_explained`` of its instance
    segment and of its visible surface, and, with its own instance segment, the camera sees
    through less than ``verification.stand_seen_through`` of it (a version that applied that
    bar without instance masks too left objects interpenetrating, 20.7 mm on Table I's
    structures without masks, seed 1005; how was not traced)."""
    v = config.verification
    if ev.explained is not None and ev.explained < v.stand_explained:
        return f"accounts for only {100 * ev.explained:.0f} % of its segment"
    if ev.fit < v.stand_explained:
        return f"explains only {100 * ev.fit:.0f} % of its visible surface"
    if ev.explained is not None and ev.seen_through >= v.stand_seen_through:
        return f"the camera sees through {100 * ev.seen_through:.0f} % of it"
    return None


def _falls(model, T, stability, ev, tree, view, config, own_label, before) -> str | None:
    """Why a new object that would fall at ``T`` (4x4, m; its ``stability`` term below
    ``verification.fall_stability``; ``ev``: its evidence there) is not held by something
    undetected, or None (it stands on its data): the data rules a holder out (:func:`_unheld`),
    or it is weak (:func:`_weak`) at ``T`` and at its pose registered to its segment ``tree``
    (:func:`~ssp.registration.bounded_refit`: a true object a few mm and degrees off shows its
    sides' edges seen through and its surface half explained; a shape that is not what the
    camera saw, a cube fitted to a can's top or a ball, stays so however it is aligned)."""
    if stability >= config.verification.fall_stability:
        return None
    unheld = _unheld(model, T, tree, own_label, view, config, before)
    if unheld is not None:
        return unheld
    weak = _weak(ev, config)
    if weak is None or tree is None or view is None or ev.explained is None:
        return weak  # registered only to its own instance segment (a cluster may be several)
    T_fit = bounded_refit(model, T, tree.data, view.T_world_cam[:3, 3], config)
    if T_fit is None:
        return weak
    ev_fit = evidence(model, T_fit, tree, view, config, own_label=own_label)
    return None if _weak(ev_fit, config) is None else weak


def may_hold_up(verdict: Verdict, config: SSPConfig) -> bool:
    """Whether a new object that failed :func:`verify_final` may stay for holding others up
    (:func:`held_up`): not when its volume is seen empty (``temporal.seen_through_fraction``):
    the camera's direct view of free space is not overruled by objects resting on it (as for
    known objects, :mod:`ssp.retention`); a false hypothesis on an object not in the library
    would otherwise stay as long as what lies on that object is in the scene."""
    return verdict.evidence is None or not verdict.evidence.seen_empty(config)


def held_up(
    unverified: Iterable[str], stays: Iterable[str], children: Callable[[str], Iterable[str]]
) -> dict[str, list[str]]:
    """The unverified objects that stay because they hold up an object that stays: ``id ->``
    the staying objects it holds up. ``stays``: the objects kept on their own (verified or
    known); ``children(id)``: the objects ``id`` supports (support graph). An object kept this
    way counts as staying for the objects under it (a chain down to the table stays), but
    unverified objects that hold up only each other, or only rejected ones, do not: two false
    objects stacked on one another do not vouch for each other."""
    pending = list(unverified)
    staying = set(stays)
    out: dict[str, list[str]] = {}
    changed = True
    while changed:
        changed = False
        for oid in pending:
            if oid in out:
                continue
            kids = [c for c in children(oid) if c in staying]
            if kids:
                out[oid] = kids
                staying.add(oid)
                changed = True
    return out


def data_fallbacks(score, scorer, groups, config: SSPConfig) -> dict[str, tuple[np.ndarray, str]]:
    """No worse than the evidence: the detected objects whose searched pose explains much
    less of their visible surface (data fit ``c``, Eq. 12) than their best hypothesis does,
    by more than ``verification.fallback_fit_drop``: the search moved them off their data,
    typically because what holds them up is not in the scene (an undetected object, a
    distractor) and physics let them fall or tilt. ``id -> (that hypothesis's pose, the
    warning)``; the parser puts them back there unless that pose interpenetrates another
    object (``verification.fallback_collision``).

    Args:
        score: the searched scene's :class:`ssp.scoring.SceneScore`.
        scorer: the frame's :class:`ssp.scoring.SceneScorer` (same world order).
        groups: ``id -> hypotheses`` of the detected objects.
    """
    drop = config.verification.fallback_fit_drop
    out: dict[str, tuple[np.ndarray, str]] = {}
    for oid, hyps in groups.items():
        if oid not in score.ids:
            continue
        i = score.ids.index(oid)
        if not score.enabled[i] or not hyps:
            continue
        fits = [scorer.fit_fraction(i, h.T_world_obj) for h in hyps]
        j = int(np.argmax(fits))
        if fits[j] - float(score.fit[i]) > drop:
            note = (
                f"the search moved it off its data (fit {score.fit[i]:.2f} against "
                f"{fits[j]:.2f} at its best hypothesis): kept at that hypothesis; what holds "
                "it up may be undetected"
            )
            out[oid] = (np.asarray(hyps[j].T_world_obj, dtype=float).copy(), note)
    return out


def _unheld(model, T_world_obj, tree: cKDTree | None, own_label: int | None, view, config,
            before: Sequence[Rejected] = ()) -> str | None:  # fmt: skip
    """:func:`~ssp.holders.nothing_holds` with an object's own instance segment (``tree``'s
    points) and the previous frame's rejections ``before`` (:attr:`Rejected.unheld`): why
    nothing undetected holds it up there, or None (also without one: a cluster's points near
    it say nothing of what lies below it)."""
    if own_label is None or tree is None:
        return None
    ruled = [(r.T_world_obj, r.unheld) for r in before if r.class_name == model.name and r.unheld]
    return nothing_holds(
        model, T_world_obj, tree.data, view, own_label, config.verification.fallback_below,
        ruled, config.temporal.association_distance,
    )  # fmt: skip


def still_visible(ev: Evidence, config: SSPConfig) -> bool:
    """An undetected known object is still there when enough of it is visible
    (``verification.min_visible_samples``) and explained (``fit >= temporal.visible_fit``)
    with its volume not seen empty."""
    return (
        ev.visible >= config.verification.min_visible_samples
        and ev.fit >= config.temporal.visible_fit
        and ev.seen_through < config.temporal.seen_through_fraction
    )


def verify_and_place(
    world, scorer, score, models, groups, segments, owner, view, skip, config, timer, before=()
) -> tuple[dict[str, Verdict], dict[str, np.ndarray]]:
    """Parser step 8: :func:`verify_final` of every new object (not in ``skip``: known or
    removed ones) at its searched pose (``score``: the scene ``world`` holds, scored by
    ``scorer``; ``groups``, ``owner``: the hypotheses and label per id; ``segments``: the
    frame's :class:`~ssp.segments.SegmentTrees`);
    those kept at a hypothesis instead are put there in ``world``, one at a time, strongest data
    first, unless there it would be inside another object (its collision term below
    ``verification.fallback_collision``, the data fallbacks' rule): then it stays where
    the search put it and fails (a duplicate of a kept object, or a hypothesis physics
    cannot hold), unless it accounts for its own instance segment: then it is kept there
    with that doubt in its reason (and so in the frame's warnings). ``before``: the previous
    frame's rejections (:func:`verify_final`). Returns the verdicts and the objects put at a
    hypothesis."""
    cfg = config
    ids = score.ids
    verdicts: dict[str, Verdict] = {}
    for oid in ids:
        if oid in skip:
            continue
        i = ids.index(oid)
        verdicts[oid] = verify_final(
            models[oid],
            score.poses[i],
            [h.T_world_obj for h in groups.get(oid, ())],
            segments.tree(oid),
            view,
            cfg,
            own_label=owner.get(oid),
            stability=float(score.terms[i, Term.STABILITY]),
            segment_spacing=segments.spacing(oid),
            before=before,
        )
    to_place = [oid for oid, v in verdicts.items() if v.keep and v.T_world_obj is not None]

    def strength(oid: str) -> float:
        e = verdicts[oid].judged
        return -(e.fit if e.explained is None else e.explained)

    placed: dict[str, np.ndarray] = {}
    # judged against what stays for sure: known and verified objects and those placed
    # before it; not against a failed one (it may be a false object, as a false cube under
    # a true one, though it may still stay, holding others), nor against the others still
    # to place (where the search left them is where their data says they are not)
    unverified = [oid for oid, v in verdicts.items() if not v.keep]
    for oid in unverified + to_place:
        world.set_enabled(oid, False)
    for oid in sorted(to_place, key=lambda o: (strength(o), o)):
        verdicts[oid] = _place(oid, verdicts[oid], world, scorer, models[oid], segments,
                               owner.get(oid), view, cfg, timer, before)  # fmt: skip
        target = verdicts[oid].T_world_obj
        if verdicts[oid].keep and target is not None:
            placed[oid] = target
    for oid in unverified + to_place:
        world.set_enabled(oid, True)
    return verdicts, placed


# ------------------------------------------------------------------ the parser's stages
def verify_new_objects(ctx: FrameContext) -> None:
    """Stage *verification of the new*: :func:`verify_new` on the objects not seen before; a
    rejected one leaves the frame (its group, provisional pose and class). The groups that
    association dropped for lying in a known object's volume (:mod:`ssp.shared_volume`) are
    rejected with them.

    Sets ``rejected``; updates ``groups``, ``first`` and ``classes``.
    """
    new = [oid for oid in ctx.groups if oid not in ctx.known]
    ctx.rejected = dict(ctx.assoc.shared)
    ctx.rejected.update(verify_new(
        new, ctx.groups, ctx.models, ctx.segment_trees, ctx.owner, ctx.view, ctx.config
    ))  # fmt: skip
    new_rejected = [oid for oid in ctx.rejected if oid in ctx.groups]
    for oid in new_rejected:
        del ctx.groups[oid], ctx.first[oid], ctx.classes[oid]


def fall_back_to_data(ctx: FrameContext) -> None:
    """Stage *fallbacks*: data wins over physics for objects new in this frame, or held by
    their data before (an established object keeps its physically consistent pose): those the
    search moved off their data (:func:`data_fallbacks`) go back to their best hypothesis,
    unless there they would be inside another object (``verification.fallback_collision``),
    or the data rules out a holder there (:func:`~ssp.holders.nothing_holds`: their own
    instance segment reaches below them, or the camera sees under them).

    Sets ``fallbacks``; updates ``score`` and ``chosen``.
    """
    cfg, known, sim = ctx.config, ctx.known, ctx.sim
    world, scorer = sim.world, sim.scorer
    may_fall_back = {oid for oid in ctx.groups if oid not in known or known[oid].held}
    fallbacks = data_fallbacks(
        ctx.scene_score, scorer, {oid: ctx.groups[oid] for oid in may_fall_back}, cfg
    )
    for oid in [o for o in fallbacks if o in ctx.owner]:  # what it shows under it
        why = _unheld(ctx.models[oid], fallbacks[oid][0], ctx.segment_trees.tree(oid),
                      ctx.owner[oid], ctx.view, cfg, ctx.remembered)  # fmt: skip
        if why is not None:
            log.info("%s: not put back at its hypothesis: %s", oid, why)
            del fallbacks[oid]
    if fallbacks:
        searched = {oid: world.get_pose(oid) for oid in fallbacks}
        world.set_poses({oid: T for oid, (T, _) in fallbacks.items()})
        moved = scorer.evaluate(world, ctx.timer)
        # data wins over physics only where it does not put one object into another
        clash = {
            oid
            for oid in fallbacks
            if moved.terms[world.index(oid), Term.COLLISION] < cfg.verification.fallback_collision
        }
        for oid in clash:
            world.set_pose(oid, searched[oid])
            del fallbacks[oid]
        ctx.score = scorer.evaluate(world, ctx.timer) if clash else moved
        ctx.chosen.update({oid: "hypothesis (data fallback)" for oid in fallbacks})
    ctx.fallbacks = fallbacks


def place_new(ctx: FrameContext) -> None:
    """Stage *placement*: every new object verified at its final pose
    (:func:`verify_and_place`; those kept at a hypothesis are put there), and every object's
    :func:`evidence` at its final pose.

    Sets ``final_verdicts``, ``placed`` and ``evidence``; updates ``score``.
    """
    cfg, sim, trees = ctx.config, ctx.sim, ctx.segment_trees
    world, scorer = sim.world, sim.scorer
    ctx.final_verdicts, ctx.placed = verify_and_place(
        world, scorer, ctx.scene_score, ctx.models, ctx.groups, trees, ctx.owner, ctx.view,
        set(ctx.prev_pose) | set(ctx.removed), cfg, ctx.timer, ctx.remembered,
    )  # fmt: skip
    if ctx.placed:
        ctx.score = scorer.evaluate(world, ctx.timer)
    score = ctx.scene_score
    ctx.evidence = {
        oid: evidence(
            ctx.models[oid],
            score.poses[world.index(oid)],
            trees.tree(oid),
            ctx.view,
            cfg,
            own_label=ctx.owner.get(oid),
            segment_spacing=trees.spacing(oid),
        )  # fmt: skip
        for oid in world.ids
        if oid not in ctx.removed
    }


def judge_final(ctx: FrameContext) -> None:
    """Stage *final verdicts*: a new object that failed at its final pose stays if it holds up
    an object that stays and the camera does not see through it (:func:`held_up`,
    :func:`may_hold_up`; kept with a warning), else it is rejected, with what rests on it
    named. Unverified objects holding up only each other, or only rejected ones, go together.

    Sets ``warnings`` (the fallbacks', the placed objects', the held-up ones'), ``reasons``
    and ``gone``; updates ``rejected``.
    """
    cfg, score, models = ctx.config, ctx.scene_score, ctx.models
    ids = score.ids
    warnings = [f"{oid}: {note}" for oid, (_, note) in sorted(ctx.fallbacks.items())]
    rejected = dict(ctx.rejected)
    failed: dict[str, Verdict] = {}
    for oid, verdict in ctx.final_verdicts.items():
        if verdict.keep:
            ctx.reasons[oid] = verdict.reason
            if oid in ctx.placed:  # kept where its data puts it
                warnings.append(f"{oid}: {verdict.reason}")
        else:
            failed[oid] = verdict
    holds = held_up(
        [oid for oid, v in failed.items() if may_hold_up(v, cfg)],
        [oid for oid in ids if oid not in ctx.removed and oid not in failed | rejected.keys()],
        lambda oid: [ids[c] for c in score.graph.children(ids.index(oid))],
    )
    for oid, verdict in failed.items():
        i = ids.index(oid)
        if oid in holds:
            ctx.reasons[oid] = f"unverified ({verdict.reason}) but holds up {', '.join(holds[oid])}"
            warnings.append(f"{oid}: {ctx.reasons[oid]}")
            continue
        seg = ctx.groups[oid][0].segment if oid in ctx.groups else None
        why = verdict.reason
        on_it = [ids[c] for c in score.graph.children(i) if ids[c] not in ctx.removed]
        if on_it:
            why += f" (what rests on it, {', '.join(on_it)}, does not keep it)"
        rejected[oid] = Rejected(
            oid, models[oid].name, score.poses[i].copy(), why, verdict.judged.as_dict(), seg,
            verdict.unheld,
        )  # fmt: skip
        log.info("%s (%s) rejected at its final pose: %s", oid, models[oid].name, why)
    ctx.warnings, ctx.rejected = warnings, rejected
    ctx.gone = set(ctx.removed) | set(rejected)


def doubt(ev: Evidence, stability: float, config: SSPConfig) -> tuple[str, bool] | None:
    """Why the data contradicts a known object at its final pose, or None: enough of it is
    visible (``verification.min_visible_samples``: a hidden object is not doubted) and it fails
    :func:`check_new` (its volume seen empty, its visible surface not explained), or it would
    fall where it is and its data is weak (:func:`falls_unheld`, the rule of
    :func:`verify_final`). A known object is never judged by the share of a segment it
    accounts for: without its own instance segment that share says nothing. Returns ``(why,
    falls)``: ``falls`` for the last rule (a better-fitting hypothesis would not stand
    either)."""
    if ev.visible < config.verification.min_visible_samples:
        return None
    verdict = check_new(replace(ev, explained=None), config, counted=False)
    if not verdict.keep:
        return verdict.reason, False
    if falls_unheld(stability, ev.fit, config):
        return (
            f"would fall where it is (stability term {stability:.0f}) and explains only "
            f"{100 * ev.fit:.0f} % of its visible surface"
        ), True
    return None


def falls_unheld(stability: float, strength: float, config: SSPConfig) -> bool:
    """A known object whose stability term says it would fall (below
    ``verification.fall_stability``) stands only with strong data (``strength``, a fit or an
    explained fraction, at least ``verification.stand_explained``: held by something
    undetected); a cube proposed on a ball explains half of the ball and cannot rest on it
    (:func:`doubt`; a new object is judged by :func:`verify_final`'s stricter rule)."""
    v = config.verification
    return stability < v.fall_stability and strength < v.stand_explained


#: A doubted known object whose hypothesis the data supports (:func:`check_new`) and fits by
#: more than this (fraction of the visible surface) better than its final pose is misplaced,
#: not false (:func:`doubt_known`).
DOUBT_FIT_SLACK = 0.05


def _better_hypothesis(ctx: FrameContext, oid: str, fit: float) -> bool:
    """Does a hypothesis of ``oid`` this frame pass :func:`check_new` with a fit above
    ``fit``?"""
    trees = ctx.segment_trees
    for h in ctx.groups.get(oid, ()):
        ev = evidence(
            ctx.models[oid], h.T_world_obj, trees.tree(oid), ctx.view, ctx.config,
            segment_spacing=trees.spacing(oid),
        )  # fmt: skip
        if ev.fit > fit and check_new(ev, ctx.config).keep:
            return True
    return False


def doubt_known(ctx: FrameContext) -> None:
    """Stage *re-verification*: a known object is verified once, when it is new; with an
    instance segment that check holds (it accounts for its segment), without one (clusters, a
    bare cloud) a false object the data supported once by chance - a tool proposed on a
    distractor, 52 % of its visible surface explained, that would fall where it is - stayed
    for good, proposed again frame after frame, or kept as hidden inside the distractor when
    it was not. In a frame without instance masks, every known object, detected or not, is
    checked at its final pose (:func:`doubt`); one that fails (seen empty
    or unexplained where none of its hypotheses is supported and fits better, by
    :data:`DOUBT_FIT_SLACK`: then it is there, misplaced; or it would fall with weak data) in
    this frame and in the previous one too leaves the scene (removed, with both reasons),
    unless it holds up an object that stays. One failure is remembered
    (``Known.doubt``), not acted on: on Table I's realistic tool stream without masks the
    true objects never failed twice running and the false ones did.

    Sets ``doubts`` and ``doubted``; updates ``removed``, ``gone`` and ``score``.
    """
    cfg, score, world = ctx.config, ctx.scene_score, ctx.sim.world
    ids = score.ids
    ctx.doubts, ctx.doubted = {}, {}
    if ctx.frame.instance_masks:
        return  # instance masks: every object's segment is its own, or it has none
    for oid in ids:
        if oid not in ctx.known or oid in ctx.gone:
            continue
        if oid not in ctx.evidence:
            continue
        i = ids.index(oid)
        ev = ctx.evidence[oid]
        found = doubt(ev, float(score.terms[i, Term.STABILITY]), cfg)
        if found is None:
            continue
        why, falls = found
        if not falls and _better_hypothesis(ctx, oid, ev.fit + DOUBT_FIT_SLACK):
            continue  # there, misplaced: one of its hypotheses is supported and fits better
        before = ctx.known[oid].doubt
        holds = [ids[c] for c in score.graph.children(i) if ids[c] not in ctx.gone]
        if before is None or holds:
            ctx.doubts[oid] = why
            continue
        ctx.doubted[oid] = f"its data contradicts it two frames running: {why} (before: {before})"
        log.info("%s (%s) removed: %s", oid, ctx.models[oid].name, ctx.doubted[oid])
    if ctx.doubted:
        for oid in ctx.doubted:
            world.set_enabled(oid, False)
        ctx.removed |= set(ctx.doubted)
        ctx.gone |= set(ctx.doubted)
        ctx.score = ctx.sim.scorer.evaluate(world, ctx.timer)
