"""Unchanged segments keep their hypotheses: the estimator's memory between frames (issue 34).

A static camera filming a static object sees its segment change by sensor noise only, and the
estimator, asked again, proposes the same poses up to that noise, at 40-50 ms a segment of a
640 x 480 frame (about half of such a frame's time with the built-in estimator). The front end
remembers what each segment looked like when its hypotheses were estimated
(:class:`SegmentShape`: the camera pose, the point count, the centroid and the covariance of
its points), and a segment of a later frame that looks the same keeps those hypotheses instead
of being estimated again (:attr:`SegmentResult.reused`):

* the camera pose the same (:func:`ssp.geometry.same_camera_pose`: within 1 mm and 0.5 deg;
  a static camera's pose is the same every frame, given or located);
* its points' count within :data:`SAME_POINTS` of the count then, their centroid within
  :data:`SAME_CENTROID`, their covariance within :data:`SAME_SPREAD` (relative, Frobenius);
* the same instance label and candidate classes.

Instance segments only (masks): a cluster of the cloud above the table is no object's, and
clusters merge and split with the noise (keeping the few that looked the same changed the
tools without masks for the worse on development seeds, and saved no time).

The thresholds sit at the upper end of a static segment's frame-to-frame noise on the
realistic sensor model (development seed 3 of ``ssp bench frame``'s sequences) and below a
move the parser tells from a static object (``temporal.static_translation``, 7.5 mm). The
shape compared is always the one the hypotheses were estimated on, so a slow drift is
estimated again once it adds up; a segment not seen in a frame is forgotten. Only a confident
estimate is kept (:func:`confident`): a doubtful one, or one whose view allows another
orientation nearly as well, is made again each frame. The hypotheses are proposals: the
parser aligns the poses it keeps to each frame's points.

The memory is part of a run's state (:meth:`SegmentMemory.state`), so a resumed run estimates
what the uninterrupted one did.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ssp.errors import SSPError
from ssp.geometry import same_camera_pose, validate_pose
from ssp.perception.estimator import SegmentResult
from ssp.scene import Hypothesis

__all__ = [
    "SAME_CENTROID",
    "SAME_POINTS",
    "SAME_SPREAD",
    "SegmentMemory",
    "SegmentShape",
    "confident",
]

#: A segment's point count within this fraction of the count then ...
SAME_POINTS = 0.04
#: ... its centroid within this (m) ...
SAME_CENTROID = 0.002
#: ... and its covariance within this fraction (Frobenius norms) look the same.
SAME_SPREAD = 0.05


@dataclass(frozen=True)
class SegmentShape:
    """What a segment looked like: ``T_world_cam`` (4, 4; None: no camera pose), ``points``
    (count), ``centroid`` (3,) m and ``spread`` (3, 3) covariance of its points, m^2."""

    T_world_cam: np.ndarray | None
    points: int
    centroid: np.ndarray
    spread: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, T_world_cam: np.ndarray | None) -> SegmentShape:
        """The shape of the segment ``points (K, 3)`` (world, m; K >= 2) seen from
        ``T_world_cam``."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        centroid = p.mean(axis=0)
        d = p - centroid
        spread = d.T @ d / max(len(p) - 1, 1)
        cam = None if T_world_cam is None else np.asarray(T_world_cam, dtype=float)
        return cls(cam, len(p), centroid, spread)

    def same(self, other: SegmentShape) -> bool:
        """Whether ``other`` (this frame's) looks like this one (module docstring); never
        without a camera pose."""
        if self.points <= 0 or not same_camera_pose(self.T_world_cam, other.T_world_cam):
            return False
        if abs(other.points - self.points) > SAME_POINTS * self.points:
            return False
        if np.linalg.norm(other.centroid - self.centroid) > SAME_CENTROID:
            return False
        scale = np.linalg.norm(self.spread)
        return bool(np.linalg.norm(other.spread - self.spread) <= SAME_SPREAD * scale)


