"""The final polish (stage 7 of :class:`ssp.parser.SceneParser`, ``forces.final_icp``).

ICP alone is precise but knows no physics (it floats and interpenetrates objects); the data
forces alone are physical but converge slowly. A spring toward each object's ICP pose inside
the simulation gets both: every enabled object with data is pulled toward its point-to-plane
ICP pose on its segment for ``search.final_settle`` s, then the scene settles for
``search.settle_without_forces`` s without forces. The ICP and its bounds (a jump of 2 cm or
20 deg is a wrong minimum) are :func:`ssp.registration.bounded_refit`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import PhysicsError
from ssp.physics import World
from ssp.registration import bounded_refit
from ssp.search import Simulator
from ssp.threads import thread_map
from ssp.timing import StageTimer

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = ["polish", "polish_scene"]

log = logging.getLogger(__name__)


def polish(
    world: World,
    sim: Simulator,
    segments: Mapping[str, np.ndarray],
    camera_position: np.ndarray | None,
    config: SSPConfig,
    timer: StageTimer,
) -> None:
    """Pull every enabled object with a segment ``(K, 3)`` (world, m) toward its ICP pose and
    settle (module docstring). ``camera_position``: (3,) world, m, or None (every model
    sample may match). A settle that fails leaves the scene as it was, with a warning."""
    forces = sim.forces
    with timer("icp"):
        # the world is read here; the threads get only arrays and models to align
        todo = [(oid, world.model_of(oid), world.get_pose(oid), seg)
                for oid, seg in segments.items() if world.is_enabled(oid)]  # fmt: skip
        refits = thread_map(
            lambda job: bounded_refit(*job[1:], camera_position, config), todo, name="ssp-icp"
        )
        for (oid, *_), T_icp in zip(todo, refits, strict=True):
            if T_icp is not None:
                forces.set_pose_target(world.index(oid), T_icp)
    forces.reset()
    state = world.save_state()
    try:
        sim.settle(config.search.final_settle, with_forces=True)
        sim.settle(config.search.settle_without_forces, with_forces=False)
    except PhysicsError as exc:  # pragma: no cover - a settled scene pulled a little
        log.warning("final ICP settle failed (%s); keeping the searched scene", exc)
        world.restore_state(state)
    for k in range(len(world.ids)):
        forces.set_pose_target(k, None)


def polish_scene(ctx: FrameContext) -> None:
    """Stage *polish*: :func:`polish` of the objects with data (``forces.final_icp``), then the
    scene scored again (also after the unchanged shortcut, whose settle left no score).

    Updates ``score``.
    """
    cfg, sim = ctx.config, ctx.sim
    if cfg.forces.final_icp:
        segments = {oid: ctx.segments[oid] for oid in sim.with_data}
        polish(sim.world, sim.simulator, segments, sim.camera_position, cfg, ctx.timer)
    if ctx.unchanged or cfg.forces.final_icp:
        ctx.score = sim.scorer.evaluate(sim.world, ctx.timer)
