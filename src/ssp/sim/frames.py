"""Synthetic :class:`ssp.scene.Frame` objects from a ground-truth scene, for tests and demos.

The cloud is a real rendered depth image (:func:`ssp.sim.render.render`) of the ground-truth
objects on the table, optionally with Kinect-like noise (:func:`ssp.sim.render.add_depth_noise`),
so occlusions, self-occlusion and the table are as a camera would see them. Pose hypotheses
stand in for a pose estimator: the ground-truth pose perturbed by a random rotation and
translation. What is *not* modelled: detector failure modes other than missed objects (no
false positives, no wrong classes, no multi-modal errors such as a flipped symmetric object),
and any dependence of the hypothesis error on how much of the object is visible.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.scene import Frame, Hypothesis
from ssp.sim.render import Camera, RenderResult, add_depth_noise, render

__all__ = ["perturb_pose", "render_scene", "synthetic_frame", "visible_fractions"]

#: Ground truth: instance id -> (class name, T_world_obj (4, 4)).
GroundTruth = Mapping[str, tuple[str, np.ndarray]]


def render_scene(
    library: Mapping,
    gt: GroundTruth,
    *,
    T_world_cam: np.ndarray,
    camera: Camera | None = None,
    stride: int = 1,
    table: bool = True,
) -> RenderResult:
    """Render the ground-truth scene (object ``i`` of the result is the ``i``-th of ``gt``).

    ``library`` maps class names to models with a ``.mesh`` (an :class:`ObjectLibrary`).
    """
    objects = [(iid, library[cls].mesh, T) for iid, (cls, T) in gt.items()]
    return render(objects, T_world_cam, camera, table=table, stride=stride)


def perturb_pose(
    T: np.ndarray, rng: np.random.Generator, sigma_t: float, sigma_r_deg: float
) -> np.ndarray:
    """``T`` (4, 4) rotated about its own origin by ``|N(0, sigma_r_deg)|`` degrees about a
    uniformly random axis, and translated by ``N(0, (sigma_t / sqrt 3)^2)`` per axis (m), so
    that the RMS translation error is ``sigma_t`` and the RMS rotation error ``sigma_r_deg``.
    """
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    angle = abs(rng.standard_normal()) * np.deg2rad(sigma_r_deg)
    out = np.array(T, dtype=float)
    out[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix() @ out[:3, :3]
    out[:3, 3] += rng.standard_normal(3) * (sigma_t / np.sqrt(3.0))
    return out


def synthetic_frame(
    library: Mapping,
    gt: GroundTruth,
    *,
    T_world_cam: np.ndarray,
    camera: Camera | None = None,
    stamp: float = 0.0,
    rng: np.random.Generator | int,
    k: int = 5,
    sigma_t: float = 0.005,
    sigma_r_deg: float = 5.0,
    noise: bool = True,
    stride: int = 2,
    give_ids: bool = False,
    give_segments: bool = False,
    detect: Collection[str] | None = None,
    table: bool = True,
) -> Frame:
    """A frame as a camera at ``T_world_cam`` and a pose estimator would report the scene.

    Args:
        library: class name -> model with ``.mesh`` (an :class:`ssp.library.ObjectLibrary`).
        gt: instance id -> ``(class name, T_world_obj)``; its order defines the labels.
        T_world_cam: camera pose (4, 4), OpenCV frame (see :func:`ssp.sim.render.look_at`).
        camera: intrinsics (:meth:`Camera.default` if None), rendered with ``stride``.
        stamp: frame time, s.
        rng: numpy Generator (or a seed); all randomness (depth noise, then hypotheses) comes
            from it, so a seed gives the same frame.
        k: hypotheses per detected object, scores ``1, 1 - 1/k, ...`` (first highest; the
            order is random with respect to the error).
        sigma_t, sigma_r_deg: RMS translation (m) and rotation (deg) error of the hypotheses
            (see :func:`perturb_pose`).
        noise: add depth noise (:func:`add_depth_noise` defaults) before building the cloud.
        give_ids: hypotheses carry the ground-truth ``instance_id`` (else None).
        give_segments: fill ``Frame.segments`` with each object's points, by instance id.
        detect: the ids that get hypotheses (default: all); the others are undetected (their
            points are still in the cloud).
        table: render the table top (label -1).

    Returns:
        Frame with ``points`` (N, 3) from the (noisy) depth image, ``labels`` (N,) = index of
        the object in ``gt`` (0..n-1) or -1 for the table, ``hypotheses`` and ``T_world_cam``.
    """
    rng = np.random.default_rng(rng)
    ids = list(gt)
    if detect is None:
        detect = ids
    unknown = set(detect) - set(ids)
    if unknown:
        raise ValueError(f"detect names ids not in the ground truth: {sorted(unknown)}")
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")

    result = render_scene(
        library, gt, T_world_cam=T_world_cam, camera=camera, stride=stride, table=table
    )
    depth = add_depth_noise(result.depth, rng) if noise else result.depth
    points = result.points_world(depth=depth)
    labels = result.labels(depth=depth)

    hypotheses = []
    detected = set(detect)
    for iid in ids:
        if iid not in detected:
            continue
        cls, T = gt[iid]
        for j in range(k):
            hypotheses.append(
                Hypothesis(
                    class_name=cls,
                    T_world_obj=perturb_pose(T, rng, sigma_t, sigma_r_deg),
                    score=1.0 - j / k,
                    instance_id=iid if give_ids else None,
                )
            )

    segments = None
    if give_segments:
        segments = {iid: points[labels == i] for i, iid in enumerate(ids)}
    return Frame(
        stamp=float(stamp),
        points=points,
        hypotheses=hypotheses,
        labels=labels,
        segments=segments,
        T_world_cam=np.array(result.T_world_cam),
    )


def visible_fractions(
    library: Mapping,
    gt: GroundTruth,
    *,
    T_world_cam: np.ndarray,
    camera: Camera | None = None,
    stride: int = 2,
    table: bool = True,
) -> dict[str, float]:
    """Per instance id: pixels seen in the scene / pixels seen with the object alone.

    Measures occlusion by the other objects (the table is in both renders, so an object
    partly below ``z = 0`` is not counted as occluded by it). 0.0 for an object outside the
    view or entirely hidden by the table. Costs ``len(gt) + 1`` renders.
    """
    scene = render_scene(
        library, gt, T_world_cam=T_world_cam, camera=camera, stride=stride, table=table
    )
    counts = scene.pixel_counts()
    out = {}
    for iid, (cls, T) in gt.items():
        alone = render_scene(
            library,
            {iid: (cls, T)},
            T_world_cam=T_world_cam,
            camera=camera,
            stride=stride,
            table=table,
        ).pixel_counts()[iid]
        out[iid] = counts[iid] / alone if alone else 0.0
    return out
