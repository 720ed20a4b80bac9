"""``ssp bench calibrate``: measure the engine-specific constants of the stability and collision
terms (DESIGN section 4: "calibrate so solver residue passes and a real overlap fails").

Scenes built from the built-in models are measured exactly as the scorer reads a simulated state
(:class:`ssp.scoring.SceneScorer`): wrenches cleared, accelerations from rest (``beta_t =
|a| / g``, ``beta_R = |alpha| / alpha_max``), the deepest penetration ``d`` of each object (its
contacts, the table included), and the overlap fraction ``v_c / v_t``
(:func:`ssp.overlap.overlap_fractions`, only for objects deeper than ``collision.min_depth``,
against the objects they touch that deeply and the table), giving ``e_C = d / diameter *
v_c / v_t``.

* **resting** (must score stable and collision-free): cube towers (2-10), cube pyramids
  (3-2-1), dropped block piles, tool scatters, dropped tool piles, bridges (a block, or a link,
  on two cubes). The builder's poses are settled into a ground truth (dynamics, then a
  quasi-static window; a scene that does not come to rest is dropped and listed), measured
  (stage ``exact``), then every object gets a random pose error (uniform direction, size up to
  ``noise_translation``; rotation about its centre of mass, random axis, angle up to
  ``noise_rotation_deg``) and the scene is relaxed like a hypothesis in the search: quasi-static
  steps with no external force at full friction, measured after each of ``windows`` (stages
  ``0.10s``, ``0.25s``), and, separately, the search's whole per-hypothesis window
  (:meth:`ssp.search.Simulator.window`: data forces towards perfect segments, i.e. the surface
  samples at the ground-truth pose, at zero friction, then the window without forces; stage
  ``search``).
* **bad** (must score low), deterministic: hovering objects (5, 10 mm above the table, a cube
  or a bridge), overhanging ones (centre of mass 2-20 mm beyond the supporting cube's edge), a
  cube tilted 10-20 deg onto one edge of the cube below, and interpenetrations (1, 2, 5, 10 mm:
  into the table, into the cube below, side by side), measured at the set pose *without
  stepping* (stage ``set``) and after each window.

The constants are chosen by :func:`choose_logistic` from the resting objects of the basis stage
and the bad ones at their set pose. Everything is deterministic (fixed seeds; the wall time is
reported apart from the measurements).
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ssp import __version__
from ssp.config import CollisionConfig, LibraryConfig, SSPConfig, StabilityConfig
from ssp.eval import scenes
from ssp.forces import SegmentField
from ssp.geometry import make_pose
from ssp.library import ObjectInstance, ObjectLibrary, ObjectModel
from ssp.library.builtin import TOOL_NAMES
from ssp.physics import World
from ssp.probability import collision_severity, log_collision, log_stability
from ssp.scoring import contact_overlaps
from ssp.search import Simulator
from ssp.support import build_support_graph
from ssp.timing import StageTimer

__all__ = [
    "RESTING_FAMILIES",
    "Case",
    "calibrate",
    "choose_logistic",
    "summarize",
    "write_report",
]

#: Families of resting scenes (the ``families`` argument of :func:`calibrate`).
RESTING_FAMILIES = ("tower", "pyramid", "block_pile", "tool_scatter", "tool_pile", "bridge")
#: Kinds of bad scenes.
BAD_KINDS = ("hover", "overhang", "tilted", "overlap")
#: Kinds of bad scenes that judge the stability term / the collision term.
STABILITY_BAD = ("hover", "overhang", "tilted")
COLLISION_BAD = ("overlap",)
#: Percentiles reported for every distribution.
PERCENTILES = (50, 95, 99)
#: Ground truth: dynamic settle, then a quasi-static one (s).
GT_DYNAMIC_S = 1.5
GT_QUASI_STATIC_S = 0.1
#: A ground truth is at rest when every object has ``max(beta_t, beta_R)`` at most this; else it
#: is settled 1 s more, at most ``GT_RETRIES`` times, and dropped if it never comes to rest.
GT_REST_BETA = 0.01
GT_RETRIES = 3
#: Probability targets: resting objects at least, bad objects at most.
TARGET_REST = 0.95
TARGET_BAD = 0.05

Progress = Callable[[str], None]


@dataclass
class Case:
    """One scene to measure.

    Attributes:
        name: unique scene name (e.g. ``tower5_s3``, ``hover_cube_table_5mm``).
        family: resting family or bad kind.
        cls: ``"resting"`` or ``"bad"``.
        instances, poses: the objects and their poses (ground truth or the bad pose).
        targets: ids of the objects to record (None: all).
        param: the case's parameter (gap, overhang, tilt, overlap; mm or deg), if any.
        seed: noise seed of a resting case.
    """

    name: str
    family: str
    cls: str
    instances: list[ObjectInstance]
    poses: dict[str, np.ndarray]
    targets: list[str] | None = None
    param: float | None = None
    seed: int | None = None


# --------------------------------------------------------------------------------------------
# measurement


def _measure(world: World, cfg: SSPConfig, targets: Sequence[str] | None) -> list[dict]:
    """Per-object stability and collision inputs of the world's current state, as the scorer
    reads them (:class:`ssp.scoring.SceneScorer`)."""
    g = float(cfg.physics.gravity)
    ids = world.ids
    models = [world.model_of(i) for i in ids]
    world.clear_wrenches()
    lin, ang = world.acceleration_from_rest()
    contacts = world.contacts()
    graph = build_support_graph(contacts, world.masses, g)
    depth = np.asarray(graph.penetration, dtype=float)
    poses = world.pose_array()
    min_depth = float(cfg.collision.min_depth)
    frac = contact_overlaps(models, contacts, poses, depth > min_depth, min_depth)
    diam = np.array([m.diameter for m in models])
    e_c = collision_severity(depth, frac, diam)
    amax = np.array([m.max_angular_acceleration(g) for m in models])
    beta_t = np.linalg.norm(lin, axis=1) / g
    beta_r = np.linalg.norm(ang, axis=1) / amax
    keep = set(ids) if targets is None else set(targets)
    out = []
    for k, oid in enumerate(ids):
        if oid not in keep:
            continue
        out.append(
            {
                "object": oid,
                "model": models[k].name,
                "beta_t": float(beta_t[k]),
                "beta_r": float(beta_r[k]),
                "depth_mm": float(depth[k] * 1000.0),
                "overlap": float(frac[k]),
                "e_c": float(e_c[k]),
            }
        )
    return out


def _steps(seconds: float, dt: float) -> int:
    return int(round(seconds / dt))


def _noisy(
    poses: dict[str, np.ndarray],
    models: dict[str, ObjectModel],
    rng: np.random.Generator,
    trans: float,
    rot_deg: float,
) -> dict[str, np.ndarray]:
    """Every pose moved by a random error: translation of uniform direction and magnitude in
    ``[0, trans]`` m, rotation about the centre of mass of random axis and angle in
    ``[0, rot_deg]`` deg (ids in sorted order, so the draw does not depend on dict order)."""
    out = {}
    for oid in sorted(poses):
        T = poses[oid].copy()
        u = rng.normal(size=3)
        dt = u / np.linalg.norm(u) * rng.uniform(0.0, trans)
        v = rng.normal(size=3)
        R_err = Rotation.from_rotvec(
            v / np.linalg.norm(v) * math.radians(rng.uniform(0.0, rot_deg))
        ).as_matrix()
        com = T[:3, :3] @ models[oid].center_of_mass + T[:3, 3]
        T[:3, :3] = R_err @ T[:3, :3]
        T[:3, 3] = R_err @ (T[:3, 3] - com) + com + dt
        out[oid] = T
    return out


def _stage_name(seconds: float) -> str:
    return f"{seconds:.2f}s"


def _settle_ground_truth(world: World, cfg: SSPConfig, targets) -> list[dict] | None:
    """Settle the builder's poses into a resting ground truth: dynamics, then a short
    quasi-static window; repeated (up to ``GT_RETRIES`` more times) while some object still has
    ``beta > GT_REST_BETA``. Returns the measurement of the ground truth, or None if the scene
    does not come to rest."""
    dt = world.timestep
    for attempt in range(GT_RETRIES + 1):
        world.step(_steps(GT_DYNAMIC_S if attempt == 0 else 1.0, dt), quasi_static=False)
        world.step(_steps(GT_QUASI_STATIC_S, dt))
        rows = _measure(world, cfg, None)
        if max(max(r["beta_t"], r["beta_r"]) for r in rows) <= GT_REST_BETA:
            keep = set(r["object"] for r in rows) if targets is None else set(targets)
            return [r for r in rows if r["object"] in keep]
    return None


def _search_window(world: World, cfg: SSPConfig, gt: dict[str, np.ndarray]) -> None:
    """The search's per-hypothesis window (:meth:`Simulator.window`) with data forces towards
    perfect segments: every object's surface samples at its ground-truth pose (a full view: no
    camera, so every sample pulls), built as the parser builds them otherwise."""
    ids = world.ids
    fields = []
    for oid in ids:
        m = world.model_of(oid)
        pts = np.asarray(m.surface_points) @ gt[oid][:3, :3].T + gt[oid][:3, 3]
        fields.append(SegmentField(pts, cfg.forces.max_distance))
    Simulator.for_world(world, fields, cfg, StageTimer()).window()
    world.clear_wrenches()


def _run_resting(
    case: Case, cfg: SSPConfig, windows: Sequence[float], noise, search: bool
) -> list[dict] | None:
    world = World(case.instances, config=cfg.physics)
    dt = world.timestep
    world.set_poses(case.poses)
    exact = _settle_ground_truth(world, cfg, case.targets)
    if exact is None:
        return None
    rows = [{**r, "stage": "exact"} for r in exact]
    gt = world.poses()
    base = world.save_state()
    models = {i.id: i.model for i in case.instances}
    rng = np.random.default_rng([case.seed or 0, len(case.instances), _name_key(case.name)])
    noisy = _noisy(gt, models, rng, *noise)
    world.set_poses(noisy)
    done = 0.0
    for w in sorted(windows):
        world.step(_steps(w - done, dt))
        done = w
        rows += [{**r, "stage": _stage_name(w)} for r in _measure(world, cfg, case.targets)]
    if search:
        world.restore_state(base)
        world.set_poses(noisy)
        _search_window(world, cfg, gt)
        rows += [{**r, "stage": "search"} for r in _measure(world, cfg, case.targets)]
    return rows


def _name_key(name: str) -> int:
    """A stable small integer from a scene name (seeding; ``hash`` is salted per process)."""
    return sum((k + 1) * ord(c) for k, c in enumerate(name)) % 100_003


def _run_bad(case: Case, cfg: SSPConfig, windows: Sequence[float]) -> list[dict]:
    world = World(case.instances, config=cfg.physics)
    dt = world.timestep
    world.set_poses(case.poses)
    rows = [{**r, "stage": "set"} for r in _measure(world, cfg, case.targets)]
    done = 0.0
    for w in sorted(windows):
        world.step(_steps(w - done, dt))
        done = w
        rows += [{**r, "stage": _stage_name(w)} for r in _measure(world, cfg, case.targets)]
    return rows


# --------------------------------------------------------------------------------------------
# scenes


def _on_table(model: ObjectModel, x: float = 0.0, y: float = 0.0, R=None) -> np.ndarray:
    """Pose of ``model`` rotated by ``R`` with its lowest point on z = 0 and its bounding-box
    centre over (x, y)."""
    R = np.eye(3) if R is None else np.asarray(R, dtype=float)
    v = np.asarray(model.mesh.vertices) @ R.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    c = (lo + hi) / 2
    return make_pose(R, [x - c[0], y - c[1], -lo[2]])


def _stack_on(lower: np.ndarray, lower_model: ObjectModel, model: ObjectModel, dx=0.0, R=None):
    """Pose of ``model`` (rotated by ``R``) resting on the top of the box-like ``lower``."""
    top = float(np.max(np.asarray(lower_model.mesh.vertices) @ lower[:3, :3].T[:, 2]))
    top += float(lower[2, 3])
    T = _on_table(model, float(lower[0, 3]) + dx, float(lower[1, 3]), R)
    T[2, 3] += top
    return T


def _yaw(rad: float) -> np.ndarray:
    return Rotation.from_euler("z", rad).as_matrix()


def resting_cases(
    lib: ObjectLibrary,
    seeds: Iterable[int],
    families: Sequence[str] = RESTING_FAMILIES,
    tower_sizes: Sequence[int] = tuple(range(2, 11)),
) -> list[Case]:
    """The resting ground truths (before settling and noise), one set per seed."""
    unknown = sorted(set(families) - set(RESTING_FAMILIES))
    if unknown:
        raise ValueError(f"unknown resting families {unknown}; known: {RESTING_FAMILIES}")
    cube, block, link = lib["cube"], lib["block"], lib["link"]
    tools = [lib[n] for n in TOOL_NAMES]
    h = float(cube.extents[2])
    cases: list[Case] = []
    for seed in seeds:
        rng = np.random.default_rng(10_000 + seed)
        if "tower" in families:
            for n in tower_sizes:
                inst, poses = scenes.tower(cube, n)
                for oid in poses:
                    poses[oid][:3, :3] = _yaw(rng.uniform(0, np.pi / 2))
                cases.append(Case(f"tower{n}_s{seed}", "tower", "resting", inst, poses, seed=seed))
        if "pyramid" in families:
            gap = 0.001
            inst, poses = [], {}
            for row, count in enumerate((3, 2, 1)):
                for k in range(count):
                    x = (k - (count - 1) / 2) * (h + gap)
                    o = ObjectInstance(f"cube_r{row}_{k}", cube)
                    inst.append(o)
                    poses[o.id] = make_pose(t=[x, 0.0, h / 2 + row * h])
            cases.append(Case(f"pyramid6_s{seed}", "pyramid", "resting", inst, poses, seed=seed))
        if "block_pile" in families:
            inst, poses = scenes.pile([block], 6, seed=seed, spread=0.03)
            cases.append(
                Case(f"block_pile6_s{seed}", "block_pile", "resting", inst, poses, seed=seed)
            )
        if "tool_scatter" in families:
            inst, poses = scenes.scatter(tools, len(tools), 0.4, seed=seed)
            cases.append(
                Case(f"tool_scatter8_s{seed}", "tool_scatter", "resting", inst, poses, seed=seed)
            )
        if "tool_pile" in families:
            order = [tools[(seed + k) % len(tools)] for k in range(3)]
            inst, poses = scenes.pile(order, 3, seed=seed, spread=0.03)
            cases.append(
                Case(f"tool_pile3_s{seed}", "tool_pile", "resting", inst, poses, seed=seed)
            )
        if "bridge" in families:
            for top, span in ((block, 0.02), (link, None)):
                if span is None:  # link: its end blocks on the cubes
                    arm = float(top.extents[0]) / 2 - float(top.extents[1]) / 2
                else:
                    arm = h / 2 + span / 2
                a = ObjectInstance("cube_a", cube)
                b = ObjectInstance("cube_b", cube)
                c = ObjectInstance(f"{top.name}_top", top)
                Ta = make_pose(t=[-arm, 0.0, h / 2])
                Tb = make_pose(t=[arm, 0.0, h / 2])
                Tc = _stack_on(Ta, cube, top, dx=arm)
                cases.append(
                    Case(
                        f"bridge_{top.name}_s{seed}",
                        "bridge",
                        "resting",
                        [a, b, c],
                        {a.id: Ta, b.id: Tb, c.id: Tc},
                        seed=seed,
                    )
                )
    return cases


def bad_cases(lib: ObjectLibrary, quick: bool = False) -> list[Case]:
    """The deterministic bad scenes; ``quick`` keeps one of each kind and parameter."""
    cube, block = lib["cube"], lib["block"]
    h = float(cube.extents[2])
    cases: list[Case] = []

    def add(name, kind, objs, poses, targets, param):
        inst = [ObjectInstance(oid, m) for oid, m in objs]
        cases.append(Case(name, kind, "bad", inst, poses, targets, param))

    # hovering: gap between the object and its support
    hover_models = [cube] if quick else [cube, block, lib["drill"], lib["mallet"]]
    for gap_mm in (5.0, 10.0):
        gap = gap_mm / 1000
        for m in hover_models:
            T = scenes.resting_pose(m, 0.0, 0.0) if m.name in TOOL_NAMES else _on_table(m)
            T[2, 3] += gap
            add(
                f"hover_{m.name}_table_{gap_mm:g}mm",
                "hover",
                [(m.name, m)],
                {m.name: T},
                [m.name],
                gap_mm,
            )
        Tl = _on_table(cube)
        Tu = _stack_on(Tl, cube, cube)
        Tu[2, 3] += gap
        add(
            f"hover_cube_on_cube_{gap_mm:g}mm",
            "hover",
            [("lower", cube), ("upper", cube)],
            {"lower": Tl, "upper": Tu},
            ["upper"],
            gap_mm,
        )
        if not quick:
            arm = h / 2 + 0.01
            Ta, Tb = make_pose(t=[-arm, 0, h / 2]), make_pose(t=[arm, 0, h / 2])
            Tc = _stack_on(Ta, cube, block, dx=arm)
            Tc[2, 3] += gap
            add(
                f"hover_block_on_bridge_{gap_mm:g}mm",
                "hover",
                [("a", cube), ("b", cube), ("top", block)],
                {"a": Ta, "b": Tb, "top": Tc},
                ["top"],
                gap_mm,
            )

    # overhang: centre of mass beyond the supporting cube's edge
    for over_mm in (2.0, 5.0, 10.0, 20.0):
        for m in [block] if quick else [block, cube]:
            Tl = _on_table(cube)
            Tu = _stack_on(Tl, cube, m, dx=h / 2 + over_mm / 1000)
            add(
                f"overhang_{m.name}_{over_mm:g}mm",
                "overhang",
                [("lower", cube), ("upper", m)],
                {"lower": Tl, "upper": Tu},
                ["upper"],
                over_mm,
            )

    # tilted: a cube on a cube, turned about y onto one edge, centre of mass over the centre
    for tilt in (10.0, 15.0, 20.0) if not quick else (10.0,):
        R = Rotation.from_euler("y", tilt, degrees=True).as_matrix()
        Tl = _on_table(cube)
        Tu = make_pose(
            R,
            [0.0, 0.0, h + (h / 2) * (math.sin(math.radians(tilt)) + math.cos(math.radians(tilt)))],
        )
        add(
            f"tilted_cube_{tilt:g}deg",
            "tilted",
            [("lower", cube), ("upper", cube)],
            {"lower": Tl, "upper": Tu},
            ["upper"],
            tilt,
        )

    # interpenetration of depth k
    sink_models = [cube] if quick else [cube, block, lib["drill"], lib["mallet"]]
    for k_mm in (1.0, 2.0, 5.0, 10.0):
        k = k_mm / 1000
        for m in sink_models:
            T = scenes.resting_pose(m, 0.0, 0.0) if m.name in TOOL_NAMES else _on_table(m)
            T[2, 3] -= k
            add(
                f"overlap_{m.name}_table_{k_mm:g}mm",
                "overlap",
                [(m.name, m)],
                {m.name: T},
                [m.name],
                k_mm,
            )
        Tl = _on_table(cube)
        Tu = _stack_on(Tl, cube, cube)
        Tu[2, 3] -= k
        add(
            f"overlap_cube_in_cube_{k_mm:g}mm",
            "overlap",
            [("lower", cube), ("upper", cube)],
            {"lower": Tl, "upper": Tu},
            ["lower", "upper"],
            k_mm,
        )
        if not quick:
            Ta = _on_table(cube, -h / 2 + k / 2)
            Tb = _on_table(cube, h / 2 - k / 2)
            add(
                f"overlap_cubes_side_{k_mm:g}mm",
                "overlap",
                [("left", cube), ("right", cube)],
                {"left": Ta, "right": Tb},
                ["left", "right"],
                k_mm,
            )
            Tl = _on_table(cube)
            Tu = _stack_on(Tl, cube, block)
            Tu[2, 3] -= k
            add(
                f"overlap_block_in_cube_{k_mm:g}mm",
                "overlap",
                [("lower", cube), ("upper", block)],
                {"lower": Tl, "upper": Tu},
                ["upper"],
                k_mm,
            )
    return cases


# --------------------------------------------------------------------------------------------
# statistics and the choice of constants


def _dist(x: Sequence[float]) -> dict:
    a = np.asarray(x, dtype=float)
    if len(a) == 0:
        return {"n": 0}
    out = {"n": int(len(a))}
    for p in PERCENTILES:
        out[f"p{p}" if p != 50 else "median"] = float(np.percentile(a, p))
    out["max"] = float(a.max())
    out["min"] = float(a.min())
    return out


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def choose_logistic(
    rest_hi: float,
    bad_lo: float,
    *,
    rest_factors: int = 1,
    target_rest: float = TARGET_REST,
    target_bad: float = TARGET_BAD,
    sig: int = 2,
) -> dict:
    """Midpoint ``a`` and steepness ``s`` of ``P = L(-s (x - a))`` (``rest_factors`` such
    factors multiplied for a resting object, one enough for a bad one) that give every input
    ``<= rest_hi`` ``P >= target_rest`` and every input ``>= bad_lo`` ``P <= target_bad``.

    The smallest steepness that meets both targets puts the midpoint where the two margins are
    equal: ``s (a - rest_hi) = logit(target_rest^(1/rest_factors))`` and ``s (bad_lo - a) =
    logit(1 - target_bad)``. Both are rounded to ``sig`` significant digits (the steepness up),
    so the targets still hold. Returns ``{"midpoint", "steepness", "achievable", ...}``; when
    ``bad_lo <= rest_hi`` there is no such pair (``achievable`` False) and the midpoint is put
    at ``bad_lo`` with the steepness that keeps ``P >= target_rest`` at 0.
    """
    k_rest = _logit(target_rest ** (1.0 / rest_factors))
    k_bad = _logit(1.0 - target_bad)

    def rnd(x: float, up: bool = False) -> float:
        if x <= 0:
            return 0.0
        e = math.floor(math.log10(x)) - (sig - 1)
        f = x / 10**e
        return (math.ceil(f - 1e-9) if up else round(f)) * 10**e

    out = {"rest_reference": rest_hi, "bad_reference": bad_lo}
    if bad_lo > rest_hi:
        a = (k_bad * rest_hi + k_rest * bad_lo) / (k_rest + k_bad)
        a = rnd(a)
        if not (rest_hi < a < bad_lo):
            a = (rest_hi + bad_lo) / 2
        s = rnd(max(k_rest / (a - rest_hi), k_bad / (bad_lo - a)), up=True)
        out.update(midpoint=a, steepness=s, achievable=True)
    else:
        a = bad_lo if bad_lo > 0 else max(rest_hi, 1e-12)
        s = rnd(k_rest / a, up=True)
        out.update(midpoint=a, steepness=s, achievable=False)
    return out


def _p_stability(rows: list[dict], s_cfg: StabilityConfig, g: float = 9.81) -> np.ndarray:
    if not rows:
        return np.zeros(0)
    bt = np.array([r["beta_t"] for r in rows])
    br = np.array([r["beta_r"] for r in rows])
    # log_stability takes accelerations; beta_t g along x, beta_r alpha_max with alpha_max = 1
    lin = np.zeros((len(rows), 3))
    ang = np.zeros((len(rows), 3))
    lin[:, 0] = bt * g
    ang[:, 0] = br
    return np.exp(log_stability(lin, ang, 1.0, g, s_cfg))


def _p_collision(rows: list[dict], c_cfg: CollisionConfig) -> np.ndarray:
    if not rows:
        return np.zeros(0)
    return np.exp(log_collision(np.array([r["e_c"] for r in rows]), c_cfg))


def _beta(r: dict) -> float:
    return max(r["beta_t"], r["beta_r"])


def _stage_stats(rows: list[dict]) -> dict:
    return {
        "objects": len(rows),
        "beta_t": _dist([r["beta_t"] for r in rows]),
        "beta_r": _dist([r["beta_r"] for r in rows]),
        "beta": _dist([_beta(r) for r in rows]),
        "depth_mm": _dist([r["depth_mm"] for r in rows]),
        "overlap": _dist([r["overlap"] for r in rows]),
        "e_c": _dist([r["e_c"] for r in rows]),
    }


def _stability_choice(rest: list[dict], bad_min: float) -> dict:
    """:func:`choose_logistic` on resting ``beta``: its maximum when that is below the smallest
    bad ``beta``, else its 99th percentile."""
    b = np.array([_beta(r) for r in rest]) if rest else np.zeros(1)
    p99, mx = float(np.percentile(b, 99)), float(b.max())
    basis = "max" if bad_min > mx else "p99"
    out = choose_logistic(mx if basis == "max" else p99, bad_min, rest_factors=2)
    out.update(rest_basis=basis, rest_p99=p99, rest_max=mx, bad_min=bad_min)
    return out


def summarize(
    records: list[dict],
    *,
    basis: str,
    bad_overlap_mm: float = 2.0,
    config: SSPConfig | None = None,
) -> dict:
    """Distributions per class, the chosen constants and the probabilities they give.

    Args:
        records: per-object rows of :func:`calibrate`.
        basis: the resting stage the constants are chosen from (``"search"``, or a window
            such as ``"0.10s"``); bad objects are always taken at their set pose.
        bad_overlap_mm: overlaps at least this deep must get ``P_C <= TARGET_BAD``.
        config: the current defaults to compare with.

    Stability is chosen from ``beta = max(beta_t, beta_R)`` of the hover, overhang and tilted
    cases; collision from ``e_C`` of the overlap cases. When no overlap depth from
    ``bad_overlap_mm`` on can be separated from the resting objects, the smallest depth that
    can is used instead (and ``achievable_for_requested`` is False).
    """
    cfg = config or SSPConfig()
    resting_rows = [r for r in records if r["cls"] == "resting"]
    stages = list(dict.fromkeys(r["stage"] for r in resting_rows))
    if basis not in stages:
        raise ValueError(f"basis stage {basis!r} not measured; stages: {stages}")
    by_stage = {st: [r for r in resting_rows if r["stage"] == st] for st in stages}
    resting = {}
    for st, rows in by_stage.items():
        resting[st] = _stage_stats(rows)
        resting[st]["by_family"] = {
            f: _stage_stats([r for r in rows if r["family"] == f])
            for f in dict.fromkeys(r["family"] for r in rows)
        }

    bad_rows = [r for r in records if r["cls"] == "bad"]
    bad_table = []  # per scene and stage, the largest value over its recorded objects
    for name in dict.fromkeys(r["scene"] for r in bad_rows):
        rows = [r for r in bad_rows if r["scene"] == name]
        for st in dict.fromkeys(r["stage"] for r in rows):
            sr = [r for r in rows if r["stage"] == st]
            bad_table.append(
                {
                    "scene": name,
                    "kind": sr[0]["family"],
                    "param": sr[0]["param"],
                    "stage": st,
                    "beta_t": max(r["beta_t"] for r in sr),
                    "beta_r": max(r["beta_r"] for r in sr),
                    "beta": max(_beta(r) for r in sr),
                    "depth_mm": max(r["depth_mm"] for r in sr),
                    "overlap": max(r["overlap"] for r in sr),
                    "e_c": max(r["e_c"] for r in sr),
                }
            )

    # --- stability: per resting stage, then the basis
    stab_bad = [r for r in bad_rows if r["family"] in STABILITY_BAD and r["stage"] == "set"]
    bad_min = min((_beta(r) for r in stab_bad), default=math.inf)
    stability_by_stage = {
        st: _stability_choice(rows, bad_min) for st, rows in by_stage.items() if st != "exact"
    }
    stab = dict(stability_by_stage[basis])
    stab["smallest_bad_case"] = min(stab_bad, key=_beta)["scene"] if stab_bad else None

    # --- collision
    rest = by_stage[basis]
    coll_set = [r for r in bad_rows if r["family"] in COLLISION_BAD and r["stage"] == "set"]
    e_rest_max = max((r["e_c"] for r in rest), default=0.0)
    levels = sorted({r["param"] for r in coll_set})
    separable = {
        lv: all(r["e_c"] > e_rest_max for r in coll_set if r["param"] == lv) for lv in levels
    }
    smallest_caught = next(
        (lv for k, lv in enumerate(levels) if all(separable[x] for x in levels[k:])), None
    )
    requested_ok = all(separable[lv] for lv in levels if lv >= bad_overlap_mm)
    used = bad_overlap_mm if requested_ok or smallest_caught is None else smallest_caught
    e_bad_min = min((r["e_c"] for r in coll_set if r["param"] >= used), default=math.inf)
    coll = choose_logistic(e_rest_max, e_bad_min, rest_factors=1)
    coll.update(
        achievable_for_requested=bool(requested_ok and coll["achievable"]),
        bad_overlap_mm_requested=bad_overlap_mm,
        bad_overlap_mm_used=used,
        smallest_overlap_mm_caught=smallest_caught,
        e_c_zero_at_mm=[
            lv for lv in levels if all(r["e_c"] == 0 for r in coll_set if r["param"] == lv)
        ],
    )

    # --- min_depth: twice the deepest resting penetration (0.1 mm steps, at least 0.2 mm),
    # at most half the shallowest bad overlap
    d_rest_max = max(
        (r["depth_mm"] for st, rows in by_stage.items() if st != "exact" for r in rows),
        default=0.0,
    )
    d_bad_min = min(levels, default=1.0)
    min_depth_mm = min(max(0.2, math.ceil(2.0 * d_rest_max * 10 - 1e-9) / 10), d_bad_min / 2)

    def with_(section, **kw):
        return type(section)(**{**section.model_dump(), **kw})

    chosen_s = with_(cfg.stability, steepness=stab["steepness"], midpoint=stab["midpoint"])
    chosen_c = with_(cfg.collision, steepness=coll["steepness"], midpoint=coll["midpoint"])

    def p_table(s_cfg: StabilityConfig, c_cfg: CollisionConfig) -> dict:
        out = {}
        for st, rows in by_stage.items():
            pb, pc = _p_stability(rows, s_cfg), _p_collision(rows, c_cfg)
            out[f"resting@{st}"] = {
                "objects": len(rows),
                "P_B_min": float(pb.min()),
                "P_B_p1": float(np.percentile(pb, 1)),
                "P_B_p5": float(np.percentile(pb, 5)),
                "P_B_share_ok": float(np.mean(pb >= TARGET_REST)),
                "P_C_min": float(pc.min()),
                "P_C_share_ok": float(np.mean(pc >= TARGET_REST)),
            }
        for kind in BAD_KINDS:
            rows_k = [r for r in bad_rows if r["family"] == kind]
            for st in dict.fromkeys(r["stage"] for r in rows_k):
                for lv in sorted({r["param"] for r in rows_k}):
                    sr = [r for r in rows_k if r["param"] == lv and r["stage"] == st]
                    pb, pc = _p_stability(sr, s_cfg), _p_collision(sr, c_cfg)
                    # per scene: the product over its recorded objects (a pair counts once)
                    names = [r["scene"] for r in sr]
                    sb = {n: 1.0 for n in names}
                    sc = {n: 1.0 for n in names}
                    for n, b, c in zip(names, pb, pc, strict=True):
                        sb[n] *= float(b)
                        sc[n] *= float(c)
                    out[f"{kind}_{lv:g}@{st}"] = {
                        "scenes": len(sb),
                        "P_B_max": max(sb.values()),
                        "P_C_max": max(sc.values()),
                        "P_max": max(sb[n] * sc[n] for n in sb),
                    }
        return out

    return {
        "basis_stage": basis,
        "stages": stages,
        "resting": resting,
        "bad": bad_table,
        "stability_by_stage": stability_by_stage,
        "chosen": {
            "stability": stab,
            "collision": coll,
            "min_depth_m": min_depth_mm / 1000.0,
            "min_depth_basis": {
                "resting_depth_max_mm": d_rest_max,
                "smallest_bad_overlap_mm": d_bad_min,
            },
        },
        "probabilities": {
            "chosen": p_table(chosen_s, chosen_c),
            "current_defaults": p_table(cfg.stability, cfg.collision),
        },
        "current_defaults": {
            "stability": {"steepness": cfg.stability.steepness, "midpoint": cfg.stability.midpoint},
            "collision": {
                "steepness": cfg.collision.steepness,
                "midpoint": cfg.collision.midpoint,
                "min_depth_m": cfg.collision.min_depth,
            },
        },
    }


# --------------------------------------------------------------------------------------------
# entry points


@lru_cache(maxsize=2)
def _builtin(library_config_json: str) -> ObjectLibrary:
    """The built-in library for a library configuration (built once per process: ~1 s)."""
    return ObjectLibrary.builtin(LibraryConfig.model_validate_json(library_config_json))


def calibrate(
    config: SSPConfig | None = None,
    seeds: Iterable[int] = range(50),
    *,
    windows: Sequence[float] = (0.1, 0.25),
    families: Sequence[str] = RESTING_FAMILIES,
    tower_sizes: Sequence[int] = tuple(range(2, 11)),
    quick_bad: bool = False,
    noise_translation: float = 0.002,
    noise_rotation_deg: float = 2.0,
    bad_overlap_mm: float = 2.0,
    search: bool = True,
    library: ObjectLibrary | None = None,
    progress: Progress | None = None,
    on_total: Callable[[int], None] | None = None,
) -> dict:
    """Measure resting and bad scenes and choose the stability and collision constants.

    Args:
        config: the configuration measured (physics settings, ``collision.min_depth``); the
            search window ``search.settle_without_forces`` is added to ``windows``.
        seeds: noise and scene seeds of the resting scenes (one set of scenes per seed).
        windows: quasi-static windows without forces after which the scenes are measured, s.
        families: resting families (:data:`RESTING_FAMILIES`).
        tower_sizes: cube counts of the towers.
        quick_bad: one bad scene per kind and parameter (fast tests).
        noise_translation, noise_rotation_deg: the largest pose error of a resting object
            (m, deg).
        bad_overlap_mm: overlaps from this depth on must score ``P_C <= 0.05``.
        search: also relax every noisy resting scene with the search's full window
            (:meth:`ssp.search.Simulator.window`: data forces towards perfect segments, then
            the window without forces); stage ``"search"``.
        library: the built-in library to take the models from (default: built for
            ``config.library``, once per process).
        progress: called with each scene's name once it is measured.
        on_total: called once with the number of scenes.

    Returns:
        ``{"records": [...], "summary": {...}, ...}`` (see :func:`summarize`).
    """
    cfg = config or SSPConfig()
    seeds = [int(s) for s in seeds]
    search_window = float(cfg.search.settle_without_forces)
    windows = sorted({round(float(w), 6) for w in windows} | {round(search_window, 6)})
    lib = library if library is not None else _builtin(cfg.library.model_dump_json())
    cases = resting_cases(lib, seeds, families, tower_sizes) + bad_cases(lib, quick_bad)
    if on_total is not None:
        on_total(len(cases))
    noise = (float(noise_translation), float(noise_rotation_deg))
    records: list[dict] = []
    rejected: list[str] = []
    t0 = time.perf_counter()
    for case in cases:
        if case.cls == "resting":
            rows = _run_resting(case, cfg, windows, noise, search)
        else:
            rows = _run_bad(case, cfg, windows)
        if rows is None:
            rejected.append(case.name)
        for r in rows or ():
            r = {k: float(f"{v:.6g}") if isinstance(v, float) else v for k, v in r.items()}
            records.append(
                {
                    "scene": case.name,
                    "family": case.family,
                    "cls": case.cls,
                    "seed": case.seed,
                    "param": case.param,
                    **r,
                }
            )
        if progress is not None:
            progress(case.name)
    seconds = time.perf_counter() - t0
    import mujoco

    basis = "search" if search else _stage_name(search_window)
    summary = summarize(records, basis=basis, bad_overlap_mm=bad_overlap_mm, config=cfg)
    return {
        "protocol": "calibration",
        "ssp_version": __version__,
        "mujoco_version": mujoco.__version__,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
        },
        "settings": {
            "seeds": seeds,
            "windows_s": windows,
            "search_window_s": search_window,
            "timestep_s": cfg.physics.timestep,
            "families": list(families),
            "tower_sizes": list(tower_sizes),
            "noise_translation_m": noise[0],
            "noise_rotation_deg": noise[1],
            "ground_truth_settle_s": {"dynamic": GT_DYNAMIC_S, "quasi_static": GT_QUASI_STATIC_S},
            "min_depth_m": cfg.collision.min_depth,
            "targets": {"resting_at_least": TARGET_REST, "bad_at_most": TARGET_BAD},
            "bad_overlap_mm": bad_overlap_mm,
        },
        "scenes": len(cases),
        "rejected_scenes": rejected,
        "seconds": seconds,
        "summary": summary,
        "records": records,
    }


def write_report(result: dict, out_dir: Path | str) -> list[Path]:
    """Write ``out_dir/calibration.json`` and ``out_dir/calibration.png``; returns the paths.

    The plot: histograms of ``beta = max(beta_t, beta_R)`` and of ``e_C`` for the resting
    objects (the basis stage and the window without forces) against the bad ones at their set
    pose, log-scaled, with the chosen midpoints; below, the chosen and the default logistic
    curves.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "calibration.json"
    head = {k: v for k, v in result.items() if k != "records"}
    rows = ",\n  ".join(json.dumps(r, separators=(",", ":")) for r in result.get("records", []))
    # the summary indented, the per-object records one per line (valid JSON either way)
    json_path.write_text(
        json.dumps(head, indent=1)[:-2] + ',\n "records": [\n  ' + rows + "\n ]\n}\n"
    )

    s = result["summary"]
    basis = s["basis_stage"]
    nf = _stage_name(result["settings"]["search_window_s"])
    rec = result["records"]
    stab_bad = [r for r in rec if r["family"] in STABILITY_BAD and r["stage"] == "set"]
    coll_bad = [r for r in rec if r["family"] in COLLISION_BAD and r["stage"] == "set"]
    st, co = s["chosen"]["stability"], s["chosen"]["collision"]
    floor_b, floor_e = 1e-6, 1e-7
    shown = [basis] + ([nf] if nf != basis else [])

    fig, axs = plt.subplots(2, 2, figsize=(13, 8.5))
    ax = axs[0, 0]
    bins = np.logspace(-6, 1.2, 73)
    for k, stage in enumerate(shown):
        b = [_beta(r) for r in rec if r["cls"] == "resting" and r["stage"] == stage]
        label = "search window" if stage == "search" else f"{stage} without forces"
        ax.hist(
            np.maximum(b, floor_b),
            bins=bins,
            histtype="step",
            lw=1.5,
            color=f"C{k}",
            label=f"resting, {label} ({len(b)})",
        )
    for k, kind in enumerate(STABILITY_BAD):
        b = [_beta(r) for r in stab_bad if r["family"] == kind]
        ax.hist(
            np.maximum(b, floor_b),
            bins=bins,
            alpha=0.6,
            histtype="stepfilled",
            color=f"C{k + 3}",
            label=f"bad: {kind}, set pose ({len(b)})",
        )
    ax.axvline(st["midpoint"], color="k", ls="--", label=f"chosen a_B = {st['midpoint']:g}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("beta = max(beta_t, beta_R)   (values below 1e-6 drawn at 1e-6)")
    ax.set_ylabel("objects")
    ax.set_title("stability input")
    ax.legend(fontsize=7)

    ax = axs[0, 1]
    bins = np.logspace(-7, -0.5, 66)
    e = [r["e_c"] for r in rec if r["cls"] == "resting" and r["stage"] == basis]
    ax.hist(
        np.maximum(e, floor_e),
        bins=bins,
        histtype="step",
        lw=1.5,
        label=f"resting, {basis} ({len(e)})",
    )
    for k, lv in enumerate(sorted({r["param"] for r in coll_bad})):
        e = [r["e_c"] for r in coll_bad if r["param"] == lv]
        ax.hist(
            np.maximum(e, floor_e),
            bins=bins,
            alpha=0.6,
            histtype="stepfilled",
            color=f"C{k + 3}",
            label=f"overlap {lv:g} mm, set pose ({len(e)})",
        )
    ax.axvline(co["midpoint"], color="k", ls="--", label=f"chosen a_c = {co['midpoint']:g}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("e_C = d / diameter * overlap fraction   (0 drawn at 1e-7)")
    ax.set_ylabel("objects")
    ax.set_title("collision input")
    ax.legend(fontsize=7)

    def logistic(x, steep, mid):
        return 1.0 / (1.0 + np.exp(np.clip(steep * (x - mid), -500, 500)))

    ax = axs[1, 0]
    d = s["current_defaults"]["stability"]
    x = np.logspace(-4, 0.5, 400)
    ax.plot(
        x,
        logistic(x, st["steepness"], st["midpoint"]) ** 2,
        label=f"chosen s_B={st['steepness']:g}, a_B={st['midpoint']:g}",
    )
    ax.plot(
        x,
        logistic(x, d["steepness"], d["midpoint"]) ** 2,
        ls=":",
        label=f"defaults s_B={d['steepness']:g}, a_B={d['midpoint']:g}",
    )
    ax.axvspan(
        1e-4,
        st["rest_reference"],
        color="C0",
        alpha=0.15,
        label=f"resting ({basis}, {st['rest_basis']})",
    )
    ax.axvline(st["bad_reference"], color="C3", label="smallest bad beta")
    ax.axhline(TARGET_REST, color="grey", lw=0.5)
    ax.axhline(TARGET_BAD, color="grey", lw=0.5)
    ax.set_xscale("log")
    ax.set_xlabel("beta (both factors equal)")
    ax.set_ylabel("P_B")
    ax.legend(fontsize=7)

    ax = axs[1, 1]
    d = s["current_defaults"]["collision"]
    x = np.logspace(-6, -0.5, 400)
    ax.plot(
        x,
        logistic(x, co["steepness"], co["midpoint"]),
        label=f"chosen s_c={co['steepness']:g}, a_c={co['midpoint']:g}",
    )
    ax.plot(
        x,
        logistic(x, d["steepness"], d["midpoint"]),
        ls=":",
        label=f"defaults s_c={d['steepness']:g}, a_c={d['midpoint']:g}",
    )
    ax.axvline(
        co["bad_reference"],
        color="C3",
        label=f"smallest bad e_C (overlap >= {co['bad_overlap_mm_used']:g} mm)",
    )
    ax.axhline(TARGET_REST, color="grey", lw=0.5)
    ax.axhline(TARGET_BAD, color="grey", lw=0.5)
    ax.set_xscale("log")
    ax.set_xlabel("e_C")
    ax.set_ylabel("P_C")
    ax.legend(fontsize=7)
    fig.suptitle(
        f"ssp calibration (mujoco {result['mujoco_version']}, "
        f"{len(result['settings']['seeds'])} seeds, {result['scenes']} scenes)"
    )
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.07, top=0.92, hspace=0.3, wspace=0.18)
    png = out / "calibration.png"
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return [json_path, png]
