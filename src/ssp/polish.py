"""The final polish (stage 7 of :class:`ssp.parser.SceneParser`, ``forces.final_icp``).

ICP alone is precise but knows no physics (it floats and interpenetrates objects); the data
forces alone are physical but converge slowly. A spring toward each object's ICP pose inside
the simulation gets both: every enabled object with data is pulled toward its point-to-plane
ICP pose on its segment for ``search.final_settle`` s, then the scene settles for
``search.settle_without_forces`` s without forces.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import PhysicsError
from ssp.physics import World
from ssp.probability import pose_change
from ssp.registration import icp_refine
from ssp.search import Simulator
from ssp.timing import StageTimer

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "ICP_ITERATIONS",
    "ICP_TOLERANCE",
    "MAX_JUMP_DEG",
    "MAX_JUMP_M",
    "polish",
    "polish_scene",
]

log = logging.getLogger(__name__)

#: ICP results that move an object more than this (m, deg at its centre of mass) are a wrong
#: local minimum and are ignored.
MAX_JUMP_M = 0.02
MAX_JUMP_DEG = 20.0

#: Segments with fewer points are not registered.
MIN_POINTS = 30

#: ICP steps at most, and the step (m and rad) below which it stops: the spring target need not
#: be finer than 10 um. At most 8 steps left a carton of a real capture (``examples/real_dev.py``,
#: the milk scene) where it would fall.
ICP_ITERATIONS = 20
ICP_TOLERANCE = 1e-5


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
        for oid, seg in segments.items():
            if not world.is_enabled(oid) or len(seg) < MIN_POINTS:
                continue
            model = world.model_of(oid)
            T = world.get_pose(oid)
            T_icp = icp_refine(
                model,
                T,
                seg,
                camera_position,
                max_distance=config.forces.icp_max_distance,
                iterations=ICP_ITERATIONS,
                tolerance=ICP_TOLERANCE,
            )
            dt, dth = pose_change(T, T_icp, None, model.center_of_mass)
            if dt < MAX_JUMP_M and dth < math.radians(MAX_JUMP_DEG):
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
