"""The world frame of an input whose camera pose is not given (issue 32).

A BOP scene without ``cam_R_w2c`` or a bag without tf gives each frame's cloud in its camera's
frame only. :class:`CameraLocator` puts the frames in one world frame, the table's in the first
frame, by locating the camera in each (:class:`ssp.perception.egomotion.CameraTracker`: the
table plane, then a registration of the points above the table to those of the frames
before, checked against the free space the new view sees; a jump, as between BOP-style
keyframes, by the global search). The frame JSON's ``camera`` says how
(:meth:`ssp.perception.egomotion.CameraFix.as_dict`).

The parser's objects are not a registration target here, though the tracker can take them
(:meth:`~ssp.perception.egomotion.CameraTracker.know`): objects estimated in a frame carry
that frame's camera error into the next (on a development orbit, with an earlier version of
the tracker, registering to them made the camera's error several times the points' alone).

A frame whose camera cannot be located is not guessed: the world frame starts again from its
table (``camera.how`` ``"restarted"``, a warning of the frame), and the parser forgets the
scene (its objects were placed in the old frame; :func:`ssp.pipeline.run.run` calls
:meth:`ssp.parser.SceneParser.reset` with ``keep_ids``): the frame's objects are new tracks
with new ids, and nothing the old frame held is reported moved. A resumed run brings the
locator to where the uninterrupted run left it from the committed frames' records
(:meth:`CameraLocator.replay`): their camera poses, exactly as written.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from ssp.errors import PerceptionError
from ssp.perception.egomotion import CameraFix, CameraNotLocatedError, CameraTracker, table_pose

__all__ = ["GIVEN_HEIGHT", "GIVEN_SHIFT", "GIVEN_TILT_DEG", "RESTARTED", "CameraLocator"]

log = logging.getLogger(__name__)

RESTARTED = "restarted"
"""``camera.how`` of a frame whose camera was not located: the world frame starts again."""
GIVEN_TILT_DEG = 2.0
"""A given camera pose whose world z leans from the table's normal by more than this
(degrees) ..."""
GIVEN_HEIGHT = 0.01
"""... or puts the table farther than this from z = 0 (m) ..."""
GIVEN_SHIFT = 0.005
"""... or whose frame's static points register farther than this (m, on average) from where
it puts them, relative to the frames given before, is said in the frame's warnings."""


class CameraLocator:
    """``T_world_cam`` of the frames of a camera with no pose given (:meth:`locate`; module
    docstring), or the check of a given one (:meth:`check`).

    Args:
        table_distance: the table fit's inlier distance, m.
    """

    def __init__(self, table_distance: float) -> None:
        self.table_distance = float(table_distance)
        self.tracker = CameraTracker(self.table_distance, search=True)

    @property
    def started(self) -> bool:
        """Whether a frame has been located (or replayed)."""
        return self.tracker.T_world_cam is not None

    def locate(self, points_cam: np.ndarray, warnings: list[str]) -> tuple[np.ndarray, dict]:
        """``(T_world_cam (4, 4), how it was found: CameraFix.as_dict() with "how")`` of the
        frame of camera-frame points ``points_cam`` (N, 3; m). A camera not located starts
        the world frame again (``how`` :data:`RESTARTED`; a warning in ``warnings``).

        Raises:
            TableNotFoundError: no table in the frame (the locator is unchanged).
        """
        try:
            fix = self.tracker.update(points_cam)
            return fix.T_world_cam, fix.as_dict()
        except CameraNotLocatedError as exc:
            tracker = CameraTracker(self.table_distance, search=True)
            fix = tracker.update(points_cam)  # the table's frame; raises when there is none
            self.tracker = tracker
            warnings.append(
                f"camera not located ({exc}): the world frame starts again from this frame's "
                "table and the objects before are forgotten (a moving camera's pose can be "
                "given: cam_R_w2c/cam_t_w2c in scene_camera.json, or tf)"
            )
            log.warning("%s", warnings[-1])
            return fix.T_world_cam, {**fix.as_dict(), "how": RESTARTED}

    def own_table(self, points_cam: np.ndarray) -> tuple[np.ndarray, dict]:
        """``(T_world_cam, how: "table")`` of a frame in its own world, its table's
        (:func:`ssp.perception.egomotion.table_pose`), the frames before not used: for
        single-frame work (the estimator alone), where a located camera costs a registration
        a frame and buys nothing.

        Raises:
            TableNotFoundError: no table in the frame.
        """
        T = table_pose(points_cam, self.table_distance)
        return T, CameraFix(T, "table").as_dict()

    def check(self, points_cam: np.ndarray, T_world_cam: np.ndarray, warnings: list[str]) -> dict:
        """How a given camera pose agrees with the frame's data
        (:meth:`ssp.perception.egomotion.CameraTracker.check`; the frame JSON's ``camera``,
        ``how`` ``"given"``): a pose that does not put the table at z = 0 with z up, or that
        the static points of the frames given before contradict, is said in ``warnings``
        (:data:`GIVEN_TILT_DEG`, :data:`GIVEN_HEIGHT`, :data:`GIVEN_SHIFT`); it is used all
        the same (ssp does not overrule a given pose).

        A frame without a table is not checked (``tilt_deg`` None).
        """
        try:
            out = self.tracker.check(points_cam, T_world_cam)
        except PerceptionError as exc:  # no table to check by: the pose is used unchecked
            log.debug("given camera pose not checked: %s", exc)
            return {"how": "given", "tilt_deg": None, "height_mm": None, "shift_mm": None,
                    "inliers": None}  # fmt: skip
        said = len(warnings)
        if out["tilt_deg"] > GIVEN_TILT_DEG or abs(out["height_mm"]) > 1000 * GIVEN_HEIGHT:
            warnings.append(
                f"the given camera pose puts the table {out['height_mm']:.0f} mm from z = 0 and "
                f"its normal {out['tilt_deg']:.1f} deg from z: ssp's world is z up with the "
                "table top at z = 0 (physics pulls along -z)"
            )
        if out["shift_mm"] is not None and out["shift_mm"] > 1000 * GIVEN_SHIFT:
            warnings.append(
                f"the given camera pose disagrees with the static scene: the points above the "
                f"table register {out['shift_mm']:.1f} mm (on average) from where it puts "
                "them, relative to the frames before (a wrong extrinsic or stamp, or most of "
                "the scene moved)"
            )
        for w in warnings[said:]:
            log.warning("%s", w)
        return out

    def replay(self, points_cam: np.ndarray, record: Mapping) -> None:
        """A committed frame of a resumed run: its frame JSON ``record`` (``T_world_cam`` and
        ``camera``) and its points. A failed frame (no pose) leaves the locator unchanged."""
        T = record.get("T_world_cam")
        camera = record.get("camera") or {}
        if record.get("status") == "failed" or T is None:
            return
        if camera.get("how") == RESTARTED:
            self.tracker = CameraTracker(self.table_distance, search=True)
        try:
            if camera.get("how") == "given":
                self.tracker.checked(T, points_cam, camera)
            else:
                tracked = camera.get("how") in ("tracked", "kept", "searched")
                self.tracker.accept(np.asarray(T, dtype=float), np.asarray(points_cam, dtype=float),
                                    tracked)  # fmt: skip
        except PerceptionError:
            pass  # a given pose on a frame without a table: the run did not map it either
