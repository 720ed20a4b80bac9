"""The first guess: where each object starts before the search (DESIGN section 1, step 3).

Alg. 3 of the paper takes a support graph as given; it does not say which scene it comes from.

Before the search tests any candidate, every object is put at one pose and the scene is
settled with data forces; the support graph of that settled scene gives the search its layers
(Alg. 2). :func:`first_guess` is an object's *provisional* pose, before its segment is known
(it votes for the segment and is what the undetected-object triage tests against);
:func:`best_first_guess` the pose it takes in the first-guess scene, once the scorer can weigh
its candidates by the terms that need no simulation (data fit and transition). A static object
whose hidden part fits a wrong pose best thus starts where it was, and the objects on it settle
onto it: the search tests each object with the objects it carries at their first-guess poses.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import TemporalConfig
from ssp.errors import PhysicsError
from ssp.library.symmetry import Symmetry
from ssp.probability import pose_change
from ssp.scene import Hypothesis
from ssp.static import settle_moved, settled_objects

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = ["best_first_guess", "first_guess", "first_guess_scene"]

log = logging.getLogger(__name__)


def first_guess(
    hypotheses: Sequence[Hypothesis],
    T_prev: np.ndarray | None,
    symmetry: Symmetry,
    config: TemporalConfig,
    centre: np.ndarray | None = None,
) -> np.ndarray:
    """An object's provisional pose (4x4, m), before its segment is known: its previous pose
    ``T_prev`` when one of its ``hypotheses`` (best first) lies within the static thresholds of
    it (symmetry-aware), else its best hypothesis. It votes for the object's segment label and
    is the pose the undetected-object triage tests against; the first-guess scene then takes,
    per object, the best of this pose and the hypotheses by data fit and transition."""
    if T_prev is not None:
        for h in hypotheses:
            dt, dth = pose_change(T_prev, h.T_world_obj, symmetry, centre)
            if dt < config.static_translation and dth < config.static_rotation:
                return T_prev
    return hypotheses[0].T_world_obj


def best_first_guess(
    hypotheses: Sequence[Hypothesis],
    T_prev: np.ndarray | None,
    score: Callable[[np.ndarray], float],
) -> np.ndarray:
    """The object's pose in the first-guess scene (4x4, m): the highest ``score`` (the terms
    that need no simulation, :meth:`SceneScorer.unsimulated`) among its previous pose
    ``T_prev`` (when known) and its ``hypotheses``; ties keep the earlier, previous pose
    first."""
    poses = [h.T_world_obj for h in hypotheses]
    if T_prev is not None:
        poses.insert(0, T_prev)
    return max(poses, key=score)


def first_guess_scene(ctx: FrameContext) -> None:
    """Stage *first guess* (not run when nothing changed): the objects that keep their
    previous pose untested (:func:`ssp.static.settled_objects`), every other detected object
    at its :func:`best_first_guess`, the scene settled with data forces
    (``search.initial_settle``; a failed settle keeps the unsettled guess) and scored.

    Sets ``first``, ``settled`` and ``first_score``.
    """
    cfg, sim, prev_pose, models = ctx.config, ctx.sim, ctx.prev_pose, ctx.models
    world, scorer = sim.world, sim.scorer
    ids = world.ids
    settled: set[str] = set()
    if cfg.search.skip_settled:
        reach_poses = {
            oid: [prev_pose[oid]]
            if oid in ctx.static
            else [*ctx.cand_poses[oid], *([prev_pose[oid]] if oid in prev_pose else [])]
            for oid in ids
        }
        settled = settled_objects(ctx.static, reach_poses, models, cfg.search.reach)
    for oid in sorted(ctx.groups):
        i = world.index(oid)
        if oid in settled:
            ctx.first[oid] = prev_pose[oid]
            continue

        def unsimulated(T: np.ndarray, i: int = i) -> float:
            return scorer.unsimulated(i, T)

        ctx.first[oid] = best_first_guess(ctx.groups[oid], prev_pose.get(oid), unsimulated)
    world.set_poses({oid: ctx.first[oid] if oid in ctx.first else prev_pose[oid] for oid in ids})
    base = world.save_state()
    try:
        sim.simulator.settle(cfg.search.initial_settle, with_forces=True)
    except PhysicsError as exc:
        log.warning("first-guess settle failed (%s); using the unsettled guess", exc)
        world.restore_state(base)
    # an object the first-guess settle moved is not where it was any more (what held it is
    # gone or moved): it is searched after all
    settled -= settle_moved(
        {oid: (prev_pose[oid], world.get_pose(oid), models[oid]) for oid in settled}
    )
    ctx.settled = settled
    ctx.first_score = scorer.evaluate(world, ctx.timer)
