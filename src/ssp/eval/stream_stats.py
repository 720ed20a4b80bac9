"""How a pose estimator fails over a sequence: the statistics the realistic stream is set from.

:func:`stream_records` takes a synthetic sequence whose hypotheses came from an estimator that
tags each hypothesis with the instance segment it was estimated from (the built-in front end
with instance masks, :func:`ssp.eval.estimated.estimate_sequence`) and lists, per ground-truth
object and frame, what the estimator said about it. :func:`summarize_stream` turns the records
into the rates and magnitudes of :class:`ssp.sim.realistic.RealisticNoise`:

* ``dropout``: visible objects (at least 10 % seen) without any hypothesis, and the lengths of
  such runs over consecutive frames of one static scene;
* ``top1``: the best-scored hypothesis: wrong class, gross (> 1 cm or > 10 deg off, measured at
  the centre of mass, symmetry-aware), and the errors of the others (mean, median);
* ``hypotheses``: the same over all hypotheses of the object, and the size of the gross errors;
* ``persistence``: over the frames of one static scene, the share of the top-1 error that is a
  persistent bias: ``|mean e|^2 / mean |e|^2`` of the centre error vectors ``e`` (1: the error
  never changes, about ``1/n`` for independent errors over ``n`` frames), and the lag-1
  autocorrelation of ``e``; likewise the share of gross top-1 frames that follow a gross one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ssp.eval.metrics import pose_error
from ssp.sim.sequence import SimSequence

__all__ = ["GROSS_DEG", "GROSS_MM", "stream_records", "summarize_stream"]

#: An estimate is gross beyond these (the gross_rate of the benchmarks).
GROSS_MM = 10.0
GROSS_DEG = 10.0
#: Objects less visible than this are not expected to be detected.
VISIBLE = 0.1


def stream_records(seq: SimSequence, library: Mapping) -> list[dict]:
    """One record per ground-truth object and frame (module docstring). Hypotheses belong to
    the object whose instance index is their ``segment``."""
    out = []
    for sf in seq.frames:
        ids = list(sf.gt)
        by_seg: dict[int, list] = {}
        for h in sf.hypotheses:
            if h.segment is not None:
                by_seg.setdefault(int(h.segment), []).append(h)
        for k, gid in enumerate(ids):
            cls, T_gt = sf.gt[gid]
            model = library[cls]
            hyps = sorted(by_seg.get(k, []), key=lambda h: -float(h.score))
            rows = []
            for h in hyps:
                if h.class_name == cls:
                    mm, deg = pose_error(T_gt, h.T_world_obj, model.symmetry, model.center_of_mass)
                    c = np.asarray(model.center_of_mass, dtype=float)
                    e = (h.T_world_obj[:3, :3] @ c + h.T_world_obj[:3, 3]) - (
                        T_gt[:3, :3] @ c + T_gt[:3, 3]
                    )
                    rows.append((True, mm, deg, e.tolist()))
                else:
                    rows.append((False, None, None, None))
            out.append(
                {
                    "frame": sf.index,
                    "group": sf.static_group,
                    "object": gid,
                    "class": cls,
                    "visib_fract": float(sf.visib_fract.get(gid, 0.0)),
                    "hypotheses": rows,
                }
            )
    return out


def _gross(row) -> bool:
    ok, mm, deg, _ = row
    return (not ok) or mm > GROSS_MM or deg > GROSS_DEG


def _mean(values) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def summarize_stream(records: Sequence[dict]) -> dict:
    """Rates and magnitudes over :func:`stream_records` (module docstring); JSON-ready."""
    vis = [r for r in records if r["visib_fract"] >= VISIBLE]
    detected = [r for r in vis if r["hypotheses"]]
    # dropout runs: consecutive frames of one object in one static group without hypotheses
    runs: list[int] = []
    by_obj: dict[tuple, list[dict]] = {}
    for r in vis:
        by_obj.setdefault((r["object"], r["group"]), []).append(r)
    for rows in by_obj.values():
        n = 0
        for r in sorted(rows, key=lambda r: r["frame"]):
            if r["hypotheses"]:
                if n:
                    runs.append(n)
                n = 0
            else:
                n += 1
        if n:
            runs.append(n)
    top = [r["hypotheses"][0] for r in detected]
    top_ok = [t for t in top if t[0] and not _gross(t)]
    allh = [h for r in detected for h in r["hypotheses"]]
    gross_h = [h for h in allh if h[0] and _gross(h)]
    # persistence of the top-1 error within a static scene (objects with >= 3 frames)
    shares, lag_num, lag_den, follow, gross_prev = [], 0.0, 0.0, 0, 0
    for rows in by_obj.values():
        rows = sorted((r for r in rows if r["hypotheses"]), key=lambda r: r["frame"])
        es = [
            np.asarray(r["hypotheses"][0][3])
            for r in rows
            if r["hypotheses"][0][0] and not _gross(r["hypotheses"][0])
        ]
        if len(es) >= 3:
            E = np.array(es)
            shares.append(float(np.sum(E.mean(axis=0) ** 2) / np.mean(np.sum(E * E, axis=1))))
            lag_num += float(np.sum(E[1:] * E[:-1]))
            lag_den += float(np.sum(E * E))
        g = [_gross(r["hypotheses"][0]) for r in rows]
        for a, b in zip(g[:-1], g[1:], strict=True):
            if a:
                gross_prev += 1
                follow += int(b)
    return {
        "object_frames": len(records),
        "visible_object_frames": len(vis),
        "dropout_rate": 1.0 - len(detected) / len(vis) if vis else None,
        "dropout_runs": {
            "count": len(runs),
            "mean_frames": _mean(runs),
            "max_frames": int(max(runs)) if runs else 0,
        },
        "top1": {
            "wrong_class": _mean([not t[0] for t in top]),
            "gross": _mean([_gross(t) for t in top]),
            "trans_mm_mean": _mean([t[1] for t in top_ok]),
            "trans_mm_median": _median([t[1] for t in top_ok]),
            "rot_deg_mean": _mean([t[2] for t in top_ok]),
            "rot_deg_median": _median([t[2] for t in top_ok]),
        },
        "hypotheses": {
            "per_object": _mean([len(r["hypotheses"]) for r in detected]),
            "wrong_class": _mean([not h[0] for h in allh]),
            "gross": _mean([_gross(h) for h in allh]),
            "gross_trans_mm_median": _median([h[1] for h in gross_h]),
            "gross_rot_deg_median": _median([h[2] for h in gross_h]),
            "gross_rot_deg_quantiles": [
                float(np.quantile([h[2] for h in gross_h], q)) for q in (0.1, 0.5, 0.9)
            ]
            if gross_h
            else None,
        },
        "persistence": {
            "bias_share_mean": _mean(shares),
            "objects": len(shares),
            "lag1_autocorrelation": lag_num / lag_den if lag_den else None,
            "gross_after_gross": follow / gross_prev if gross_prev else None,
        },
    }
