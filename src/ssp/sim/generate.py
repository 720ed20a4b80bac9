"""Synthetic sequences of the paper's simulated experiments (Table I), built by physics.

Two experiments (paper, section "Simulated Data"; DESIGN section 5):

``"isolated"``
    Tool-like objects (every library class but the block-world ones ``cube``, ``block``,
    ``link``, ``node``) dropped at random, non-overlapping spots of the table, in a random
    stable resting orientation (trimesh stable poses, weighted by their probability) and a
    random yaw, ``objects_per_stage`` (3) more in each of ``stages`` (5) stages: up to 15
    objects. Classes cycle through random permutations, so every model appears before one
    repeats. Objects keep a clearance (their convex footprints on the table at least
    ``ISOLATED_CLEARANCE`` apart) and never touch (no object-object contact after settling).
``"structure"``
    Cubes and blocks (2x1x1 inch) built into a cluster of structures near the table centre:
    towers of cubes (optionally a block on top), bridges (a block across two cubes with a gap,
    optionally a cube on top), running-bond walls of blocks, pyramids of cubes and cribs of
    crossed block pairs, each with a random position and yaw and small placement jitter. All
    pieces are ordered bottom layer first and added in ``stages`` (5) nearly equal groups,
    9-13 objects in all, so lower objects become occluded as the structure grows (the
    reference's struct_1 had 2, 4, 7, 9, 11 objects).

Ground truth is physically consistent: new objects are placed (a little above their resting
height), then the whole scene is simulated dynamically with MuJoCo
(:class:`ssp.physics.World`, ``quasi_static=False``) until every object is at rest (0.2-2 s);
the settled poses are the ground truth, and objects already placed stay where physics left
them. A stage whose settling fails a check is resampled: isolated objects must not touch or
leave the view; in a structure no object may move more than ``STRUCTURE_MAX_SHIFT`` (2 mm) or
3 degrees while settling (otherwise the layout is redrawn).

The camera is static: ``CAMERA_DISTANCE`` (1 m) from the workspace centre, looking down at
``CAMERA_ELEVATION_DEG`` (45 degrees) from the -y side (:func:`default_camera_pose`), with the
Kinect-like intrinsics of :meth:`Camera.default`. Every object is inside its view (all its
hull vertices project at least :data:`ssp.sim.placement.VIEW_MARGIN_PX` pixels inside the
full-resolution image). A moving camera (``camera_path``, :mod:`ssp.sim.camera_path`) starts
there and ray casts every frame from its own pose; objects may then leave its view (their
``visib_fract`` says so), as they do for a user walking around a table.

Each stage is shown for ``frames_per_stage`` frames (the paper: the parser ran 4-5 times on
each static scene), all with the same ground truth. Per stage the clean scene is ray cast once
(:func:`ssp.sim.render.render`) and each object once alone (in its image bounding box only),
which gives the BOP ``visib_fract`` (visible pixels in the scene / pixels of the object
alone, the table present in both). Per frame, fresh Kinect-like depth noise
(:func:`ssp.sim.render.add_depth_noise`: axial noise growing with distance squared, disparity
quantisation :data:`~ssp.sim.render.KINECT_QUANTUM`, missing pixels at edges) and fresh hypotheses
(:func:`ssp.sim.hypotheses.draw_hypotheses`) are drawn.

Randomness: the layout comes from ``default_rng([seed, 0, experiment code])`` and frame ``i``
from ``default_rng([seed, 1, i])`` (depth noise, then hypotheses), so a seed gives identical
arrays, and a frame's noise does not depend on how often the layout was resampled. Seeds 0-99
are for development and calibration; 1000+ are reserved for reporting.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ssp.config import PhysicsConfig
from ssp.errors import ArgumentError
from ssp.geometry import yaw_pose
from ssp.library.builtin import BLOCK_NAMES
from ssp.library.model import ObjectInstance, ObjectModel
from ssp.physics.world import World
from ssp.probability import pose_change
from ssp.sim.camera_path import camera_path
from ssp.sim.distractors import distractor_models
from ssp.sim.events import run_event
from ssp.sim.hypotheses import (
    CHI3_MEAN,
    PAPER_INDUCED_NOISE,
    HypothesisNoise,
    draw_hypotheses,
    induced_errors,
)
from ssp.sim.masks import add_mask_defects
from ssp.sim.placement import (
    footprint,
    hull_world,
    in_view,
    poly_distance,
    random_resting,
)
from ssp.sim.realistic import RealisticNoise, RealisticStream, SceneRealism
from ssp.sim.render import (
    KINECT_QUANTUM,
    Camera,
    add_depth_noise,
    image_window,
    look_at,
    render,
)
from ssp.sim.sequence import SimFrame, SimSequence

__all__ = [
    "EXPERIMENTS",
    "calibrate_noise",
    "default_camera_pose",
    "generate_sequence",
    "generate_sequences",
    "observe_static_scene",
]

EXPERIMENTS = ("isolated", "structure")
_EXPERIMENT_CODE = {"isolated": 0, "structure": 1}
GENERATOR_VERSION = 1

#: Camera distance to the workspace centre, m, and elevation of the view, degrees.
CAMERA_DISTANCE = 1.0
CAMERA_ELEVATION_DEG = 45.0

#: Where isolated objects are dropped (x range, y range), m; the view check trims the corners.
ISOLATED_REGION = ((-0.45, 0.45), (-0.32, 0.55))
#: Minimum distance between the convex table footprints of two isolated objects when placed, m.
ISOLATED_CLEARANCE = 0.015
#: ... and after settling (they may roll a little), m.
ISOLATED_CLEARANCE_AFTER = 0.005
#: Height above the resting pose from which isolated objects are dropped, m.
ISOLATED_DROP = 0.002

#: Where structure components are placed (x range, y range of their origin), m.
STRUCTURE_REGION = ((-0.13, 0.13), (-0.10, 0.14))
#: Minimum distance between the footprints of two different structure components, m.
STRUCTURE_CLEARANCE = 0.012
#: Gap between side-by-side pieces of a component, m, and the lift of every placed piece.
STRUCTURE_GAP = 0.0015
STRUCTURE_LIFT = 0.0005
#: Placement jitter of structure pieces: uniform +-xy (m) and +-yaw (deg).
STRUCTURE_JITTER_XY = 0.0003
STRUCTURE_JITTER_YAW_DEG = 0.5
#: Largest motion of any object while a structure stage settles (else the layout is redrawn).
STRUCTURE_MAX_SHIFT = 0.002
STRUCTURE_MAX_TILT_DEG = 3.0
#: Default total object count of a structure sequence (inclusive range).
STRUCTURE_OBJECTS = (9, 13)

_MAX_STAGE_ATTEMPTS = 30
_MAX_LAYOUTS = 40


# ---------------------------------------------------------------------------------- camera
def default_camera_pose(
    distance: float = CAMERA_DISTANCE,
    elevation_deg: float = CAMERA_ELEVATION_DEG,
    target=(0.0, 0.0, 0.0),
) -> np.ndarray:
    """``T_world_cam`` of the static camera: ``distance`` m from ``target`` on the -y side,
    looking down at ``elevation_deg`` degrees (OpenCV axes, image up = away from the camera)."""
    e = np.radians(elevation_deg)
    target = np.asarray(target, dtype=float)
    eye = target + distance * np.array([0.0, -np.cos(e), np.sin(e)])
    return look_at(eye, target)


# ---------------------------------------------------------------------------------- layouts
@dataclass
class _Stage:
    poses: dict[str, np.ndarray]  # present objects, in order of addition
    added: tuple[str, ...]
    settle_s: float
    extras: dict[str, np.ndarray] = field(default_factory=dict)  # distractor id -> pose
    event: dict | None = None  # the event that led to this stage (realistic scenes)


@dataclass
class _Layout:
    classes: dict[str, str]  # instance id -> class, in order of addition
    stages: list[_Stage]
    resamples: int = 0
    notes: dict = field(default_factory=dict)
    skipped_events: list[dict] = field(default_factory=list)


# ---------------------------------------------------------------------------------- isolated
def _build_isolated(
    library: Mapping[str, ObjectModel],
    rng: np.random.Generator,
    *,
    stages: int,
    per_stage: int,
    classes: Sequence[str] | None,
    T_wc: np.ndarray,
    camera: Camera,
    config: PhysicsConfig,
) -> _Layout:
    # the built-in block-world models (no source file) are not tools; a user folder's
    # models are all used, whatever their names
    tools = (
        list(classes)
        if classes is not None
        else [n for n, m in library.items() if not (n in BLOCK_NAMES and m.source is None)]
    )
    if not tools:
        raise ValueError(
            "isolated experiment: the library has no tool-like classes (every class is a "
            f"built-in block-world model, {BLOCK_NAMES}); pass classes=... explicitly"
        )
    n_total = stages * per_stage
    order: list[str] = []
    while len(order) < n_total:
        order += [tools[i] for i in rng.permutation(len(tools))]
    order = order[:n_total]
    instances = [ObjectInstance(f"{cls}_{i}", library[cls]) for i, cls in enumerate(order)]
    world = World(instances, config=config)
    for inst in instances:
        world.set_enabled(inst.id, False)
    models = {inst.id: inst.model for inst in instances}

    present: list[str] = []
    out: list[_Stage] = []
    resamples = 0
    for s in range(stages):
        new = [inst.id for inst in instances[s * per_stage : (s + 1) * per_stage]]
        saved = world.save_state()
        for _attempt in range(_MAX_STAGE_ATTEMPTS):
            polys = [footprint(models[i], world.get_pose(i)) for i in present]
            placed = _place_isolated(new, models, polys, rng, T_wc, camera)
            if placed is None:
                resamples += 1
                continue
            world.set_poses(placed)
            for iid in new:
                world.set_enabled(iid, True)
            t = world.settle()
            if t is not None and _isolated_ok(world, present + new, models, T_wc, camera):
                break
            world.restore_state(saved)
            resamples += 1
        else:
            raise RuntimeError(
                f"isolated: could not place stage {s} ({len(present)} objects present, "
                f"{len(new)} to add) in {_MAX_STAGE_ATTEMPTS} attempts; use fewer objects"
            )
        present += new
        out.append(_Stage({i: world.get_pose(i) for i in present}, tuple(new), float(t)))
    return _Layout({inst.id: inst.model.name for inst in instances}, out, resamples)


def _place_isolated(new, models, polys, rng, T_wc, camera, tries: int = 400):
    placed: dict[str, np.ndarray] = {}
    polys = list(polys)
    for iid in new:
        model = models[iid]
        for _ in range(tries):
            T = random_resting(model, rng, ISOLATED_REGION)
            if not in_view(model, T, T_wc, camera):
                continue
            poly = footprint(model, T)
            if all(poly_distance(poly, q) >= ISOLATED_CLEARANCE for q in polys):
                break
        else:
            return None
        T[2, 3] += ISOLATED_DROP
        placed[iid] = T
        polys.append(poly)
    return placed


def _isolated_ok(world: World, ids, models, T_wc, camera) -> bool:
    c = world.contacts()
    if (c.obj_b >= 0).any():
        return False
    poses = {i: world.get_pose(i) for i in ids}
    if not all(in_view(models[i], T, T_wc, camera) for i, T in poses.items()):
        return False
    polys = [footprint(models[i], poses[i]) for i in ids]
    for a in range(len(polys)):
        for b in range(a + 1, len(polys)):
            if poly_distance(polys[a], polys[b]) < ISOLATED_CLEARANCE_AFTER:
                return False
    return True


# ---------------------------------------------------------------------------------- structure
# A piece of a component: (layer, class, x, y, z of the model origin, yaw), component frame.
_Piece = tuple[int, str, float, float, float, float]


def _component(kind: str, rng: np.random.Generator, cube: np.ndarray, block: np.ndarray):
    """Pieces of one structure component (bottom layer first); ``cube``/``block`` extents."""
    c = float(cube[2])
    L, W, H = (float(x) for x in block)
    gp = STRUCTURE_GAP
    p: list[_Piece] = []
    if kind == "tower":
        n = int(rng.integers(2, 4))
        for i in range(n):
            p.append((i, "cube", 0.0, 0.0, c / 2 + i * c, 0.0))
        if rng.random() < 0.5:
            p.append((n, "block", 0.0, 0.0, n * c + H / 2, float(rng.choice([0.0, np.pi / 2]))))
    elif kind == "bridge":
        g = float(rng.uniform(0.25, 0.6)) * L
        p += [(0, "cube", -(g + c) / 2, 0.0, c / 2, 0.0), (0, "cube", (g + c) / 2, 0.0, c / 2, 0.0)]
        p.append((1, "block", 0.0, 0.0, c + H / 2, 0.0))
        if rng.random() < 0.6:
            p.append((2, "cube", 0.0, 0.0, c + H + c / 2, 0.0))
    elif kind == "wall":
        n = int(rng.integers(2, 4))
        for r in range(n):
            m = n - r
            for i in range(m):
                p.append((r, "block", (i - (m - 1) / 2) * (L + gp), 0.0, H / 2 + r * H, 0.0))
    elif kind == "pyramid":
        p += [
            (0, "cube", -(c + gp) / 2, 0.0, c / 2, 0.0),
            (0, "cube", (c + gp) / 2, 0.0, c / 2, 0.0),
        ]
        p.append((1, "cube", 0.0, 0.0, 1.5 * c, 0.0))
        if rng.random() < 0.5:
            p.append((2, "block", 0.0, 0.0, 2 * c + H / 2, 0.0))
    elif kind == "crib":
        n = int(rng.integers(2, 4))
        for r in range(n):
            off = (W + gp) / 2
            if r % 2 == 0:
                p += [(r, "block", 0.0, -off, H / 2 + r * H, 0.0)]
                p += [(r, "block", 0.0, off, H / 2 + r * H, 0.0)]
            else:
                p += [(r, "block", -off, 0.0, H / 2 + r * H, np.pi / 2)]
                p += [(r, "block", off, 0.0, H / 2 + r * H, np.pi / 2)]
    else:  # pragma: no cover - internal
        raise ValueError(kind)
    return sorted(p, key=lambda q: q[0])


_KINDS = ("tower", "bridge", "wall", "pyramid", "crib")
_KIND_WEIGHTS = np.array([0.25, 0.25, 0.2, 0.15, 0.15])


def _plan_structure(library, rng, n_total: int, T_wc, camera):
    """Pieces ``(iid, class, T planned, layer, component)`` in addition order, or None."""
    cube, block = library["cube"], library["block"]
    models = {"cube": cube, "block": block}
    comps: list[list[tuple[int, str, np.ndarray]]] = []
    kinds: list[str] = []
    polys: list[np.ndarray] = []
    total = 0
    for _ in range(60):
        if total >= n_total:
            break
        kind = _KINDS[int(rng.choice(len(_KINDS), p=_KIND_WEIGHTS))]
        pieces = _component(kind, rng, cube.extents, block.extents)[: n_total - total]
        for _try in range(80):
            T_c = yaw_pose(
                float(rng.uniform(-np.pi, np.pi)),
                (rng.uniform(*STRUCTURE_REGION[0]), rng.uniform(*STRUCTURE_REGION[1]), 0.0),
            )
            placed, new_polys = [], []
            for layer, cls, x, y, z, yaw in pieces:
                jx, jy = rng.uniform(-STRUCTURE_JITTER_XY, STRUCTURE_JITTER_XY, 2)
                jyaw = np.radians(rng.uniform(-STRUCTURE_JITTER_YAW_DEG, STRUCTURE_JITTER_YAW_DEG))
                T = T_c @ yaw_pose(yaw + jyaw, (x + jx, y + jy, z + STRUCTURE_LIFT))
                placed.append((layer, cls, T))
                new_polys.append(footprint(models[cls], T))
            if not all(in_view(models[cls], T, T_wc, camera) for _, cls, T in placed):
                continue
            if all(poly_distance(a, b) >= STRUCTURE_CLEARANCE for a in new_polys for b in polys):
                break
        else:
            continue
        comps.append(placed)
        kinds.append(kind)
        polys += new_polys
        total += len(placed)
    if total < n_total:
        return None
    rows = [
        (layer, ci, pi, cls, T)
        for ci, comp in enumerate(comps)
        for pi, (layer, cls, T) in enumerate(comp)
    ]
    rows.sort(key=lambda r: (r[0], r[1], r[2]))
    plan = [(f"{cls}_{k}", cls, T, layer, ci) for k, (layer, ci, _, cls, T) in enumerate(rows)]
    return plan, kinds


def _build_structure(
    library: Mapping[str, ObjectModel],
    rng: np.random.Generator,
    *,
    stages: int,
    n_objects,
    T_wc: np.ndarray,
    camera: Camera,
    config: PhysicsConfig,
) -> _Layout:
    missing = [c for c in ("cube", "block") if c not in library]
    if missing:
        raise ValueError(
            f"structure experiment needs the classes 'cube' and 'block' (missing {missing}); "
            "use the built-in library"
        )
    resamples = 0
    for _layout in range(_MAX_LAYOUTS):
        if n_objects is None:
            lo, hi = STRUCTURE_OBJECTS
            n_total = int(rng.integers(lo, hi + 1))
        elif isinstance(n_objects, (tuple, list)):
            n_total = int(rng.integers(int(n_objects[0]), int(n_objects[1]) + 1))
        else:
            n_total = int(n_objects)
        if n_total < stages:
            raise ValueError(f"structure: {n_total} objects cannot fill {stages} stages")
        planned = _plan_structure(library, rng, n_total, T_wc, camera)
        if planned is None:
            resamples += 1
            continue
        plan, kinds = planned
        stages_out = _run_structure(library, plan, stages, T_wc, camera, config)
        if stages_out is not None:
            layout = _Layout({iid: cls for iid, cls, *_ in plan}, stages_out, resamples)
            layout.notes = {
                "components": kinds,
                "layers": [int(p[3]) for p in plan],
                "component_of": [int(p[4]) for p in plan],
            }
            return layout
        resamples += 1
    raise RuntimeError(f"structure: no stable layout in {_MAX_LAYOUTS} attempts")


def _run_structure(library, plan, stages, T_wc, camera, config) -> list[_Stage] | None:
    instances = [ObjectInstance(iid, library[cls]) for iid, cls, *_ in plan]
    planned = {iid: T for iid, _, T, *_ in plan}
    models = {inst.id: inst.model for inst in instances}
    world = World(instances, config=config)
    for inst in instances:
        world.set_enabled(inst.id, False)
    ids = [inst.id for inst in instances]
    present: list[str] = []
    out: list[_Stage] = []
    for chunk in np.array_split(np.arange(len(ids)), stages):
        new = [ids[j] for j in chunk]
        before = {i: world.get_pose(i) for i in present}
        before.update({i: planned[i] for i in new})
        world.set_poses({i: planned[i] for i in new})
        for iid in new:
            world.set_enabled(iid, True)
        t = world.settle()
        if t is None:
            return None
        present += new
        poses = {i: world.get_pose(i) for i in present}
        for i, T in poses.items():
            dt, dr = pose_change(before[i], T)
            if dt > STRUCTURE_MAX_SHIFT or np.degrees(dr) > STRUCTURE_MAX_TILT_DEG:
                return None
            if not in_view(models[i], T, T_wc, camera):
                return None
        out.append(_Stage(poses, tuple(new), float(t)))
    return out


# ---------------------------------------------------------------------------------- realism
#: Distractors keep this much clearance (m) from every object's footprint.
DISTRACTOR_CLEARANCE = 0.02


def _realistic_layout(
    layout: _Layout,
    library: Mapping[str, ObjectModel],
    realism: SceneRealism,
    rng: np.random.Generator,
    experiment: str,
    T_wc: np.ndarray,
    camera: Camera,
    config: PhysicsConfig,
) -> dict[str, ObjectModel]:
    """Add distractors to every stage of ``layout`` and the dynamic events after its last
    stage (in place); the distractors' models by id. Distractors rest at free spots of
    :data:`ISOLATED_REGION` (in view, :data:`DISTRACTOR_CLEARANCE` from every footprint of
    the last stage, where every object is present); each event (:func:`ssp.sim.events.
    run_event`) is simulated in one world holding every object and distractor."""
    last = layout.stages[-1]
    models = {iid: library[layout.classes[iid]] for iid in last.poses}
    polys = [footprint(models[i], T) for i, T in last.poses.items()]
    shapes = distractor_models()
    names = list(shapes)
    extras: dict[str, ObjectModel] = {}
    placed: dict[str, np.ndarray] = {}
    for j in rng.permutation(len(names))[: realism.distractors]:
        model = shapes[names[int(j)]]
        for _ in range(400):
            T = random_resting(model, rng, ISOLATED_REGION)
            poly = footprint(model, T)
            if in_view(model, T, T_wc, camera) and all(
                poly_distance(poly, q) >= DISTRACTOR_CLEARANCE for q in polys
            ):
                did = f"distractor_{len(extras)}"
                extras[did], placed[did] = model, T
                polys.append(poly)
                break
    world = World([ObjectInstance(i, m) for i, m in {**models, **extras}.items()], config=config)
    world.set_poses({**last.poses, **placed})
    world.settle()
    still = {d: world.get_pose(d) for d in extras}
    for stage in layout.stages:
        stage.extras = dict(still)
    movable = list(last.poses)
    prefer: list[str] = []
    for kind in realism.events_for(experiment):
        ev = run_event(
            kind, world, movable, rng, T_wc=T_wc, camera=camera, region=ISOLATED_REGION,
            prefer=prefer if kind == "stack" else (),
        )  # fmt: skip
        note = {"kind": kind, "stage": len(layout.stages)}
        if ev is None:
            note["skipped"] = True  # no attempt passed the event's checks
            layout.skipped_events.append(note)
            continue
        prefer = [ev.target]
        note.update(target=ev.target, moved=list(ev.moved))
        layout.stages.append(
            _Stage(
                {i: world.get_pose(i) for i in movable},
                (),
                0.0,
                extras={d: world.get_pose(d) for d in extras},
                event=note,
            )
        )
    return extras


# ---------------------------------------------------------------------------------- rendering
def _alone_count(model: ObjectModel, T: np.ndarray, T_wc: np.ndarray, cam: Camera) -> int:
    """Pixels of the object rendered alone (table present), ray casting only its image
    bounding box (``cam`` is the already subsampled camera)."""
    win = image_window(hull_world(model, T), T_wc, cam)
    if win is None:
        return 0
    r = render([("o", model.mesh, T)], T_wc, win.camera(cam))
    return int(r.pixel_counts()["o"])


def observe_static_scene(
    library, gt, T_wc, camera: Camera, stride: int, cache: dict, extras: Mapping | None = None
):
    """Ray cast one static scene: ``(render, visib_fract, alone pixel counts, scene pixel
    counts)``; ``gt`` is instance id -> ``(class, T_world_obj)``, ``camera`` full resolution.
    ``extras`` (id -> ``(model, T_world_obj)``: distractors) are rendered after the ground
    truth (their instance labels follow its), hide it, and get no visible fraction.
    ``cache`` (a dict kept by the caller) remembers each object's alone count while its pose
    and the camera's do not change."""
    objects = [(iid, library[cls].mesh, T) for iid, (cls, T) in gt.items()]
    objects += [(did, m.mesh, T) for did, (m, T) in (extras or {}).items()]
    scene = render(objects, T_wc, camera, stride=stride)
    counts = scene.pixel_counts()
    cam = scene.camera
    visib, alone = {}, {}
    for iid, (cls, T) in gt.items():
        hit = cache.get(iid)
        if (
            hit is not None
            and np.allclose(hit[0], T, rtol=0.0, atol=1e-7)
            and np.allclose(hit[1], T_wc, rtol=0.0, atol=1e-9)
        ):
            n = hit[2]
        else:
            n = _alone_count(library[cls], T, T_wc, cam)
            cache[iid] = (T.copy(), np.array(T_wc, dtype=float), n)
        alone[iid] = n
        visib[iid] = min(1.0, counts[iid] / n) if n else 0.0
    return scene, visib, alone, counts


