"""Hypothesis evaluation: simulate a candidate scene (Alg. 1) and the layered search (Alg. 3).

:class:`Simulator` is ``SimulateWorld`` of Alg. 1: quasi-static steps under gravity, contacts and
the data-guiding forces (paper Eq. 13-14), then a window without the forces
so that what remains is what physics alone holds up. Wrenches are recomputed every
``force_refresh_every`` steps (their nearest-neighbour targets too) and held in between.

:func:`layered_search` is ``EvaluateHypotheses`` of Alg. 3, O(N k): objects are visited layer by
layer from the ground (support graph of the settled first guess, Alg. 2); each object's
candidates (frame hypotheses, its previous-frame pose, and its current pose, the incumbent) are
set in turn, its supported objects from the next layers are added back for the test (the
paper's ``AddChildOf``), the partial scene is simulated and scored, and the best *simulated*
state is kept. Because the incumbent is always among the candidates, keeping the best of each
object's tests is the same as keeping the best scene within the layer (DESIGN section 4: "global
within the layer"), and no test can make the partial scene worse than before it.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import PhysicsError
from ssp.forces import DataForces, SegmentField
from ssp.frame_context import Simulation
from ssp.geometry import hull_box, poses_within
from ssp.lanes import ForkLanes
from ssp.physics import World, WorldState
from ssp.retention import TriageState
from ssp.scoring import SceneScore, SceneScorer
from ssp.timing import StageTimer

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "Candidate",
    "CandidateSource",
    "SearchResult",
    "Simulator",
    "TestResult",
    "distinct_starts",
    "layered_search",
    "prepare_world",
    "search_scene",
]

log = logging.getLogger(__name__)

#: A candidate test's outcome: ``(total log-probability, or None when the simulation failed;
#: the state it ended in, or None; the error message, or None)``
TestResult = tuple[float | None, WorldState | None, str | None]


class CandidateSource(str, Enum):
    """Where the pose an object was given came from (:attr:`ssp.estimate.ObjectEstimate.source`);
    the value is its name in words (it compares equal to that string)."""

    #: one of the frame's hypotheses
    HYPOTHESIS = "hypothesis"
    #: its pose in the previous frame
    PREVIOUS = "previous"
    #: where the search found it (the incumbent)
    CURRENT = "current"
    #: its previous pose, untested (``ssp.static.settled_objects``)
    SETTLED = "previous (settled)"
    #: nothing changed: the previous scene, settled (``search.unchanged_shortcut``)
    UNCHANGED = "unchanged"
    #: put back at its best hypothesis (``ssp.verification.fall_back_to_data``)
    DATA_FALLBACK = "hypothesis (data fallback)"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True, eq=False)
class Candidate:
    """One pose to test for an object: ``T_world_obj`` (4x4, m) and where it came from, with
    the detector score if any."""

    T_world_obj: np.ndarray
    source: CandidateSource
    score: float = 0.0


class Simulator:
    """Alg. 1 ``SimulateWorld`` on one world with the frame's data forces.

    Args:
        world: the frame's world.
        forces: data forces in the world's id order.
        config: windows, force cadence, gravity.
        timer: stage timer (``forces``, ``stepping``).
    """

    def __init__(
        self, world: World, forces: DataForces, config: SSPConfig, timer: StageTimer
    ) -> None:
        self.world = world
        self.forces = forces
        self.config = config
        self.timer = timer
        self.every = int(config.search.force_refresh_every)
        self.steps = 0

    @classmethod
    def for_world(
        cls,
        world: World,
        fields,
        config: SSPConfig,
        timer: StageTimer,
        *,
        camera_position: np.ndarray | None = None,
        sample_filter=None,
    ) -> Simulator:
        """A simulator whose data forces pull each object of ``world`` toward its
        :class:`~ssp.forces.SegmentField` in ``fields`` (world id order; None: no pull), with
        the sample budget, cadence and seed of ``config``."""
        forces = DataForces(
            [world.model_of(i) for i in world.ids],
            fields,
            config=config.forces,
            max_points=config.search.force_samples,
            refresh_every=config.search.correspondence_every,
            masses=world.masses,
            seed=config.seed,
            camera_position=camera_position,
            sample_filter=sample_filter,
        )
        return cls(world, forces, config, timer)

    def _n_steps(self, seconds: float) -> int:
        return int(round(seconds / self.world.timestep))

    def settle(self, seconds: float, *, with_forces: bool) -> None:
        """Quasi-static steps for ``seconds`` of simulated time, with or without data forces.

        Raises :class:`PhysicsError` if the simulation fails (the caller restores a state).
        """
        world = self.world
        n = self._n_steps(seconds)
        if n <= 0:
            return
        if not with_forces:
            world.clear_wrenches()
            with self.timer("stepping"):
                self.steps += self._until_rest(n)
            return
        g = float(self.config.physics.gravity)
        done = 0
        world.set_friction_scale(self.config.forces.friction_scale)
        try:
            while done < n:
                with self.timer("forces"):
                    f, t = self.forces.compute(world.pose_array(), g, world.enabled)
                    world.apply_wrenches(f, t)
                k = min(self.every, n - done)
                with self.timer("stepping"):
                    world.step(k)
                done += k
        finally:
            world.set_friction_scale(1.0)
            world.clear_wrenches()
        self.steps += n

    def _until_rest(self, n: int) -> int:
        """Up to ``n`` steps without forces, in chunks of ``search.rest_check_every``; stops
        once a chunk moved no object more than ``search.rest_translation`` (m) and
        ``search.rest_rotation`` (rad) per step: the scene is at rest and further steps would
        leave it where it is. Returns the steps taken. (0 disables the check.)"""
        s = self.config.search
        chunk = int(s.rest_check_every)
        if chunk <= 0:
            self.world.step(n)
            return n
        done = 0
        tol_t = chunk * float(s.rest_translation)
        tol_q = chunk * float(s.rest_rotation) / 2.0  # a quaternion moves by about angle / 2
        while done < n:
            k = min(chunk, n - done)
            q0 = self.world.configuration()
            self.world.step(k)
            done += k
            d = np.abs(self.world.configuration() - q0)
            moved_t = d[:, :3].max(initial=0.0)
            if k == chunk and moved_t <= tol_t and d[:, 3:].max(initial=0.0) <= tol_q:
                break
        return done

    def window(self) -> None:
        """The per-hypothesis window: with forces, then without (``config.search``)."""
        s = self.config.search
        self.settle(s.settle_with_forces, with_forces=True)
        self.settle(s.settle_without_forces, with_forces=False)


@dataclass
class SearchResult:
    """Outcome of :func:`layered_search`.

    Attributes:
        score: the final scene's score (every object enabled, after the final settle).
        chosen: ``id -> source`` of the candidate kept for each object.
        tested: number of candidate simulations run.
        merged: candidates not simulated because they start where an earlier one of the same
            object did (:func:`distinct_starts`).
        failed: candidates whose simulation failed (physics error), as ``(id, source)``.
    """

    score: SceneScore
    chosen: dict[str, str]
    tested: int = 0
    merged: int = 0
    failed: list[tuple[str, str]] = field(default_factory=list)


def distinct_starts(tests: Sequence[Candidate], shift: float, turn: float) -> list[Candidate]:
    """``tests`` without those that start the same window as one before them: within
    ``shift`` (m) and ``turn`` (rad) of it (``search.same_start_translation`` /
    ``same_start_rotation``). A window corrects errors of several millimetres (the
    module's quasi-static stepping), so two starts a millimetre apart end where one of them
    does, and the test of the later one is a second simulation of the same outcome (an
    estimator's refined proposals often converge to nearly one pose, and an unmoved object's
    previous pose lies near its first guess). The earlier candidate is kept, as the search's
    ties keep the earlier one."""
    if shift <= 0.0 or turn <= 0.0:
        return list(tests)
    kept: list[Candidate] = []
    for c in tests:
        if not any(poses_within(k.T_world_obj, c.T_world_obj, shift, turn) for k in kept):
            kept.append(c)
    return kept


def _boxes(world: World, indices, poses=None) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned boxes ``(lo (m, 3), hi (m, 3))`` of objects ``indices`` (their
    convex hull vertices at their current poses, or at ``poses``)."""
    ids = world.ids
    lo, hi = [], []
    for j, k in enumerate(indices):
        T = world.get_pose(ids[k]) if poses is None else poses[j]
        b_lo, b_hi = hull_box(world.model_of(ids[k]).hull_vertices, [T])
        lo.append(b_lo)
        hi.append(b_hi)
    return np.array(lo).reshape(-1, 3), np.array(hi).reshape(-1, 3)


def _out_of_reach(
    world: World,
    i: int,
    poses: Sequence[np.ndarray],
    kids: Sequence[int],
    reach: float,
    parents: Mapping[int, Sequence[int]],
) -> list[int]:
    """Enabled objects whose box stays farther than ``reach`` (m, per axis) from object ``i``'s
    boxes at every candidate pose and from its children's boxes, and that support none of the
    objects that stay (``parents``: object -> its supporters in the first-guess graph; a
    tower's lower objects hold up the ones in reach however far they are)."""
    others = [int(k) for k in np.flatnonzero(world.enabled) if k != i and k not in kids]
    if not others:
        return []
    lo_i, hi_i = _boxes(world, [i] * len(poses), poses)
    lo_k, hi_k = _boxes(world, list(kids))
    lo = np.concatenate([lo_i, lo_k]) - reach
    hi = np.concatenate([hi_i, hi_k]) + reach
    lo_o, hi_o = _boxes(world, others)
    touch = np.all((lo_o[:, None] <= hi[None]) & (hi_o[:, None] >= lo[None]), axis=2).any(axis=1)
    far = {k for k, t in zip(others, touch, strict=True) if not t}
    stack = [i, *kids, *(k for k in others if k not in far)]
    while stack:  # keep every supporter, transitively, of an object that stays
        for p in parents.get(stack.pop(), ()):
            if p in far:
                far.discard(p)
                stack.append(p)
    return sorted(far)


def layered_search(
    world: World,
    sim: Simulator,
    scorer: SceneScorer,
    candidates: Mapping[str, Sequence[Candidate]],
    layers: Sequence[Sequence[int]],
    children: Mapping[int, Sequence[int]],
    timer: StageTimer,
    settled: Collection[int] = (),
    processes: int = 1,
) -> SearchResult:
    """Alg. 3 on ``world``, whose objects sit at their settled first guesses.

    Args:
        world: every object of the frame, enabled or not, at its first-guess pose.
        sim: the frame's simulator.
        scorer: the frame's scorer.
        candidates: ``id -> candidate poses`` (the current pose is always tested as well).
        layers: object indices by support layer (:meth:`SupportGraph.layers`).
        children: object index -> indices of the objects it supports (first-guess graph).
        timer: stage timer.
        settled: object indices that keep their current pose untested, in their layer
            (:func:`ssp.static.settled_objects`; ``chosen`` says ``"previous (settled)"``,
            :attr:`CandidateSource.SETTLED`).
        processes: test an object's candidates in this many processes at once
            (:class:`ssp.lanes.ForkLanes`); the choices are the same for any number.

    Returns:
        The final scene (all objects in ``layers`` enabled, settled ``config.search.final_settle``
        with forces) and the choice per object. The world is left in that state.
    """
    ids = world.ids
    reach = float(sim.config.search.reach)
    same = (sim.config.search.same_start_translation, sim.config.search.same_start_rotation)
    parents: dict[int, list[int]] = {}
    for p, kids_of_p in children.items():
        for c in kids_of_p:
            parents.setdefault(c, []).append(p)
    in_search = sorted({i for layer in layers for i in layer})
    for k in range(len(ids)):
        world.set_enabled(ids[k], False)
    chosen: dict[str, str] = {}
    tested = merged = 0
    failed: list[tuple[str, str]] = []

    def test(job: tuple[str, tuple[int, ...], np.ndarray], base: WorldState) -> TestResult:
        """One candidate ``(object id, children to add back, T_world_obj)`` from ``base``:
        its window, then the score (Alg. 3)."""
        oid, kids, T = job
        world.restore_state(base)
        for c in kids:
            world.set_enabled(ids[c], True)
        world.set_pose(oid, T)
        sim.forces.reset()
        try:
            sim.window()
        except PhysicsError as exc:
            return None, None, str(exc)
        return scorer.evaluate(world, timer).total, world.save_state(), None

    with ForkLanes(test, processes, timer) as lanes:
        for layer in layers:
            for i in layer:
                world.set_enabled(ids[i], True)
            for i in sorted(layer, key=lambda k: ids[k]):
                oid = ids[i]
                if i in settled:
                    chosen[oid] = CandidateSource.SETTLED
                    continue
                kids = [c for c in children.get(i, ()) if not world.is_enabled(ids[c])]
                current = Candidate(world.get_pose(oid), CandidateSource.CURRENT)
                every = [current, *candidates.get(oid, ())]
                tests = distinct_starts(every, *same)
                chosen[oid] = _test_candidates(world, i, tests, kids, reach, parents, lanes, failed)
                tested += len(tests)
                merged += len(every) - len(tests)
    for i in in_search:
        world.set_enabled(ids[i], True)
    score = _final_settle(world, sim, scorer, timer)
    return SearchResult(score=score, chosen=chosen, tested=tested, merged=merged, failed=failed)


def _test_candidates(
    world: World,
    i: int,
    tests: Sequence[Candidate],
    kids: Sequence[int],
    reach: float,
    parents: Mapping[int, list[int]],
    lanes: ForkLanes,
    failed: list[tuple[str, str]],
) -> CandidateSource:
    """Alg. 3's inner loop for object ``i``: each of its candidate ``tests`` simulated with its
    children ``kids`` added back, from the same state; the world is left in the best test's
    end state with the children set aside again. Returns the source of the best candidate
    (ties keep the earlier); failed simulations are appended to ``failed``."""
    ids = world.ids
    oid = ids[i]
    # Objects out of reach of every candidate (and of the children) that hold up none of the
    # others are set aside for this object's tests, so a test costs about the same in a scene
    # of 5 or 50 objects; the candidates are compared on the same set of objects, as the
    # scores require.
    far = _out_of_reach(world, i, [c.T_world_obj for c in tests], kids, reach, parents)
    for k in far:
        world.set_enabled(ids[k], False)
    base = world.save_state()
    kid_poses = {ids[c]: world.get_pose(ids[c]) for c in kids}
    results = lanes.run(base, [(oid, tuple(kids), c.T_world_obj) for c in tests])
    best_total, best_state, best_source = -np.inf, None, CandidateSource.CURRENT
    for cand, (total, state, error) in zip(tests, results, strict=True):
        if total is None:
            log.warning("candidate %s of %s failed in simulation: %s", cand.source, oid, error)
            failed.append((oid, cand.source))
            continue
        if total > best_total:  # ties keep the earlier candidate
            best_total, best_state, best_source = total, state, cand.source
    world.restore_state(best_state if best_state is not None else base)
    for kid, T in kid_poses.items():  # children are tested in their own layer
        world.set_pose(kid, T)
        world.set_enabled(kid, False)
    for k in far:
        world.set_enabled(ids[k], True)
    return best_source


def _final_settle(
    world: World, sim: Simulator, scorer: SceneScorer, timer: StageTimer
) -> SceneScore:
    """The searched scene settled ``search.final_settle`` with forces (kept as the search left
    it if that fails), and its score."""
    sim.forces.reset()
    chosen_state = world.save_state()
    try:
        sim.settle(sim.config.search.final_settle, with_forces=True)
    except PhysicsError as exc:  # pragma: no cover - the states before it were all stable
        log.warning("final settle failed (%s); keeping the scene as the search left it", exc)
        world.restore_state(chosen_state)
    return scorer.evaluate(world, timer)


# ------------------------------------------------------------------ the parser's stages
def prepare_world(ctx: FrameContext) -> None:
    """Stage *world*: the frame's physics world (every object not removed, reset so that a
    reused world behaves exactly as a new one), its data forces (detected objects and
    undetected ones still seen; only the samples the camera could see when
    ``forces.visible_samples_only``, and not those other objects hide) and its scorer.

    Sets ``simulation``.
    """
    cfg, frame, segments, owner, view = ctx.config, ctx.frame, ctx.segments, ctx.owner, ctx.view
    present = [oid for oid in sorted(ctx.classes) if oid not in ctx.removed]
    world = ctx.world_for({oid: ctx.classes[oid] for oid in present})
    ids = world.ids
    world.reset()  # a reused world must behave exactly as a new one (determinism)
    see = cfg.forces.visible_samples_only and frame.T_world_cam is not None
    cam = frame.T_world_cam[:3, 3] if see and frame.T_world_cam is not None else None
    sample_filter = None
    if see and frame.labels is not None and owner and view is not None:
        own = [owner.get(oid) for oid in ids]
        hiding = view

        def sample_filter(k: int, pts: np.ndarray, _normals: np.ndarray) -> np.ndarray:
            label = own[k]
            if label is None:
                return np.ones(len(pts), dtype=bool)
            return ~hiding.hidden_by_others(pts, label)

    # data forces and fit: detected objects and undetected ones still seen
    with_data = {
        oid for oid in ids if oid in ctx.groups or ctx.verdicts[oid].state == TriageState.VISIBLE
    }
    fields = [
        SegmentField(segments[oid], cfg.forces.max_distance)
        if oid in with_data and len(segments[oid])
        else None
        for oid in ids
    ]
    simulator = Simulator.for_world(
        world, fields, cfg, ctx.timer, camera_position=cam, sample_filter=sample_filter
    )
    scorer = SceneScorer(
        world,
        cfg,
        {oid: segments[oid] for oid in ids if oid in with_data},
        {oid: ctx.prev_pose.get(oid) for oid in ids},
        camera_position=cam,
        trees=ctx.segment_trees,
    )
    ctx.simulation = Simulation(world, simulator, scorer, with_data, cam)


def search_scene(ctx: FrameContext) -> None:
    """Stage *search* (not run when nothing changed): :func:`layered_search` over the layers
    of the settled first-guess scene's support graph (Alg. 2), without the removed objects;
    each object's candidates are its hypotheses (none for a static object unless
    ``search.retest_static``) and its previous pose (``search.previous_candidates``, or when
    undetected). The removed objects stay disabled.

    Sets ``score``, ``chosen`` and ``tested``.
    """
    cfg, sim, prev_pose = ctx.config, ctx.sim, ctx.prev_pose
    world, ids = sim.world, sim.world.ids
    assert ctx.first_score is not None, "after the first guess"
    graph0 = ctx.first_score.graph
    index = {oid: i for i, oid in enumerate(ids)}
    gone = {index[oid] for oid in ctx.removed if oid in index}
    layers = [[i for i in layer if i not in gone] for layer in graph0.layers()]
    layers = [layer for layer in layers if layer]
    children = {i: [c for c in graph0.children(i) if c not in gone] for i in range(len(ids))}
    candidates: dict[str, list[Candidate]] = {}
    for oid in ids:
        # without retest_static, an unchanged object near a change tests only where it was
        # and its first guess (the best of that and its hypotheses by data fit and transition)
        static = oid in ctx.static and not cfg.search.retest_static
        hyps = [] if static else ctx.groups.get(oid, [])
        cands = [Candidate(h.T_world_obj, CandidateSource.HYPOTHESIS, h.score) for h in hyps]
        if oid in prev_pose and (cfg.search.previous_candidates or oid not in ctx.groups):
            cands.append(Candidate(prev_pose[oid], CandidateSource.PREVIOUS))
        candidates[oid] = cands
    result = layered_search(
        world, sim.simulator, sim.scorer, candidates, layers, children, ctx.timer,
        settled={index[oid] for oid in ctx.settled}, processes=cfg.search.processes,
    )  # fmt: skip
    ctx.score, ctx.chosen, ctx.tested = result.score, result.chosen, result.tested
    for oid in ctx.removed:
        if oid in index:
            world.set_enabled(oid, False)
