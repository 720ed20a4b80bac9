"""Baselines of Table I, side by side with ssp (DESIGN section 5).

Each method is a small class with ``reset()`` and ``update(frame) -> list[Detection]``
(``Detection`` is a ``(class_name, T_world_obj)`` named tuple), deterministic, fed the frames
of one sequence in time order. Hypotheses are grouped per object as the parser groups them
(:func:`ssp.temporal.associate` with the parser's per-class gate, best score first, and
clusters that share a volume merged: :func:`ssp.temporal.same_volume_test`), and the object's
segment of the cloud is found as the parser finds it (:func:`ssp.segments.object_segments`: the
label most of the pose's model samples land on).

* ``estimator``: the best-scored hypothesis of each object (the pose estimator alone).
* ``icp``: the estimator's pose refined by point-to-plane ICP on the object's segment.
* ``ray_slide``: the estimator's pose slid along its viewing ray to the observed depth (the
  median depth offset of its silhouette, :func:`ssp.correction.median_slide`): the simplest
  fix a user of an RGB estimator would write.
* ``bestfit``: among the (at most ``search.hypotheses_per_object``) hypotheses of each object,
  the one with the best data fit (the ``c`` of Eq. 12, camera-facing samples only); no physics.
* ``temporal_filter``: the estimator smoothed over time per tracked object.
* ``icp_filter``: ICP-refined hypotheses through a tracker with gating, median and coasting.
* ``ssp_single``: the scene parser with memory off (each frame parsed alone).
* ``ssp``: :class:`ssp.parser.SceneParser`.

Each output :class:`Detection` carries the method's confidence (the hypothesis score; for
ssp the data fit of the object) and, for the methods that track objects over frames
(``temporal_filter``, ``icp_filter``, ``ssp``), its instance id.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np
from scipy.spatial import cKDTree

from ssp.config import SSPConfig
from ssp.correction import camera_view, median_slide
from ssp.errors import SSPError
from ssp.eval.metrics import chordal_mean_rotation
from ssp.geometry import transform_points
from ssp.library.model import ObjectModel
from ssp.parser import SceneParser
from ssp.probability import data_fit_fraction, pose_change
from ssp.registration import even_rows, facing_mask, icp_refine
from ssp.scene import Frame, Hypothesis
from ssp.segments import object_segments
from ssp.temporal import (
    associate,
    association_gates,
    default_id_factory,
    one_object_per_segment,
    same_volume_test,
    snap_symmetric,
)

__all__ = [
    "METHODS",
    "BestFit",
    "Detection",
    "Estimator",
    "ICPFilter",
    "ICPRefine",
    "RaySlide",
    "Method",
    "SSPMethod",
    "SSPSingleFrame",
    "TemporalFilter",
    "data_fit",
    "make_method",
]

log = logging.getLogger(__name__)


class Detection(NamedTuple):
    """One output object: its class and pose ``T_world_obj`` (4, 4), m; the method's
    confidence ``score`` (higher is better; orders estimates for the BOP metrics) and its
    instance ``id`` when the method tracks objects over frames (None for memoryless ones)."""

    class_name: str
    T_world_obj: np.ndarray
    score: float = 1.0
    id: str | None = None


class Method(Protocol):
    """What :func:`ssp.eval.table1.run_table1` needs of a method."""

    name: str

    def reset(self) -> None: ...

    def update(self, frame: Frame) -> list[Detection]: ...


def data_fit(
    model: ObjectModel,
    T_world_obj: np.ndarray,
    segment: np.ndarray | cKDTree,
    radius: float,
    camera_position: np.ndarray | None = None,
    n_samples: int = 1000,
) -> float:
    """Data fit ``c`` (Eq. 12) of ``model`` at a pose, as :meth:`SceneScorer.fit_fraction`
    computes it: the fraction of (at most ``n_samples``, evenly chosen) camera-facing surface
    samples with a segment point within ``radius``."""
    pts, nrm = even_rows(
        n_samples,
        np.asarray(model.surface_points, dtype=float),
        np.asarray(model.surface_normals, dtype=float),
    )
    T = np.asarray(T_world_obj, dtype=float)
    pw = transform_points(T, pts)
    pw = pw[facing_mask(pw, nrm @ T[:3, :3].T, camera_position)]
    return data_fit_fraction(pw, segment, radius)


class Estimator:
    """The pose estimator alone: each object's best-scored hypothesis (no state)."""

    name = "estimator"
    #: Whether the method's detections carry ids that persist over frames.
    tracks_ids = False

    def __init__(self, library: Mapping[str, ObjectModel], config: SSPConfig | None = None):
        self.library = library
        self.config = config if config is not None else SSPConfig()
        self._symmetries = {n: m.symmetry for n, m in library.items()}
        self._gates = association_gates(library, self.config.temporal)
        self._same_volume = same_volume_test(library, self.config.temporal.merge_overlap)

    def reset(self) -> None:
        """Forget everything (nothing to forget for a memoryless method)."""

    def _groups(
        self, frame: Frame, previous: Mapping[str, tuple[str, np.ndarray]] | None = None, **kw
    ) -> dict[str, list[Hypothesis]]:
        """The frame's hypotheses per object, best score first, associated as the parser
        does (clusters whose best poses share a volume are one object; one object per
        instance segment: a tracked object's class first, else the best-scored one)."""
        groups = associate(
            frame.hypotheses,
            previous or {},
            self._symmetries,
            max_distance=self._gates,
            same_volume=self._same_volume,
            **kw,
        )
        known = set(previous or ())
        kept, _ = one_object_per_segment(groups, lambda oid, h: (oid in known, h[0].score))
        return kept

    def _segments(
        self, frame: Frame, poses: Mapping[str, list[np.ndarray]], classes: Mapping[str, str]
    ) -> dict[str, np.ndarray]:
        segs, _ = object_segments(
            frame,
            {oid: (self.library[classes[oid]], poses[oid]) for oid in poses},
            radius=self.config.forces.max_distance,
        )
        return segs

    def update(self, frame: Frame) -> list[Detection]:
        frame = frame.validate(self.library)
        return [
            Detection(hyps[0].class_name, np.array(hyps[0].T_world_obj), hyps[0].score)
            for hyps in self._groups(frame).values()
        ]


