"""Pinhole camera intrinsics (OpenCV convention), shared by perception, rendering and I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ssp.errors import ArgumentError

__all__ = ["Camera"]


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics: image ``width`` x ``height`` (pixels), focal lengths and principal
    point in pixels (OpenCV convention, pixel centres at integer coordinates)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        """ArgumentError (a ValueError) for a size that is not positive, a focal length that is
        not a positive finite number, or a principal point that is not finite."""
        if int(self.width) < 1 or int(self.height) < 1:
            raise ArgumentError(f"camera size must be positive, got {self.width} x {self.height}")
        if not (0 < self.fx < math.inf and 0 < self.fy < math.inf):
            raise ArgumentError(
                f"focal lengths must be positive finite numbers, got fx={self.fx}, fy={self.fy}"
            )
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ArgumentError(
                f"the principal point must be finite, got cx={self.cx}, cy={self.cy}"
            )

    @classmethod
    def default(cls) -> Camera:
        """640 x 480, ``fx = fy = 554.25``, ``(cx, cy) = (320.5, 240.5)``: the Kinect-like
        camera of the paper's Gazebo setup (about 60 degrees horizontal field of view)."""
        return cls(640, 480, 554.25, 554.25, 320.5, 240.5)

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``, the shape of this camera's images."""
        return (int(self.height), int(self.width))

    def subsample(self, stride: int) -> Camera:
        """The camera whose pixel ``(j, i)`` is pixel ``(stride j, stride i)`` of this one
        (every ``stride``-th column and row, starting with the first)."""
        s = int(stride)
        if s < 1:
            raise ValueError(f"stride must be a positive integer, got {stride}")
        if s == 1:
            return self
        return Camera(
            (int(self.width) + s - 1) // s,
            (int(self.height) + s - 1) // s,
            self.fx / s,
            self.fy / s,
            self.cx / s,
            self.cy / s,
        )

    def _rays_z1(self) -> np.ndarray:
        """``(H*W, 3)`` ray directions scaled to ``z = 1`` (normalised image coordinates)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        x = (u.ravel() - self.cx) / self.fx
        y = (v.ravel() - self.cy) / self.fy
        return np.column_stack([x, y, np.ones_like(x)])

    def rays(self) -> np.ndarray:
        """``(H*W, 3)`` unit ray directions in the camera frame, one per pixel, row-major."""
        d = self._rays_z1()
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``(N, 2)`` as ``(u, v)`` of camera-frame points ``(N, 3)`` (m).

        Points with ``z <= 0`` (behind the camera) give NaN. No bounds check: ``u`` in
        ``[-0.5, width - 0.5)`` and ``v`` in ``[-0.5, height - 0.5)`` are inside the image.
        """
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        out = np.full((len(p), 2), np.nan)
        front = z > 0
        out[front, 0] = self.fx * p[front, 0] / z[front] + self.cx
        out[front, 1] = self.fy * p[front, 1] / z[front] + self.cy
        return out

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(H, W, 3)`` (m) of a depth image ``(H, W)`` (z, m)."""
        depth = np.asarray(depth, dtype=float)
        if depth.shape != self.shape:
            raise ValueError(f"depth image has shape {depth.shape}, camera is {self.shape}")
        return self._rays_z1().reshape(*self.shape, 3) * depth[..., None]
