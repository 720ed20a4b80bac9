"""The scene parser: ``SceneParser.update(frame) -> SceneEstimate`` (DESIGN sections 1, 6).

:meth:`SceneParser.update` runs these stages, each in the module of its concept:

1. **Validate** the frame (:meth:`Frame.validate`); a bad frame raises :class:`FrameError` and
   leaves the parser's state untouched.
2. **Associate** hypotheses with known objects (:func:`ssp.temporal.associate`: instance ids,
   else a globally optimal assignment on class and pose distance measured at the centre of
   mass, with a gate of at most ``association_size_fraction`` of the class's median extent);
   one object per instance segment (:func:`ssp.temporal.one_object_per_segment`: the class
   whose hypotheses account for most of the segment's points, a known object's with a
   margin); the best ``k`` per object are kept; a new
   group whose segment an undetected object explains where it was is that object's duplicate
   (:func:`ssp.temporal.duplicates_of_undetected`).
3. **Segments** per object (:func:`ssp.segments.object_segments`).
4. **Verify** new objects (:func:`ssp.verification.verify_new`): one the data does not
   support at any of its hypotheses (not visible, its volume seen empty, or explaining almost
   nothing) is rejected before the search.
5. **Undetected objects** (:func:`ssp.retention.triage`): replaced, still visible, seen empty,
   hidden (ephemeral) or unseen.
6. **First guess and support graph**: every object at the pose among its previous pose and
   its hypotheses with the best terms that need no simulation (data fit and transition,
   :meth:`SceneScorer.unsimulated`), settled with data forces; support graph and layers
   (Alg. 2). An undetected object of which the camera saw nothing either way that holds up
   objects which would fall without it (:func:`ssp.retention.support_retained`) is
   **support-retained**; it and the objects seen empty are otherwise removed.
7. **Layered search** (Alg. 3, :func:`ssp.search.layered_search`) over the candidates: the
   frame's hypotheses, the previous pose, the current pose; then the ICP polish. An object
   unchanged since the previous frame that no change comes near keeps its previous pose
   untested (:func:`ssp.static.settled_objects`).
8. **Verify** the new objects again at their final poses (:func:`ssp.verification.check_new`);
   an object rejected there is left out unless it holds others up (then kept, with a warning).
9. **Transition modes**, symmetric snapping (the output orientation is the symmetric
   equivalent closest to the previous one), and **re-identification**: a new object where a
   known one of its class vanished this frame is that object, moved
   (:func:`ssp.temporal.reidentify`). Every object, removed object, rejected object and
   instance segment gets its reason; scene-level doubts become warnings. The state is
   committed.

When nothing changed (every known object is unchanged, :func:`ssp.static.is_unchanged`, and no
object appeared or vanished) step 7 is replaced by a settle of the previous scene
(``search.unchanged_shortcut``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np

from ssp.config import SSPConfig, TemporalConfig
from ssp.errors import InvalidPoseError, PhysicsError, SSPError, UnknownObjectError
from ssp.estimate import ObjectEstimate, Rejected, SceneEstimate, SupportEdge
from ssp.forces import SegmentField
from ssp.forces import load_kernels as load_force_kernels
from ssp.geometry import validate_pose
from ssp.library.library import ObjectLibrary
from ssp.library.model import ObjectInstance, ObjectModel
from ssp.library.symmetry import Symmetry
from ssp.physics import World
from ssp.polish import polish
from ssp.probability import pose_change
from ssp.registration import load_kernels as load_icp_kernels
from ssp.retention import REMOVABLE, Triage, support_retained, triage
from ssp.scene import Frame, FrameError, Hypothesis, TransitionMode
from ssp.scoring import SceneScore, SceneScorer
from ssp.search import Candidate, Simulator, layered_search
from ssp.segments import SegmentTrees, explained_fraction, object_segments
from ssp.static import is_unchanged, settle_moved, settled_objects
from ssp.support import GROUND
from ssp.temporal import (
    associate,
    association_gates,
    classify,
    duplicates_of_undetected,
    one_object_per_segment,
    reidentify,
    same_volume_test,
    snap_symmetric,
)
from ssp.timing import StageTimer
from ssp.verification import (
    Evidence,
    Verdict,
    data_fallbacks,
    evidence,
    held_up,
    may_hold_up,
    verify_and_place,
    verify_new,
)
from ssp.visibility import CameraView

__all__ = [
    "ObjectEstimate",
    "Rejected",
    "SceneEstimate",
    "SceneParser",
    "SupportEdge",
    "best_first_guess",
    "first_guess",
    "parse_sequence",
]

log = logging.getLogger(__name__)

#: A known object keeps its class on its segment unless another class accounts for this much
#: more of the segment's points (a fraction).
CLASS_MARGIN = 0.05

STATE_FORMAT = "ssp-scene-state"
STATE_VERSION = 1
#: Name of the ground in support edges.
TABLE = "table"


@dataclass
class _Known:
    """What the parser remembers of an object between frames."""

    class_name: str
    T_world_obj: np.ndarray
    ephemeral: bool = False
    fit: float = 0.0  # data fit c at T_world_obj in the frame that set it
    held: bool = False  # its data holds it where nothing in the scene does (data fallback)


def _report_moved(
    estimate: SceneEstimate, moved: Mapping[str, np.ndarray | None], gone: Mapping[str, _Known]
) -> SceneEstimate:
    """The estimate with :attr:`Frame.moved` said: a moved object that is still in the scene
    is ``perturbed``, with the reason; one that left is among the removed objects."""
    note = "moved by the caller (Frame.moved)"
    objects = tuple(
        replace(o, mode=TransitionMode.PERTURBED, reason=f"{o.reason}; {note}")
        if o.id in moved and o.mode == TransitionMode.STATIC
        else replace(o, reason=f"{o.reason}; {note}")
        if o.id in moved
        else o
        for o in estimate.objects
    )
    removed = estimate.removed + tuple(
        ObjectEstimate(
            oid,
            k.class_name,
            k.T_world_obj.copy(),
            TransitionMode.REMOVED,
            source="removed",
            reason="left the scene (Frame.moved: None)",
        )  # fmt: skip
        for oid, k in sorted(gone.items())
    )
    return replace(estimate, objects=objects, removed=removed)


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


# ------------------------------------------------------------------------------ the parser
class SceneParser:
    """Sequential scene parsing: feed frames in time order to :meth:`update`.

    Args:
        library: the object models (every hypothesis class must be in it).
        config: the method's constants (default ``SSPConfig()``).
        table: the world has a table plane at z = 0 (DESIGN section 3).
    """

    def __init__(
        self, library: ObjectLibrary, config: SSPConfig | None = None, *, table: bool = True
    ) -> None:
        self.library = library
        self.config = config if config is not None else SSPConfig()
        self.table = bool(table)
        self._known: dict[str, _Known] = {}
        self._counters: dict[str, int] = {}
        self._frame_index = 0
        self._last_stamp: float | None = None
        self._world: World | None = None
        self._world_key: tuple[tuple[str, str], ...] | None = None
        # the compiled data forces and the polish's ICP, loaded here rather than in a frame
        load_force_kernels()
        load_icp_kernels()

    def __repr__(self) -> str:
        return f"SceneParser({len(self._known)} objects, {self._frame_index} frames)"

    @property
    def objects(self) -> dict[str, tuple[str, np.ndarray]]:
        """Current scene: ``id -> (class_name, T_world_obj)`` (copies)."""
        return {k: (v.class_name, v.T_world_obj.copy()) for k, v in self._known.items()}

    def reset(self) -> None:
        """Forget every object (the next frame starts a new scene)."""
        self._known.clear()
        self._counters.clear()
        self._frame_index = 0
        self._last_stamp = None

    # -------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """JSON-ready snapshot of everything the next :meth:`update` depends on."""
        return {
            "format": STATE_FORMAT,
            "version": STATE_VERSION,
            "frame_index": self._frame_index,
            "last_stamp": self._last_stamp,
            "id_counters": dict(sorted(self._counters.items())),
            "objects": [
                {
                    "id": oid,
                    "class": k.class_name,
                    "T_world_obj": k.T_world_obj.tolist(),
                    "ephemeral": k.ephemeral,
                    "fit": k.fit,
                    "held": k.held,
                }
                for oid, k in sorted(self._known.items())
            ],
        }

    @classmethod
    def from_state(
        cls,
        library: ObjectLibrary,
        state: Mapping[str, Any],
        config: SSPConfig | None = None,
        *,
        table: bool = True,
    ) -> SceneParser:
        """A parser that continues from :meth:`state` (same library and config expected).

        Raises:
            SSPError: not a scene state, or an unsupported version.
            UnknownObjectError: a class missing from ``library``.
            InvalidPoseError: a pose that is not rigid.
        """
        if not isinstance(state, Mapping) or state.get("format") != STATE_FORMAT:
            raise SSPError(f"not an ssp scene state (expected format {STATE_FORMAT!r})")
        if state.get("version") != STATE_VERSION:
            raise SSPError(
                f"scene state version {state.get('version')!r} is not supported "
                f"(this ssp reads version {STATE_VERSION})"
            )
        parser = cls(library, config, table=table)
        try:
            parser._frame_index = int(state["frame_index"])
            stamp = state.get("last_stamp")
            parser._last_stamp = None if stamp is None else float(stamp)
            parser._counters = {str(k): int(v) for k, v in state.get("id_counters", {}).items()}
            for o in state["objects"]:
                cls_name = str(o["class"])
                if cls_name not in library:
                    raise UnknownObjectError(
                        f"scene state object {o['id']!r} has class {cls_name!r}, which is not in "
                        f"the library ({', '.join(library.names) or 'empty'})"
                    )
                T = validate_pose(np.asarray(o["T_world_obj"], dtype=float), f"object {o['id']}")
                parser._known[str(o["id"])] = _Known(
                    cls_name,
                    T,
                    bool(o.get("ephemeral")),
                    float(o.get("fit", 0.0)),
                    bool(o.get("held", False)),
                )
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InvalidPoseError | UnknownObjectError):
                raise
            raise SSPError(f"malformed scene state: {exc!r}") from exc
        return parser

    # -------------------------------------------------------------- helpers
    def _world_for(self, objects: Mapping[str, str]) -> World:
        key = tuple(sorted(objects.items()))
        if self._world is None or self._world_key != key:
            instances = [ObjectInstance(oid, self.library[c]) for oid, c in key]
            self._world = World(instances, table=self.table, config=self.config.physics)
            self._world_key = key
        return self._world

    def _id_factory(self, counters: dict[str, int], taken: set[str]):
        def new_id(class_name: str) -> str:
            while True:
                k = counters.get(class_name, 0)
                counters[class_name] = k + 1
                candidate = f"{class_name}_{k}"
                if candidate not in taken:
                    taken.add(candidate)
                    return candidate

        return new_id

    # -------------------------------------------------------------- update
    def update(self, frame: Frame) -> SceneEstimate:
        """Parse one frame; returns the scene estimate and advances the parser's state.

        Raises:
            FrameError: the frame is invalid (the state is unchanged).
            PhysicsError: the simulation failed beyond recovery (the state is unchanged).
        """
        timer = StageTimer()
        with timer("total"):
            frame = frame.validate(self.library)
            if self._last_stamp is not None and frame.stamp < self._last_stamp:
                raise FrameError(
                    f"frame stamp {frame.stamp} is earlier than the previous frame's "
                    f"({self._last_stamp}); frames must come in time order"
                )
            known_before = dict(self._known)
            gone = self._apply_moved(frame.moved or {})
            try:
                estimate, commit = self._update(frame, timer)
            except BaseException:
                self._known = known_before  # the state is that of the last good frame
                self._world, self._world_key = None, None  # never reuse a half-used world
                raise
        commit()
        if frame.moved:
            estimate = _report_moved(estimate, frame.moved, gone)
        return replace(estimate, timings=dict(timer.seconds))

    def _apply_moved(self, moved: Mapping[str, np.ndarray | None]) -> dict[str, _Known]:
        """Take :attr:`Frame.moved` into the remembered scene: a moved object's previous pose
        becomes the one it was put at; one that left the scene is forgotten (returned, for
        the report). FrameError for an id the parser does not know."""
        unknown = sorted(set(moved) - set(self._known))
        if unknown:
            raise FrameError(
                f"moved names objects not in the scene: {', '.join(unknown)} (known: "
                f"{', '.join(sorted(self._known)) or 'none'})"
            )
        gone: dict[str, _Known] = {}
        for oid, T in moved.items():
            if T is None:
                gone[oid] = self._known.pop(oid)
            else:
                self._known[oid] = _Known(self._known[oid].class_name, np.array(T, dtype=float))
        return gone

    def _associate(self, frame: Frame) -> _Association:
        """Stage 2: hypotheses grouped per object (module docstring)."""
        cfg = self.config
        previous = {oid: (k.class_name, k.T_world_obj) for oid, k in self._known.items()}
        counters = dict(self._counters)
        taken = set(previous) | {h.instance_id for h in frame.hypotheses if h.instance_id}
        groups = associate(
            frame.hypotheses,
            previous,
            {n: m.symmetry for n, m in self.library.items()},
            max_distance=association_gates(self.library, cfg.temporal),
            same_volume=same_volume_test(self.library, cfg.temporal.merge_overlap),
            new_id=self._id_factory(counters, taken),
            centres={n: m.center_of_mass for n, m in self.library.items()},
        )
        for oid, hyps in groups.items():
            known = self._known.get(oid)
            if known is not None and known.class_name != hyps[0].class_name:
                raise FrameError(
                    f"instance id {oid!r} is a {known.class_name!r} but this frame's "
                    f"hypothesis calls it a {hyps[0].class_name!r}"
                )
        k_max = cfg.search.hypotheses_per_object
        labels = None if frame.labels is None else np.asarray(frame.labels)
        # a scene point on the surface lies up to about one sample spacing from a sample
        radius = cfg.data.inlier_radius + cfg.library.surface_spacing

        def rank(oid: str, hyps: list[Hypothesis]) -> tuple:
            """Which class a segment is: the group that accounts for most of its points (a
            known object's with a margin: its class is not given up for a near tie)."""
            if labels is None or hyps[0].segment is None:
                return (oid in self._known, float(hyps[0].score))
            points = frame.points[labels == hyps[0].segment]
            model = self.library[hyps[0].class_name]
            best = max(
                explained_fraction(points, model, h.T_world_obj, radius) for h in hyps[:k_max]
            )
            return (best + (CLASS_MARGIN if oid in self._known else 0.0), float(hyps[0].score))

        groups, confused = one_object_per_segment(groups, rank)
        groups = {oid: hyps[:k_max] for oid, hyps in groups.items()}
        claimed: dict[str, int] = {}
        duplicates: dict[str, str] = {}
        if labels is not None:

            def explained(u: str, points: np.ndarray) -> float:
                k = self._known[u]
                return explained_fraction(points, self.library[k.class_name], k.T_world_obj, radius)

            groups, claimed, duplicates = duplicates_of_undetected(
                groups,
                previous,
                lambda seg: frame.points[labels == seg],
                explained,
                cfg.temporal.explained_fraction,
            )
            for oid, u in duplicates.items():
                log.info("new %s: its segment lies on %s where it was; a duplicate", oid, u)
        for oid, winner in confused.items():
            log.info("%s dropped: its segment is %s's (one object per segment)", oid, winner)
        return _Association(groups, counters, claimed, confused, duplicates)

    def _update(self, frame: Frame, timer: StageTimer):
        cfg = self.config
        lib = self.library

        with timer("association"):
            assoc = self._associate(frame)
        groups, claimed = assoc.groups, assoc.claimed
        classes = {oid: hyps[0].class_name for oid, hyps in groups.items()}
        classes.update({oid: k.class_name for oid, k in self._known.items() if oid not in groups})
        models: dict[str, ObjectModel] = {oid: lib[c] for oid, c in classes.items()}
        prev_pose = {oid: self._known[oid].T_world_obj for oid in self._known}

        # Provisional pose per detected object (segment vote, triage of undetected objects);
        # replaced by the first guess once the scorer can weigh the candidates.
        first = {
            oid: first_guess(
                hyps,
                prev_pose.get(oid),
                models[oid].symmetry,
                cfg.temporal,
                models[oid].center_of_mass,
            )  # fmt: skip
            for oid, hyps in groups.items()
        }
        with timer("segments"):
            cand_poses = {
                oid: [first[oid], *(h.T_world_obj for h in groups[oid])] for oid in groups
            }
            cand_poses.update({oid: [T] for oid, T in prev_pose.items() if oid not in groups})
            # the segment each object's hypotheses came from, and those undetected objects took
            segment_labels = {oid: hyps[0].segment for oid, hyps in groups.items()}
            segment_labels = {oid: s for oid, s in segment_labels.items() if s is not None}
            segment_labels.update(claimed)
            members: dict[str, int] = {}
            segments, owner = object_segments(
                frame,
                {oid: (models[oid], cand_poses[oid]) for oid in cand_poses},
                radius=cfg.forces.max_distance,
                table=self.table,
                labels=segment_labels,
                members=members,
                known=set(self._known),
            )
            view = None
            if frame.T_world_cam is not None:
                view = CameraView(
                    frame.points,
                    frame.T_world_cam,
                    labels=frame.labels,
                    depth_tolerance=cfg.temporal.depth_tolerance,
                )
        trees = SegmentTrees(segments)
        with timer("verification"):
            rejected = verify_new(
                [oid for oid in groups if oid not in self._known],
                groups, models, trees, owner, view, cfg,
            )  # fmt: skip
            for oid in rejected:
                del groups[oid], first[oid], classes[oid]
            missing = sorted(set(self._known) - set(groups))
            verdicts = triage(
                [oid for oid in missing if oid not in claimed],
                models, prev_pose, first, segments, owner, view, cfg,
            )  # fmt: skip
            verdicts.update(
                {
                    oid: Triage("visible", "undetected; its segment's points lie on it")
                    for oid in claimed
                }
            )
        detected = sorted(groups)
        removed = {oid for oid, v in verdicts.items() if v.state == "replaced"}
        present = [oid for oid in sorted(classes) if oid not in removed]
        with timer("world"):
            world = self._world_for({oid: classes[oid] for oid in present})
            ids = world.ids
            world.reset()  # a reused world must behave exactly as a new one (determinism)
            see = cfg.forces.visible_samples_only and frame.T_world_cam is not None
            cam = frame.T_world_cam[:3, 3] if see else None
            sample_filter = None
            if see and frame.labels is not None and owner:
                own = [owner.get(oid) for oid in ids]

                def sample_filter(k, pts, _normals):
                    if own[k] is None:
                        return np.ones(len(pts), dtype=bool)
                    return ~view.hidden_by_others(pts, own[k])

            # Data forces and fit: detected objects and undetected ones still seen.
            with_data = {oid for oid in ids if oid in groups or verdicts[oid].state == "visible"}
            fields = [
                SegmentField(segments[oid], cfg.forces.max_distance)
                if oid in with_data and len(segments[oid])
                else None
                for oid in ids
            ]
            sim = Simulator.for_world(
                world, fields, cfg, timer, camera_position=cam, sample_filter=sample_filter
            )
            scorer = SceneScorer(
                world,
                cfg,
                {oid: segments[oid] for oid in ids if oid in with_data},
                {oid: prev_pose.get(oid) for oid in ids},
                camera_position=cam,
                trees=trees,
            )

        static = {
            oid
            for oid in detected
            if oid in self._known
            and is_unchanged(
                scorer,
                world.index(oid),
                self._known[oid].T_world_obj,
                self._known[oid].fit,
                groups[oid],
                models[oid],
                cfg,
            )  # fmt: skip
        }
        unchanged = (
            cfg.search.unchanged_shortcut
            and bool(self._known)
            and not missing
            and set(detected) == set(self._known)
            and static == set(detected)
        )
        retained: dict[str, list[str]] = {}
        tested = 0
        chosen: dict[str, str] = {}
        if unchanged:
            world.set_poses({oid: prev_pose[oid] for oid in ids})
            if not cfg.forces.final_icp:
                sim.settle(cfg.search.final_settle, with_forces=True)
            chosen = {oid: "unchanged" for oid in ids}
        else:
            # First guess: the candidate that best fits the data and the previous pose. A
            # static object whose hidden part fits a wrong pose best thus starts where it was,
            # and the objects on it settle onto it: the search tests each object with the
            # objects it carries at their first-guess poses.
            settled = set()
            if cfg.search.skip_settled:
                settled = settled_objects(
                    static,
                    {
                        oid: [prev_pose[oid]]
                        if oid in static
                        else [*cand_poses[oid], *([prev_pose[oid]] if oid in prev_pose else [])]
                        for oid in ids
                    },
                    models,
                    cfg.search.reach,
                )
            for oid in detected:
                i = world.index(oid)
                if oid in settled:
                    first[oid] = prev_pose[oid]
                    continue
                first[oid] = best_first_guess(
                    groups[oid], prev_pose.get(oid), lambda T, i=i: scorer.unsimulated(i, T)
                )
            world.set_poses({oid: first.get(oid, prev_pose.get(oid)) for oid in ids})
            base = world.save_state()
            try:
                sim.settle(cfg.search.initial_settle, with_forces=True)
            except PhysicsError as exc:
                log.warning("first-guess settle failed (%s); using the unsettled guess", exc)
                world.restore_state(base)
            # an object the first-guess settle moved is not where it was any more (what held
            # it is gone or moved): it is searched after all
            settled -= settle_moved(
                {oid: (prev_pose[oid], world.get_pose(oid), models[oid]) for oid in settled}
            )
            score0 = scorer.evaluate(world, timer)
            graph0 = score0.graph
            retained = support_retained(
                world, graph0, [o for o, v in verdicts.items() if v.state == "unseen"], cfg
            )
            for oid in sorted(o for o, v in verdicts.items() if v.state in REMOVABLE):
                if oid not in retained:
                    world.set_enabled(oid, False)
                    removed.add(oid)
            index = {oid: i for i, oid in enumerate(ids)}
            gone = {index[oid] for oid in removed if oid in index}
            layers = [[i for i in layer if i not in gone] for layer in graph0.layers()]
            layers = [layer for layer in layers if layer]
            children = {
                i: [c for c in graph0.children(i) if c not in gone] for i in range(len(ids))
            }
            candidates: dict[str, list[Candidate]] = {}
            for oid in ids:
                # without retest_static, an unchanged object near a change tests only where
                # it was and its first guess (the best of that and its hypotheses by data fit
                # and transition)
                hyps = [] if oid in static and not cfg.search.retest_static else groups.get(oid, [])
                cands = [Candidate(h.T_world_obj, "hypothesis", h.score) for h in hyps]
                if oid in prev_pose and (cfg.search.previous_candidates or oid not in groups):
                    cands.append(Candidate(prev_pose[oid], "previous"))
                candidates[oid] = cands
            result = layered_search(
                world, sim, scorer, candidates, layers, children, timer,
                settled={index[oid] for oid in settled}, processes=cfg.search.processes,
            )  # fmt: skip
            score, chosen, tested = result.score, result.chosen, result.tested
            for oid in removed:
                if oid in index:
                    world.set_enabled(oid, False)
        if cfg.forces.final_icp:
            polish(world, sim, {oid: segments[oid] for oid in with_data}, cam, cfg, timer)
        if unchanged or cfg.forces.final_icp:
            score = scorer.evaluate(world, timer)
        # data wins over physics for objects new in this frame, or held by their data before:
        # an established object keeps its physically consistent pose
        may_fall_back = {oid for oid in groups if oid not in self._known or self._known[oid].held}
        fallbacks = data_fallbacks(score, scorer, {oid: groups[oid] for oid in may_fall_back}, cfg)
        if fallbacks:
            searched = {oid: world.get_pose(oid) for oid in fallbacks}
            world.set_poses({oid: T for oid, (T, _) in fallbacks.items()})
            moved = scorer.evaluate(world, timer)
            # data wins over physics only where it does not put one object into another
            clash = {
                oid
                for oid in fallbacks
                if moved.terms[world.index(oid), 1] < cfg.verification.fallback_collision
            }
            for oid in clash:
                world.set_pose(oid, searched[oid])
                del fallbacks[oid]
            score = scorer.evaluate(world, timer) if clash else moved
            chosen.update({oid: "hypothesis (data fallback)" for oid in fallbacks})

        with timer("verification"):
            final_verdicts, placed = verify_and_place(
                world, scorer, score, models, groups, trees, owner, view,
                set(prev_pose) | set(removed), self.config, timer,
            )  # fmt: skip
            if placed:
                score = scorer.evaluate(world, timer)
            final = {
                oid: evidence(
                    models[oid],
                    score.poses[world.index(oid)],
                    trees.tree(oid),
                    view,
                    cfg,
                    own_label=owner.get(oid),
                    segment_spacing=trees.spacing(oid),
                )  # fmt: skip
                for oid in ids
                if oid not in removed
            }
        return self._finish(
            frame,
            _Outcome(
                score=score,
                models=models,
                prev_pose=prev_pose,
                groups=groups,
                removed=removed,
                retained=retained,
                verdicts=verdicts,
                chosen=chosen,
                tested=tested,
                unchanged=unchanged,
                evidence=final,
                rejected=rejected,
                owner=owner,
                members=members,
                association=assoc,
                segments=segments,
                view=view,
                fallbacks={oid: note for oid, (_, note) in fallbacks.items()},
                final_verdicts=final_verdicts,
                placed=placed,
                rescore=partial(_rescore, world, scorer, timer),
            ),
        )

    # -------------------------------------------------------------- output
    def _finish(self, frame: Frame, out: _Outcome):
        """Stages 8-9: final verification, modes, re-identification, reasons, warnings."""
        cfg = self.config
        score, models, prev_pose = out.score, out.models, out.prev_pose
        ids = score.ids
        warnings: list[str] = [f"{oid}: {note}" for oid, note in sorted(out.fallbacks.items())]
        rejected = dict(out.rejected)
        reasons: dict[str, str] = {}
        evidences: dict[str, Evidence] = {}
        failed: dict[str, Verdict] = {}
        placed = dict(out.placed)  # in the scene's poses already
        for oid, verdict in out.final_verdicts.items():
            evidences[oid] = verdict.evidence
            if verdict.keep:
                reasons[oid] = verdict.reason
                if oid in placed:  # kept where its data puts it
                    warnings.append(f"{oid}: {verdict.reason}")
            else:
                failed[oid] = verdict
        # an unverified object stays if it holds up an object that stays (verified, known, or
        # itself kept so) and the camera does not see through it; unverified objects holding
        # up only each other, or only rejected ones, go together
        holds = held_up(
            [oid for oid, v in failed.items() if may_hold_up(v, cfg)],
            [oid for oid in ids if oid not in out.removed and oid not in failed | rejected.keys()],
            lambda oid: [ids[c] for c in score.graph.children(ids.index(oid))],
        )
        for oid, verdict in failed.items():
            i = ids.index(oid)
            if oid in holds:
                reasons[oid] = f"unverified ({verdict.reason}) but holds up {', '.join(holds[oid])}"
                warnings.append(f"{oid}: {reasons[oid]}")
            else:
                seg = out.groups[oid][0].segment if oid in out.groups else None
                why = verdict.reason
                on_it = [ids[c] for c in score.graph.children(i) if ids[c] not in out.removed]
                if on_it:
                    why += f" (what rests on it, {', '.join(on_it)}, does not keep it)"
                rejected[oid] = Rejected(
                    oid, models[oid].name, score.poses[i].copy(), why,
                    verdict.evidence.as_dict(), seg,
                )  # fmt: skip
                log.info("%s (%s) rejected at its final pose: %s", oid, models[oid].name,
                         why)  # fmt: skip
        gone = set(out.removed) | set(rejected)

        # a new object where a known one of its class just vanished is that object, moved;
        # so is one beside a known object that the depth contradicts (seen through): the known
        # object's pose was wrong, and the new one is where it really is
        vanished = {
            oid: (models[oid].name, prev_pose[oid])
            for oid in out.removed
            if out.verdicts.get(oid) is not None
            and out.verdicts[oid].state in ("replaced", "seen_empty")
        }
        contradicted = {
            oid: (models[oid].name, score.poses[ids.index(oid)])
            for oid in ids
            if oid in prev_pose and oid not in gone and out.evidence[oid].seen_empty(cfg)
        }
        added = {
            oid: (models[oid].name, placed.get(oid, score.poses[ids.index(oid)]))
            for oid in ids
            if oid not in gone and oid not in prev_pose
        }
        renamed = reidentify(
            {**vanished, **contradicted},
            added,
            {oid: models[oid].diameter for oid in contradicted},  # beside it, not elsewhere
        )
        old_of = dict(renamed)  # new id -> old id
        moved_away = set(renamed.values())
        superseded = moved_away & set(contradicted)  # their new pose replaces them
        gone |= superseded
        dropped = [oid for oid in ids if oid in gone and oid not in out.removed]
        if dropped:  # the output's terms and support without what is not in it
            score = out.rescore(dropped)

        objects: list[ObjectEstimate] = []
        known: dict[str, _Known] = {}
        for i, oid in enumerate(ids):
            if oid in gone:
                continue
            model = models[oid]
            T = placed.get(oid, score.poses[i])
            out_id = old_of.get(oid, oid)
            prev = prev_pose.get(out_id)
            if prev is not None:
                T = snap_symmetric(prev, T, model.symmetry)
            v = out.verdicts.get(oid)
            ephemeral = v is not None and v.state == "ephemeral"
            supports = bool(score.graph.children(i))
            retained = oid in out.retained or (ephemeral and supports)
            mode = classify(prev, T, model.symmetry, cfg.temporal, retained, model.center_of_mass)
            terms = score.object_terms(i)
            if oid in old_of and out_id in superseded:
                reason = (
                    f"found again where the depth puts it (re-identified: {oid} is {out_id}, "
                    "whose pose the camera saw through)"
                )
            elif oid in old_of:
                dist = np.linalg.norm(T[:3, 3] - prev[:3, 3])
                reason = f"moved {1000 * dist:.0f} mm (re-identified: {oid} is {out_id})"
            elif oid in out.retained:
                reason = f"support-retained: holds up {', '.join(out.retained[oid])}"
            elif v is not None:
                reason = v.reason
            elif oid in reasons:
                reason = reasons[oid]
            else:
                src = out.chosen.get(oid, "current")
                reason = f"detected; the search kept its {src} pose"
            ev = out.evidence.get(oid)
            if oid not in placed and ev is not None and ev.seen_empty(cfg):
                warnings.append(
                    f"{out_id}: the camera sees through {100 * ev.seen_through:.0f} % of it"
                )
            if terms.stability < cfg.verification.fall_stability:
                warnings.append(f"{out_id}: would fall (stability term {terms.stability:.1f})")
            objects.append(
                ObjectEstimate(
                    out_id,
                    model.name,
                    T,
                    mode,
                    ephemeral=ephemeral,
                    terms=terms,
                    source=out.chosen.get(oid, "current"),
                    fit=float(score.fit[i]),
                    reason=reason,
                    evidence=evidences[oid].as_dict() if oid in evidences else None,
                )
            )
            known[out_id] = _Known(
                model.name, T, ephemeral, float(score.fit[i]), held=oid in out.fallbacks
            )
        removed = tuple(
            ObjectEstimate(
                oid,
                models[oid].name,
                prev_pose[oid],
                TransitionMode.REMOVED,
                source="removed",
                reason=out.verdicts[oid].reason if oid in out.verdicts else "",
            )  # fmt: skip
            for oid in sorted(out.removed)
            if oid not in moved_away
        )
        support = []
        g = score.graph
        for a, b, f in zip(g.supporter, g.supported, g.edge_fraction, strict=True):
            if ids[b] in gone or (a != GROUND and ids[a] in gone):
                continue
            sup = TABLE if a == GROUND else old_of.get(ids[a], ids[a])
            support.append(SupportEdge(sup, old_of.get(ids[b], ids[b]), float(f)))
        segments = _segment_verdicts(
            frame, out.members, {o.id for o in objects}, old_of, rejected, out.association
        )
        estimate = SceneEstimate(
            stamp=frame.stamp,
            frame_index=self._frame_index,
            objects=tuple(objects),
            removed=removed,
            rejected=tuple(rejected[k] for k in sorted(rejected)),
            segments=segments,
            warnings=tuple(warnings),
            support=tuple(support),
            log_prob=float(sum(o.log_prob for o in objects)),
            hypotheses_tested=out.tested,
            unchanged=out.unchanged,
        )
        for w in warnings:
            log.warning("frame %d: %s", self._frame_index, w)
        counters = out.association.counters

        def commit() -> None:
            self._known = known
            self._counters = counters
            self._frame_index += 1
            self._last_stamp = frame.stamp

        return estimate, commit


def _rescore(world: World, scorer: SceneScorer, timer, drop: Sequence[str]) -> SceneScore:
    """The scene's score with the objects ``drop`` disabled (then enabled again)."""
    for oid in drop:
        world.set_enabled(oid, False)
    try:
        return scorer.evaluate(world, timer)
    finally:
        for oid in drop:
            world.set_enabled(oid, True)


def _segment_verdicts(
    frame: Frame,
    owner: Mapping[str, int],
    kept: set[str],
    old_of: Mapping[str, str],
    rejected: Mapping[str, Rejected],
    assoc: _Association,
) -> dict[int, str]:
    """Label -> what became of it: the object it is (``owner``: the label each object lies
    in), or why none (every label of the cloud that is not the table or background)."""
    if frame.labels is None:
        return {}
    held: dict[int, set[str]] = {}
    for oid, label in owner.items():
        out_id = old_of.get(oid, oid)
        if out_id in kept:
            held.setdefault(int(label), set()).add(out_id)
    out: dict[int, str] = {
        label: ("object " if len(ids) == 1 else "objects ") + ", ".join(sorted(ids))
        for label, ids in held.items()
    }
    said: dict[int, list[str]] = {}
    for r in sorted(rejected.values(), key=lambda r: r.id):
        # the segment its hypotheses came from, else the one it took (a cluster, a class mask)
        label = r.segment if r.segment is not None else owner.get(r.id)
        if label is not None and int(label) not in out:
            said.setdefault(int(label), []).append(f"rejected {r.class_name} {r.id}: {r.reason}")
    out.update({label: "; ".join(texts) for label, texts in said.items()})
    for label in np.unique(np.asarray(frame.labels)):
        if label >= 0 and int(label) not in out:
            out[int(label)] = "no object: no hypothesis was given for it"
    return dict(sorted(out.items()))


@dataclass
class _Association:
    """What stage 2 found: the groups per object id, the id counters after it, the segments
    undetected objects took, and the groups dropped (class confusions, duplicates)."""

    groups: dict[str, list[Hypothesis]]
    counters: dict[str, int]
    claimed: dict[str, int]
    confused: dict[str, str]
    duplicates: dict[str, str]


@dataclass
class _Outcome:
    """Everything the output stage needs from the frame's stages."""

    score: SceneScore
    models: Mapping[str, ObjectModel]
    prev_pose: Mapping[str, np.ndarray]
    groups: Mapping[str, list[Hypothesis]]
    removed: set[str]
    retained: Mapping[str, list[str]]
    verdicts: Mapping[str, Triage]
    chosen: Mapping[str, str]
    tested: int
    unchanged: bool
    evidence: Mapping[str, Evidence]
    rejected: Mapping[str, Rejected]
    owner: Mapping[str, int]
    #: the label each object lies in (instance segments and clusters alike)
    members: Mapping[str, int]
    association: _Association
    segments: Mapping[str, np.ndarray]
    view: CameraView | None
    fallbacks: Mapping[str, str]
    #: step 8's verdict on each new object, and those put at a hypothesis by it
    final_verdicts: Mapping[str, Verdict]
    placed: Mapping[str, np.ndarray]
    #: the scene scored again without some objects (those the output leaves out)
    rescore: Callable[[Sequence[str]], SceneScore]


def parse_sequence(
    parser: SceneParser, frames: Iterable[Frame]
) -> Iterator[tuple[int, SceneEstimate | Exception]]:
    """Feed ``frames`` to ``parser``; yields ``(index, estimate)`` or ``(index, error)``.

    A frame that fails is logged and skipped: the parser's state stays that of the last good
    frame, and the sequence goes on. Bad input and physics failures raise :class:`SSPError`
    (logged as a warning); any other exception is a bug, logged with its traceback as an error
    and yielded all the same, so one frame never ends the sequence. ``KeyboardInterrupt`` and
    ``SystemExit`` are not caught.
    """
    for i, frame in enumerate(frames):
        try:
            estimate = parser.update(frame)
        except SSPError as exc:
            log.warning("frame %d skipped: %s", i, exc)
            yield i, exc
        except Exception as exc:  # a bug: count it, keep its traceback, go on
            log.error("frame %d failed with an unexpected error", i, exc_info=exc)
            yield i, exc
        else:
            yield i, estimate
