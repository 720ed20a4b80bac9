"""Instance masks from the pose hypotheses' own silhouettes, for a depth image without masks.

A published BOP scene has no masks but the ground truth's, and a user without a 2D detector
has none at all; clustering the cloud above the table then makes objects of clutter and merges
touching objects. The estimator's hypotheses already say where each object is in the image: an
RGB estimator's pose is centimetres off along the viewing ray but a few millimetres across it
(MegaPose on LM-O: median 14 mm along, 5 mm across), so its rendered silhouette covers the
object's pixels. :func:`silhouette_detections` turns each hypothesis into a detection of its
class:

1. hypotheses best score first; each one's model is ray cast (:func:`ssp.sim.render.render`,
   within the bounding box of its projection) into its silhouette ``(H, W)``;
2. a silhouette that overlaps (intersection over union at least :data:`SAME_OBJECT_IOU`) a
   kept one of the same class is the same object's (a worse hypothesis of it) and is left out;
3. a pixel in several kept silhouettes is the one's rendered nearest (the occluder's, whatever
   the scores: an RGB estimator's depth errors rarely swap two objects that overlap in the
   image, its scores often rank the hidden one first);
4. of its pixels, those whose measured depth is within ``max_gap`` of the silhouette's own
   depth range are the detection's mask (the wall behind an edge pixel is not the object's;
   the table under it is removed by the table fit as always).

The detections go through the same path as a detector's
(:func:`ssp.io.detections.instance_labels`, :func:`ssp.io.detections.match_segments`). The
hypotheses are the estimator's guesses, so the segments are only as good as they are: a
missed object has no segment (its points are no object's), a false one gets the points under
it (verification then judges it as always).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ssp.camera import Camera
from ssp.io.detections import Detection
from ssp.scene import Hypothesis

__all__ = ["MIN_PIXELS", "SAME_OBJECT_IOU", "hypothesis_silhouette", "silhouette_detections"]

#: Two silhouettes of one class overlapping at least this much (IoU) are one object's.
SAME_OBJECT_IOU = 0.5
#: A silhouette with fewer measured pixels than this makes no detection.
MIN_PIXELS = 20


def hypothesis_silhouette(
    mesh, T_cam_obj: np.ndarray, camera: Camera
) -> tuple[np.ndarray, np.ndarray] | None:
    """The silhouette of ``mesh`` (model frame, m) at ``T_cam_obj`` (4, 4): ``(H, W)`` bool and
    its rendered depth ``(H, W)`` (m, 0 outside), ray cast within the bounding box of the
    vertices' projection; None when none of it is in front of the camera and in the image."""
    from ssp.sim.render import render

    v = np.asarray(mesh.vertices, dtype=float) @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    v = v[v[:, 2] > 1e-3]
    if not len(v):
        return None
    uv = camera.project(v)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if not len(uv):
        return None
    x0 = max(0, math.floor(uv[:, 0].min()) - 1)
    y0 = max(0, math.floor(uv[:, 1].min()) - 1)
    x1 = min(camera.width, math.ceil(uv[:, 0].max()) + 2)
    y1 = min(camera.height, math.ceil(uv[:, 1].max()) + 2)
    if x1 <= x0 or y1 <= y0:
        return None
    crop = Camera(x1 - x0, y1 - y0, camera.fx, camera.fy, camera.cx - x0, camera.cy - y0)
    r = render([("h", mesh, T_cam_obj)], np.eye(4), crop, table=False)
    depth = np.zeros((camera.height, camera.width))
    depth[y0:y1, x0:x1] = r.depth
    return depth > 0, depth


def silhouette_detections(
    hypotheses: Sequence[Hypothesis],
    library: Mapping,
    obj_ids: Mapping[str, int],
    camera: Camera,
    depth: np.ndarray,
    T_cam_frame: np.ndarray | None = None,
    *,
    im_id: int = 0,
    max_gap: float = 0.12,
) -> list[Detection]:
    """One detection per object the hypotheses show (module docstring), best score first.

    Args:
        hypotheses: the image's hypotheses (poses in the camera frame, or in the frame
            ``T_cam_frame`` (4, 4) maps to the camera).
        library: class name -> model (``mesh``).
        obj_ids: class name -> BOP obj_id (the detections' ``category_id``); a class without
            one makes no detection.
        camera: the depth image's intrinsics; ``depth`` ``(H, W)`` m, 0 where none.
        max_gap: m; a silhouette pixel is the object's when its measured depth is within this
            of the silhouette's rendered depth range (``correction.max_shift``: the farthest
            the depth correction moves a hypothesis).
    """
    from pycocotools import mask as mask_util

    depth = np.asarray(depth, dtype=float)
    order = sorted(range(len(hypotheses)), key=lambda i: (-hypotheses[i].score, i))
    kept: list[tuple[Hypothesis, np.ndarray, np.ndarray]] = []
    for i in order:
        h = hypotheses[i]
        if h.class_name not in obj_ids or h.class_name not in library:
            continue
        T = np.asarray(h.T_world_obj, dtype=float)
        T_co = T if T_cam_frame is None else np.asarray(T_cam_frame, dtype=float) @ T
        sil = hypothesis_silhouette(library[h.class_name].mesh, T_co, camera)
        if sil is None:
            continue
        if any(k.class_name == h.class_name and _iou(sil[0], m) >= SAME_OBJECT_IOU
               for k, m, _ in kept):  # fmt: skip
            continue
        kept.append((h, *sil))
    if not kept:
        return []
    # each pixel is the nearest silhouette's (an occluder's, whatever the scores)
    nearest = np.full(depth.shape, np.inf, dtype=np.float32)
    owner = np.full(depth.shape, -1, dtype=np.int64)
    for j, (_, inside, z) in enumerate(kept):
        closer = inside & (z < nearest)
        nearest[closer] = z[closer]
        owner[closer] = j
    out: list[Detection] = []
    for j, (h, inside, z) in enumerate(kept):
        zs = z[inside]
        near = (owner == j) & (depth > 0)
        near &= (depth >= zs.min() - max_gap) & (depth <= zs.max() + max_gap)
        if np.count_nonzero(near) < MIN_PIXELS:
            continue
        rle = mask_util.encode(np.asfortranarray(near.astype(np.uint8)))
        out.append(
            Detection(
                entry=len(out),
                scene_id=0,
                im_id=int(im_id),
                obj_id=int(obj_ids[h.class_name]),
                score=float(h.score),
                bbox=None,
                size=(int(depth.shape[0]), int(depth.shape[1])),
                counts=rle["counts"].decode("ascii"),
            )
        )
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    inter = np.count_nonzero(a & b)
    return inter / max(1, np.count_nonzero(a | b))
