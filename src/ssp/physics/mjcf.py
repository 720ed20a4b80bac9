"""Build the MuJoCo model of a scene (``mujoco.MjSpec``, compiled in memory).

The model is built with ``MjSpec`` rather than an MJCF string, so every float (vertices, mass,
inertia, solver settings) reaches MuJoCo without a text round trip. Layout of the compiled model,
which :class:`ssp.physics.world.World` relies on:

- body 0 is the world; body ``i + 1`` is object ``i`` (instance order), a free body whose frame
  is the object's model frame, so ``qpos[7 i: 7 i + 7]`` is its pose ``(x, y, z, qw, qx, qy, qz)``
  and ``qvel[6 i: 6 i + 6]`` its velocity (linear of the body origin in the world frame, angular in
  the body frame);
- the table (when present) is an infinite plane geom of the world body at z = 0;
- every convex part of an object's model is one mesh geom (MuJoCo collides with its convex hull);
  one mesh asset per (model class, part) is shared by all instances of that class;
- the inertial is explicit: the model's mass, centre of mass and full inertia tensor (from the
  watertight mesh), never MuJoCo's hull-derived inertia;
- the arena (MuJoCo's contact and constraint memory) is sized from the scene
  (:func:`arena_bytes`), so models of many convex parts do not overflow it.
"""

from __future__ import annotations

import copy
from collections import OrderedDict
from collections.abc import Sequence

import mujoco
import numpy as np

from ssp.config import PhysicsConfig
from ssp.errors import PhysicsError
from ssp.library.model import ObjectInstance, ObjectModel

#: Contact dimensionality of every geom. 3 = normal + 2D sliding friction, as measured in
#: notes/engines.md; with 3 the torsional and rolling coefficients are stored but inert
#: (MuJoCo uses them only for condim 4 and 6).
CONDIM = 3

_INTEGRATORS = {
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}
_CONES = {
    "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC,
    "pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL,
}


def contact_margin(config: PhysicsConfig) -> float:
    """Contact margin of every geom pair, m: ``config.contact_margin`` or ``0.08 g dt^2``.

    Stiff contacts still rest at a small penetration that grows with the load and with dt^2. At
    dt = 5 ms (measured, 92 g cubes): 0.0025 mm for one cube on the table, 0.005-0.045 mm per
    interface of a 10-cube tower (0.25 mm of total sink). Without a margin, touching objects only
    get a contact once they interpenetrate, so a stack placed in exact contact falls one contact
    per step (the top of a 10-cube tower dips 13 mm before it settles). With the default margin
    the contacts engage 0.02 mm before the surfaces touch: no such transient, and resting objects
    stay within about 0.02-0.08 mm (single object to 10-cube tower) of their geometric contact.
    Contacts then report a negative depth (a gap) up to the margin.
    """
    if config.contact_margin is not None:
        return float(config.contact_margin)
    return 0.08 * float(config.gravity) * float(config.timestep) ** 2


#: MuJoCo's own arena size when none is given (``<size memory>`` unset), bytes.
DEFAULT_ARENA_BYTES = 13_631_488
#: Arena bytes per contact: the contact itself, its 3 constraint rows (condim 3) and the
#: solver's per-row arrays, plus a per-dof share for the Jacobian rows (measured with MuJoCo
#: 4.0.1: 1.7-2.8 kB per contact for 1-4 free bodies; the formula stays above that).
ARENA_BYTES_PER_CONTACT = 2000
ARENA_BYTES_PER_CONTACT_DOF = 96
#: Contacts budgeted per convex part (its contacts with the table and its neighbours).
CONTACTS_PER_PART = 4
#: Largest arena ssp asks for, bytes; beyond it an overflow raises PhysicsError instead.
MAX_ARENA_BYTES = 1 << 30


