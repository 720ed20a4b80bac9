"""Identity over time: id switches of tracked estimates, as multi-object tracking counts them.

CLEAR MOT (Bernardin and Stiefelhagen, 2008): each ground-truth object remembers the id of the
estimate it was last matched to; when it is matched to an estimate with another id, that is an
*id switch* (two objects that swap ids are two switches). Frames in which the object is not
matched do not reset the memory, so an object that is lost and found again under a new id also
counts. A switch is *static* when the object has not moved since its last match (its true pose
within :data:`STATIC_SHIFT` and :data:`STATIC_TILT_DEG`): a tracker should never switch then.
Methods without ids (memoryless estimators) have no switches to count.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ssp.probability import pose_change

__all__ = ["FLIP_DEG", "STATIC_SHIFT", "STATIC_TILT_DEG", "Flips", "IdSwitches", "ReportedMoves"]

#: A ground-truth object moved less than this since its last match is static (m, deg).
STATIC_SHIFT = 0.0005
STATIC_TILT_DEG = 0.5

#: An estimate of an object that did not move, turned by more than this (deg, symmetry-aware)
#: since its last match, flipped (an estimator's distinct orientations differ by more).
FLIP_DEG = 15.0


class IdSwitches:
    """Counts id switches over one sequence (module docstring); :meth:`update` per frame."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[str, np.ndarray]] = {}
        self.switches = 0
        self.static_switches = 0
        self.events: list[dict] = []

    def update(
        self,
        frame: int,
        gt: Mapping[str, tuple[str, np.ndarray]],
        matched_ids: Mapping[str, str | None],
    ) -> None:
        """``matched_ids``: ground-truth id -> id of the estimate matched to it this frame
        (absent or None: not matched, or the estimate has no id)."""
        for gid, eid in matched_ids.items():
            if eid is None or gid not in gt:
                continue
            T = np.asarray(gt[gid][1], dtype=float)
            last = self._last.get(gid)
            if last is not None and last[0] != eid:
                dt, dr = pose_change(last[1], T)
                static = dt < STATIC_SHIFT and math.degrees(dr) < STATIC_TILT_DEG
                self.switches += 1
                self.static_switches += int(static)
                self.events.append(
                    {"frame": int(frame), "object": gid, "from": last[0], "to": eid,
                     "static": bool(static)}
                )  # fmt: skip
            self._last[gid] = (eid, T.copy())


class Flips:
    """Orientation flips over one sequence: an object that did not move since its last match
    (as for a static id switch) whose matched estimate turned by more than :data:`FLIP_DEG`
    (symmetry-aware, about its centre of mass). ``from_right``: those that left an
    orientation within ``right_deg`` of the truth (a decided object should never)."""

    def __init__(self, right_deg: float = 10.0) -> None:
        self._last: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # id -> (T_gt, T_est)
        self.right_deg = float(right_deg)
        self.flips = 0
        self.from_right = 0

    def update(
        self,
        gt: Mapping[str, tuple[str, np.ndarray]],
        matched: Mapping[str, np.ndarray],
        models: Mapping,
    ) -> None:
        """``matched``: ground-truth id -> the pose (4x4) of the estimate matched to it this
        frame; ``models``: class name -> model (its symmetry and centre of mass)."""
        for gid, T_est in matched.items():
            cls, T_gt = gt[gid]
            m = models[cls]
            T_gt, T_est = np.asarray(T_gt, dtype=float), np.asarray(T_est, dtype=float)
            last = self._last.get(gid)
            if last is not None:
                dt, dr = pose_change(last[0], T_gt)
                if dt < STATIC_SHIFT and math.degrees(dr) < STATIC_TILT_DEG:
                    turn = pose_change(last[1], T_est, m.symmetry, m.center_of_mass)[1]
                    if math.degrees(turn) > FLIP_DEG:
                        self.flips += 1
                        was = pose_change(T_gt, last[1], m.symmetry, m.center_of_mass)[1]
                        self.from_right += int(math.degrees(was) <= self.right_deg)
            self._last[gid] = (T_gt, T_est)


class ReportedMoves:
    """Transition modes against the truth. *Reported moved, not moved*: a matched estimate
    whose transition mode is ``perturbed`` while its object has not moved in the world since
    its last match (as for a static id switch); a moving camera must not make the scene's
    objects move, nor a corrected estimate. *Moved, reported static*: a matched estimate whose
    mode is ``static`` while its object moved more than the parser's static thresholds
    (``shift``, m; ``tilt_deg``; ``temporal.static_translation`` and ``static_rotation``)
    since its last match. Only methods that report transition modes (ssp) are counted;
    ``static`` and ``moving``: the object-frames that could have been so reported."""

    def __init__(self, shift: float = 0.0075, tilt_deg: float = 5.0) -> None:
        self._last: dict[str, np.ndarray] = {}
        self._shift, self._tilt = shift, tilt_deg
        self.static = 0
        self.moved = 0
        self.moving = 0
        self.unreported = 0

    def update(self, gt: Mapping[str, tuple[str, np.ndarray]], modes: Mapping[str, str]) -> None:
        """``modes``: ground-truth id -> the transition mode of the estimate matched to it
        this frame (ids without a match or a mode left out)."""
        for gid, mode in modes.items():
            T = np.asarray(gt[gid][1], dtype=float)
            last = self._last.get(gid)
            if last is not None:
                dt, dr = pose_change(last, T)
                if dt < STATIC_SHIFT and math.degrees(dr) < STATIC_TILT_DEG:
                    self.static += 1
                    self.moved += int(str(mode) == "perturbed")
                elif dt >= self._shift or math.degrees(dr) >= self._tilt:
                    self.moving += 1
                    self.unreported += int(str(mode) == "static")
            self._last[gid] = T.copy()
