"""Table I with hypotheses from the perception front end instead of noisy ground truth.

:func:`estimate_sequence` replaces the hypotheses of every frame of a synthetic sequence by the
front end's (:class:`ssp.perception.Perception` on the rendered, noisy depth image, segmented
by its instance mask, with the sequence's camera pose), and measures the estimator itself:

* time per segment (s; normals + pose hypotheses of one segment);
* recall: the fraction of ground-truth objects with at least one hypothesis of their class
  within 1 cm and 10 degrees (symmetry-aware, :func:`ssp.eval.metrics.pose_error`) among the
  hypotheses of the frame, over all objects and over objects at least 10 % visible;
* top-1 recall: the same for the best-scored hypothesis of the object's segment.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np

from ssp.config import SSPConfig
from ssp.eval.metrics import pose_error
from ssp.perception.pipeline import Perception
from ssp.sim.sequence import SimSequence

__all__ = [
    "RECALL_DEG", "RECALL_MM", "estimate_sequence", "perceive_frame", "summarize_estimator",
]  # fmt: skip

#: Recall thresholds: a hypothesis within this translation (mm) and rotation (deg).
RECALL_MM = 10.0
RECALL_DEG = 10.0
#: Objects less visible than this are reported separately.
VISIBLE = 0.1


def estimate_sequence(
    seq: SimSequence,
    library: Mapping,
    config: SSPConfig | None = None,
    progress: Callable[[str], None] | None = None,
    *,
    masks: bool = True,
) -> tuple[SimSequence, list[dict]]:
    """The sequence with estimated hypotheses, and one record per ground-truth object and frame.

    Each record: ``frame``, ``object``, ``class``, ``visib_fract``, ``segment_points``,
    ``seconds`` (its segment's estimator time, None when it had no segment), ``recalled``
    (any hypothesis within the thresholds), ``top1`` (the segment's best hypothesis is).

    ``masks`` False: the front end clusters the cloud above the table (``ssp run --masks
    none``); a cluster is no object's, so the object records have no ``seconds``,
    ``segment_points`` or ``top1`` (None), and each cluster has a record of its own
    (``object`` None, ``cluster``, ``segment_points``, ``seconds``, ``objects_found``).
    """
    cfg = config if config is not None else SSPConfig()
    perception = Perception(library, cfg, classes=seq.models or None)
    frames, records = [], []
    for i, sf in enumerate(seq.frames):
        if progress is not None:
            progress(f"estimating hypotheses, frame {i + 1}/{len(seq)}")
        res = perceive_frame(perception, seq, sf, masks=masks)
        hyps = res.frame.hypotheses
        frames.append(replace(sf, hypotheses=list(hyps)))
        labels = np.asarray(sf.instance).astype(np.int64)
        counts = np.bincount(labels[labels >= 0].ravel(), minlength=len(sf.gt))
        for k, (gid, (cls, T_gt)) in enumerate(sf.gt.items()):
            sym = library[cls].symmetry
            seg = res.segments.get(k) if masks else None
            top = seg.hypotheses[0] if seg is not None and seg.hypotheses else None
            records.append(
                {
                    "frame": sf.index,
                    "object": gid,
                    "class": cls,
                    "visib_fract": float(sf.visib_fract.get(gid, 0.0)),
                    "segment_points": int(counts[k]) if masks else None,
                    "seconds": None if seg is None else float(seg.seconds),
                    "recalled": any(_close(h, cls, T_gt, sym) for h in hyps),
                    "top1": (top is not None and _close(top, cls, T_gt, sym)) if masks else None,
                }
            )
        if not masks:
            cluster_sizes = np.bincount(res.frame.labels[res.frame.labels >= 0])
            for label, seg in sorted(res.segments.items()):
                records.append(
                    {
                        "frame": sf.index,
                        "object": None,
                        "cluster": int(label),
                        "segment_points": int(cluster_sizes[label]),
                        "seconds": float(seg.seconds),
                        "objects_found": len(seg.objects),
                    }
                )
    info = dict(seq.info or {})
    info.pop("hypothesis_sources", None)  # the sources of the noisy hypotheses no longer apply
    info["hypotheses"] = "estimated"
    return replace(seq, frames=frames, info=info), records


def _camera_of(seq: SimSequence, sf) -> np.ndarray:
    """The camera pose of frame ``sf`` (its own when the camera moves)."""
    return seq.T_world_cam if sf.T_world_cam is None else sf.T_world_cam


def perceive_frame(
    perception: Perception, seq: SimSequence, sf, hypotheses=None, *, masks: bool = True
):
    """:meth:`Perception.from_depth` of the rendered frame ``sf`` of ``seq``, segmented by its
    instance mask (``masks`` False: clustered), with the sequence's camera pose
    (the frame's own when the camera moves; ``hypotheses``: given instead of estimated,
    ``[]`` to segment only)."""
    mask = None
    if masks:
        mask = np.asarray(sf.instance).astype(np.int64)
        mask[mask < -1] = -1
    return perception.from_depth(
        sf.depth, seq.camera, stamp=sf.stamp, T_world_cam=_camera_of(seq, sf), mask=mask,
        hypotheses=hypotheses,
    )  # fmt: skip


def _close(h, cls: str, T_gt: np.ndarray, symmetry) -> bool:
    """Hypothesis ``h`` is of class ``cls`` and within the recall thresholds of ``T_gt``."""
    if h.class_name != cls:
        return False
    dt, dr = pose_error(T_gt, h.T_world_obj, symmetry)
    return dt <= RECALL_MM and dr <= RECALL_DEG


def summarize_estimator(records: list[dict]) -> dict:
    """Time per segment and recall over :func:`estimate_sequence` records (JSON-ready)."""
    secs = [r["seconds"] for r in records if r["seconds"] is not None]
    frames = {(r.get("sequence"), r["frame"]) for r in records}
    clusters = [r for r in records if r["object"] is None]
    records = [r for r in records if r["object"] is not None]
    vis = [r for r in records if r["visib_fract"] >= VISIBLE]

    def frac(rows: list[dict], key: str) -> float | None:
        rows = [r for r in rows if r[key] is not None]
        return float(np.mean([r[key] for r in rows])) if rows else None

    more = {}
    if clusters:  # without masks: what each cluster gave
        found = [r["objects_found"] for r in clusters]
        more = {"clusters": len(clusters), "objects_per_cluster_mean": float(np.mean(found)),
                "objects_per_frame_mean": float(sum(found) / len(frames))}  # fmt: skip
    return {
        "segments": len(secs),
        "sec_per_segment_mean": float(np.mean(secs)) if secs else None,
        "sec_per_segment_median": float(np.median(secs)) if secs else None,
        "sec_per_segment_p95": float(np.percentile(secs, 95)) if secs else None,
        "objects": len(records),
        "recall": frac(records, "recalled"),
        "recall_visible": frac(vis, "recalled"),
        "top1_recall_visible": frac(vis, "top1"),
        "visible_objects": len(vis),
        "recall_mm": RECALL_MM,
        "recall_deg": RECALL_DEG,
        "visible_fraction": VISIBLE,
        **more,
    }
