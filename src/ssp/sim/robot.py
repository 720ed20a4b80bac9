"""An idealised pick-and-place robot that acts on perceived poses (the tower case study).

The robot only knows the poses perception gives it; the world (:class:`ssp.physics.World`)
holds the true ones. So a perception error becomes a placement error, and physics decides
what happens next.

* **Grasp** (:func:`gripper_pose`, :func:`grasp`). A grasp from the top of the perceived
  object, planned in the perceived object's frame, as a robot that grasps relative to the
  detected object does. The gripper frame ``G`` is the perceived pose, taken as the symmetric
  equivalent whose z axis points most upward (:func:`upright`), moved to the centre of the
  model's bounding box. The jaws close on the real object nearest that centre, if it is
  within ``tolerance``; otherwise the grasp misses. The object is then held rigidly at its
  *true* pose relative to the gripper, ``T_grip_obj = inv(T_world_grip) @ T_world_obj``. The
  whole difference between the perceived and the true pose (translation and rotation) becomes
  the object's offset in the hand. The jaws do not centre or square the object.
* **Place** (:func:`place`). The robot moves the gripper so that the held object's *perceived*
  pose lands on a target pose (for a tower: the perceived top, one cube higher along its
  perceived up axis). The true object follows rigidly. The gripper comes down vertically from
  ``approach`` m above and stops at the first contact (a guarded move: a robot with a force
  stop does not push a block into the tower) or at the target, whichever comes first.
* **Release** (:func:`release`). The object is let go at rest, and the whole world is
  simulated dynamically until everything is at rest again.

Nothing here models the arm's own collisions, grasp slip or the jaws' compliance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ssp.library.model import ObjectModel
from ssp.physics.world import World

__all__ = [
    "Grasp",
    "grasp",
    "gripper_pose",
    "place",
    "release",
    "tilt_deg",
    "upright",
    "upright_yaw",
]

#: Penetration (m) that counts as touching in the guarded move.
CONTACT_DEPTH = 1e-4
#: Resolution of the guarded move, m.
DESCENT_RESOLUTION = 1e-4


@dataclass(frozen=True)
class Grasp:
    """An object in the gripper.

    Attributes:
        oid: the world id of the object actually held.
        T_world_grip: (4, 4) gripper pose at the grasp, m.
        T_grip_obj: (4, 4) the object's true pose in the gripper frame (rigid while held).
        T_grip_perceived: (4, 4) where the robot believes the object is in the gripper frame.
    """

    oid: str
    T_world_grip: np.ndarray
    T_grip_obj: np.ndarray
    T_grip_perceived: np.ndarray


def upright(model: ObjectModel, T_world_obj: np.ndarray) -> np.ndarray:
    """The symmetric equivalent ``T @ S`` (4, 4) of ``T_world_obj`` whose model z axis points
    most upward (the same physical pose; only its parametrisation changes)."""
    T = np.asarray(T_world_obj, dtype=float)
    S = model.symmetry.discrete
    z_up = S[:, :3, 2] @ T[2, :3]  # world z of each equivalent's z axis
    return T @ S[int(np.argmax(z_up))]


def upright_yaw(model: ObjectModel, T_world_obj: np.ndarray) -> float:
    """Yaw (rad) about the world z axis of the object's model x axis, taken on the symmetric
    equivalent of ``T_world_obj`` whose z axis is most upward."""
    R = upright(model, T_world_obj)[:3, :3]
    return math.atan2(R[1, 0], R[0, 0])


def tilt_deg(model: ObjectModel, T_world_obj: np.ndarray) -> float:
    """Angle (deg) between the world z axis and the most upward model axis allowed by the
    model's discrete symmetries (0 for a cube resting on any face)."""
    R = upright(model, T_world_obj)[:3, :3]
    return math.degrees(math.acos(float(np.clip(R[2, 2], -1.0, 1.0))))


def _centred(model: ObjectModel, T_world_obj: np.ndarray) -> np.ndarray:
    """The frame ``T_world_obj`` moved to the centre of the model's bounding box."""
    T = np.array(T_world_obj, dtype=float)
    T[:3, 3] = T[:3, :3] @ model.mesh.bounds.mean(axis=0) + T[:3, 3]
    return T