class ICPRefine(Estimator):
    """The estimator's pose refined by :func:`icp_refine` (1 cm correspondences, 20
    iterations) on the object's segment, camera-facing model samples only."""

    name = "icp"

    def __init__(
        self,
        library: Mapping[str, ObjectModel],
        config: SSPConfig | None = None,
        *,
        max_distance: float = 0.01,
        iterations: int = 20,
    ) -> None:
        super().__init__(library, config)
        self.max_distance = float(max_distance)
        self.iterations = int(iterations)

    def update(self, frame: Frame) -> list[Detection]:
        frame = frame.validate(self.library)
        groups = self._groups(frame)
        classes = {oid: hyps[0].class_name for oid, hyps in groups.items()}
        segs = self._segments(
            frame, {oid: [hyps[0].T_world_obj] for oid, hyps in groups.items()}, classes
        )
        cam = None if frame.T_world_cam is None else frame.T_world_cam[:3, 3]
        out = []
        for oid, hyps in groups.items():
            model = self.library[classes[oid]]
            T = icp_refine(
                model,
                hyps[0].T_world_obj,
                segs[oid],
                cam,
                max_distance=self.max_distance,
                iterations=self.iterations,
                n_samples=self.config.search.fit_samples,
            )
            out.append(Detection(classes[oid], T, hyps[0].score))
        return out


class RaySlide(Estimator):
    """The estimator's pose slid along its viewing ray to the depth its silhouette sees
    (:func:`ssp.correction.median_slide`); unchanged without a camera pose or data."""

    name = "ray_slide"

    def update(self, frame: Frame) -> list[Detection]:
        frame = frame.validate(self.library)
        view = camera_view(frame, self.config)
        out = []
        for hyps in self._groups(frame).values():
            h = hyps[0]
            T = None if view is None else median_slide(h, self.library[h.class_name], view, frame)
            pose = np.array(h.T_world_obj) if T is None else T
            out.append(Detection(h.class_name, pose, h.score))
        return out


