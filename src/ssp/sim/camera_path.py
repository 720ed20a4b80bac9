"""Camera paths of the simulated protocols (issue 32: moving cameras).

The paper's sensor is static; the data users bring is not. BOP test scenes are filmed by a
camera moving around the table, images often 10-30 degrees apart; a hand-held or wrist camera
shakes. Each path gives one ``T_world_cam`` (4, 4, OpenCV axes) per frame; frame 0 is always
the static camera (:func:`ssp.sim.generate.default_camera_pose`), so a path changes only what
follows:

``"static"``
    every frame at the static camera (the paper's protocol).
``"orbit"``
    around the vertical axis through the workspace centre, :data:`ORBIT_DEG` per frame,
    drifting sideways :data:`ORBIT_DRIFT` per frame, its elevation swaying
    :data:`ORBIT_SWAY_DEG` (a user walking around the table with the camera: the issue's
    real YCB-V re-projection turned 36 degrees and drifted 72 mm in 10 frames).
``"handheld"``
    about the static camera, shaking: the eye and the point looked at follow a random walk
    pulled back to the static pose (AR(1) with :data:`HANDHELD_RHO`; stationary spreads
    :data:`HANDHELD_EYE` and :data:`HANDHELD_TARGET`), rolled by about :data:`HANDHELD_ROLL_DEG`.
``"keyframes"``
    BOP-style sparse views: each frame turned :data:`KEYFRAME_STEP_DEG` (10-30 degrees, one
    direction per sequence) about the table's vertical axis from the last, at an elevation
    and distance drawn from :data:`KEYFRAME_ELEVATION_DEG` and :data:`KEYFRAME_DISTANCE`.

Randomness: ``default_rng([seed, 3])``, apart from the layout's and the frames' streams, so a
path never changes the scene, its depth noise or its hypotheses' draws.
"""

from __future__ import annotations

import numpy as np

from ssp.errors import ArgumentError
from ssp.geometry import yaw_pose
from ssp.sim.render import look_at

__all__ = [
    "CAMERA_PATHS",
    "HANDHELD_EYE",
    "HANDHELD_RHO",
    "HANDHELD_ROLL_DEG",
    "HANDHELD_TARGET",
    "KEYFRAME_DISTANCE",
    "KEYFRAME_ELEVATION_DEG",
    "KEYFRAME_STEP_DEG",
    "ORBIT_DEG",
    "ORBIT_DRIFT",
    "ORBIT_SWAY_DEG",
    "camera_path",
]

#: The camera paths (module docstring).
CAMERA_PATHS: tuple[str, ...] = ("static", "orbit", "handheld", "keyframes")

ORBIT_DEG = 3.6
"""Orbit: azimuth per frame, degrees."""
ORBIT_DRIFT = 0.0036
"""Orbit: sideways drift of the eye and the point looked at per frame, m."""
ORBIT_SWAY_DEG = 5.0
"""Orbit: amplitude of the elevation's sway (one period over the sequence), degrees."""

HANDHELD_RHO = 0.8
"""Hand-held: AR(1) coefficient of the shake from one frame to the next."""
HANDHELD_EYE = 0.008
"""Hand-held: stationary standard deviation of the eye's offset per axis, m."""
HANDHELD_TARGET = 0.015
"""Hand-held: stationary standard deviation of the looked-at point's offset per axis, m
(about 1 degree of turn at 1 m)."""
HANDHELD_ROLL_DEG = 1.0
"""Hand-held: stationary standard deviation of the roll about the optical axis, degrees."""

KEYFRAME_STEP_DEG = (10.0, 30.0)
"""Keyframes: range of the azimuth step between frames, degrees."""
KEYFRAME_ELEVATION_DEG = (35.0, 60.0)
"""Keyframes: range of the elevation, degrees."""
KEYFRAME_DISTANCE = (0.9, 1.1)
"""Keyframes: range of the distance to the workspace centre, m."""


def _orbit_eye(target: np.ndarray, distance: float, azimuth: float, elevation: float):
    """The eye ``distance`` m from ``target`` at ``azimuth`` (rad, 0: the static camera's -y
    side, counter-clockwise seen from above) and ``elevation`` (rad)."""
    ce = np.cos(elevation)
    return target + distance * np.array(
        [np.sin(azimuth) * ce, -np.cos(azimuth) * ce, np.sin(elevation)]
    )


def camera_path(
    kind: str,
    n_frames: int,
    seed: int,
    *,
    distance: float,
    elevation_deg: float,
    target=(0.0, 0.0, 0.0),
) -> list[np.ndarray]:
    """``n_frames`` camera poses ``T_world_cam`` (4, 4) of path ``kind`` (module docstring)
    around the static camera ``distance`` m from ``target`` at ``elevation_deg``.

    Raises:
        ArgumentError: an unknown ``kind``.
    """
    if kind not in CAMERA_PATHS:
        raise ArgumentError(f"unknown camera path {kind!r}; expected one of {CAMERA_PATHS}")
    target = np.asarray(target, dtype=float)
    e0 = np.radians(elevation_deg)
    static = look_at(_orbit_eye(target, distance, 0.0, e0), target)
    rng = np.random.default_rng([int(seed), 3])
    out = [static]
    if kind == "static":
        return [static.copy() for _ in range(n_frames)]
    if kind == "orbit":
        for i in range(1, n_frames):
            shift = np.array([ORBIT_DRIFT * i, 0.0, 0.0])
            sway = np.radians(ORBIT_SWAY_DEG) * np.sin(2 * np.pi * i / max(n_frames, 2))
            az = np.radians(ORBIT_DEG * i)
            out.append(look_at(_orbit_eye(target, distance, az, e0 + sway) + shift, target + shift))
        return out
    if kind == "handheld":
        eye0 = _orbit_eye(target, distance, 0.0, e0)
        spread = np.array([HANDHELD_EYE] * 3 + [HANDHELD_TARGET] * 3 + [HANDHELD_ROLL_DEG])
        state = np.zeros(7)
        innovation = spread * np.sqrt(1.0 - HANDHELD_RHO**2)
        for _ in range(1, n_frames):
            state = HANDHELD_RHO * state + innovation * rng.standard_normal(7)
            T = look_at(eye0 + state[:3], target + state[3:6])
            out.append(T @ yaw_pose(np.radians(state[6])))  # rolled
        return out
    # keyframes
    sign = 1.0 if rng.random() < 0.5 else -1.0
    az = 0.0
    for _ in range(1, n_frames):
        az += sign * np.radians(rng.uniform(*KEYFRAME_STEP_DEG))
        el = np.radians(rng.uniform(*KEYFRAME_ELEVATION_DEG))
        d = float(rng.uniform(*KEYFRAME_DISTANCE))
        out.append(look_at(_orbit_eye(target, d, az, el), target))
    return out
