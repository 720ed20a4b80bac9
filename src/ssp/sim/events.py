"""Dynamic events between the static scenes of a synthetic sequence.

What a robot's camera sees on a real table: an object picked and put down elsewhere, an object
pushed, a stack knocked over, an object put on top of another. Each event acts on a MuJoCo world
(:class:`ssp.physics.World`, table at z = 0) holding every object of the scene (distractors
included) at rest, simulates plain dynamics until everything is at rest again, and checks the
outcome (else the world is restored and the event retried, up to :data:`ATTEMPTS` times):

``move``
    An object that carries nothing is lifted and put down at a random free spot of ``region``
    (a random resting pose and yaw, its footprint ``clearance`` from every other), in view.
    The others must stay put (:data:`STILL_SHIFT`, :data:`STILL_TILT_DEG`).
``push``
    An object that carries nothing slides 3-8 cm and turns 10-40 degrees about the vertical;
    same checks.
``knock``
    The highest object that rests on another one is pushed sideways (an impulse that gives it
    0.6-1.2 m/s); whatever falls, falls. At least one object must end more than 2 cm from
    where it was, and all stay in view and on the table.
``stack``
    An object that carries nothing is put on the top face of another that carries nothing and
    stands level (tilt below 5 degrees), centred and with the lower one's yaw; it must come to
    rest there (within 3 mm of the planned height) and the others stay put.

Randomness: all from the ``rng`` passed in.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ssp.camera import Camera
from ssp.geometry import yaw_pose
from ssp.physics.world import World
from ssp.probability import pose_change
from ssp.sim.placement import footprint, hull_world, in_view, poly_distance, random_resting
from ssp.support import build_support_graph

__all__ = ["ATTEMPTS", "EVENT_KINDS", "Event", "run_event"]

EVENT_KINDS = ("move", "push", "knock", "stack")
#: Tries per event before it is given up.
ATTEMPTS = 25
#: Objects not acted on must not move more than this (m, deg).
STILL_SHIFT = 0.002
STILL_TILT_DEG = 3.0


@dataclass(frozen=True)
class Event:
    """An event that happened: its ``kind``, the object acted on, and those that moved."""

    kind: str
    target: str
    moved: tuple[str, ...]


def _children(world: World) -> dict[str, list[str]]:
    """Object id -> the objects it holds up (contact forces of the world at rest)."""
    g = build_support_graph(world.contacts(), world.masses, float(world.config.gravity))
    ids = world.ids
    return {ids[i]: [ids[c] for c in g.children(i)] for i in range(len(ids))}


def _free(world: World, movable: Sequence[str]) -> list[str]:
    """The objects of ``movable`` that hold nothing up."""
    kids = _children(world)
    return [oid for oid in movable if not kids.get(oid)]


def _settled(world: World) -> bool:
    return world.settle(min_s=0.2, max_s=3.0) is not None


def _still(world: World, before: Mapping[str, np.ndarray], exclude: set[str]) -> bool:
    for oid, T in before.items():
        if oid in exclude:
            continue
        dt, dr = pose_change(T, world.get_pose(oid))
        if dt > STILL_SHIFT or math.degrees(dr) > STILL_TILT_DEG:
            return False
    return True


def _in_view_all(world: World, T_wc, camera: Camera) -> bool:
    return all(in_view(world.model_of(o), world.get_pose(o), T_wc, camera) for o in world.ids)


def _clear_spot(world, oid, T, clearance) -> bool:
    poly = footprint(world.model_of(oid), T)
    return all(
        poly_distance(poly, footprint(world.model_of(o), world.get_pose(o))) >= clearance
        for o in world.ids
        if o != oid
    )


def _move(world, oid, rng, region, clearance, T_wc, camera) -> np.ndarray | None:
    model = world.model_of(oid)
    for _ in range(200):
        T = random_resting(model, rng, region)
        T[2, 3] += 0.002
        if in_view(model, T, T_wc, camera) and _clear_spot(world, oid, T, clearance):
            return T
    return None


def _push(world, oid, rng, clearance, T_wc, camera) -> np.ndarray | None:
    model = world.model_of(oid)
    T0 = world.get_pose(oid)
    c = T0[:3, :3] @ np.asarray(model.center_of_mass) + T0[:3, 3]
    for _ in range(50):
        a = rng.uniform(-math.pi, math.pi)
        d = rng.uniform(0.03, 0.08)
        turn = math.radians(rng.uniform(10.0, 40.0)) * rng.choice([-1.0, 1.0])
        T = yaw_pose(turn, c) @ yaw_pose(0.0, -c) @ T0  # turned about the centre
        T[0, 3] += d * math.cos(a)
        T[1, 3] += d * math.sin(a)
        T[2, 3] += 0.001
        if in_view(model, T, T_wc, camera) and _clear_spot(world, oid, T, clearance):
            return T
    return None


def _stack_pose(world, oid, base) -> np.ndarray | None:
    """``oid`` centred on the top face of ``base``, with ``base``'s yaw, 1 mm above it."""
    Tb = world.get_pose(base)
    mb = world.model_of(base)
    up = Tb[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    if math.degrees(math.acos(min(1.0, float(np.abs(up).max())))) > 5.0:
        return None  # not standing level on a face
    To = world.get_pose(oid)
    mo = world.model_of(oid)
    yaw_b = math.atan2(Tb[1, 0], Tb[0, 0])
    yaw_o = math.atan2(To[1, 0], To[0, 0])
    T = yaw_pose(yaw_b - yaw_o) @ To
    top = float(hull_world(mb, Tb)[:, 2].max())
    low = float(hull_world(mo, T)[:, 2].min())
    cb = Tb[:3, :3] @ np.asarray(mb.center_of_mass) + Tb[:3, 3]
    co = T[:3, :3] @ np.asarray(mo.center_of_mass) + T[:3, 3]
    T[0, 3] += cb[0] - co[0]
    T[1, 3] += cb[1] - co[1]
    T[2, 3] += top - low + 0.001
    return T


def run_event(
    kind: str,
    world: World,
    movable: Sequence[str],
    rng: np.random.Generator,
    *,
    T_wc: np.ndarray,
    camera: Camera,
    region,
    clearance: float = 0.015,
    prefer: Sequence[str] = (),
) -> Event | None:
    """Carry out one event of ``kind`` (module docstring) on ``world`` (at rest), acting on
    objects of ``movable`` only (``prefer``: try these first, e.g. the object moved last);
    the event, or None (the world restored) when no attempt passed its checks."""
    if kind not in EVENT_KINDS:
        raise ValueError(f"unknown event {kind!r}; known: {', '.join(EVENT_KINDS)}")
    start = world.save_state()
    before = world.poses()
    for _ in range(ATTEMPTS):
        world.restore_state(start)
        free = _free(world, movable)
        if kind in ("move", "push", "stack"):
            pool = [o for o in prefer if o in free] or free
            if not pool:
                return None
            oid = pool[int(rng.integers(len(pool)))] if not prefer else pool[0]
            if kind == "move":
                T = _move(world, oid, rng, region, clearance, T_wc, camera)
            elif kind == "push":
                T = _push(world, oid, rng, clearance, T_wc, camera)
            else:
                bases = [o for o in free if o != oid]
                if not bases:
                    return None
                T = _stack_pose(world, oid, bases[int(rng.integers(len(bases)))])
            if T is None:
                continue
            world.set_pose(oid, T)
            if not _settled(world) or not _still(world, before, {oid}):
                continue
            if not _in_view_all(world, T_wc, camera):
                continue
            if kind == "stack" and abs(world.get_pose(oid)[2, 3] - T[2, 3]) > 0.003:
                continue
            return Event(kind, oid, (oid,))
        # knock: the highest object resting on another, pushed sideways
        kids = _children(world)
        on_top = {c for cs in kids.values() for c in cs}
        cands = [o for o in movable if o in on_top]
        if not cands:
            return None
        oid = max(cands, key=lambda o: (world.get_pose(o)[2, 3], o))
        a = rng.uniform(-math.pi, math.pi)
        speed = rng.uniform(0.6, 1.2)
        m = float(world.masses[world.index(oid)])
        dur = 0.03
        f = m * speed / dur
        n = max(1, round(dur / world.timestep))
        world.apply_wrench(oid, [f * math.cos(a), f * math.sin(a), 0.0], [0.0, 0.0, 0.0])
        world.step(n, quasi_static=False)
        world.clear_wrenches()
        if not _settled(world) or not _in_view_all(world, T_wc, camera):
            continue
        moved = tuple(
            o
            for o in world.ids
            if np.linalg.norm(world.get_pose(o)[:3, 3] - before[o][:3, 3]) > 0.02
        )
        if not moved or any(world.get_pose(o)[2, 3] < -0.005 for o in world.ids):
            continue
        return Event(kind, oid, moved)
    world.restore_state(start)
    return None