# ---------------------------------------------------------------------------------- API
def generate_sequence(
    experiment: str,
    seed: int,
    library: Mapping[str, ObjectModel],
    *,
    frames_per_stage: int = 4,
    stages: int | None = None,
    camera: Camera | None = None,
    stride: int = 1,
    hypotheses: HypothesisNoise | RealisticNoise | None = None,
    realism: SceneRealism | None = None,
    objects_per_stage: int = 3,
    n_objects: int | tuple[int, int] | None = None,
    classes: Sequence[str] | None = None,
    T_world_cam: np.ndarray | None = None,
    frame_period: float = 1.0,
    physics: PhysicsConfig | None = None,
    camera_path: str = "static",
) -> SimSequence:
    """One synthetic sequence of ``experiment`` (see the module docstring).

    Args:
        experiment: ``"isolated"`` or ``"structure"``.
        seed: non-negative integer; the same seed gives identical arrays.
        library: class name -> model (an :class:`ssp.library.ObjectLibrary`); ``"structure"``
            needs ``cube`` and ``block``, ``"isolated"`` uses every other non-block class.
        frames_per_stage: repeated frames of each static scene (the paper: 4-5).
        stages: number of static scenes (default 5).
        camera: full-resolution intrinsics (:meth:`Camera.default` if None).
        stride: render every ``stride``-th pixel (the sequence's camera is subsampled).
        hypotheses: noise model (default: the experiment's calibrated preset); a
            :class:`~ssp.sim.realistic.RealisticNoise` draws the realistic estimator stream
            (:class:`~ssp.sim.realistic.RealisticStream`).
        realism: distractors, dynamic events and mask defects
            (:class:`~ssp.sim.realistic.SceneRealism`; module docstring), or None.
        objects_per_stage: isolated: objects added per stage (3: 15 objects in 5 stages).
        n_objects: structure: total objects, or an inclusive ``(lo, hi)`` range to draw from
            (default ``STRUCTURE_OBJECTS`` = 9-13); split over the stages bottom-up.
        classes: isolated: the classes to draw from (default: all non-block classes).
        T_world_cam: camera pose (default :func:`default_camera_pose`) of a static camera.
        camera_path: ``"static"`` or a moving camera's path starting at the static camera
            (:mod:`ssp.sim.camera_path`): each frame is then ray cast from its own camera
            (``SimFrame.T_world_cam``); the layout is the static camera's.
        frame_period: time between frames, s (``stamp = index * frame_period``).
        physics: MuJoCo settings for settling (default ``PhysicsConfig()``).

    Returns:
        A :class:`SimSequence`; ``info`` holds the settings, per stage the objects added,
        settling time and alone pixel counts (``px_count_all``), per frame the source
        instance of every hypothesis (``hypothesis_sources``, for evaluation only) and, for
        the realistic stream, its kind (``hypothesis_kinds``), and the events (``events``).
    """
    if experiment not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {experiment!r}; expected one of {EXPERIMENTS}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    stages = 5 if stages is None else int(stages)
    if stages < 1 or frames_per_stage < 1:
        raise ValueError("stages and frames_per_stage must be >= 1")
    camera = camera or Camera.default()
    T_wc = default_camera_pose() if T_world_cam is None else np.asarray(T_world_cam, float)
    if camera_path != "static" and T_world_cam is not None:
        raise ArgumentError("a camera path starts at the static camera: give no T_world_cam")
    noise = hypotheses if hypotheses is not None else HypothesisNoise.for_experiment(experiment)
    config = physics or PhysicsConfig()
    rng = np.random.default_rng([seed, 0, _EXPERIMENT_CODE[experiment]])

    if experiment == "isolated":
        layout = _build_isolated(
            library,
            rng,
            stages=stages,
            per_stage=int(objects_per_stage),
            classes=classes,
            T_wc=T_wc,
            camera=camera,
            config=config,
        )
    else:
        layout = _build_structure(
            library, rng, stages=stages, n_objects=n_objects, T_wc=T_wc, camera=camera,
            config=config,
        )  # fmt: skip

    extra_models: dict[str, ObjectModel] = {}
    if realism is not None:
        rng_r = np.random.default_rng([seed, 2, _EXPERIMENT_CODE[experiment]])
        extra_models = _realistic_layout(
            layout, library, realism, rng_r, experiment, T_wc, camera, config
        )
    used = set(layout.classes.values())
    stream = None
    if isinstance(noise, RealisticNoise):
        stream = RealisticStream(
            library,
            noise,
            seed,
            classes=[n for n in library if n in used],
            resting_pose=lambda m, r: random_resting(m, r, ISOLATED_REGION),
            T_world_cam=T_wc,
        )

    path = _camera_path(camera_path, len(layout.stages) * int(frames_per_stage), seed)
    frames: list[SimFrame] = []
    sources: list[list[str | None]] = []
    kinds: list[list[str]] = []
    px_all: list[dict[str, int]] = []
    cache: dict = {}
    cam_s = camera.subsample(stride)
    for g, stage in enumerate(layout.stages):
        gt = {iid: (layout.classes[iid], T) for iid, T in stage.poses.items()}
        extras = {did: (extra_models[did], T) for did, T in stage.extras.items()}
        scene, visib, alone, _ = observe_static_scene(
            library, gt, path[len(frames)] if path else T_wc, camera, stride, cache, extras
        )
        px_all.append(alone)
        labels = {oid: k for k, oid in enumerate([*gt, *extras])}
        for k in range(frames_per_stage):
            i = len(frames)
            T_wc_i = path[i] if path else T_wc
            if path and k > 0:  # a moving camera: this frame's own view
                scene, visib, _, _ = observe_static_scene(
                    library, gt, T_wc_i, camera, stride, cache, extras
                )
            frng = np.random.default_rng([seed, 1, i])
            depth = add_depth_noise(scene.depth, frng, quantum=KINECT_QUANTUM)
            instance = scene.instance
            if realism is not None and realism.mask_defects is not None:
                depth, instance, _ = add_mask_defects(
                    depth, instance, frng, fraction=realism.mask_defects
                )
            if stream is None:
                hyps, src = draw_hypotheses(gt, visib, library, noise, frng)
                kind = ["nominal"] * len(hyps)
            else:
                drawn = stream.draw(
                    i, gt, visib, segments=labels, distractors=extras, T_world_cam=T_wc_i
                )
                hyps = [d.hypothesis for d in drawn]
                src, kind = [d.source for d in drawn], [d.kind for d in drawn]
            frames.append(
                SimFrame(
                    index=i,
                    stamp=i * float(frame_period),
                    gt={iid: (cls, T.copy()) for iid, (cls, T) in gt.items()},
                    depth=depth.astype(np.float32),
                    instance=instance.astype(np.int16),
                    visib_fract=dict(visib),
                    hypotheses=hyps,
                    static_group=g,
                    distractors={d: (m.name, T.copy()) for d, (m, T) in extras.items()},
                    T_world_cam=np.array(T_wc_i, dtype=float),
                )
            )
            sources.append(src)
            kinds.append(kind)

    info = {
        "generator": "ssp.sim.generate",
        "generator_version": GENERATOR_VERSION,
        "experiment": experiment,
        "seed": seed,
        "stages": stages,
        "frames_per_stage": int(frames_per_stage),
        "stride": int(stride),
        "frame_period": float(frame_period),
        "camera_full": _camera_dict(camera),
        "noise": noise.to_dict(),
        "camera_path": camera_path,
        "library_classes": list(library),
        "stage_objects": [len(s.poses) for s in layout.stages],
        "stage_added": [list(s.added) for s in layout.stages],
        "settle_s": [round(s.settle_s, 6) for s in layout.stages],
        "resamples": int(layout.resamples),
        "px_count_all": px_all,
        "hypothesis_sources": sources,
        **({"layout": layout.notes} if layout.notes else {}),
    }
    if stream is not None:
        info["hypothesis_kinds"] = kinds
    if realism is not None:
        info["realism"] = realism.to_dict()
        info["events"] = [s.event for s in layout.stages if s.event is not None]
        info["events_skipped"] = layout.skipped_events
        info["distractors"] = {d: m.name for d, m in extra_models.items()}
    return SimSequence(
        experiment=experiment,
        seed=seed,
        camera=cam_s,
        T_world_cam=T_wc.copy(),
        frames=frames,
        models=tuple(n for n in library if n in used),
        info=info,
    )


