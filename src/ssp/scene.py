"""Inputs of one frame: the scene cloud, pose hypotheses, transition modes (DESIGN section 1).

Units are metres, the world frame has z up (DESIGN section 3). :meth:`Frame.validate` is the one
place where a frame from outside (files, ROS, a user's script) is checked and cleaned before the
scene parser sees it: everything after it may assume finite points and rigid poses.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ssp.errors import InvalidPoseError, SSPError
from ssp.geometry import validate_pose

__all__ = ["MM_CLOUD_MEDIAN", "Frame", "FrameError", "Hypothesis", "TransitionMode"]

log = logging.getLogger(__name__)

#: A cloud whose median distance from the world origin exceeds this (m) is taken to be in mm.
MM_CLOUD_MEDIAN = 50.0
#: That median is taken over at most about this many evenly strided points of the cloud.
UNITS_SAMPLE = 10_000


class FrameError(SSPError, ValueError):
    """A frame (cloud, labels, hypotheses, camera pose) that cannot be used."""


class TransitionMode(str, enum.Enum):
    """The five transition modes of an object between two frames (paper section IV-C)."""

    ADDED = "added"
    REMOVED = "removed"
    PERTURBED = "perturbed"
    STATIC = "static"
    SUPPORT_RETAINED = "support_retained"

    def __str__(self) -> str:
        return self.value


@dataclass
class Hypothesis:
    """One pose hypothesis: an object of ``class_name`` at ``T_world_obj`` (4x4, metres).

    ``score`` is the pose generator's confidence (higher is better; only its order matters).
    ``instance_id`` is set when the source already knows which object this is (tracking,
    simulation ground truth); otherwise :func:`ssp.temporal.associate` assigns one.
    ``segment`` is the label of the instance segment (one object, this frame only) the
    hypothesis was estimated from, when the segmentation separates objects: hypotheses of
    different segments are then never taken for one object.
    """

    class_name: str
    T_world_obj: np.ndarray
    score: float = 1.0
    instance_id: str | None = None
    segment: int | None = None


#: What a label of :attr:`Frame.labels` may be.
LABEL_KINDS = ("instance", "cluster")


@dataclass
class Frame:
    """One observation: the cloud and the hypotheses at time ``stamp`` (s).

    Attributes:
        stamp: time of the frame, s.
        points: ``(N, 3)`` scene points in the world frame, m.
        hypotheses: pose hypotheses (several may describe one object).
        labels: optional ``(N,)`` integer segment label per point; negative labels mark points
            of no object (table, background).
        label_kind: what a label is: ``"instance"`` one object's segment (an instance mask),
            or ``"cluster"`` a piece of the cloud that may hold several objects (touching
            objects clustered together): an object is then not judged by how much of its
            label it accounts for, and its data are the points near it, not the whole label.
        segments: optional points ``(K, 3)`` per instance id (the object's own segment).
        T_world_cam: optional camera pose (OpenCV camera frame), for visibility reasoning.
        moved: optional ``{id: T_world_obj or None}``: known objects that something which
            knows (the robot that picked and placed them) moved since the previous frame, with
            the pose it put each one at (4, 4, m), or None when it left the scene (held in
            the gripper, taken away). The parser takes that pose as the object's previous
            one; the data still decides where it is. Without it, an object picked from a place
            the camera cannot see (hidden behind a tower) stays there as a ghost.
    """

    stamp: float
    points: np.ndarray
    hypotheses: list[Hypothesis] = field(default_factory=list)
    labels: np.ndarray | None = None
    segments: dict[str, np.ndarray] | None = None
    T_world_cam: np.ndarray | None = None
    moved: dict[str, np.ndarray | None] | None = None
    label_kind: str = "instance"

    @property
    def instance_masks(self) -> bool:
        """Whether the frame has instance masks: labels, each one object's segment."""
        return self.labels is not None and self.label_kind == "instance"

    def moved_by(self, T_new_world: np.ndarray) -> Frame:
        """This frame expressed in another world frame: points, segments, hypotheses, the
        camera pose and ``moved`` poses moved by ``T_new_world`` (4, 4; the new world from
        this one's), labels and stamps as they are."""
        M = np.asarray(T_new_world, dtype=float)

        def pts(p):
            return np.asarray(p, dtype=float) @ M[:3, :3].T + M[:3, 3]

        return replace(
            self,
            points=pts(self.points),
            hypotheses=[replace(h, T_world_obj=M @ h.T_world_obj) for h in self.hypotheses],
            segments=None
            if self.segments is None
            else {k: pts(v) for k, v in self.segments.items()},
            T_world_cam=None if self.T_world_cam is None else M @ self.T_world_cam,
            moved=None
            if self.moved is None
            else {k: None if T is None else M @ T for k, T in self.moved.items()},
        )

    def validate(self, library: Mapping[str, Any]) -> Frame:
        """Return a cleaned copy of this frame, or raise :class:`FrameError`.

        Checks, in order: ``stamp`` finite; ``points`` shaped ``(N, 3)`` and numeric, non-finite
        rows dropped (the count is logged; ``labels`` are dropped with them), at least one left;
        the cloud is in metres (median distance from the origin <= :data:`MM_CLOUD_MEDIAN`, over
        about :data:`UNITS_SAMPLE` points);
        ``labels`` integer-valued of length N; each segment ``(K, 3)`` (non-finite rows
        dropped); ``T_world_cam`` rigid; ``hypotheses`` a list of :class:`Hypothesis` with a
        class name (str) in ``library``, ``instance_id`` None or a str, ``segment`` None or an
        int, a finite score and a rigid pose (:func:`validate_pose`, re-orthonormalised) within
        :data:`MM_CLOUD_MEDIAN` of the origin; one instance id never names two classes; ``moved``
        a mapping of ids to rigid poses or None.

        Args:
            library: the object library (anything with ``in`` and ``names``/iteration, such
                as :class:`ssp.library.ObjectLibrary`).
        """
        stamp = _finite_float(self.stamp, "frame stamp")
        points, keep = _validate_cloud(self.points)
        if self.label_kind not in LABEL_KINDS:
            raise FrameError(
                f"label_kind must be one of {', '.join(LABEL_KINDS)}, got {self.label_kind!r}"
            )
        labels = None if self.labels is None else _validate_labels(self.labels, keep)
        segments = None if self.segments is None else _validate_segments(self.segments)
        T_world_cam = None
        if self.T_world_cam is not None:
            try:
                T_world_cam = validate_pose(self.T_world_cam, "T_world_cam")
            except InvalidPoseError as exc:
                raise FrameError(f"camera pose is invalid: {exc}") from exc

        hypotheses = _validate_hypotheses(self.hypotheses, library, points)
        return Frame(
            stamp=stamp,
            points=points,
            hypotheses=hypotheses,
            labels=labels,
            segments=segments,
            T_world_cam=T_world_cam,
            moved=_validate_moved(self.moved),
            label_kind=self.label_kind,
        )


def _validate_cloud(raw: Any) -> tuple[np.ndarray, np.ndarray]:
    """:attr:`Frame.points` without its non-finite rows, and the mask of the rows kept;
    checks that some are left and that they are in metres."""
    points, keep = _clean_points(raw, "frame points")
    if len(points) == 0:
        raise FrameError(
            "empty cloud: the frame has no finite points"
            + (f" (all {len(keep)} were NaN or infinite)" if len(keep) else "")
        )
    # the units check needs no more than an evenly strided subset of a large cloud
    sample = points[:: max(1, len(points) // UNITS_SAMPLE)]
    median = float(np.median(np.linalg.norm(sample, axis=1)))
    if median > MM_CLOUD_MEDIAN:
        raise FrameError(
            f"cloud median distance from the origin is {median:.1f} m; points look like "
            "millimetres (ssp works in metres): divide them by 1000"
        )
    return points, keep


def _validate_labels(raw: Any, keep: np.ndarray) -> np.ndarray:
    """:attr:`Frame.labels` (integer-valued, one per point) of the points ``keep`` kept."""
    labels = np.asarray(raw)
    if labels.ndim != 1 or len(labels) != len(keep):
        raise FrameError(
            f"labels must have shape ({len(keep)},) (one per point), got {labels.shape}"
        )
    if not np.issubdtype(labels.dtype, np.integer):
        if not (
            np.issubdtype(labels.dtype, np.number)
            and np.all(np.isfinite(labels))
            and np.all(labels == np.round(labels))
        ):
            raise FrameError("labels must be integers (one segment label per point)")
    return labels[keep].astype(np.int64)


def _validate_segments(raw: Any) -> dict[str, np.ndarray]:
    """Checked copy of :attr:`Frame.segments` (string ids, non-finite rows dropped)."""
    if not isinstance(raw, Mapping):
        raise FrameError(
            f"segments must be a mapping {{instance id: (K, 3) points}}, got {type(raw).__name__}"
        )
    segments = {}
    for key, seg in raw.items():
        segments[str(key)], _ = _clean_points(seg, f"segment {key!r}", allow_empty=True)
    return segments


def _validate_moved(moved: Any) -> dict[str, np.ndarray | None] | None:
    """Checked copy of :attr:`Frame.moved` (ids are strings, poses rigid or None)."""
    if moved is None:
        return None
    if not isinstance(moved, Mapping):
        raise FrameError(
            f"moved must be a mapping {{object id: T_world_obj or None}}, got "
            f"{type(moved).__name__}"
        )
    out: dict[str, np.ndarray | None] = {}
    for oid, T in moved.items():
        if not isinstance(oid, str) or not oid:
            raise FrameError(f"moved: object ids must be non-empty strings, got {oid!r}")
        if T is None:
            out[oid] = None
            continue
        try:
            out[oid] = validate_pose(T, f"moved[{oid!r}]")
        except InvalidPoseError as exc:
            raise FrameError(f"invalid pose: {exc}") from exc
    return out


def _validate_hypotheses(
    hypotheses: Any, library: Mapping[str, Any], points: np.ndarray
) -> list[Hypothesis]:
    """Checked copies of a frame's hypotheses (:meth:`Frame.validate`); FrameError naming the
    hypothesis (index and class) and the problem."""
    if not isinstance(hypotheses, (list, tuple)):
        raise FrameError(
            "hypotheses must be a list of ssp.Hypothesis (an empty list for none), got "
            f"{type(hypotheses).__name__}"
        )
    known = ", ".join(getattr(library, "names", None) or list(library)) or "none"
    out: list[Hypothesis] = []
    classes_of_id: dict[str, tuple[int, str]] = {}
    for i, h in enumerate(hypotheses):
        if not isinstance(h, Hypothesis):
            raise FrameError(
                f"hypothesis {i}: expected an ssp.Hypothesis, got {type(h).__name__} "
                "(build one with Hypothesis(class_name, T_world_obj, score))"
            )
        if not isinstance(h.class_name, str) or not h.class_name:
            raise FrameError(
                f"hypothesis {i}: class_name must be a non-empty string, got "
                f"{type(h.class_name).__name__} {h.class_name!r}"
            )
        what = f"hypothesis {i} ({h.class_name!r})"
        if h.class_name not in library:
            raise FrameError(f"{what}: unknown object class; known classes: {known}")
        iid = h.instance_id
        if iid is not None and (not isinstance(iid, str) or not iid):
            raise FrameError(
                f"{what}: instance_id must be None or a non-empty string, got "
                f"{type(iid).__name__} {iid!r}" + (f" (use {str(iid)!r})" if iid != "" else "")
            )
        seg = h.segment
        if seg is not None:
            if isinstance(seg, bool) or not isinstance(seg, (int, np.integer)):
                raise FrameError(
                    f"{what}: segment must be None or an integer label, got "
                    f"{type(seg).__name__} {seg!r}"
                )
            seg = int(seg)
        if iid is not None:
            first = classes_of_id.setdefault(iid, (i, h.class_name))
            if first[1] != h.class_name:
                raise FrameError(
                    f"instance id {iid!r} is given to two classes in one frame: hypothesis "
                    f"{first[0]} ({first[1]!r}) and {what}; one id is one object"
                )
        try:
            T = validate_pose(h.T_world_obj, what)
        except InvalidPoseError as exc:
            raise FrameError(f"invalid pose of {exc}") from exc
        score = _finite_float(h.score, f"{what}: score")
        out.append(replace(h, T_world_obj=T, score=score, segment=seg))
    far = [k for k, h in enumerate(out) if np.linalg.norm(h.T_world_obj[:3, 3]) > MM_CLOUD_MEDIAN]
    if far:
        raise FrameError(_far_message(out, far[0], points))
    return out


def _far_message(hypotheses: list[Hypothesis], k: int, points: np.ndarray) -> str:
    """Why hypothesis ``k`` (farther than :data:`MM_CLOUD_MEDIAN` from the origin) is rejected:
    its distance from the origin and from the cloud, and "millimetres" only when that is
    plausible (scaled by 1/1000 it lies in the cloud's box, and no hypothesis of the frame
    lies near the cloud in metres)."""
    h = hypotheses[k]
    t = h.T_world_obj[:3, 3]
    lo, hi = points.min(axis=0), points.max(axis=0)

    def gap(p: np.ndarray) -> float:  # distance from the cloud's bounding box, m
        return float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - p, p - hi))))

    nearest = float(np.sqrt(np.min(np.sum((points - t) ** 2, axis=1))))
    reach = float(np.max(np.linalg.norm(points, axis=1)))
    msg = (
        f"hypothesis {k} ({h.class_name!r}): translation {np.round(t, 3).tolist()} is "
        f"{np.linalg.norm(t):.1f} m from the world origin and {nearest:.1f} m from the nearest "
        f"point of the cloud (which lies within {reach:.2f} m of the origin)"
    )
    in_metres = [j for j, o in enumerate(hypotheses) if gap(o.T_world_obj[:3, 3]) < 1.0]
    if gap(t / 1000.0) < 0.1 and not in_metres:
        return msg + "; it looks like millimetres (ssp works in metres): divide it by 1000"
    if in_metres:
        return msg + (
            f"; the frame's other hypotheses (e.g. {in_metres[0]}) lie at the cloud, so this "
            "one is an outlier or a wrong pose"
        )
    return msg + "; no object of the scene can be there: check its frame and pose"


def _clean_points(
    points: Any, what: str, allow_empty: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``(finite points (M, 3) float64, keep mask (N,))``; FrameError on a wrong shape."""
    try:
        arr = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise FrameError(f"{what}: not a numeric (N, 3) array ({exc})") from exc
    if arr.size == 0 and (allow_empty or arr.ndim < 2):
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FrameError(f"{what}: expected shape (N, 3), got {arr.shape}")
    finite = np.isfinite(arr)
    if finite.all():  # the common case, without a row-wise reduction and a masked copy
        return arr.copy(), np.ones(len(arr), dtype=bool)
    keep = finite.all(axis=1)
    dropped = int(len(keep) - keep.sum())
    if dropped and keep.any():
        log.info("%s: dropped %d of %d non-finite points", what, dropped, len(keep))
    return arr[keep], keep


def _finite_float(value: object, what: str) -> float:
    """``value`` as a finite float, or :class:`FrameError` naming ``what``."""
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise FrameError(f"{what} must be a number, got {value!r}") from exc
    if not math.isfinite(out):
        raise FrameError(f"{what} must be finite, got {out}")
    return out