def arena_bytes(part_counts: Sequence[int]) -> int:
    """Arena size (bytes) for objects with ``part_counts`` convex parts each (one per object).

    Budget: :data:`CONTACTS_PER_PART` contacts per part, plus one contact for every pair of
    parts of the two objects with the most parts (one of them pushed fully into the other, as
    a bad hypothesis can be). Never below MuJoCo's default, never above
    :data:`MAX_ARENA_BYTES`. The arena is allocated once per world.
    """
    counts = sorted((int(c) for c in part_counts), reverse=True)
    if not counts:
        return DEFAULT_ARENA_BYTES
    nv = 6 * len(counts)
    worst_pair = counts[0] * (counts[1] if len(counts) > 1 else 1)
    contacts = CONTACTS_PER_PART * (sum(counts) + 1) + worst_pair
    # Jacobian rows are sparse beyond 60 dofs (MuJoCo's automatic choice)
    per_contact = ARENA_BYTES_PER_CONTACT + ARENA_BYTES_PER_CONTACT_DOF * min(nv, 60)
    return int(min(MAX_ARENA_BYTES, max(DEFAULT_ARENA_BYTES, contacts * per_contact)))


def _check_model(model: ObjectModel, oid: str) -> None:
    """Reject mass properties MuJoCo would refuse (or silently clamp), naming the object."""
    mass = float(model.mass)
    com = np.asarray(model.center_of_mass, dtype=float)
    inertia = np.asarray(model.inertia, dtype=float)
    problems = []
    if not (np.isfinite(mass) and mass > 0):
        problems.append(f"mass {mass!r} must be finite and > 0")
    if com.shape != (3,) or not np.all(np.isfinite(com)):
        problems.append("center_of_mass must be 3 finite numbers")
    if inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)):
        problems.append("inertia must be a finite 3x3 matrix")
    elif (
        not np.allclose(inertia, inertia.T, rtol=1e-6, atol=1e-15)
        or np.linalg.eigvalsh(0.5 * (inertia + inertia.T))[0] <= 0
    ):
        problems.append("inertia must be symmetric positive definite")
    if not model.convex_parts:
        problems.append("it has no convex parts (nothing to collide with)")
    if not (np.isfinite(model.friction) and model.friction >= 0):
        problems.append(f"friction {model.friction!r} must be finite and >= 0")
    if problems:
        raise PhysicsError(
            f"object {oid!r} (model {model.name!r}) cannot be simulated: " + "; ".join(problems)
        )


def _new_spec(instances: Sequence[ObjectInstance], config: PhysicsConfig) -> mujoco.MjSpec:
    """An empty ``MjSpec`` with ssp's compiler settings, ``config``'s solver options and an
    arena sized for ``instances``."""
    spec = mujoco.MjSpec()
    spec.modelname = "ssp_world"
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    spec.compiler.alignfree = False  # body frame stays the model frame
    spec.compiler.balanceinertia = False
    memory = arena_bytes([len(inst.model.convex_parts) for inst in instances])
    if memory > DEFAULT_ARENA_BYTES:
        spec.memory = memory

    opt = spec.option
    opt.timestep = float(config.timestep)
    opt.gravity = [0.0, 0.0, -float(config.gravity)]
    opt.integrator = _INTEGRATORS[config.integrator]
    opt.cone = _CONES[config.cone]
    opt.iterations = int(config.solver_iterations)
    opt.tolerance = float(config.solver_tolerance)
    opt.noslip_iterations = int(config.noslip_iterations)
    return spec


def _add_meshes(spec: mujoco.MjSpec, model: ObjectModel, k: int) -> list[str]:
    """Add the convex parts of ``model`` (the ``k``-th distinct model) to ``spec`` as mesh
    assets; returns their names."""
    names = []
    for j, part in enumerate(model.convex_parts):
        verts = np.asarray(part.vertices, dtype=float)
        if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) < 4:
            raise PhysicsError(f"model {model.name!r}: convex part {j} needs at least 4 vertices")
        if not np.all(np.isfinite(verts)):
            raise PhysicsError(f"model {model.name!r}: convex part {j} has NaN vertices")
        name = f"model{k}_part{j}"
        spec.add_mesh(
            name=name,
            uservert=verts.ravel().tolist(),
            inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX,
        )
        names.append(name)
    return names


