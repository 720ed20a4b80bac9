"""The scene parser: ``SceneParser.update(frame) -> SceneEstimate`` (DESIGN section 1).

One frame, in order (paper sections IV-V; DESIGN section 4):

1. **Validate** the frame (:meth:`Frame.validate`); a bad frame raises :class:`FrameError` and
   leaves the parser's state untouched.
2. **Associate** hypotheses with known objects (:func:`ssp.temporal.associate`: instance ids,
   else a globally optimal assignment on class and pose distance, with a gate of at most
   ``association_size_fraction`` of the class's smallest extent). The best ``k`` per object
   are kept. A new group whose segment an undetected object explains where it was is that
   object's duplicate and is dropped (``temporal.explained_fraction``).
3. **Segments** per object (:func:`ssp.segments.object_segments`) and the data forces.
4. **Undetected objects** (known, no hypothesis this frame): *replaced* (another object's best
   hypothesis fills ``replaced_overlap`` of its volume) -> removed; *still visible* (data fit at
   its old pose >= ``visible_fit``) -> kept; *seen through* (the camera sees depth behind its
   surface: its volume is empty) -> removed; *occluded* (its surface lies behind observed
   depth) -> kept as **ephemeral**; otherwise a removal candidate.
5. **First guess and support graph**: every object at the pose among its previous pose and
   its hypotheses with the best terms that need no simulation (data fit and transition,
   :meth:`SceneScorer.unsimulated`), settled with data forces; support graph and layers
   (Alg. 2). A removal candidate that carries objects which move without it is
   **support-retained**; the others are removed.
6. **Layered search** (Alg. 3, :func:`ssp.search.layered_search`) over the candidates: the
   frame's hypotheses, the previous pose, the current pose.
7. **Transition modes** and symmetric snapping (the output orientation is the symmetric
   equivalent closest to the previous one), then the state is committed.

When nothing changed (every known object has a hypothesis within the static thresholds of its
previous pose, no object appeared or vanished) step 6 is replaced by a settle of the previous
scene (``search.unchanged_shortcut``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ssp.config import SSPConfig, TemporalConfig
from ssp.errors import InvalidPoseError, PhysicsError, SSPError, UnknownObjectError
from ssp.forces import SegmentField
from ssp.geometry import transform_points, validate_pose
from ssp.library.library import ObjectLibrary
from ssp.library.model import ObjectInstance, ObjectModel
from ssp.library.symmetry import Symmetry
from ssp.overlap import overlap_fractions
from ssp.physics import World
from ssp.probability import ObjectTerms, data_fit_fraction, pose_change
from ssp.registration import icp_refine
from ssp.scene import Frame, FrameError, Hypothesis, TransitionMode
from ssp.scoring import SceneScore, SceneScorer
from ssp.search import Candidate, Simulator, layered_search
from ssp.segments import explained_fraction, object_segments
from ssp.support import GROUND
from ssp.temporal import (
    associate,
    association_gates,
    classify,
    same_volume_test,
    snap_symmetric,
)
from ssp.timing import StageTimer
from ssp.visibility import CameraView

__all__ = [
    "ObjectEstimate",
    "SceneEstimate",
    "SceneParser",
    "SupportEdge",
    "best_first_guess",
    "first_guess",
    "parse_sequence",
]

log = logging.getLogger(__name__)

STATE_FORMAT = "ssp-scene-state"
STATE_VERSION = 1
#: Name of the ground in support edges.
TABLE = "table"


# ------------------------------------------------------------------------------ results
@dataclass(frozen=True, eq=False)
class ObjectEstimate:
    """One object of a :class:`SceneEstimate`.

    Attributes:
        id: instance id (stable across frames).
        class_name: model name in the library.
        T_world_obj: (4, 4) pose, m (for removed objects: the last known pose).
        mode: transition mode since the previous frame.
        ephemeral: kept although undetected, because the camera could not see it.
        terms: the five log-probability terms (None for removed objects).
        source: which candidate the search kept (``hypothesis``, ``previous``, ``current``,
            ``unchanged``, ``retained``), or ``removed``.
        fit: data fit fraction c at the output pose (0..1).
    """

    id: str
    class_name: str
    T_world_obj: np.ndarray
    mode: TransitionMode
    ephemeral: bool = False
    terms: ObjectTerms | None = None
    source: str = ""
    fit: float = 0.0

    @property
    def log_prob(self) -> float:
        """Sum of the terms (``-inf`` for a removed object)."""
        return self.terms.total if self.terms is not None else -math.inf

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (pose as a nested list)."""
        return {
            "id": self.id,
            "class": self.class_name,
            "T_world_obj": np.asarray(self.T_world_obj).tolist(),
            "mode": str(self.mode),
            "ephemeral": self.ephemeral,
            "terms": self.terms.as_dict() if self.terms is not None else None,
            "log_prob": self.log_prob if self.terms is not None else None,
            "source": self.source,
            "fit": self.fit,
        }