class BestFit(Estimator):
    """Among each object's hypotheses (the best ``search.hypotheses_per_object`` by score,
    as the parser keeps), the one with the highest data fit :func:`data_fit` to its segment
    (``data.inlier_radius``); ties go to the higher score. No physics."""

    name = "bestfit"

    def update(self, frame: Frame) -> list[Detection]:
        frame = frame.validate(self.library)
        k = self.config.search.hypotheses_per_object
        groups = {oid: hyps[:k] for oid, hyps in self._groups(frame).items()}
        classes = {oid: hyps[0].class_name for oid, hyps in groups.items()}
        segs = self._segments(
            frame, {oid: [h.T_world_obj for h in hyps] for oid, hyps in groups.items()}, classes
        )
        cam = None if frame.T_world_cam is None else frame.T_world_cam[:3, 3]
        out = []
        for oid, hyps in groups.items():
            model = self.library[classes[oid]]
            seg = segs[oid]
            best = hyps[0]
            if len(seg) and len(hyps) > 1:
                tree = cKDTree(seg)
                fits = [
                    data_fit(
                        model,
                        h.T_world_obj,
                        tree,
                        self.config.data.inlier_radius,
                        cam,
                        self.config.search.fit_samples,
                    )
                    for h in hyps
                ]
                best = hyps[int(np.argmax(fits))]  # first maximum: the higher score
            out.append(Detection(classes[oid], np.array(best.T_world_obj), best.score))
        return out


@dataclass
class _Track:
    class_name: str
    poses: deque = field(default_factory=deque)  # snapped estimator poses, newest last
    output: np.ndarray | None = None
    missed: int = 0


class TemporalFilter(Estimator):
    """The estimator smoothed over time: a moving average of the best hypothesis per track.

    Tracks: each frame's hypotheses are associated with the tracks' last outputs
    (:func:`ssp.temporal.associate`, the parser's gate, Hungarian on translation and
    symmetry-aware rotation). A track's new estimator pose is snapped to the symmetric
    equivalent closest to the track's last output (:func:`ssp.temporal.snap_symmetric`) and
    appended to its window of the last ``window`` poses; the output is the window's mean
    (translation mean, chordal rotation mean). A jump of more than ``jump_translation`` (2 cm)
    or ``jump_rotation`` (30 deg, symmetry-aware) from the last output restarts the window with
    the new pose (the object was moved). A track without a hypothesis in a frame outputs
    nothing, is kept for association for ``max_missed`` frames, then dropped.
    """

    name = "temporal_filter"
    tracks_ids = True

    def __init__(
        self,
        library: Mapping[str, ObjectModel],
        config: SSPConfig | None = None,
        *,
        window: int = 5,
        jump_translation: float = 0.02,
        jump_rotation: float = math.radians(30.0),
        max_missed: int = 3,
    ) -> None:
        super().__init__(library, config)
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.window = int(window)
        self.jump_translation = float(jump_translation)
        self.jump_rotation = float(jump_rotation)
        self.max_missed = int(max_missed)
        self._tracks: dict[str, _Track] = {}
        self._new_id = default_id_factory()

    def reset(self) -> None:
        self._tracks = {}
        self._new_id = default_id_factory()

    def update(self, frame: Frame) -> list[Detection]:
        frame = frame.validate(self.library)
        previous = {
            tid: (tr.class_name, tr.output)
            for tid, tr in self._tracks.items()
            if tr.output is not None
        }
        groups = self._groups(frame, previous, new_id=self._new_id)
        out = []
        for tid, hyps in groups.items():
            cls = hyps[0].class_name
            T_new = np.array(hyps[0].T_world_obj, dtype=float)
            sym = self.library[cls].symmetry
            tr = self._tracks.get(tid)
            if tr is None:
                tr = self._tracks[tid] = _Track(cls, deque(maxlen=self.window))
            if tr.output is not None:
                dt, dth = pose_change(tr.output, T_new, sym)
                if dt > self.jump_translation or dth > self.jump_rotation:
                    tr.poses.clear()
                else:
                    T_new = snap_symmetric(tr.output, T_new, sym)
            tr.poses.append(T_new)
            tr.missed = 0
            T_out = np.eye(4)
            T_out[:3, 3] = np.mean([T[:3, 3] for T in tr.poses], axis=0)
            T_out[:3, :3] = chordal_mean_rotation([T[:3, :3] for T in tr.poses])
            tr.output = T_out
            out.append(Detection(cls, T_out.copy(), hyps[0].score, tid))
        for tid in list(self._tracks):
            if tid not in groups:
                self._tracks[tid].missed += 1
                if self._tracks[tid].missed > self.max_missed:
                    del self._tracks[tid]
        return out