def gripper_pose(model: ObjectModel, T_world_perceived: np.ndarray) -> np.ndarray:
    """Gripper pose (4, 4) for a grasp from the top of an object perceived at
    ``T_world_perceived``: its upright equivalent (:func:`upright`) at the bounding-box
    centre."""
    return _centred(model, upright(model, T_world_perceived))


def grasp(
    world: World,
    model: ObjectModel,
    T_world_perceived: np.ndarray,
    *,
    candidates: tuple[str, ...] | None = None,
    tolerance: float = 0.02,
) -> Grasp | None:
    """Close the gripper on an object perceived at ``T_world_perceived``.

    Args:
        world: the true world.
        model: the model of the perceived object (all candidates share it).
        T_world_perceived: (4, 4) the perceived pose the grasp is planned on, m.
        candidates: world ids that can be grasped (default: all).
        tolerance: largest distance (m) between the gripper centre and the centre of the
            object that ends up in the gripper.

    Returns:
        The :class:`Grasp`, or None when no candidate's centre is within ``tolerance``.
    """
    T_wg = gripper_pose(model, T_world_perceived)
    ids = world.ids if candidates is None else tuple(candidates)
    best, best_d = None, float(tolerance)
    for oid in ids:
        c = _centred(world.model_of(oid), world.get_pose(oid))[:3, 3]
        d = float(np.linalg.norm(c - T_wg[:3, 3]))
        if d <= best_d:
            best, best_d = oid, d
    if best is None:
        return None
    T_gw = np.linalg.inv(T_wg)
    return Grasp(
        oid=best,
        T_world_grip=T_wg,
        T_grip_obj=T_gw @ world.get_pose(best),
        T_grip_perceived=T_gw @ np.asarray(T_world_perceived, dtype=float),
    )


def _touches(world: World, k: int) -> bool:
    c = world.contacts()
    mine = (c.obj_a == k) | (c.obj_b == k)
    return bool((c.depth[mine] > CONTACT_DEPTH).any())


def place(
    world: World,
    held: Grasp,
    T_world_target: np.ndarray,
    *,
    approach: float = 0.05,
) -> float:
    """Bring the held object down so that its *perceived* pose reaches ``T_world_target``.

    The gripper goes to the pose that puts the perceived object at the target,
    ``T_world_grip = gripper_pose(T_world_target) @ inv(gripper_pose(T_grip_perceived))``, and
    the true object follows rigidly (``T_world_grip @ T_grip_obj``). The descent is vertical,
    from ``approach`` m above; it stops at the first contact (penetration over
    :data:`CONTACT_DEPTH` with anything, table included), to :data:`DESCENT_RESOLUTION`.

    Returns:
        Height (m, >= 0) above the target at which the descent stopped.
    """
    model = world.model_of(held.oid)
    k = world.index(held.oid)
    T_wg = gripper_pose(model, T_world_target) @ np.linalg.inv(
        gripper_pose(model, held.T_grip_perceived)
    )
    T_obj = T_wg @ held.T_grip_obj

    def at(dz: float) -> bool:
        T = T_obj.copy()
        T[2, 3] += dz
        world.set_pose(held.oid, T)
        return _touches(world, k)

    # coarse sweep down from the approach height, then bisect the first contact
    step = 0.002
    free = float(approach)
    if at(free):  # something is already in the way up there; stay there
        return free
    dz = free
    while dz > 0.0:
        nxt = max(dz - step, 0.0)
        if at(nxt):
            lo, hi = nxt, dz  # lo touches, hi is free
            while hi - lo > DESCENT_RESOLUTION:
                mid = 0.5 * (lo + hi)
                if at(mid):
                    lo = mid
                else:
                    hi = mid
            at(hi)
            return hi
        dz = nxt
    return 0.0


def release(world: World, *, max_s: float = 3.0) -> float | None:
    """Let go and simulate dynamics until the world is at rest; the time taken (s), or None
    if it is still moving after ``max_s``."""
    return world.settle(min_s=0.3, max_s=max_s)