@dataclass(frozen=True)
class SupportEdge:
    """``supporter`` (an id, or ``"table"``) carries ``fraction`` of ``supported``'s weight."""

    supporter: str
    supported: str
    fraction: float


@dataclass(frozen=True, eq=False)
class SceneEstimate:
    """The parser's answer for one frame.

    Attributes:
        stamp: the frame's time stamp, s.
        frame_index: 0-based count of frames this parser accepted.
        objects: the objects in the scene, by id.
        removed: objects removed in this frame (mode ``REMOVED``, last known pose).
        support: support edges with the fraction of the supported object's weight.
        log_prob: ``log Pr(s | C, D)``, the sum of every object's terms.
        timings: wall seconds per stage (``association``, ``segments``, ``world``,
            ``forces``, ``stepping``, ``contacts``, ``scoring``, ``total``).
        hypotheses_tested: candidate simulations run by the search.
        unchanged: the frame took the unchanged-scene shortcut.
    """

    stamp: float
    frame_index: int
    objects: tuple[ObjectEstimate, ...]
    removed: tuple[ObjectEstimate, ...] = ()
    support: tuple[SupportEdge, ...] = ()
    log_prob: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    hypotheses_tested: int = 0
    unchanged: bool = False

    def __getitem__(self, oid: str) -> ObjectEstimate:
        for o in self.objects:
            if o.id == oid:
                return o
        raise KeyError(oid)

    def __contains__(self, oid: object) -> bool:
        return any(o.id == oid for o in self.objects)

    def __len__(self) -> int:
        return len(self.objects)

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(o.id for o in self.objects)

    def poses(self) -> dict[str, np.ndarray]:
        """``id -> T_world_obj`` of the objects in the scene."""
        return {o.id: o.T_world_obj for o in self.objects}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of the whole estimate."""
        return {
            "stamp": self.stamp,
            "frame_index": self.frame_index,
            "log_prob": self.log_prob,
            "objects": [o.to_dict() for o in self.objects],
            "removed": [o.to_dict() for o in self.removed],
            "support": [
                {"supporter": e.supporter, "supported": e.supported, "fraction": e.fraction}
                for e in self.support
            ],
            "timings": dict(self.timings),
            "hypotheses_tested": self.hypotheses_tested,
            "unchanged": self.unchanged,
        }


@dataclass
class _Known:
    """What the parser remembers of an object between frames."""

    class_name: str
    T_world_obj: np.ndarray
    ephemeral: bool = False
    fit: float = 0.0  # data fit c at T_world_obj in the frame that set it


def first_guess(
    hypotheses: Sequence[Hypothesis],
    T_prev: np.ndarray | None,
    symmetry: Symmetry,
    config: TemporalConfig,
) -> np.ndarray:
    """An object's provisional pose (4x4, m), before its segment is known: its previous pose
    ``T_prev`` when one of its ``hypotheses`` (best first) lies within the static thresholds of
    it (symmetry-aware), else its best hypothesis. It votes for the object's segment label and
    is the pose the undetected-object triage tests against; the first-guess scene then takes,
    per object, the best of this pose and the hypotheses by data fit and transition."""
    if T_prev is not None:
        for h in hypotheses:
            dt, dth = pose_change(T_prev, h.T_world_obj, symmetry)
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
                    cls_name, T, bool(o.get("ephemeral")), float(o.get("fit", 0.0))
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
            try:
                estimate, commit = self._update(frame, timer)
            except BaseException:
                self._world, self._world_key = None, None  # never reuse a half-used world
                raise
        commit()
        return _with_timings(estimate, timer)

    def _update(self, frame: Frame, timer: StageTimer):
        cfg = self.config
        lib = self.library
        k_max = cfg.search.hypotheses_per_object

        with timer("association"):
            previous = {oid: (k.class_name, k.T_world_obj) for oid, k in self._known.items()}
            counters = dict(self._counters)
            taken = set(previous) | {h.instance_id for h in frame.hypotheses if h.instance_id}
            groups = associate(
                frame.hypotheses,
                previous,
                {n: m.symmetry for n, m in lib.items()},
                max_distance=association_gates(self.library, cfg.temporal),
                same_volume=same_volume_test(self.library, cfg.temporal.merge_overlap),
                new_id=self._id_factory(counters, taken),
            )
            for oid, hyps in groups.items():
                known = self._known.get(oid)
                if known is not None and known.class_name != hyps[0].class_name:
                    raise FrameError(
                        f"instance id {oid!r} is a {known.class_name!r} but this frame's "
                        f"hypothesis calls it a {hyps[0].class_name!r}"
                    )
            groups = {oid: hyps[:k_max] for oid, hyps in groups.items()}
            groups, claimed = self._explained_by_undetected(frame, groups)
            detected = sorted(groups)
            missing = sorted(set(self._known) - set(groups))

        classes = {oid: groups[oid][0].class_name for oid in detected}
        classes.update({oid: self._known[oid].class_name for oid in missing})
        models: dict[str, ObjectModel] = {oid: lib[c] for oid, c in classes.items()}
        prev_pose = {oid: self._known[oid].T_world_obj for oid in self._known}

        # Provisional pose per detected object (segment vote, triage of undetected objects);
        # replaced by the first guess once the scorer can weigh the candidates.
        first = {
            oid: first_guess(groups[oid], prev_pose.get(oid), models[oid].symmetry, cfg.temporal)
            for oid in detected
        }

        with timer("segments"):
            cand_poses = {
                oid: [first[oid], *(h.T_world_obj for h in groups[oid])] for oid in detected
            }
            cand_poses.update({oid: [prev_pose[oid]] for oid in missing})
            # the segment each object's hypotheses came from, and those undetected objects took
            segment_labels = {oid: groups[oid][0].segment for oid in detected}
            segment_labels = {oid: s for oid, s in segment_labels.items() if s is not None}
            segment_labels.update(claimed)
            segments, owner = object_segments(
                frame,
                {oid: (models[oid], cand_poses[oid]) for oid in cand_poses},
                radius=cfg.forces.max_distance,
                table=self.table,
                labels=segment_labels,
            )
            view = None
            if frame.T_world_cam is not None:
                view = CameraView(
                    frame.points,
                    frame.T_world_cam,
                    labels=frame.labels,
                    depth_tolerance=cfg.temporal.depth_tolerance,
                )
            verdicts = self._triage_missing(
                view,
                [oid for oid in missing if oid not in claimed],
                models,
                prev_pose,
                first,
                segments,
            )
            verdicts.update({oid: "visible" for oid in claimed})

        removed = {oid for oid, v in verdicts.items() if v == "removed"}
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
            with_data = {oid for oid in ids if oid in groups or verdicts.get(oid) == "visible"}
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
            )

        unchanged = (
            cfg.search.unchanged_shortcut
            and bool(self._known)
            and not missing
            and set(detected) == set(self._known)
            and all(
                self._unchanged(scorer, world.index(oid), self._known[oid], groups[oid])
                for oid in detected
            )
        )
        retained: set[str] = set()
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
            for oid in detected:
                i = world.index(oid)
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
            score0 = scorer.evaluate(world, timer)
            graph0 = score0.graph
            undecided = [oid for oid, v in verdicts.items() if v == "candidate"]
            for oid in undecided:
                if self._carries_load(world, sim, graph0, oid):
                    retained.add(oid)
                else:
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
                cands = [
                    Candidate(h.T_world_obj, "hypothesis", h.score) for h in groups.get(oid, [])
                ]
                if oid in prev_pose and (cfg.search.previous_candidates or oid not in groups):
                    cands.append(Candidate(prev_pose[oid], "previous"))
                candidates[oid] = cands
            result = layered_search(world, sim, scorer, candidates, layers, children, timer)
            score, chosen, tested = result.score, result.chosen, result.tested
            for oid in removed:
                if oid in index:
                    world.set_enabled(oid, False)
        if cfg.forces.final_icp:
            self._polish(world, sim, {oid: segments[oid] for oid in with_data}, cam, timer)
        if unchanged or cfg.forces.final_icp:
            score = scorer.evaluate(world, timer)

        return self._finish(
            frame,
            score,
            models,
            prev_pose,
            removed,
            retained,
            verdicts,
            chosen,
            tested,
            unchanged,
            counters,
        )

    def _explained_by_undetected(
        self, frame: Frame, groups: dict[str, list[Hypothesis]]
    ) -> tuple[dict[str, list[Hypothesis]], dict[str, int]]:
        """Drop the new objects whose hypotheses duplicate an undetected object.

        A new hypothesis group (no known object took it) estimated from segment ``s`` of
        ``frame.labels`` is the same object as an undetected known one when that object's
        previous pose explains at least ``temporal.explained_fraction`` of the points of ``s``
        (:func:`ssp.segments.explained_fraction`, within the data fit's inlier radius plus
        the surface-sample spacing): typically a mostly hidden object for which the estimator
        proposed only a wrong class. The group is dropped, and the undetected object takes the
        segment and counts as still visible (its data forces hold it where it is seen).

        Returns:
            the remaining groups, and ``undetected id -> label`` of the segments taken.
        """
        t = self.config.temporal
        undetected = sorted(set(self._known) - set(groups))
        if frame.labels is None or t.explained_fraction >= 1 or not undetected:
            return groups, {}
        labels = np.asarray(frame.labels)
        # a scene point on the surface lies up to about one sample spacing from a sample
        radius = self.config.data.inlier_radius + self.config.library.surface_spacing
        kept = dict(groups)
        claimed: dict[str, int] = {}
        for oid in sorted(groups):
            seg = groups[oid][0].segment
            if oid in self._known or seg is None:
                continue
            points = frame.points[labels == seg]
            best, best_fraction = None, t.explained_fraction
            for u in undetected:
                if claimed.get(u, seg) != seg:
                    continue
                known = self._known[u]
                f = explained_fraction(
                    points,
                    self.library[known.class_name],
                    known.T_world_obj,
                    radius,
                )
                if f >= best_fraction:
                    best, best_fraction = u, f
            if best is not None:
                log.info(
                    "new %s (segment %d): %.0f %% of its points lie on %s where it was; "
                    "a duplicate, dropped",
                    oid,
                    seg,
                    100 * best_fraction,
                    best,
                )
                del kept[oid]
                claimed[best] = seg
        return kept, claimed

    def _unchanged(self, scorer: SceneScorer, i: int, known: _Known, hyps) -> bool:
        """Is object ``i`` where it was? Its hypotheses agree (their per-axis median position
        lies within the static threshold of the previous pose) and the previous pose fits this
        frame's data about as well as it fitted the frame that set it
        (``c_now >= ratio c_then - tolerance``)."""
        s = self.config.search
        cfg_t = self.config.temporal
        centre = np.median([h.T_world_obj[:3, 3] for h in hyps], axis=0)  # per-axis median
        if np.linalg.norm(centre - known.T_world_obj[:3, 3]) >= cfg_t.static_translation:
            return False
        c_now = scorer.fit_fraction(i, known.T_world_obj)
        return c_now >= s.unchanged_fit_ratio * known.fit - s.unchanged_fit_tolerance

    def _polish(
        self,
        world: World,
        sim: Simulator,
        segments: Mapping[str, np.ndarray],
        camera_position: np.ndarray | None,
        timer: StageTimer,
    ) -> None:
        """Pull every enabled object with data toward its ICP pose (``forces.final_icp``) for
        ``search.final_settle`` s, then ``search.settle_without_forces`` s without forces.

        ICP alone is precise but knows no physics (it floats and interpenetrates objects);
        the data forces alone are physical but converge slowly. A spring toward the ICP pose
        inside the simulation gets both. ICP results that jump more than 2 cm or 20 degrees
        are ignored (a wrong local minimum), as are segments with fewer than 30 points.
        """
        cfg = self.config
        forces = sim.forces
        with timer("icp"):
            for oid, seg in segments.items():
                if not world.is_enabled(oid) or len(seg) < 30:
                    continue
                k = world.index(oid)
                T = world.get_pose(oid)
                T_icp = icp_refine(
                    world.model_of(oid),
                    T,
                    seg,
                    camera_position,
                    max_distance=cfg.forces.icp_max_distance,
                )
                dt, dth = pose_change(T, T_icp)
                if dt < 0.02 and dth < math.radians(20.0):
                    forces.set_pose_target(k, T_icp)
        forces.reset()
        state = world.save_state()
        try:
            sim.settle(cfg.search.final_settle, with_forces=True)
            sim.settle(cfg.search.settle_without_forces, with_forces=False)
        except PhysicsError as exc:  # pragma: no cover - a settled scene pulled a little
            log.warning("final ICP settle failed (%s); keeping the searched scene", exc)
            world.restore_state(state)
        for k in range(len(world.ids)):
            forces.set_pose_target(k, None)

    # -------------------------------------------------------------- undetected objects
    def _triage_missing(
        self,
        view: CameraView | None,
        missing: list[str],
        models: Mapping[str, ObjectModel],
        prev_pose: Mapping[str, np.ndarray],
        first: Mapping[str, np.ndarray],
        segments: Mapping[str, np.ndarray],
    ) -> dict[str, str]:
        """Verdict per undetected object, in the paper's order (section V-C): ``removed``
        (another object's best hypothesis fills its volume), ``visible`` (still fits the data:
        kept), ``ephemeral`` (hidden behind observed depth: kept) or ``candidate``: removed
        unless objects it supports move without it (support-retained), which is decided after
        the first settle. Physics wins over a contradictory view: an object seen through but
        carrying load is retained (and the contradiction logged)."""
        t = self.config.temporal
        verdicts: dict[str, str] = {}
        if not missing:
            return verdicts
        det_ids = sorted(first)
        for oid in missing:
            model, T = models[oid], prev_pose[oid]
            if det_ids:
                members = [oid, *det_ids]
                frac = overlap_fractions(
                    [models[m] for m in members],
                    np.stack([T, *(first[m] for m in det_ids)]),
                    table=False,
                    pairs=[(0, j) for j in range(1, len(members))],
                )[0]
                if frac >= t.replaced_overlap:
                    log.info("%s: its volume is taken by another object: removed", oid)
                    verdicts[oid] = "removed"
                    continue
            seg = segments.get(oid)
            c = 0.0
            if seg is not None and len(seg):
                c = data_fit_fraction(
                    transform_points(T, model.surface_points), seg, self.config.data.inlier_radius
                )
            if min(c / self.config.data.c_max, 1.0) >= t.visible_fit:
                verdicts[oid] = "visible"
                continue
            verdicts[oid] = "candidate"
            if view is not None:
                rep = view.report_pose(model.surface_points, model.surface_normals, T)
                if rep.n_facing and rep.seen_through >= t.seen_through_fraction:
                    log.info("%s: its volume is seen empty (%.0f %%)", oid, 100 * rep.seen_through)
                elif rep.n_facing and rep.occluded >= t.occluded_fraction:
                    verdicts[oid] = "ephemeral"
        return verdicts

    def _carries_load(self, world: World, sim: Simulator, graph, oid: str) -> bool:
        """Would the objects ``oid`` supports move without it? (support-retained test)"""
        k = world.index(oid)
        kids = [world.ids[c] for c in graph.children(k)]
        if not kids:
            return False
        t = self.config.temporal
        state = world.save_state()
        before = {c: world.get_pose(c) for c in kids}
        world.set_enabled(oid, False)
        moved = False
        try:
            sim.settle(self.config.search.retain_settle, with_forces=False)
            for c in kids:
                dt, dth = pose_change(before[c], world.get_pose(c), world.model_of(c).symmetry)
                moved |= dt >= t.static_translation or dth >= t.static_rotation
        except PhysicsError:
            moved = True
        world.restore_state(state)
        log.info(
            "%s undetected; objects it supports %s without it", oid, "move" if moved else "stay"
        )
        return moved

    # -------------------------------------------------------------- output
    def _finish(
        self,
        frame: Frame,
        score: SceneScore,
        models: Mapping[str, ObjectModel],
        prev_pose: Mapping[str, np.ndarray],
        removed: set[str],
        retained: set[str],
        verdicts: Mapping[str, str],
        chosen: Mapping[str, str],
        tested: int,
        unchanged: bool,
        counters: dict[str, int],
    ):
        cfg = self.config
        objects: list[ObjectEstimate] = []
        known: dict[str, _Known] = {}
        ids = score.ids
        for i, oid in enumerate(ids):
            if oid in removed:
                continue
            model = models[oid]
            T = score.poses[i]
            prev = prev_pose.get(oid)
            if prev is not None:
                T = snap_symmetric(prev, T, model.symmetry)
            ephemeral = verdicts.get(oid) == "ephemeral"
            supports = bool(score.graph.children(i))
            mode = classify(
                prev,
                T,
                model.symmetry,
                cfg.temporal,
                retained=oid in retained or (ephemeral and supports),
            )
            objects.append(
                ObjectEstimate(
                    oid,
                    model.name,
                    T,
                    mode,
                    ephemeral=ephemeral,
                    terms=score.object_terms(i),
                    source=chosen.get(oid, "current"),
                    fit=float(score.fit[i]),
                )
            )
            known[oid] = _Known(model.name, T, ephemeral, float(score.fit[i]))
        gone = tuple(
            ObjectEstimate(
                oid, models[oid].name, prev_pose[oid], TransitionMode.REMOVED, source="removed"
            )
            for oid in sorted(removed)
        )
        support = []
        g = score.graph
        for a, b, f in zip(g.supporter, g.supported, g.edge_fraction, strict=True):
            if ids[b] in removed or (a != GROUND and ids[a] in removed):
                continue
            support.append(SupportEdge(TABLE if a == GROUND else ids[a], ids[b], float(f)))
        log_prob = float(sum(o.log_prob for o in objects))
        estimate = SceneEstimate(
            stamp=frame.stamp,
            frame_index=self._frame_index,
            objects=tuple(objects),
            removed=gone,
            support=tuple(support),
            log_prob=log_prob,
            hypotheses_tested=tested,
            unchanged=unchanged,
        )

        def commit() -> None:
            self._known = known
            self._counters = counters
            self._frame_index += 1
            self._last_stamp = frame.stamp

        return estimate, commit


def _with_timings(estimate: SceneEstimate, timer: StageTimer) -> SceneEstimate:
    from dataclasses import replace

    return replace(estimate, timings=dict(timer.seconds))


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