class SSPMethod:
    """ssp itself: :class:`SceneParser` (every object of :attr:`SceneEstimate.objects`,
    ephemeral and support-retained ones included). A frame the parser rejects
    (:class:`SSPError`) is logged and answered with the previous output (the parser's state
    is that of the last good frame); any other exception too, logged with its traceback."""

    name = "ssp"
    tracks_ids = True

    def __init__(self, library, config: SSPConfig | None = None) -> None:
        self.library = library
        self.config = config if config is not None else SSPConfig()
        self.parser = SceneParser(library, self.config)
        self._last: list[Detection] = []
        self.last_estimate = None

    def reset(self) -> None:
        self.parser = SceneParser(self.library, self.config)
        self._last = []
        self.last_estimate = None

    def update(self, frame: Frame) -> list[Detection]:
        try:
            est = self.parser.update(frame)
        except Exception as exc:  # SSPError: bad frame; anything else a bug, with traceback
            log.warning(
                "ssp: frame at t = %s skipped: %s", frame.stamp, exc,
                exc_info=None if isinstance(exc, SSPError) else exc,
            )  # fmt: skip
            return [Detection(d.class_name, d.T_world_obj.copy()) for d in self._last]
        self.last_estimate = est
        self._last = [
            Detection(o.class_name, np.array(o.T_world_obj), float(o.fit), o.id)
            for o in est.objects
        ]
        return list(self._last)


class SSPSingleFrame(SSPMethod):
    """ssp without memory: every frame is parsed as the first of a new scene (the parser is
    reset before it). Physics and data terms choose and correct the hypotheses; nothing is
    carried from the previous frame (no previous poses, no retained or ephemeral objects, no
    ids kept). A single-frame physical-plausibility refinement."""

    name = "ssp_single"
    tracks_ids = False

    def update(self, frame: Frame) -> list[Detection]:
        self.parser.reset()
        return [d._replace(id=None) for d in super().update(frame)]


@dataclass
class _GatedTrack:
    class_name: str
    poses: deque  # accepted (ICP-refined, snapped) poses, newest last
    output: np.ndarray
    score: float
    missed: int = 0
    outliers: list = field(default_factory=list)  # consecutive rejected measurements


