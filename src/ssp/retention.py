"""Known objects without a hypothesis this frame: kept, or removed, and why (paper IV-C).

An estimator misses objects: hidden ones, and visible ones too (a dropout). :func:`triage`
decides, for each undetected known object at its previous pose, in this order:

``visible``
    still visible (:func:`ssp.verification.still_visible`: its visible surface explained,
    its volume not seen empty): kept where it was (a missed detection), whatever other
    objects' hypotheses say (the data outranks them; the paper tests replacement first),
    unless a newcomer of another class explains the data in its volume better (*contested*,
    :mod:`ssp.shared_volume`, without instance masks): then replacement is tested first;
``replaced``
    another object's first guess fills ``temporal.replaced_overlap`` of its volume: removed;
``seen_empty``
    its camera-facing surface is seen through (``temporal.seen_through_fraction``): the
    camera sees empty space where it was; removed (what it held up, if anything, is then
    held by its own data or falls: the camera's direct view of free space is not overruled by
    objects resting on a ghost);
``ephemeral``
    hidden behind observed depth (``temporal.occluded_fraction``), or outside the camera's
    field of view (a moving camera looked elsewhere: the fraction outside plus the fraction
    hidden reach ``temporal.occluded_fraction``): kept, as the camera could not have seen it;
``unseen``
    none of these (no data either way): removed unless it holds others up.

An object not visible at its pose nor a little off it (registered to its own instance
segment, ``visible`` too) that explains almost none of the instance segment the label vote
gave it (:data:`FOREIGN_EXPLAINED`) is judged with that segment as another object's: the
points in front of it then hide it.

:func:`support_retained` is the *support-retained* test of ``unseen`` objects: would the
objects that stay, and that it holds up in the settled first-guess scene, fall without it
(:func:`carries_load`)? Read from the contact forces: with the
object disabled, the acceleration from rest of each object it supports
(:meth:`ssp.physics.World.acceleration_from_rest`) exceeds ``temporal.retain_acceleration``
of ``g`` (linear) or of its largest angular acceleration under gravity. An unsupported cube
falls at ``g`` at once, however short a quasi-static settle would have been.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import SSPConfig
from ssp.library.model import ObjectModel
from ssp.overlap import overlap_fractions
from ssp.physics import World
from ssp.registration import bounded_refit
from ssp.verification import Evidence, evidence, still_visible
from ssp.visibility import CameraView

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "REMOVABLE",
    "Triage",
    "TriageState",
    "carries_load",
    "retain_or_remove",
    "support_retained",
    "triage",
    "triage_undetected",
]

log = logging.getLogger(__name__)


class TriageState(str, Enum):
    """What became of an undetected known object (module docstring); the value is its name in
    words (it compares equal to that string)."""

    VISIBLE = "visible"
    REPLACED = "replaced"
    SEEN_EMPTY = "seen_empty"
    EPHEMERAL = "ephemeral"
    UNSEEN = "unseen"

    def __str__(self) -> str:
        return self.value


#: Triage states whose objects are removed (``unseen`` ones unless they hold others up).
REMOVABLE = (TriageState.SEEN_EMPTY, TriageState.UNSEEN)


@dataclass(frozen=True)
class Triage:
    """The state of an undetected known object (module docstring) and the reason, in words."""

    state: TriageState
    reason: str
    evidence: Evidence | None = None


def triage(
    missing: Sequence[str],
    models: Mapping[str, ObjectModel],
    prev_pose: Mapping[str, np.ndarray],
    first: Mapping[str, np.ndarray],
    segments: Mapping[str, np.ndarray],
    owner: Mapping[str, int],
    view: CameraView | None,
    config: SSPConfig,
    contested: Mapping[str, str] | None = None,
) -> dict[str, Triage]:
    """State of each undetected object in ``missing`` (module docstring).

    Args:
        models, prev_pose: every object's model and previous pose.
        first: the detected objects' provisional poses.
        segments: each object's segment (world points), ``owner`` the instance label it came
            from when it is an instance segment.
        view: the frame's camera view (None without a camera pose).
        contested: id -> why a newcomer of another class explains the data in its volume
            better (:mod:`ssp.shared_volume`): replacement is tested before visibility (its
            data are the newcomer's, when the newcomer is there).
    """
    t = config.temporal
    contested = contested or {}
    out: dict[str, Triage] = {}
    det_ids = sorted(first)
    for oid in missing:
        model, T = models[oid], prev_pose[oid]
        ev = evidence(model, T, segments.get(oid), view, config, own_label=owner.get(oid))
        # the data says it is there: only a hypothesis explaining it better overrules it
        if oid not in contested and still_visible(ev, config):
            reason = f"undetected but still visible: explains {100 * ev.fit:.0f} % of its surface"
            out[oid] = Triage(TriageState.VISIBLE, reason, ev)
            continue
        if oid not in contested and oid in owner:
            found = _refit_visible(model, T, segments.get(oid), owner[oid], view, config)
            if found is not None:
                out[oid] = found
                continue
            ev = _judged_without_foreign(oid, model, T, segments.get(oid), view, config, ev)
        if det_ids:
            members = [oid, *det_ids]
            frac = overlap_fractions(
                [models[m] for m in members],
                np.stack([T, *(first[m] for m in det_ids)]),
                table=False,
                pairs=[(0, j) for j in range(1, len(members))],
            )[0]
            if frac >= t.replaced_overlap:
                why = f"another object fills {100 * frac:.0f} % of it"
                if oid in contested:
                    why += f": {contested[oid]}"
                out[oid] = Triage(TriageState.REPLACED, why)
                continue
        if oid in contested and still_visible(ev, config):
            reason = (
                f"undetected but still visible: explains {100 * ev.fit:.0f} % of its surface "
                f"(contested: {contested[oid]}, which is elsewhere)"
            )
            out[oid] = Triage(TriageState.VISIBLE, reason, ev)
            continue
        if view is not None and ev.seen_empty(config):
            reason = f"its volume is seen empty ({100 * ev.seen_through:.0f} % seen through)"
            out[oid] = Triage(TriageState.SEEN_EMPTY, reason, ev)
        elif view is not None and ev.facing and ev.occluded >= t.occluded_fraction:
            reason = f"hidden behind observed surfaces ({100 * ev.occluded:.0f} % occluded)"
            out[oid] = Triage(TriageState.EPHEMERAL, reason, ev)
        elif (
            view is not None and ev.outside > 0 and ev.outside + ev.occluded >= t.occluded_fraction
        ):
            reason = (
                f"outside the camera's view ({100 * ev.outside:.0f} % of its surface; "
                f"{100 * ev.occluded:.0f} % of what faces the camera hidden)"
            )
            out[oid] = Triage(TriageState.EPHEMERAL, reason, ev)
        else:
            out[oid] = Triage(TriageState.UNSEEN, "undetected and no data either way", ev)
        log.info("%s: %s", oid, out[oid].reason)
    return out


def _refit_visible(
    model: ObjectModel,
    T: np.ndarray,
    segment: np.ndarray | None,
    label: int,
    view: CameraView | None,
    config: SSPConfig,
) -> Triage | None:
    """An undetected object that its own instance segment ``segment`` (K, 3; world, m;
    instance ``label``; None: none this frame) does not show at its previous pose ``T`` (4x4,
    m) but shows a little off (:func:`~ssp.registration.bounded_refit`: within 2 cm and 20
    deg): ``visible`` (its data forces then pull it there), or None. A pose that drifted a few
    mm while the object was half out of a moving camera's view, or one the sensor noise left a
    few mm off, is otherwise judged at the wrong place: its facing sides seen through (removed
    as ``seen_empty``) or its surface unexplained (``unseen``), though the mask says one
    object is right there."""
    if segment is None:
        return None
    cam = None if view is None else view.T_world_cam[:3, 3]
    T_fit = bounded_refit(model, T, segment, cam, config)
    if T_fit is None:
        return None
    ev = evidence(model, T_fit, segment, view, config, own_label=label)
    if not still_visible(ev, config):
        return None
    off = 1000.0 * float(np.linalg.norm(T_fit[:3, 3] - T[:3, 3]))
    reason = (
        f"undetected but still visible {off:.0f} mm from its previous pose (its instance "
        f"segment registered): explains {100 * ev.fit:.0f} % of its surface there"
    )
    return Triage(TriageState.VISIBLE, reason, ev)


#: An undetected object that accounts for less than this fraction of the instance segment
#: it was given (a vote it lost to nothing better: the segment of the object in front of
#: it) is judged as if that segment were another object's.
FOREIGN_EXPLAINED = 0.05


def _judged_without_foreign(
    oid: str,
    model: ObjectModel,
    T: np.ndarray,
    segment: np.ndarray | None,
    view: CameraView | None,
    config: SSPConfig,
    ev: Evidence,
) -> Evidence:
    """``ev`` (its evidence with ``segment`` as its own instance segment), or, when the
    object at ``T`` (4x4, m) explains almost none of that segment (``explained <``
    :data:`FOREIGN_EXPLAINED`), its evidence with the segment taken as another object's:
    points in front of it then hide it (``occluded``) instead of being its own surface seen
    from behind. A cube hidden behind a tower, given the top cube's segment by the label
    vote, was otherwise removed as "no data either way" (wrist-camera tower, development
    seed 31, trial 1)."""
    if ev.explained is None or ev.explained >= FOREIGN_EXPLAINED:
        return ev
    log.info(
        "%s: its instance segment is another object's (explains %.0f %% of it)",
        oid,
        100 * ev.explained,
    )
    return evidence(model, T, segment, view, config)


def support_retained(
    world: World, graph, candidates: Sequence[str], config: SSPConfig
) -> dict[str, list[str]]:
    """The removal ``candidates`` (seen empty or unseen) that must stay because objects that
    stay would fall without them: ``id -> those objects``. Objects that are candidates
    themselves do not need holding up (a tower the camera sees empty goes as a whole), so the
    test runs to a fixed point: a candidate found needed stays, and its supporters are tested
    again with it among the objects that stay.

    Args:
        world: the frame's world in the settled first-guess scene.
        graph: its support graph (:class:`ssp.support.SupportGraph`, world order).
        candidates: the removal candidates' ids.
    """
    ids = world.ids
    pending = set(candidates)
    kept: dict[str, list[str]] = {}
    changed = True
    while changed:
        changed = False
        for oid in sorted(pending):
            kids = [ids[c] for c in graph.children(world.index(oid)) if ids[c] not in pending]
            falling = carries_load(world, kids, oid, config)
            if falling:
                kept[oid] = falling
                pending.discard(oid)
                changed = True
                log.info("%s undetected; without it %s would fall", oid, ", ".join(falling))
    return kept


def carries_load(world: World, kids: Sequence[str], oid: str, config: SSPConfig) -> list[str]:
    """The objects among ``kids`` (those ``oid`` holds up) that would fall without ``oid``
    (module docstring); the world is left as it was."""
    if not kids:
        return []
    g = float(config.physics.gravity)
    lim = float(config.temporal.retain_acceleration)
    was = world.is_enabled(oid)
    world.set_enabled(oid, False)
    try:
        lin, ang = world.acceleration_from_rest()
    finally:
        world.set_enabled(oid, was)
    falling = []
    for k in kids:
        i = world.index(k)
        a_max = world.model_of(k).max_angular_acceleration(g)
        if np.linalg.norm(lin[i]) > lim * g or np.linalg.norm(ang[i]) > lim * a_max:
            falling.append(k)
    return falling


# ------------------------------------------------------------------ the parser's stages
def triage_undetected(ctx: FrameContext) -> None:
    """Stage *triage of the undetected*: :func:`triage` of every known object without a group
    (one whose segment an association duplicate claimed is ``visible``); the ``replaced`` ones
    are removed.

    Sets ``missing``, ``verdicts`` and ``removed``.
    """
    claimed = ctx.assoc.claimed
    ctx.missing = sorted(set(ctx.known) - set(ctx.groups))
    verdicts = triage(
        [oid for oid in ctx.missing if oid not in claimed],
        ctx.models, ctx.prev_pose, ctx.first, ctx.segments, ctx.owner, ctx.view, ctx.config,
        ctx.assoc.contested,
    )  # fmt: skip
    reason = "undetected; its segment's points lie on it"
    verdicts.update({oid: Triage(TriageState.VISIBLE, reason) for oid in claimed})
    ctx.verdicts = verdicts
    ctx.removed = {oid for oid, v in verdicts.items() if v.state == TriageState.REPLACED}


def retain_or_remove(ctx: FrameContext) -> None:
    """Stage *support-retained* (not run when nothing changed): of the undetected objects seen
    empty or unseen, those that objects which stay would fall without (in the settled
    first-guess scene, :func:`support_retained`; only ``unseen`` ones qualify) stay; the others
    are disabled and removed.

    Sets ``retained``; updates ``removed``.
    """
    world = ctx.sim.world
    assert ctx.first_score is not None, "after the first guess"
    unseen = [o for o, v in ctx.verdicts.items() if v.state == TriageState.UNSEEN]
    ctx.retained = support_retained(world, ctx.first_score.graph, unseen, ctx.config)
    for oid in sorted(o for o, v in ctx.verdicts.items() if v.state in REMOVABLE):
        if oid not in ctx.retained:
            world.set_enabled(oid, False)
            ctx.removed.add(oid)
