"""Synthetic sequences: ground truth, rendered depth and noisy hypotheses, frame by frame.

The types here are shared by the generator (:mod:`ssp.sim.generate`), the BOP reader/writer
(:mod:`ssp.sim.bop`) and the benchmark (:mod:`ssp.eval.table1`). Units: metres inside, depth in
metres (0 = no return); poses ``T_world_obj`` 4x4; the world has z up and the table top at
z = 0; the camera is static over a sequence.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ssp.scene import Frame, Hypothesis
from ssp.sim.render import Camera

__all__ = ["SimFrame", "SimSequence", "depth_frame"]


def depth_frame(
    depth: np.ndarray,
    instance: np.ndarray | None,
    camera: Camera,
    T_world_cam: np.ndarray,
    hypotheses: list[Hypothesis],
    stamp: float,
) -> Frame:
    """The parser's input from a depth image ``(H, W)`` (m, 0 = no return): its cloud in the
    world frame, per-point labels from ``instance`` (``(H, W)`` object index, -1 table, below
    -1 nothing; labels < -1 become -1) and the hypotheses."""
    depth = np.asarray(depth, dtype=float)
    ok = depth.reshape(-1) > 0
    p_cam = camera.backproject(depth).reshape(-1, 3)[ok]
    T_wc = np.asarray(T_world_cam, dtype=float)
    points = p_cam @ T_wc[:3, :3].T + T_wc[:3, 3]
    lab = None
    if instance is not None:
        lab = np.asarray(instance).reshape(-1)[ok].astype(np.int64)
        lab[lab < -1] = -1
    return Frame(
        stamp=float(stamp),
        points=points,
        hypotheses=list(hypotheses),
        labels=lab,
        T_world_cam=T_wc.copy(),
    )


@dataclass
class SimFrame:
    """One frame of a synthetic sequence.

    Attributes:
        index: frame number in the sequence (0-based).
        stamp: time, s.
        gt: ground truth, instance id -> ``(class_name, T_world_obj)``; every object present,
            occluded ones included. Its order defines the instance labels of ``instance``.
        depth: (H, W) float32 depth image, m (0 = no return), with sensor noise.
        instance: (H, W) int16: index into ``gt`` of the object seen at each pixel (then the
            ``distractors``), -1 table, -2 nothing.
        visib_fract: instance id -> visible fraction (0..1, BOP ``visib_fract``).
        hypotheses: the pose estimator's output for this frame: noisy poses, ``instance_id``
            None (the parser never sees ground truth).
        static_group: frames with the same value show the same static scene (the repeated
            frames whose spread is the precision metric).
        distractors: objects in the scene that are not in the library (realistic scenes):
            id -> ``(model name, T_world_obj)``; their instance labels follow ``gt``'s, in
            this order. Never part of the ground truth the methods are scored against.
        T_world_cam: this frame's camera pose (4, 4; OpenCV axes); None: the sequence's
            static camera.
    """

    index: int
    stamp: float
    gt: dict[str, tuple[str, np.ndarray]]
    depth: np.ndarray
    instance: np.ndarray
    visib_fract: dict[str, float]
    hypotheses: list[Hypothesis]
    static_group: int = 0
    distractors: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    T_world_cam: np.ndarray | None = None

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(self.gt)


@dataclass
class SimSequence:
    """A sequence: camera, frames, and how it was made.

    Attributes:
        experiment: ``"isolated"`` or ``"structure"``.
        seed: the seed it was generated from.
        camera: intrinsics of ``depth``.
        T_world_cam: (4, 4) camera pose (OpenCV axes) of the first frame; a moving camera's
            frames carry their own (:meth:`camera_pose`).
        frames: the frames in time order.
        models: model class names used (a subset of the library).
        info: free-form provenance (generator settings, noise calibration).
    """

    experiment: str
    seed: int
    camera: Camera
    T_world_cam: np.ndarray
    frames: list[SimFrame]
    models: tuple[str, ...] = ()
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def camera_pose(self, i: int) -> np.ndarray:
        """``T_world_cam`` (4, 4) of frame ``i``."""
        T = self.frames[i].T_world_cam
        return self.T_world_cam if T is None else T

    @property
    def camera_moves(self) -> bool:
        """Whether any frame's camera differs from the first's."""
        return any(
            not np.allclose(self.camera_pose(i), self.T_world_cam, rtol=0.0, atol=1e-9)
            for i in range(len(self.frames))
        )

    def frame(self, i: int, *, labels: bool = True) -> Frame:
        """The parser's input for frame ``i``: the cloud back-projected from the depth image
        (world frame) with per-point instance labels (table -1) and the noisy hypotheses."""
        f = self.frames[i]
        return depth_frame(
            f.depth,
            f.instance if labels else None,
            self.camera,
            self.camera_pose(i),
            f.hypotheses,
            f.stamp,
        )

    def ground_truth(self, i: int) -> Mapping[str, tuple[str, np.ndarray]]:
        return self.frames[i].gt