def _camera_path(kind: str, n_frames: int, seed: int) -> list[np.ndarray]:
    """The cameras of a moving path's frames, or none for the static camera."""
    if kind == "static":
        return []
    return camera_path(
        kind, n_frames, seed, distance=CAMERA_DISTANCE, elevation_deg=CAMERA_ELEVATION_DEG
    )


def _camera_dict(camera: Camera) -> dict:
    return {
        "width": int(camera.width),
        "height": int(camera.height),
        "fx": float(camera.fx),
        "fy": float(camera.fy),
        "cx": float(camera.cx),
        "cy": float(camera.cy),
    }


def generate_sequences(
    experiment: str, n: int, seed: int, library: Mapping[str, ObjectModel], **kwargs
) -> list[SimSequence]:
    """``n`` sequences with seeds ``seed, seed + 1, ...`` (keyword arguments as for
    :func:`generate_sequence`). Each holds its images in memory (about 36 MB for 20 frames at
    640 x 480); write large sets with :func:`ssp.sim.bop.simulate_to_disk` instead."""
    return [generate_sequence(experiment, int(seed) + i, library, **kwargs) for i in range(n)]


def calibrate_noise(
    experiment: str,
    library: Mapping[str, ObjectModel],
    seeds: Sequence[int] = range(0, 20),
    *,
    noise: HypothesisNoise | None = None,
    target: tuple[float, float] | None = None,
    **generate_kwargs,
) -> dict:
    """Solve the base sigmas of ``noise`` so that the mean induced error of the hypotheses
    matches Table I of the paper on sequences of the default generator.

    The scenes (hence the visible fractions ``v`` of every object in every frame) do not depend
    on the noise. For per-axis Gaussian noise the error norms are chi(3)-distributed, so
    with ``g(v) = 1 + growth (1 - v)`` and weights ``w(v) = k (1 - P_miss(v))`` (expected
    hypotheses per object and frame) the expected mean error is ``CHI3_MEAN * sigma *
    E_w[g]``: linear in the base sigma, solved in closed form. The solved noise is then
    checked by drawing hypotheses on the same frames and measuring the errors with
    :func:`ssp.probability.pose_change` (symmetry aware).

    Use development seeds (0-99), never the reporting seeds (1000+).

    Args:
        experiment: ``"isolated"`` or ``"structure"``.
        library: the models (the presets were calibrated on ``ObjectLibrary.builtin()``).
        seeds: sequences to measure.
        noise: the model whose ``growth``/miss rules are kept (default: the preset).
        target: ``(translation mm, rotation deg)`` mean errors (default: Table I).
        **generate_kwargs: passed to :func:`generate_sequence` (e.g. ``stride``).

    Returns:
        A dict: ``sigma_t`` (m) and ``sigma_r_deg`` (the solved base sigmas), ``noise`` (the
        solved model as a dict), ``target``, ``predicted`` and ``measured`` ``(mean, std)``
        of the translation (mm) and rotation (deg) errors, ``paper`` (Table I mean, std),
        visibility statistics and the counts of sequences, frames and hypotheses.

    The presets :meth:`HypothesisNoise.isolated` and :meth:`HypothesisNoise.structure` were
    solved with ``seeds=range(0, 100)`` on the built-in library (measured values next to them).
    Cost: about 3 s (isolated) and 2.3 s (structure) per seed at stride 1.
    """
    base = noise if noise is not None else HypothesisNoise.for_experiment(experiment)
    paper = PAPER_INDUCED_NOISE[experiment]
    tgt_t, tgt_r = target if target is not None else (
        paper["translation_mm"][0],
        paper["rotation_deg"][0],
    )  # fmt: skip
    seqs = [
        generate_sequence(experiment, int(s), library, hypotheses=base, **generate_kwargs)
        for s in seeds
    ]
    vis = np.array([v for q in seqs for f in q.frames for v in f.visib_fract.values()], float)
    if len(vis) == 0:
        raise ValueError("calibrate_noise: no objects in the sequences")
    w = base.k * (1.0 - base.miss_probability(vis))
    g = base.sigma_scale(vis)
    m1 = float((w * g).sum() / w.sum())
    m2 = float((w * g * g).sum() / w.sum())
    sigma_t = tgt_t / 1000.0 / (CHI3_MEAN * m1)
    sigma_r_deg = tgt_r / (CHI3_MEAN * m1)
    spread = math.sqrt(max(3.0 * m2 - CHI3_MEAN**2 * m1**2, 0.0))
    solved = base.replace(sigma_t=sigma_t, sigma_r_deg=sigma_r_deg)

    # check: draw hypotheses with the solved noise on the same frames
    et, er = [], []
    for q in seqs:
        frames, srcs = [], []
        for f in q.frames:
            rng = np.random.default_rng([q.seed, 2, f.index])
            hyps, src = draw_hypotheses(f.gt, f.visib_fract, library, solved, rng)
            frames.append(
                SimFrame(f.index, f.stamp, f.gt, f.depth, f.instance, f.visib_fract, hyps)
            )
            srcs.append(src)
        err = induced_errors(frames, library, srcs)
        et.append(err["translation_mm"])
        er.append(err["rotation_deg"])
    et_a, er_a = np.concatenate(et), np.concatenate(er)
    return {
        "experiment": experiment,
        "seeds": [int(s) for s in seeds],
        "n_sequences": len(seqs),
        "n_frames": int(sum(len(q) for q in seqs)),
        "n_object_frames": int(len(vis)),
        "n_hypotheses": int(len(et_a)),
        "visib_mean": float(vis.mean()),
        "visib_quantiles": {str(p): float(np.quantile(vis, p)) for p in (0.05, 0.25, 0.5, 0.75)},
        "visib_below_0.5": float((vis < 0.5).mean()),
        "expected_missed": float((base.miss_probability(vis)).mean()),
        "sigma_scale_mean": m1,
        "sigma_t": sigma_t,
        "sigma_r_deg": sigma_r_deg,
        "noise": solved.to_dict(),
        "target": {"translation_mm": tgt_t, "rotation_deg": tgt_r},
        "predicted": {
            "translation_mm": (tgt_t, sigma_t * 1000.0 * spread),
            "rotation_deg": (tgt_r, sigma_r_deg * spread),
        },
        "measured": {
            "translation_mm": (float(et_a.mean()), float(et_a.std())),
            "rotation_deg": (float(er_a.mean()), float(er_a.std())),
        },
        "paper": paper,
    }