class ICPFilter(ICPRefine):
    """ICP-refined hypotheses through a tracker with outlier rejection: the strongest
    temporal baseline a user would build without physics.

    Tracks are associated as in :class:`TemporalFilter`. Per track and frame (*gating*): of the
    object's hypotheses (the best ``search.hypotheses_per_object``), the one nearest to the
    track's output (translation + 0.05 m/rad x symmetry-aware rotation) is refined by ICP on the
    object's segment; it is accepted when within ``gate_translation`` (2 cm) and
    ``gate_rotation`` (30 deg) of the output, else it is an outlier. The output is the *median*
    of the last ``window`` accepted poses (per-axis median translation; the rotation of the
    window's medoid, symmetric equivalents snapped to the output). ``confirm`` consecutive
    outliers that agree with each other (within the gates) restart the track at them: the
    object was moved. A track without hypotheses keeps its output for ``max_missed`` frames
    (coasting, its score halved per frame), then is dropped. New tracks start at the
    best-scored hypothesis, refined."""

    name = "icp_filter"
    tracks_ids = True

    def __init__(
        self,
        library: Mapping[str, ObjectModel],
        config: SSPConfig | None = None,
        *,
        window: int = 5,
        gate_translation: float = 0.02,
        gate_rotation: float = math.radians(30.0),
        confirm: int = 3,
        max_missed: int = 3,
    ) -> None:
        super().__init__(library, config)
        self.window = int(window)
        self.gate_translation = float(gate_translation)
        self.gate_rotation = float(gate_rotation)
        self.confirm = int(confirm)
        self.max_missed = int(max_missed)
        self.reset()

    def reset(self) -> None:
        self._tracks: dict[str, _GatedTrack] = {}
        self._new_id = default_id_factory()

    def _within(self, T_a: np.ndarray, T_b: np.ndarray, sym) -> bool:
        dt, dth = pose_change(T_a, T_b, sym)
        return dt <= self.gate_translation and dth <= self.gate_rotation

    @staticmethod
    def _median(poses, sym) -> np.ndarray:
        ref = poses[-1]
        snapped = [snap_symmetric(ref, T, sym) for T in poses]
        R = [T[:3, :3] for T in snapped]
        cost = [sum(pose_change(_rot(a), _rot(b))[1] for b in R) for a in R]
        out = np.eye(4)
        out[:3, :3] = R[int(np.argmin(cost))]
        out[:3, 3] = np.median([T[:3, 3] for T in snapped], axis=0)
        return out

    def update(self, frame: Frame) -> list[Detection]:
        frame = frame.validate(self.library)
        k = self.config.search.hypotheses_per_object
        previous = {tid: (tr.class_name, tr.output) for tid, tr in self._tracks.items()}
        groups = {
            oid: hyps[:k]
            for oid, hyps in self._groups(frame, previous, new_id=self._new_id).items()
        }
        classes = {oid: hyps[0].class_name for oid, hyps in groups.items()}
        segs = self._segments(
            frame, {oid: [h.T_world_obj for h in hyps] for oid, hyps in groups.items()}, classes
        )
        cam = None if frame.T_world_cam is None else frame.T_world_cam[:3, 3]

        def refine(cls: str, T: np.ndarray, oid: str) -> np.ndarray:
            return icp_refine(
                self.library[cls], T, segs[oid], cam, max_distance=self.max_distance,
                iterations=self.iterations, n_samples=self.config.search.fit_samples,
            )  # fmt: skip

        out = []
        for tid, hyps in groups.items():
            cls = classes[tid]
            sym = self.library[cls].symmetry
            tr = self._tracks.get(tid)
            if tr is None:
                T = refine(cls, hyps[0].T_world_obj, tid)
                tr = self._tracks[tid] = _GatedTrack(
                    cls, deque([T], maxlen=self.window), T, hyps[0].score
                )
            else:

                def cost(h, tr=tr, sym=sym):
                    dt, dth = pose_change(tr.output, h.T_world_obj, sym)
                    return dt + 0.05 * dth

                h = min(hyps, key=cost)
                T = snap_symmetric(tr.output, refine(cls, h.T_world_obj, tid), sym)
                tr.missed = 0
                if self._within(tr.output, T, sym):
                    tr.poses.append(T)
                    tr.outliers = []
                    tr.score = h.score
                else:
                    T0 = refine(cls, hyps[0].T_world_obj, tid)
                    if tr.outliers and not self._within(tr.outliers[-1], T0, sym):
                        tr.outliers = []
                    tr.outliers.append(T0)
                    if len(tr.outliers) >= self.confirm:  # it moved: restart there
                        tr.poses = deque(tr.outliers, maxlen=self.window)
                        tr.outliers = []
                        tr.score = hyps[0].score
                tr.output = self._median(list(tr.poses), sym)
            out.append(Detection(cls, tr.output.copy(), tr.score, tid))
        for tid in list(self._tracks):
            if tid in groups:
                continue
            tr = self._tracks[tid]
            tr.missed += 1
            if tr.missed > self.max_missed:
                del self._tracks[tid]
            else:  # coasting, with a confidence that halves every frame
                score = tr.score * 0.5**tr.missed
                out.append(Detection(tr.class_name, tr.output.copy(), score, tid))
        return out


def _rot(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


#: Method name -> class (constructed as ``cls(library, config)``), in Table I order.
METHODS: dict[str, type] = {
    "ssp": SSPMethod,
    "estimator": Estimator,
    "icp": ICPRefine,
    "ray_slide": RaySlide,
    "bestfit": BestFit,
    "temporal_filter": TemporalFilter,
    "icp_filter": ICPFilter,
    "ssp_single": SSPSingleFrame,
}


def make_method(name: str, library, config: SSPConfig | None = None) -> Method:
    """A fresh method by name (one of :data:`METHODS`)."""
    try:
        cls = METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; known: {', '.join(METHODS)}") from None
    return cls(library, config)
