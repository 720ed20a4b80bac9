"""How a real RGB pose estimator errs: measured on a BOP dataset's ground truth and a BOP19
results CSV (``ssp bench rgb-calibration``), the numbers behind :meth:`RealisticNoise.rgb
<ssp.sim.realistic.RealisticNoise.rgb>`.

Per target (a ground-truth instance of an image the CSV has rows for, at least ``min_visib``
visible unless said otherwise), the best-scored row of its object id in its image is compared
with the ground truth in the camera frame, up to the model's discrete symmetries (the
published ``symmetries_discrete`` of ``models_info.json`` projected onto the nearest rotation,
as published symmetries are not exact turns; the equivalent with the smallest rotation error
is used, MSSD-like). With ``u`` the unit ray from the camera to the true model origin and
``e = t_est - t_gt`` (mm):

* ``along``: ``e . u``, signed (positive: estimated too far from the camera);
* ``lateral``: ``|e - (e . u) u|`` (mm);
* ``rotation``: the angle (deg) of ``R_gt^T R_est`` (smallest over the symmetries);
* a *far outlier*: ``|e| > far_mm`` (10 cm); a *flip*: not far, rotation > 30 deg (its axis in
  the model frame, and how close it is to a model axis, say whether it is symmetry-like);
* *missed*: no row of the object in the image; *rows*: how many rows it has (extra rows are
  other detections: near the best one or not);
* *right* rows: translation error < ``right_mm`` and rotation < 30 deg; the scores of right
  and wrong rows.

Everything that depends on visibility is also given per visible-fraction bin
(:data:`VISIBILITY_BINS`). Images the CSV has no row for at all are left out (an image removed
from the file, not a miss of the estimator).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ssp.errors import InputError
from ssp.geometry import nearest_rotation
from ssp.io import write_json
from ssp.io._files import atomic_write_text
from ssp.io.results import read_bop_csv
from ssp.library.symmetry import ContinuousSymmetry

__all__ = [
    "QUANTILE_LEVELS",
    "VISIBILITY_BINS",
    "calibrate_rgb",
    "rgb_calibration_markdown",
    "target_errors",
    "write_rgb_calibration",
]

log = logging.getLogger(__name__)

#: Visible-fraction bin edges (the last bin includes 1).
VISIBILITY_BINS = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0)
#: Levels of the quantile tables.
QUANTILE_LEVELS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.98, 1.0)
FLIP_DEG = 30.0


def _symmetries(models_info: dict) -> dict[int, list[np.ndarray]]:
    """obj_id -> its symmetries (4x4, mm, identity first), as the BOP toolkit reads them: the
    discrete ones as published (rotations projected, near turns not snapped), each composed
    with the continuous axes' rotations every 5 deg (the first axis, as the toolkit does)."""
    out: dict[int, list[np.ndarray]] = {}
    for key, info in models_info.items():
        discrete = [np.eye(4)]
        for s in info.get("symmetries_discrete", []):
            S = np.asarray(s, dtype=float).reshape(4, 4)
            S[:3, :3] = nearest_rotation(S[:3, :3])
            discrete.append(S)
        turns = [np.eye(4)]
        for c in info.get("symmetries_continuous", [])[:1]:
            axis = ContinuousSymmetry(
                np.asarray(c["axis"], dtype=float) / np.linalg.norm(c["axis"]),
                np.asarray(c.get("offset", [0, 0, 0]), dtype=float),
            )
            turns = [axis.transform(np.radians(a)) for a in range(0, 360, 5)]
        out[int(key)] = [S @ T for S in discrete for T in turns]
    return out


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _row_error(R_gt, t_gt, syms, R, t) -> dict[str, Any]:
    """The error of one row (R, t mm) against the ground truth, smallest rotation over the
    symmetries: along, lateral, translation (mm), rotation (deg), the residual turn's axis in
    the model frame."""
    best = None
    for S in syms:
        Rg = R_gt @ S[:3, :3]
        a = _angle_deg(Rg.T @ R)
        if best is None or a < best[0]:
            best = (a, Rg, R_gt @ S[:3, 3] + t_gt)
    assert best is not None
    a, Rg, tg = best
    e = np.asarray(t, dtype=float) - tg
    u = tg / np.linalg.norm(tg)
    along = float(e @ u)
    rv = _axis(Rg.T @ R)
    return {
        "along": along,
        "lateral": float(np.linalg.norm(e - along * u)),
        "trans": float(np.linalg.norm(e)),
        "rot": a,
        "axis": rv,
    }


