"""From a sensor frame to the scene parser's input: table, segments, pose hypotheses.

The paper's front end (section IV-D, "Software Implementation"): the table plane gives gravity
and the world frame, the cloud above it is segmented, and a pose estimator proposes several
poses per object (here :class:`ssp.perception.estimator.HypothesisEstimator`).
:class:`Perception` chains these and returns a :class:`ssp.scene.Frame` ready for
:meth:`ssp.parser.SceneParser.update`.

Segments and candidate classes:

* instance labels (a label is one object): each segment is searched for one object of any
  class (of its class when the input names it);
* class labels or colour classes (a label is a class, several objects may share it): each
  region is split into Euclidean clusters, and each cluster is searched for as many objects of
  that class as it holds;
* no labels: the cloud above the table is clustered, and each cluster is searched for as many
  objects of any class as it holds (touching objects form one cluster).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ssp.camera import Camera
from ssp.config import PerceptionConfig, SSPConfig
from ssp.errors import InputError, InvalidPoseError, PerceptionError, UnknownObjectError
from ssp.geometry import transform_points, validate_pose
from ssp.io.hypotheses import to_world
from ssp.lanes import LANES_STAGE, ForkLanes
from ssp.library.model import ObjectModel
from ssp.perception.cleaning import clean_segment
from ssp.perception.depth import cloud_from_depth
from ssp.perception.estimator import HypothesisEstimator, SegmentResult
from ssp.perception.normals import estimate_normals
from ssp.perception.reuse import SegmentMemory, SegmentShape, confident
from ssp.perception.segmentation import Segmentation, segment_cloud
from ssp.perception.table import table_frame
from ssp.scene import Frame, Hypothesis
from ssp.threads import KERNEL_THREADS, thread_map
from ssp.timing import StageTimer

__all__ = ["Perception", "PerceptionResult", "SegmentRequest", "check_camera_axes"]

log = logging.getLogger(__name__)


#: A camera-frame cloud with fewer than this fraction of its points in front of the camera
#: (z > 0, OpenCV axes) is in other axes.
MIN_IN_FRONT = 0.5


def check_camera_axes(points: np.ndarray) -> None:
    """PerceptionError when a camera-frame cloud ``(N, 3)`` lies mostly behind the camera
    (z <= 0): it is not in OpenCV axes (x right, y down, z forward). An OpenGL-style cloud (y
    up, z backward: PCL's Kinect tutorials) otherwise gave every object 'not in the camera's
    view' and an upside-down world.

    Raises:
        InputError: ``points`` is not ``(N, 3)``.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3) (x, y, z in m), got {points.shape}")
    front = float(np.mean(points[:, 2] > 0.0)) if len(points) else 1.0
    if front < MIN_IN_FRONT:
        raise PerceptionError(
            f"only {100 * front:.0f} % of the points are in front of the camera (z > 0): the "
            "cloud is not in the camera frame with OpenCV axes (x right, y down, z forward); "
            "a cloud with y up and z backward is in OpenGL axes: negate y and z (ssp run: "
            'scene.json "camera_axes": "opengl")'
        )