def confident(
    result: SegmentResult, min_score: float, min_coverage: float, min_margin: float
) -> bool:
    """Whether ``result`` is kept for its segment's next frames: it found an object, and each
    object's best hypothesis scores at least ``min_score``, explains at least
    ``min_coverage`` of the segment's points, and beats every other orientation by at least
    ``min_margin`` (``perception.reuse_min_score``, ``reuse_min_coverage``,
    ``reuse_min_margin``). A less confident estimate is made again each frame, where another
    frame's noise may let the estimator find the object, or propose the orientation the view
    hides (docs/perception.md, "Unchanged segments keep their hypotheses"): kept, a tin
    proposed for a mug's segment just above the mug stayed for a static stage whose next
    estimates were right, and a mug whose handle the view hides kept one frame's yaws, which
    the orientations stage needs new each frame (the view-ambiguous protocol's mug error rose
    from 50.6 to 54.5 deg without the margin).
    """
    n = len(result.objects)
    if not n or len(result.coverage) != n or len(result.rival) != n:
        return False
    return all(
        best >= min_score and cover >= min_coverage and best - rival >= min_margin
        for best, cover, rival in zip(
            (max(h.score for h in obj) for obj in result.objects),
            result.coverage,
            result.rival,
            strict=True,
        )
    )


@dataclass(frozen=True)
class _Remembered:
    """A segment's hypotheses and the shape they were estimated on."""

    label: int  # the instance segment's label
    classes: tuple[str, ...]
    shape: SegmentShape
    result: SegmentResult


class SegmentMemory:
    """The segments of the last frame with the hypotheses they keep (module docstring).

    A frame asks :meth:`recall` for each of its segments and :meth:`remember` s each it
    estimated; :meth:`end_frame` then makes what this frame kept and estimated the memory of
    the next (a frame that fails before leaves the memory as it was).
    """

    def __init__(self) -> None:
        self._last: dict[int, _Remembered] = {}
        self._next: dict[int, _Remembered] = {}

    def recall(
        self, label: int, classes: Sequence[str], shape: SegmentShape
    ) -> SegmentResult | None:
        """The remembered result of instance segment ``label`` of this frame (its candidate
        ``classes``, its ``shape``) when it looks unchanged, marked reused (with no estimator
        time), or None; a recalled one is kept for the next frame with the shape it was
        estimated on."""
        r = self._last.get(label)
        if r is None or r.classes != tuple(classes) or not r.shape.same(shape):
            return None
        self._next[label] = r
        return replace(r.result, seconds=0.0, reused=True)

    def remember(
        self, label: int, classes: Sequence[str], shape: SegmentShape, result: SegmentResult
    ) -> None:
        """Remember instance segment ``label`` estimated in this frame."""
        self._next[label] = _Remembered(label, tuple(classes), shape, result)

    def end_frame(self) -> None:
        """This frame's segments become the ones the next frame recalls."""
        self._last, self._next = self._next, {}

    def begin_frame(self) -> None:
        """Drop what a frame that failed half-way recalled and remembered."""
        self._next = {}

    def forget(self) -> None:
        """Forget every segment (a frame without instance segments)."""
        self._last, self._next = {}, {}

    # ------------------------------------------------------------------ state
    def state(self) -> list[dict[str, Any]]:
        """JSON-ready: the segments the next frame recalls."""
        return [
            {
                "label": r.label,
                "classes": list(r.classes),
                "T_world_cam": None
                if r.shape.T_world_cam is None
                else np.asarray(r.shape.T_world_cam).tolist(),
                "points": r.shape.points,
                "centroid": r.shape.centroid.tolist(),
                "spread": r.shape.spread.tolist(),
                "objects": [
                    [[h.class_name, np.asarray(h.T_world_obj).tolist(), h.score] for h in obj]
                    for obj in r.result.objects
                ],
                "candidates": r.result.candidates,
                "stopped": r.result.stopped,
            }
            for r in self._last.values()
        ]

    def restore(self, state: Sequence[Mapping[str, Any]]) -> None:
        """Recall the segments of :meth:`state` next.

        Raises:
            SSPError: a malformed entry (or a pose that is not rigid).
        """
        out: dict[int, _Remembered] = {}
        try:
            for e in state:
                cam = e["T_world_cam"]
                shape = SegmentShape(
                    None if cam is None else validate_pose(np.asarray(cam, dtype=float)),
                    int(e["points"]),
                    np.asarray(e["centroid"], dtype=float).reshape(3),
                    np.asarray(e["spread"], dtype=float).reshape(3, 3),
                )
                objects = [
                    [Hypothesis(str(c), validate_pose(np.asarray(T, dtype=float)), float(s))
                     for c, T, s in obj]
                    for obj in e["objects"]
                ]  # fmt: skip
                result = SegmentResult(objects, 0.0, int(e["candidates"]), str(e["stopped"]))
                label = int(e["label"])
                out[label] = _Remembered(label, tuple(str(c) for c in e["classes"]), shape, result)
        except (KeyError, TypeError, ValueError) as exc:
            raise SSPError(f"malformed segment memory in the run state: {exc!r}") from exc
        self._last, self._next = out, {}