def _axis(R: np.ndarray) -> list[float]:
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = float(np.linalg.norm(w))
    if n < 1e-9:  # 0 or 180 deg: the axis is the eigenvector of R + I
        vals, vecs = np.linalg.eigh(R + R.T)
        w, n = vecs[:, int(np.argmax(vals))], 1.0
    return [float(x) for x in w / n]


def _scene_targets(scene: Path) -> list[dict[str, Any]]:
    """The ground-truth instances of a BOP scene folder: im_id, obj_id, R, t (mm), visib."""
    try:
        gt = json.loads((scene / "scene_gt.json").read_text())
        info = json.loads((scene / "scene_gt_info.json").read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{scene}: cannot read scene_gt / scene_gt_info: {exc}") from exc
    out = []
    for im, lst in gt.items():
        if len(info.get(im, [])) != len(lst):
            raise InputError(
                f"{scene}: im_id {im}: {len(lst)} scene_gt.json entries but "
                f"{len(info.get(im, []))} in scene_gt_info.json (one each, in the same order)"
            )
        for g, inf in zip(lst, info[im], strict=True):
            out.append({
                "scene_id": int(scene.name), "im_id": int(im), "obj_id": int(g["obj_id"]),
                "R": nearest_rotation(np.reshape(g["cam_R_m2c"], (3, 3))),
                "t": np.asarray(g["cam_t_m2c"], dtype=float), "visib": float(inf["visib_fract"]),
            })  # fmt: skip
    return out


def target_errors(data: str | Path, csv: str | Path | None = None) -> list[dict[str, Any]]:
    """Every target of the dataset folder ``data`` (``models/models_info.json``,
    ``test/<scene>/scene_gt.json`` and ``scene_gt_info.json``, a results ``*.csv`` in
    ``data`` unless ``csv`` is given) with its rows sorted by score, each row's error
    (:func:`_row_error` keys, plus ``score``); images without any row are left out.

    Raises:
        InputError: missing files, or no scene the CSV has rows for.
    """
    root = Path(data)
    if csv is None:
        found = sorted(root.glob("*.csv"))
        if len(found) != 1:
            raise InputError(f"{root}: expected one results CSV, found {len(found)}: use --csv")
        csv = found[0]
    mi = root / "models" / "models_info.json"
    try:
        syms = _symmetries(json.loads(mi.read_text()))
    except (OSError, ValueError) as exc:
        raise InputError(f"{mi}: cannot read models_info: {exc}") from exc
    rows: dict[tuple[int, int, int], list[dict]] = {}
    for r in read_bop_csv(csv):
        rows.setdefault((r["scene_id"], r["im_id"], r["obj_id"]), []).append(r)
    images = {(s, i) for s, i, _ in rows}
    scenes = sorted(p for p in (root / "test").glob("*") if (p / "scene_gt.json").is_file())
    targets = []
    for scene in scenes:
        for g in _scene_targets(scene):
            if (g["scene_id"], g["im_id"]) not in images:
                continue
            mine = sorted(rows.get((g["scene_id"], g["im_id"], g["obj_id"]), []),
                          key=lambda r: -r["score"])  # fmt: skip
            s = syms.get(g["obj_id"], [np.eye(4)])
            errs = [
                {**_row_error(g["R"], g["t"], s, r["R"], r["t"]), "score": float(r["score"])}
                for r in mine
            ]
            targets.append({**{k: g[k] for k in ("scene_id", "im_id", "obj_id", "visib")},
                            "distance": float(np.linalg.norm(g["t"])), "rows": errs})  # fmt: skip
    if not targets:
        raise InputError(f"{csv}: no row for any image of {root / 'test'}")
    return targets


def _q(values: Sequence[float]) -> list[float] | None:
    v = np.asarray(values, dtype=float)
    return None if len(v) == 0 else [round(float(x), 3) for x in np.quantile(v, QUANTILE_LEVELS)]


def _share(mask) -> float | None:
    m = np.asarray(mask, dtype=bool)
    return None if len(m) == 0 else round(float(m.mean()), 4)


def _med(values) -> float | None:
    v = np.asarray(values, dtype=float)
    return None if len(v) == 0 else round(float(np.median(v)), 3)


def _p75(values) -> float | None:
    v = np.asarray(values, dtype=float)
    return None if len(v) == 0 else round(float(np.quantile(v, 0.75)), 3)


def _block(best: list[dict], far_mm: float) -> dict[str, Any]:
    """The error statistics of the best rows ``best`` (errors of :func:`_row_error`)."""
    far = [b for b in best if b["trans"] > far_mm]
    near = [b for b in best if b["trans"] <= far_mm]
    flips = [b for b in near if b["rot"] > FLIP_DEG]
    small = [b for b in near if b["rot"] <= FLIP_DEG]
    al = np.array([b["along"] for b in near])
    a_all = np.array([b["along"] for b in best])
    return {
        "n": len(best),
        "near_n": len(near),
        "far_rate": _share([b["trans"] > far_mm for b in best]),
        "flip_rate": _share([b["rot"] > FLIP_DEG for b in near]),
        "along_abs_median_mm": _med(np.abs(a_all)),
        "along_abs_p75_mm": _p75(np.abs(a_all)),
        "along_over_10mm": _share(np.abs(a_all) > 10),
        "along_over_20mm": _share(np.abs(a_all) > 20),
        "lateral_median_mm": _med([b["lateral"] for b in best]),
        "rotation_median_deg": _med([b["rot"] for b in best]),
        "rotation_p75_deg": _p75([b["rot"] for b in best]),
        "rotation_over_30deg": _share([b["rot"] > FLIP_DEG for b in best]),
        "near": {
            "along_mm_q": _q(al),
            "along_mean_mm": None if len(al) == 0 else round(float(al.mean()), 3),
            "lateral_mm_q": _q([b["lateral"] for b in near]),
            "rotation_small_deg_q": _q([b["rot"] for b in small]),
            "flip_deg_q": _q([b["rot"] for b in flips]),
        },
        "far": {
            "along_mm_q": _q([b["along"] for b in far]),
            "lateral_mm_q": _q([b["lateral"] for b in far]),
            "rotation_deg_q": _q([b["rot"] for b in far]),
        },
    }  # fmt: skip


def _tails(values: np.ndarray) -> dict[str, Any]:
    """Bias and tail weight of a signed error: median, mean, and the ratio of the spread of
    the tails to the core's (``(q95 - q05) / (q75 - q25)``: 2.44 for a normal law)."""
    q05, q25, q50, q75, q95 = np.quantile(values, [0.05, 0.25, 0.5, 0.75, 0.95])
    return {
        "median_mm": round(float(q50), 3),
        "mean_mm": round(float(values.mean()), 3),
        "share_positive": round(float((values > 0).mean()), 4),
        "tail_ratio": round(float((q95 - q05) / max(q75 - q25, 1e-9)), 3),
        "tail_ratio_normal": 2.438,
    }


def _flip_axes(best: list[dict], far_mm: float, seed: int = 0) -> dict[str, Any]:
    """Whether flips turn about a model axis: ``max |axis_i|`` of the flips' axes in the model
    frame, against uniformly random axes (seeded)."""
    ax = np.array([b["axis"] for b in best if b["trans"] <= far_mm and b["rot"] > FLIP_DEG])
    rnd = np.random.default_rng(seed).standard_normal((20000, 3))
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    base = np.abs(rnd).max(axis=1)
    if len(ax) == 0:
        return {"n": 0}
    al = np.abs(ax).max(axis=1)
    return {
        "n": len(ax),
        "axis_alignment_median": round(float(np.median(al)), 3),
        "aligned_over_0.95": round(float((al > 0.95).mean()), 4),
        "random_axes_alignment_median": round(float(np.median(base)), 3),
        "random_aligned_over_0.95": round(float((base > 0.95).mean()), 4),
        "angle_over_150deg": round(
            float(
                np.mean(
                    [b["rot"] > 150 for b in best if b["trans"] <= far_mm and b["rot"] > FLIP_DEG]
                )
            ),
            4,
        ),  # fmt: skip
    }


def _bin_of(v: float) -> int:
    edges = VISIBILITY_BINS
    for k in range(len(edges) - 1):
        if v < edges[k + 1]:
            return k
    return len(edges) - 2


def _rows_stats(targets: list[dict], right_mm: float) -> dict[str, Any]:
    """Rows per detected target, the extra rows, and the scores of right and wrong rows."""
    detected = [t for t in targets if t["rows"]]
    hist = np.bincount([min(len(t["rows"]), 5) for t in detected], minlength=6)[1:]
    extra = [r for t in detected for r in t["rows"][1:]]

    def right(r: dict) -> bool:
        return r["trans"] < right_mm and r["rot"] <= FLIP_DEG

    scores_r = [r["score"] for t in detected for r in t["rows"] if right(r)]
    scores_w = [r["score"] for t in detected for r in t["rows"] if not right(r)]
    best_wrong_other_right = sum(
        1 for t in detected if not right(t["rows"][0]) and any(right(r) for r in t["rows"][1:])
    )
    return {
        "rows_per_detected_target": {str(k + 1): int(n) for k, n in enumerate(hist)},
        "rows_mean": round(float(np.mean([len(t["rows"]) for t in detected])), 4),
        "extra_rows": len(extra),
        "extra_right": _share([right(r) for r in extra]),
        "extra_far": _share([r["trans"] > 100.0 for r in extra]),
        "best_wrong_but_an_extra_right": best_wrong_other_right,
        "score_right_q": _q(scores_r),
        "score_wrong_q": _q(scores_w),
        "right_share": _share([right(t["rows"][0]) for t in detected]),
        "score_best_right_q": _q([t["rows"][0]["score"] for t in detected if right(t["rows"][0])]),
        "score_best_wrong_q": _q(
            [t["rows"][0]["score"] for t in detected if not right(t["rows"][0])]
        ),
        "score_extra_q": _q([r["score"] for r in extra]),
    }


def calibrate_rgb(
    data: str | Path,
    csv: str | Path | None = None,
    *,
    min_visib: float = 0.1,
    far_mm: float = 100.0,
    right_mm: float = 50.0,
) -> dict[str, Any]:
    """The error statistics of a BOP19 results CSV against a dataset's ground truth (module
    docstring): ``overall`` (targets at least ``min_visib`` visible), ``per_bin`` (per
    visible-fraction bin, :data:`VISIBILITY_BINS`, with the miss rate and rows), ``along``
    (bias and tails of the signed along-ray error), ``flips``, ``rows`` and the settings.
    Distances in mm, angles in deg; quantile tables at :data:`QUANTILE_LEVELS`.

    Raises:
        InputError: unreadable or missing inputs.
    """
    targets = target_errors(data, csv)
    seen = [t for t in targets if t["visib"] >= min_visib]
    best = [t["rows"][0] for t in seen if t["rows"]]
    per_bin = []
    for k in range(len(VISIBILITY_BINS) - 1):
        ts = [t for t in targets if _bin_of(t["visib"]) == k]
        b = [t["rows"][0] for t in ts if t["rows"]]
        per_bin.append({
            "visib": [VISIBILITY_BINS[k], VISIBILITY_BINS[k + 1]], "targets": len(ts),
            "missed": sum(1 for t in ts if not t["rows"]),
            "miss_rate": _share([not t["rows"] for t in ts]),
            **({"rows_mean": round(float(np.mean([len(t["rows"]) for t in ts if t["rows"]])), 4)}
               if b else {}),
            **_block(b, far_mm),
        })  # fmt: skip
    near_along = np.array([b["along"] for b in best if b["trans"] <= far_mm])
    return {
        "data": str(Path(data)),
        "settings": {
            "min_visib": min_visib,
            "far_mm": far_mm,
            "right_mm": right_mm,
            "flip_deg": FLIP_DEG,
            "quantile_levels": list(QUANTILE_LEVELS),
            "visibility_bins": list(VISIBILITY_BINS),
        },  # fmt: skip
        "targets": len(seen),
        "distance_median_mm": _med([t["distance"] for t in seen]),
        "missed": sum(1 for t in seen if not t["rows"]),
        "miss_rate": _share([not t["rows"] for t in seen]),
        "overall": _block(best, far_mm),
        "along_all": _tails(np.array([b["along"] for b in best])) if best else None,
        "along_near": _tails(near_along) if len(near_along) else None,
        "per_bin": per_bin,
        "flips": _flip_axes(best, far_mm),
        "rows": _rows_stats(seen, right_mm),
    }


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def rgb_calibration_markdown(result: dict) -> str:
    """A short report of :func:`calibrate_rgb`'s result."""
    o = result["overall"]
    lines = [
        f"# RGB estimator calibration: {result['data']}",
        "",
        f"{result['targets']} targets >= {result['settings']['min_visib']:.0%} visible, "
        f"{result['missed']} without a row ({result['miss_rate']:.1%}).",
        "",
        f"Best-scored row: along-ray |error| median {o['along_abs_median_mm']:.1f} mm, p75 "
        f"{o['along_abs_p75_mm']:.1f} mm, {o['along_over_10mm']:.0%} > 10 mm, "
        f"{o['along_over_20mm']:.0%} > 20 mm; lateral median {o['lateral_median_mm']:.1f} mm; "
        f"rotation median {o['rotation_median_deg']:.1f} deg, p75 {o['rotation_p75_deg']:.1f} "
        f"deg, {o['rotation_over_30deg']:.0%} > 30 deg; far (> "
        f"{result['settings']['far_mm']:.0f} mm) {o['far_rate']:.1%}.",
        "",
        "| visible | targets | miss | rows | far | flip | along med / p75 mm | lateral mm "
        "| rot deg |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for b in result["per_bin"]:
        if not b["n"]:
            lines.append(f"| {b['visib'][0]:.1f}-{b['visib'][1]:.1f} | {b['targets']} | "
                         f"{_fmt(b['miss_rate'])} | - | - | - | - | - | - |")  # fmt: skip
            continue
        lines.append(
            f"| {b['visib'][0]:.1f}-{b['visib'][1]:.1f} | {b['targets']} | {b['miss_rate']:.2f} "
            f"| {b['rows_mean']:.2f} | {b['far_rate']:.2f} | {b['flip_rate'] or 0:.2f} | "
            f"{b['along_abs_median_mm']:.1f} / {b['along_abs_p75_mm']:.1f} | "
            f"{b['lateral_median_mm']:.1f} | {b['rotation_median_deg']:.1f} |"
        )
    r, f = result["rows"], result["flips"]
    lines += [
        "",
        f"Signed along-ray error, not far: {result['along_near']}",
        f"Flips (not far, > 30 deg): {f}",
        f"Rows: {r}",
        "",
    ]
    return "\n".join(lines)


def write_rgb_calibration(result: dict, out: str | Path) -> list[Path]:
    """``results.json`` and ``results.md`` in the folder ``out``."""
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    return [
        write_json(folder / "results.json", result),
        atomic_write_text(folder / "results.md", rgb_calibration_markdown(result)),
    ]
