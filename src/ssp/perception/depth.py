"""Depth image to point cloud, with the per-pixel labels of an instance mask.

Depth is ``z`` in the OpenCV camera frame (m); pixels with a non-finite or non-positive depth
have no return and give no point. Depth in millimetres (an integer image, as most RGB-D
drivers write it, or a float image with a median above :data:`MM_DEPTH_MEDIAN`) is refused
unless ``depth_scale`` says how to convert it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ssp.camera import Camera
from ssp.errors import InvalidPoseError, PerceptionError
from ssp.geometry import transform_points, validate_pose

__all__ = [
    "MM_DEPTH_MEDIAN",
    "PLAUSIBLE_DEPTH",
    "DepthCloud",
    "cloud_from_depth",
    "depth_doubt",
    "labels_at",
]

log = logging.getLogger(__name__)

#: A depth image (m) whose median valid depth exceeds this is taken to be in millimetres.
MM_DEPTH_MEDIAN = 20.0
#: The median valid depth (m) of a plausible scene; outside, the depth scale is suspect.
PLAUSIBLE_DEPTH = (0.1, 10.0)
#: With a known camera pose: the median depth is within this factor of the camera's distance
#: to the world origin (the scene's centre, on the table), else the depth scale is suspect.
PLAUSIBLE_DEPTH_RATIO = 3.0


@dataclass(eq=False)
class DepthCloud:
    """Points of the valid pixels of a depth image, row-major.

    Attributes:
        points: ``(M, 3)`` points, m: world frame when a camera pose was given, else camera.
        labels: ``(M,)`` int64 mask value per point (negative = background), or None.
        pixels: ``(M, 2)`` int64 ``(row, col)`` of each point's pixel.
    """

    points: np.ndarray
    labels: np.ndarray | None
    pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def cloud_from_depth(
    depth: np.ndarray,
    camera: Camera,
    *,
    mask: np.ndarray | None = None,
    T_world_cam: np.ndarray | None = None,
    depth_scale: float | None = None,
) -> DepthCloud:
    """Back-project a depth image into a cloud.

    Args:
        depth: ``(H, W)`` depth (m, or raw units with ``depth_scale``); 0, negative or
            non-finite = no return. ``(H, W, 1)`` is accepted.
        camera: intrinsics; ``camera.shape`` must be ``(H, W)``.
        mask: ``(H, W)`` integer label image (instance or class; negative = background); a
            bool mask is read as label 0 (True) and -1 (False).
        T_world_cam: ``(4, 4)`` camera pose; the points are then in the world frame.
        depth_scale: metres per depth unit (e.g. 0.001 for millimetres); None for metres.

    Raises:
        PerceptionError: wrong shapes, an invalid camera pose, or depth that looks like
            millimetres without ``depth_scale``.
    """
    z = _depth_metres(depth, camera, depth_scale)
    valid = np.isfinite(z) & (z > 0)
    rows, cols = np.nonzero(valid)
    zs = z[rows, cols]
    pts = np.column_stack(
        [(cols - camera.cx) / camera.fx * zs, (rows - camera.cy) / camera.fy * zs, zs]
    )
    if T_world_cam is not None:
        try:
            pts = transform_points(validate_pose(T_world_cam, "T_world_cam"), pts)
        except InvalidPoseError as exc:
            raise PerceptionError(f"invalid camera pose: {exc}") from exc
    pixels = np.column_stack([rows, cols])
    labels = None if mask is None else labels_at(mask, camera, pixels)
    if len(zs) == 0:
        log.warning("cloud_from_depth: the depth image has no valid pixel")
    return DepthCloud(points=pts, labels=labels, pixels=pixels)


def labels_at(mask: np.ndarray, camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """The labels ``(M,)`` int64 of a ``(H, W)`` label image ``mask`` (as for
    :func:`cloud_from_depth`) at ``pixels`` ``(M, 2)`` ``(row, col)``: a cloud's labels when its
    points were made before its mask (:attr:`DepthCloud.pixels`).

    Raises:
        PerceptionError: ``mask`` not of the camera's image shape or not integer labels.
    """
    return _mask_labels(mask, camera)[pixels[:, 0], pixels[:, 1]]


def depth_doubt(
    depth: np.ndarray,
    *,
    raw_dtype: np.dtype | None = None,
    origin_distance: float | None = None,
    scale_note: str = "",
) -> str | None:
    """What is suspicious about a depth image ``(H, W)`` already in metres (0 = no return),
    or None: an 8-bit raw image (``raw_dtype``: a depth sensor writes 16 bits; 8 bits hold at
    most 255 units), a median valid depth outside :data:`PLAUSIBLE_DEPTH`, or (with
    ``origin_distance``, the camera's distance to the world origin, m) a median depth more than
    :data:`PLAUSIBLE_DEPTH_RATIO` times larger or smaller than it. ``scale_note`` says how the
    depth was scaled (e.g. ``" (depth_scale 0.1 mm per unit)"``). Never raises."""
    if raw_dtype is not None and np.dtype(raw_dtype).itemsize == 1:
        return (
            f"the depth image is 8-bit ({np.dtype(raw_dtype)}): depth sensors write 16-bit "
            "images, 8 bits hold at most 255 depth units; was it converted for viewing?"
        )
    z = np.asarray(depth, dtype=float)
    valid = z[np.isfinite(z) & (z > 0)]
    if not len(valid):
        return None
    median = float(np.median(valid))
    lo, hi = PLAUSIBLE_DEPTH
    hint = f"{scale_note}: is the depth scale right?"
    if not lo <= median <= hi:
        return f"the median depth is {median:.3g} m, outside {lo:g}-{hi:g} m{hint}"
    if origin_distance is not None and np.isfinite(origin_distance) and origin_distance > 0:
        ratio = median / float(origin_distance)
        if not 1 / PLAUSIBLE_DEPTH_RATIO <= ratio <= PLAUSIBLE_DEPTH_RATIO:
            return (
                f"the median depth is {median:.3g} m but the camera is {origin_distance:.3g} m "
                f"from the scene's origin ({ratio:.2g} times){hint}"
            )
    return None


def _depth_metres(depth: np.ndarray, camera: Camera, depth_scale: float | None) -> np.ndarray:
    """``depth`` as float64 metres ``(H, W)``, checked against ``camera`` and for mm units."""
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.shape != camera.shape:
        raise PerceptionError(
            f"depth image has shape {d.shape}, the camera's images are {camera.shape} "
            "(height, width)"
        )
    if not (np.issubdtype(d.dtype, np.integer) or np.issubdtype(d.dtype, np.floating)):
        raise PerceptionError(f"depth image must be numeric, got dtype {d.dtype}")
    if depth_scale is not None:
        scale = float(depth_scale)
        if not (np.isfinite(scale) and scale > 0):
            raise PerceptionError(f"depth_scale must be a positive number, got {depth_scale}")
        z = d.astype(float) * scale
        _check_metres(z, f" after depth_scale={depth_scale:g}")
        return z
    if np.issubdtype(d.dtype, np.integer):
        raise PerceptionError(
            f"depth image is integer ({d.dtype}): depth is probably in millimetres; "
            "pass depth_scale=0.001 (ssp works in metres)"
        )
    z = d.astype(float)
    _check_metres(z, "")
    return z


def _check_metres(z: np.ndarray, note: str) -> None:
    """PerceptionError when the median valid depth of ``z`` looks like millimetres."""
    valid = z[np.isfinite(z) & (z > 0)]
    if len(valid) and (median := float(np.median(valid))) > MM_DEPTH_MEDIAN:
        raise PerceptionError(
            f"median depth is {median:.1f} m{note}: depth is probably in millimetres; "
            "pass depth_scale=0.001 (ssp works in metres)"
        )


def _mask_labels(mask: np.ndarray, camera: Camera) -> np.ndarray:
    """``mask`` as an int64 ``(H, W)`` label image; PerceptionError otherwise."""
    m = np.asarray(mask)
    if m.shape != camera.shape:
        raise PerceptionError(
            f"mask has shape {m.shape}, the camera's images are {camera.shape} (height, width)"
        )
    if m.dtype == bool:
        return np.where(m, 0, -1).astype(np.int64)
    if not np.issubdtype(m.dtype, np.integer):
        if not (np.issubdtype(m.dtype, np.floating) and np.array_equal(m, np.round(m))):
            raise PerceptionError(f"mask must hold integer labels, got dtype {m.dtype}")
    return m.astype(np.int64)