@dataclass
class PerceptionResult:
    """What the front end made of one frame.

    Attributes:
        frame: the parser's input (world-frame points, segment labels, hypotheses, camera).
        segmentation: segment labels of ``frame.points`` and their classes when known.
        segments: per segment label, the estimator's result (empty when hypotheses were given).
        verdicts: per segment label, what the front end made of it, in words: the points it
            removed (flying pixels, stray pieces) and the hypotheses it found, or why none.
        timings: exclusive wall seconds per stage, in the order they ran, and ``total``
            (from the :class:`~ssp.timing.StageTimer`'s start: the frame's source starts it
            before reading): the source's (``read``: files and decoding, ``world frame``:
            locating a camera without pose, ``masks``: detections to labels, ``cloud``:
            depth to points), then ``checks`` (input validation), ``table``, ``segmentation``,
            ``cleaning``, ``normals``, ``hypotheses`` (the estimator; both summed over the
            segments), ``estimation`` (the estimator's rest: forking, waiting for the other
            processes) and ``frame``. They add up to ``total`` (:func:`ssp.timing.stage_sum`).
            With ``perception.processes`` > 1, ``normals`` and ``hypotheses`` are those the
            calling process ran, and ``lanes`` what the forked ones worked (CPU seconds, not
            in the sum).
    """

    frame: Frame
    segmentation: Segmentation
    segments: dict[int, SegmentResult] = field(default_factory=dict)
    verdicts: dict[int, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    #: the camera of a depth image (:meth:`Perception.from_depth`), for the recording
    camera: Camera | None = None
    #: that depth image (H, W), m (0: no return)
    depth: np.ndarray | None = None
    #: how the camera of a frame without pose was located (the frame JSON's ``camera``:
    #: :meth:`ssp.pipeline.world.CameraLocator.locate`); None: the pose was given
    camera_fix: dict | None = None

    @property
    def seconds_per_segment(self) -> float | None:
        """Mean estimator time per segment, s (None without segments searched)."""
        if not self.segments:
            return None
        return float(np.mean([r.seconds for r in self.segments.values()]))


@dataclass(frozen=True)
class SegmentRequest:
    """What the estimator is asked of one segment (:meth:`Perception.segment_request`).

    Attributes: ``label``; ``points``, ``normals`` ``(N, 3)`` (world, m; unit normals toward
    the camera); ``classes`` (candidates); ``camera`` ``(3,)`` (world) or None;
    ``single_object`` (an instance label); ``seed`` (the estimator's seed plus the label).
    """

    label: int
    points: np.ndarray
    normals: np.ndarray
    classes: tuple[str, ...]
    camera: np.ndarray | None
    single_object: bool
    seed: int

    def run(self, estimator: HypothesisEstimator) -> SegmentResult:
        """:meth:`HypothesisEstimator.estimate` of this segment."""
        return estimator.estimate(
            self.points,
            self.normals,
            self.classes,
            self.camera,
            single_object=self.single_object,
            seed=self.seed,
        )


class Perception:
    """The perception front end (module docstring).

    Args:
        library: class name -> :class:`ObjectModel` (the candidate classes).
        config: :class:`SSPConfig` (its ``perception`` section and ``seed``) or a
            :class:`PerceptionConfig`.
        classes: candidate classes (default: every class of ``library``).
    """

    def __init__(
        self,
        library: Mapping[str, ObjectModel],
        config: SSPConfig | PerceptionConfig | None = None,
        classes: Sequence[str] | None = None,
    ) -> None:
        if isinstance(config, SSPConfig):
            cfg, seed = config.perception, config.seed
        else:
            cfg, seed = (config if config is not None else PerceptionConfig()), 0
        self.cfg = cfg
        self.library = library
        names = list(classes) if classes is not None else list(library)
        unknown = [c for c in names if c not in library]
        if unknown:
            raise UnknownObjectError(f"candidate classes not in the library: {unknown}")
        if not names:
            raise PerceptionError("no candidate classes")
        self.classes = tuple(names)
        self.estimator = HypothesisEstimator(library, cfg, seed=seed)
        #: the segments of the last frame and their hypotheses (``cfg.reuse_unchanged``)
        self.memory = SegmentMemory()

    def segment_request(
        self,
        points: np.ndarray,
        segmentation: Segmentation,
        label: int,
        camera: np.ndarray | None,
        instance: bool,
    ) -> SegmentRequest:
        """The estimator's input for segment ``label`` of ``points (N, 3)`` (world, m): its
        points, their normals (``normal_neighbours``, toward ``camera``), its class when the
        segmentation names one (else every candidate class) and its seed.

        Raises:
            InputError: ``points`` not ``(N, 3)`` with ``N`` the segmentation's length, or
                ``label`` not one of its segments.
        """
        pts = np.asarray(points, dtype=float)
        n = len(segmentation.labels)
        if pts.shape != (n, 3):
            raise InputError(
                f"points must have shape ({n}, 3) (the segmentation's points), got {pts.shape}"
            )
        if label not in {int(k) for k in segmentation.segment_ids}:
            shown = ", ".join(str(int(k)) for k in segmentation.segment_ids) or "none"
            raise InputError(f"label {label!r} is not a segment of the segmentation ({shown})")
        seg = pts[segmentation.labels == label]
        return SegmentRequest(
            label=int(label),
            points=seg,
            normals=estimate_normals(seg, k=self.cfg.normal_neighbours, viewpoint=camera),
            classes=self._classes_of(segmentation, label),
            camera=camera,
            single_object=bool(instance),
            seed=self.estimator.seed + int(label),
        )

    def _classes_of(self, segmentation: Segmentation, label: int) -> tuple[str, ...]:
        """The candidate classes of segment ``label``: the one its segmentation names, else
        every candidate class."""
        cls = segmentation.classes.get(label)
        return (cls,) if cls is not None else self.classes

    # ------------------------------------------------------------------ inputs
    def from_depth(
        self,
        depth: np.ndarray,
        camera: Camera,
        *,
        stamp: float = 0.0,
        T_world_cam: np.ndarray | None = None,
        mask: np.ndarray | None = None,
        depth_scale: float | None = None,
        hypotheses: list[Hypothesis] | None = None,
        hypotheses_frame: str = "world",
        timer: StageTimer | None = None,
    ) -> PerceptionResult:
        """Perceive a depth image ``(H, W)`` (m, 0 = no return) seen by ``camera``.

        ``mask`` ``(H, W)`` holds instance labels (negative = table/background); without it
        the cloud above the table is clustered. ``T_world_cam`` None: fitted to the table.
        The other arguments as for :meth:`from_points` (the depth to points step is timed as
        ``cloud``).

        Raises:
            InputError: ``camera`` is not a :class:`~ssp.camera.Camera`, or an argument of
                :meth:`from_points` that cannot be used.
            PerceptionError: ``depth`` or ``mask`` not of the camera's image shape, or depth
                that looks like millimetres (:func:`ssp.perception.depth.cloud_from_depth`).
        """
        if not isinstance(camera, Camera):
            raise InputError(f"camera must be an ssp.camera.Camera, got {type(camera).__name__}")
        timer = timer if timer is not None else StageTimer()
        with timer("cloud"):
            cloud = cloud_from_depth(depth, camera, mask=mask, depth_scale=depth_scale)
        result = self.from_points(
            cloud.points,
            frame="camera",
            stamp=stamp,
            T_world_cam=T_world_cam,
            labels=cloud.labels,
            hypotheses=hypotheses,
            hypotheses_frame=hypotheses_frame,
            timer=timer,
        )
        result.camera = camera
        scale = 1.0 if depth_scale is None else float(depth_scale)
        result.depth = np.asarray(depth, dtype=float) * scale
        return result

    def from_points(  # noqa: C901
        self,
        points: np.ndarray,
        *,
        frame: str = "camera",
        stamp: float = 0.0,
        T_world_cam: np.ndarray | None = None,
        labels: np.ndarray | None = None,
        label_kind: str | None = "instance",
        label_classes: Mapping[int, str] | None = None,
        hypotheses: list[Hypothesis] | None = None,
        hypotheses_frame: str = "world",
        timer: StageTimer | None = None,
    ) -> PerceptionResult:
        """Perceive a cloud ``(N, 3)`` (m). Rows with a non-finite coordinate (no return in an
        organised cloud) are dropped, with their labels.

        Args:
            frame: ``"camera"``: points in the sensor frame (OpenCV axes); the world frame comes
                from ``T_world_cam``, else from the table plane. ``"world"``: z up, table top
                at z = 0; ``T_world_cam`` (optional) enables the camera-facing tests.
            labels: ``(N,)`` segment labels (negative = background) or None.
            label_kind: ``"instance"`` (a label is one object) or ``"class"`` (a label is a
                class region; ``label_classes`` names them).
            label_classes: label -> class name (for instance labels: the known classes).
            hypotheses: given pose hypotheses, used instead of the estimator.
            hypotheses_frame: ``"world"``, or ``"camera"`` (each ``T_world_obj`` then holds
                ``T_cam_obj``; moved to the world once ``T_world_cam`` is known).
            timer: the frame's timer, when the caller timed steps of its own (reading) before
                (:attr:`PerceptionResult.timings`); None: a new one.

        Raises:
            InputError: ``points`` not ``(N, 3)`` numbers or without a finite row, ``labels``
                not ``N`` integers, ``T_world_cam`` not a rigid ``(4, 4)`` pose, or a
                ``frame``, ``label_kind`` or ``hypotheses_frame`` not among those above.
            PerceptionError: the front end cannot process the frame (no table, camera-frame
                hypotheses without a camera pose, ...).
        """
        timer = timer if timer is not None else StageTimer()
        with timer("checks"):
            pts, lab = _checked_cloud(points, labels)
            _check_choice("frame", frame, ("camera", "world"))
            _check_choice("label_kind", label_kind, ("instance", "class", None))
            _check_choice("hypotheses_frame", hypotheses_frame, ("world", "camera"))
            if T_world_cam is not None:
                try:
                    T_world_cam = validate_pose(T_world_cam, "T_world_cam")
                except InvalidPoseError as exc:
                    raise InputError(str(exc)) from exc
            if frame == "camera":
                check_camera_axes(pts)

        with timer("table"):
            if frame == "camera":
                if T_world_cam is None:
                    T_world_cam, _ = table_frame(pts, distance=self.cfg.table_distance)
                pts = transform_points(np.asarray(T_world_cam, dtype=float), pts)

        with timer("segmentation"):
            instance = lab is not None and label_kind != "class"
            segmentation = segment_cloud(
                pts,
                lab,
                None if instance else label_classes,
                table_height=self.cfg.table_height,
                tolerance=self.cfg.cluster_tolerance,
                min_points=self.cfg.min_segment_points,
            )
            if instance and label_classes:
                segmentation.classes.update(
                    {k: v for k, v in label_classes.items() if k in segmentation.classes}
                )

        segments: dict[int, SegmentResult] = {}
        if hypotheses is not None and hypotheses_frame == "camera":
            if T_world_cam is None:
                raise PerceptionError("camera-frame hypotheses need the camera pose")
            with timer("frame"):
                hypotheses = to_world(hypotheses, T_world_cam)
        verdicts: dict[int, str] = {}
        if instance:  # instance masks of real sensors: drop flying pixels and stray pieces
            with timer("cleaning"):
                self._clean(pts, segmentation, verdicts)
        if hypotheses is None:
            hypotheses = self._estimate(pts, segmentation, T_world_cam, instance, segments,
                                        verdicts, timer)  # fmt: skip
        with timer("frame"):
            out_frame = Frame(
                stamp=stamp,
                points=pts,
                hypotheses=list(hypotheses),
                labels=segmentation.labels,
                T_world_cam=None if T_world_cam is None else np.asarray(T_world_cam, dtype=float),
                label_kind="instance" if instance else "cluster",
            )
        timings = {**timer.own, "total": timer.elapsed()}
        log.debug(
            "perceived %d points, %d segments, %d hypotheses in %.2f s",
            len(pts),
            len(segmentation.segment_ids),
            len(out_frame.hypotheses),
            timings["total"],
        )
        return PerceptionResult(out_frame, segmentation, segments, verdicts, timings)

    def _clean(self, pts: np.ndarray, segmentation: Segmentation, verdicts: dict[int, str]) -> None:
        """Drop each instance segment's flying pixels and stray pieces (:func:`clean_segment`:
        their labels become -1; ``verdicts`` says what went). The segments are cleaned in
        threads (:func:`ssp.threads.thread_map`: the tree queries and sorts release the GIL),
        each on its own: the same labels as one after another."""
        labels = segmentation.labels
        order = np.argsort(labels, kind="stable")
        ids, starts = np.unique(labels[order], return_index=True)
        ends = [*starts[1:], len(order)]
        groups = {int(i): order[a:b] for i, a, b in zip(ids, starts, ends, strict=True)}
        todo = [(int(label), groups[int(label)]) for label in segmentation.segment_ids]

        def one(job: tuple[int, np.ndarray]):
            _, idx = job
            return clean_segment(pts[idx], tolerance=self.cfg.cluster_tolerance,
                                 min_points=self.cfg.min_segment_points)  # fmt: skip

        cleaned = thread_map(one, todo, name="ssp-clean")
        for (label, idx), c in zip(todo, cleaned, strict=True):
            labels[idx[~c.keep]] = -1
            if c.describe():
                verdicts[label] = f"removed {c.describe()}"

    def _estimate(
        self,
        pts: np.ndarray,
        segmentation: Segmentation,
        T_world_cam: np.ndarray | None,
        instance: bool,
        segments: dict[int, SegmentResult],
        verdicts: dict[int, str],
        timer: StageTimer,
    ) -> list[Hypothesis]:
        """The estimator's hypotheses for every segment of ``pts`` (world, m), with their
        results in ``segments`` and what was found in ``verdicts`` (per label); timed as
        ``normals``, ``hypotheses`` and ``estimation`` (forked lanes: ``lanes``). A segment
        unchanged since its hypotheses were estimated keeps them (``reuse_unchanged``,
        :mod:`ssp.perception.reuse`; timed as ``unchanged segments``)."""
        hypotheses: list[Hypothesis] = []
        cam = None if T_world_cam is None else np.asarray(T_world_cam)[:3, 3]
        seg_labels = [int(label) for label in segmentation.segment_ids]
        for label in seg_labels:
            cls = segmentation.classes.get(label)
            if cls is not None and cls not in self.library:
                raise UnknownObjectError(f"segment {label}: class {cls!r} not in the library")

        def one(label: int, _base=None, clock: StageTimer = timer) -> SegmentResult:
            """Normals and hypotheses of one segment (a forked lane times them on its own
            copy of ``timer``: what it worked is ``lanes``; a thread on its own ``clock``)."""
            with clock("normals"):
                request = self.segment_request(pts, segmentation, label, cam, instance)
            with clock("hypotheses"):
                return request.run(self.estimator)

        kept, shapes = self._recall(pts, segmentation, T_world_cam, instance, timer)
        todo = [label for label in seg_labels if label not in kept]
        lane_timer = StageTimer()
        forked = self.cfg.processes > 1 and len(todo) > 1
        threaded = not forked and len(todo) > 1 and KERNEL_THREADS > 1
        with timer("estimation"):
            if forked or threaded:
                # what estimate() caches is built here, before the fork or the threads, so
                # every lane has it and no two threads build it at once
                named = [segmentation.classes.get(label) for label in todo]
                self.estimator.prepare(
                    [c for c in named if c is not None]
                    + (list(self.classes) if None in named else []),
                    kernels=forked,
                )
            if threaded:
                estimated = self._in_threads(one, todo, timer)
            else:
                with ForkLanes(one, self.cfg.processes, lane_timer) as lanes:
                    estimated = lanes.run(None, todo) if todo else []
        results = dict(kept)
        results.update(zip(todo, estimated, strict=True))
        if self.cfg.reuse_unchanged and instance:
            self._remember(segmentation, shapes, {k: results[k] for k in todo})
        for label in seg_labels:
            res = results[label]
            segments[label] = res
            if instance:  # one object per segment: never grouped with another segment's
                hypotheses.extend(replace(h, segment=label) for h in res.hypotheses)
            else:
                hypotheses.extend(res.hypotheses)
            found = (
                "; ".join(f"{len(o)} hypotheses of {o[0].class_name}" for o in res.objects)
                if res.objects
                else f"no hypothesis: {res.stopped}"
            )
            if res.reused:
                found += " (kept from an earlier frame: the segment is unchanged)"
            verdicts[label] = "; ".join(v for v in (verdicts.get(label), found) if v)
            if not res.objects:
                log.info("segment %d: %s", label, verdicts[label])
        if LANES_STAGE in lane_timer.seconds:  # forked: the lanes' CPU seconds, apart
            timer.add(LANES_STAGE, lane_timer.seconds[LANES_STAGE])
        return hypotheses

    @staticmethod
    def _in_threads(
        one: Callable[..., SegmentResult], todo: list[int], timer: StageTimer
    ) -> list[SegmentResult]:
        """``one`` of each label of ``todo`` in :data:`~ssp.threads.KERNEL_THREADS` threads
        (:func:`ssp.threads.thread_map`; the estimator's kernels and tree queries release
        the GIL): the results of one segment after another, each seeded by its label. Each
        thread times its segments on its own clock, and ``timer`` gets the wall time of them
        all split by the work each stage had (:meth:`StageTimer.share`)."""
        clocks = [StageTimer() for _ in todo]
        t0 = time.perf_counter()
        out = thread_map(
            lambda k: one(todo[k], None, clocks[k]), range(len(todo)), name="ssp-segment"
        )
        worked: dict[str, float] = {}
        for clock in clocks:
            for stage, spent in clock.own.items():
                worked[stage] = worked.get(stage, 0.0) + spent
        timer.share(time.perf_counter() - t0, worked)
        return out

    def _recall(
        self, pts: np.ndarray, segmentation: Segmentation, T_world_cam: np.ndarray | None,
        instance: bool, timer: StageTimer,
    ) -> tuple[dict[int, SegmentResult], dict[int, SegmentShape]]:  # fmt: skip
        """The instance segments of ``pts`` unchanged since their hypotheses were estimated,
        with those (:mod:`ssp.perception.reuse`), and every segment's shape: ``({}, {})`` with
        ``reuse_unchanged`` off or clusters. Timed as ``unchanged segments``."""
        kept: dict[int, SegmentResult] = {}
        shapes: dict[int, SegmentShape] = {}
        if not self.cfg.reuse_unchanged:
            return kept, shapes
        if not instance:  # clusters are no object's (module ssp.perception.reuse)
            self.memory.forget()
            return kept, shapes
        self.memory.begin_frame()
        with timer("unchanged segments"):
            for label in (int(k) for k in segmentation.segment_ids):
                shapes[label] = SegmentShape.of(pts[segmentation.labels == label], T_world_cam)
                got = self.memory.recall(
                    label, self._classes_of(segmentation, label), shapes[label]
                )
                if got is not None:
                    kept[label] = got
        return kept, shapes

    def _remember(
        self, segmentation: Segmentation, shapes: dict[int, SegmentShape],
        estimated: dict[int, SegmentResult],
    ) -> None:  # fmt: skip
        """Remember this frame's ``estimated`` segments that are :func:`confident` with their
        ``shapes``; what this frame kept and remembered is the next frame's memory."""
        cfg = self.cfg
        for label, res in estimated.items():
            if confident(res, cfg.reuse_min_score, cfg.reuse_min_coverage, cfg.reuse_min_margin):
                classes = self._classes_of(segmentation, label)
                self.memory.remember(label, classes, shapes[label], res)
        self.memory.end_frame()


def _check_choice(name: str, value: object, allowed: tuple) -> None:
    """InputError naming ``name`` unless ``value`` is one of ``allowed``."""
    if value not in allowed:
        shown = ", ".join(repr(a) for a in allowed)
        raise InputError(f"{name} must be one of {shown}, got {value!r}")


def _checked_cloud(points: object, labels: object) -> tuple[np.ndarray, np.ndarray | None]:
    """``points`` as float ``(M, 3)`` without its non-finite rows, and ``labels`` as int64
    ``(M,)`` (the labels of those rows) or None.

    Raises:
        InputError: ``points`` not ``(N, 3)`` numbers or no finite row; ``labels`` not ``N``
            integers (one per point; ``(N, 1)`` is accepted).
    """
    try:
        pts = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"points must be an (N, 3) array of numbers (m): {exc}") from exc
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3) (x, y, z in m), got {pts.shape}")
    ok = np.isfinite(pts)
    # every row finite (the common case): copies, without a row-wise reduction and a masked copy
    finite = None if ok.all() and len(pts) else ok.all(axis=1)
    if finite is not None and not finite.any():
        raise InputError(f"empty cloud: no finite points (of {len(pts)})")
    if labels is None:
        return (pts.copy() if finite is None else pts[finite]), None
    lab = np.asarray(labels)
    if lab.shape not in ((len(pts),), (len(pts), 1)):
        raise InputError(
            f"labels must have shape ({len(pts)},) (one per point of the ({len(pts)}, 3) "
            f"points), got {lab.shape}"
        )
    lab = lab.reshape(-1)
    if lab.dtype == bool or not np.issubdtype(lab.dtype, np.number):
        raise InputError(f"labels must be integers (negative: background), got dtype {lab.dtype}")
    if not np.issubdtype(lab.dtype, np.integer):
        bad = ~np.isfinite(lab) | (lab != np.round(lab))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"labels must be integers (negative: background): label {k} is {lab[k].item()!r} "
                f"({int(bad.sum())} of {len(lab)} are not)"
            )
    if finite is None:
        return pts.copy(), lab.astype(np.int64)
    return pts[finite], lab[finite].astype(np.int64)
