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


class FrameError(SSPError, ValueError):
    """A frame (cloud, labels, hypotheses, camera pose) that cannot be used."""


class TransitionMode(str, enum.Enum):
    """The five transition modes of an object between two frames (paper section V-C)."""

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


@dataclass
class Frame:
    """One observation: the cloud and the hypotheses at time ``stamp`` (s).

    Attributes:
        stamp: time of the frame, s.
        points: ``(N, 3)`` scene points in the world frame, m.
        hypotheses: pose hypotheses (several may describe one object).
        labels: optional ``(N,)`` integer segment label per point; negative labels mark points
            of no object (table, background).
        segments: optional points ``(K, 3)`` per instance id (the object's own segment).
        T_world_cam: optional camera pose (OpenCV camera frame), for visibility reasoning.
    """

    stamp: float
    points: np.ndarray
    hypotheses: list[Hypothesis] = field(default_factory=list)
    labels: np.ndarray | None = None
    segments: dict[str, np.ndarray] | None = None
    T_world_cam: np.ndarray | None = None

    def validate(self, library: Mapping[str, Any]) -> Frame:
        """Return a cleaned copy of this frame, or raise :class:`FrameError`.

        Checks, in order: ``stamp`` finite; ``points`` shaped ``(N, 3)`` and numeric, non-finite
        rows dropped (the count is logged; ``labels`` are dropped with them), at least one left;
        the cloud is in metres (median distance from the origin <= :data:`MM_CLOUD_MEDIAN`);
        ``labels`` integer-valued of length N; each segment ``(K, 3)`` (non-finite rows
        dropped); ``T_world_cam`` and every hypothesis pose rigid (:func:`validate_pose`,
        re-orthonormalised); hypothesis scores finite; every class name in ``library``.

        Args:
            library: the object library (anything with ``in`` and ``names``/iteration, such
                as :class:`ssp.library.ObjectLibrary`).
        """
        stamp = _finite_float(self.stamp, "frame stamp")

        points, keep = _clean_points(self.points, "frame points")
        if len(points) == 0:
            raise FrameError(
                "empty cloud: the frame has no finite points"
                + (f" (all {len(keep)} were NaN or infinite)" if len(keep) else "")
            )
        median = float(np.median(np.linalg.norm(points, axis=1)))
        if median > MM_CLOUD_MEDIAN:
            raise FrameError(
                f"cloud median distance from the origin is {median:.1f} m; points look like "
                "millimetres (ssp works in metres): divide them by 1000"
            )

        labels = None
        if self.labels is not None:
            labels = np.asarray(self.labels)
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
            labels = labels[keep].astype(np.int64)

        segments = None
        if self.segments is not None:
            segments = {}
            for key, seg in self.segments.items():
                segments[str(key)], _ = _clean_points(seg, f"segment {key!r}", allow_empty=True)

        T_world_cam = None
        if self.T_world_cam is not None:
            try:
                T_world_cam = validate_pose(self.T_world_cam, "T_world_cam")
            except InvalidPoseError as exc:
                raise FrameError(f"camera pose is invalid: {exc}") from exc

        known = ", ".join(getattr(library, "names", None) or list(library)) or "none"
        hypotheses = []
        for i, h in enumerate(self.hypotheses):
            what = f"hypothesis {i} ({h.class_name!r})"
            if h.class_name not in library:
                raise FrameError(f"{what}: unknown object class; known classes: {known}")
            try:
                T = validate_pose(h.T_world_obj, what)
            except InvalidPoseError as exc:
                raise FrameError(f"invalid pose of {exc}") from exc
            if np.linalg.norm(T[:3, 3]) > MM_CLOUD_MEDIAN:
                raise FrameError(
                    f"{what}: translation {np.linalg.norm(T[:3, 3]):.1f} m from the origin looks "
                    "like millimetres (ssp works in metres): divide it by 1000"
                )
            score = _finite_float(h.score, f"{what}: score")
            hypotheses.append(replace(h, T_world_obj=T, score=score))

        return Frame(
            stamp=stamp,
            points=points,
            hypotheses=hypotheses,
            labels=labels,
            segments=segments,
            T_world_cam=T_world_cam,
        )


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
    keep = np.all(np.isfinite(arr), axis=1)
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