def _add_body(
    spec: mujoco.MjSpec,
    i: int,
    model: ObjectModel,
    mesh_names: list[str],
    spin: list[float],
    contact: dict,
) -> None:
    """Add object ``i``: a free body with ``model``'s mass properties and one geom per mesh
    of ``mesh_names`` (friction ``model.friction`` then ``spin``, ``contact`` settings)."""
    body = spec.worldbody.add_body(name=f"obj{i}")
    body.add_freejoint(name=f"obj{i}_free")
    inertia = np.asarray(model.inertia, dtype=float)
    body.explicitinertial = True
    body.mass = float(model.mass)
    body.ipos = [float(x) for x in model.center_of_mass]
    body.fullinertia = [
        inertia[0, 0],
        inertia[1, 1],
        inertia[2, 2],
        inertia[0, 1],
        inertia[0, 2],
        inertia[1, 2],
    ]
    for j, name in enumerate(mesh_names):
        body.add_geom(
            name=f"obj{i}_part{j}",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=name,
            friction=[float(model.friction), *spin],
            **contact,
        )


#: Compiled scenes kept by :func:`compiled_mjmodel` (most recently used last).
COMPILED_KEPT = 8
_compiled: OrderedDict[tuple, tuple[tuple[ObjectModel, ...], mujoco.MjModel]] = OrderedDict()


def compiled_mjmodel(
    instances: Sequence[ObjectInstance], *, table: bool, config: PhysicsConfig
) -> mujoco.MjModel:
    """:func:`build_mjmodel`, from a copy of an earlier compile of the same scene when there is
    one: the same models in the same order (by identity: which instances share a model is part
    of the scene), table and settings give the same ``MjModel``, whatever the instances' ids.
    A parser whose objects change only in their ids (a new candidate in place of the last
    frame's) then skips MuJoCo's compile, the slowest part of a new world; the copy is the
    caller's to change. The last :data:`COMPILED_KEPT` scenes are kept (with their models, so
    that an id is never reused for another model while its entry lives)."""
    models = tuple(inst.model for inst in instances)
    key = (tuple(id(m) for m in models), bool(table), config.model_dump_json())
    hit = _compiled.get(key)
    if hit is None:
        hit = (models, build_mjmodel(instances, table=table, config=config))
        _compiled[key] = hit
        while len(_compiled) > COMPILED_KEPT:
            _compiled.popitem(last=False)
    else:
        _compiled.move_to_end(key)
    return copy.copy(hit[1])


def build_mjmodel(
    instances: Sequence[ObjectInstance], *, table: bool, config: PhysicsConfig
) -> mujoco.MjModel:
    """Compile the scene of ``instances`` (in order) into a new ``MjModel``.

    Raises :class:`PhysicsError` when a model's mass properties or convex parts are unusable
    (for example a degenerate, flat convex part that MuJoCo cannot compile).
    """
    spec = _new_spec(instances, config)
    spin = [float(config.torsional_friction), float(config.rolling_friction)]
    # MuJoCo 4 adds the margins of the two geoms of a pair: give each geom half.
    half_margin = 0.5 * contact_margin(config)

    # contact settings shared by every geom (table and object parts)
    contact = dict(
        solref=[float(x) for x in config.solref],
        solimp=[float(x) for x in config.solimp],
        condim=CONDIM,
        margin=half_margin,
        contype=1,
        conaffinity=1,
    )
    if table:
        spec.worldbody.add_geom(
            name="table",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[0.0, 0.0, 1.0],  # zero half-sizes: infinite plane
            friction=[float(config.table_friction), *spin],
            **contact,
        )

    mesh_names: dict[int, list[str]] = {}  # id(model) -> mesh asset names of its parts
    for i, inst in enumerate(instances):
        model = inst.model
        _check_model(model, inst.id)
        if id(model) not in mesh_names:
            mesh_names[id(model)] = _add_meshes(spec, model, len(mesh_names))
        _add_body(spec, i, model, mesh_names[id(model)], spin, contact)

    try:
        return spec.compile()
    except Exception as exc:  # MuJoCo raises ValueError with the compiler message
        raise PhysicsError(f"MuJoCo could not compile the scene: {exc}") from exc
