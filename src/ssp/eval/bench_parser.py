"""``ssp bench parser``: time per frame of :meth:`SceneParser.update` (issue 3's report).

Scenes are stacks of built-in cubes and blocks (1-3 high) on a grid, seen by a camera about
1 m away; frames are rendered depth with sensor noise (:func:`ssp.sim.frames.synthetic_frame`)
and ``k`` noisy hypotheses per object (5 mm / 5 deg RMS). Per scene size N, three frames:

* ``added``: the first frame, every object new (the most expensive case);
* ``changed``: one stack slid by 1.5 cm and the rest static (the usual changed frame);
* ``unchanged``: the same scene again with fresh hypothesis noise.

Everything runs on one core (``OMP_NUM_THREADS=1``); timings are wall seconds per frame and the
share of each stage (forces, stepping, contacts, scoring, the rest). The mean symmetry-aware
error of the estimates and of the hypotheses (ground truth is known; matched as in
:mod:`ssp.eval.metrics`) is reported alongside.
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ssp.config import SSPConfig
from ssp.eval.metrics import hypothesis_errors, match_frame
from ssp.geometry import make_pose
from ssp.library import ObjectLibrary
from ssp.parser import SceneEstimate, SceneParser
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at

__all__ = ["bench_parser", "stacks", "write_report"]

STAGES = ("forces", "stepping", "contacts", "scoring")
FRAMES = ("added", "changed", "unchanged")


def stacks(library: ObjectLibrary, n: int, seed: int = 0, spacing: float = 0.09) -> dict:
    """``n`` cubes and blocks in stacks 1-3 high on a grid: ``id -> (class, T_world_obj)``."""
    rng = np.random.default_rng(seed)
    heights = []
    while sum(heights) < n:
        heights.append(min(int(rng.integers(1, 4)), n - sum(heights)))
    side = int(np.ceil(np.sqrt(len(heights))))
    gt: dict[str, tuple[str, np.ndarray]] = {}
    for s, h in enumerate(heights):
        x = (s % side - (side - 1) / 2) * spacing
        y = (s // side - (side - 1) / 2) * spacing
        yaw = float(rng.uniform(-0.3, 0.3))
        z = 0.0
        for level in range(h):
            name = "block" if (s + level) % 2 else "cube"
            m = library[name]
            c, si = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
            T = make_pose(R, [x, y, z - float(m.mesh.bounds[0, 2])])
            gt[f"{name}_{len(gt)}"] = (name, T)
            z += float(m.extents[2])
    return gt


def _slide(gt: dict, dx: float) -> dict:
    """The same scene with the first stack (the objects at the first x, y) moved by dx in x."""
    first = next(iter(gt.values()))[1][:2, 3]
    out = {}
    for oid, (cls, T) in gt.items():
        T = T.copy()
        if np.linalg.norm(T[:2, 3] - first) < 1e-9:
            T[0, 3] += dx
        out[oid] = (cls, T)
    return out


def _errors(est: SceneEstimate, frame, gt: dict, library) -> tuple[list, list]:
    """Symmetry-aware (mm, deg) errors of the estimate's matched objects and of every
    hypothesis (:func:`ssp.eval.metrics.match_frame`, :func:`hypothesis_errors`)."""
    fm = match_frame(gt, [(o.class_name, o.T_world_obj) for o in est.objects], library)
    hyp_err, _ = hypothesis_errors(gt, frame.hypotheses, library)
    return [(m.trans_mm, m.rot_deg) for m in fm.matches], hyp_err


def _shares(est: SceneEstimate) -> dict[str, float]:
    total = est.timings.get("total", 0.0)
    out = {s: est.timings.get(s, 0.0) / total if total else 0.0 for s in STAGES}
    out["other"] = max(0.0, 1.0 - sum(out.values()))
    return out


def bench_parser(
    sizes: Sequence[int] = (5, 10, 20),
    k: int = 5,
    repeats: int = 2,
    seed: int = 0,
    config: SSPConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Time the parser on ``repeats`` scenes of each size; returns a JSON-ready dict."""
    config = config if config is not None else SSPConfig()
    lib = ObjectLibrary.builtin(config)
    T_world_cam = look_at([-0.5, -0.6, 0.65], [0.0, 0.0, 0.03])
    rows = []
    for n in sizes:
        per: dict[str, list] = {f: [] for f in FRAMES}
        err: dict[str, tuple[list, list]] = {f: ([], []) for f in FRAMES}
        for r in range(repeats):
            if progress:
                progress(f"N = {n}, scene {r + 1}/{repeats}")
            rng = np.random.default_rng([seed, n, r])
            gt = stacks(lib, n, seed=seed * 1000 + n * 10 + r)
            scenes = {"added": gt, "changed": _slide(gt, 0.015)}
            scenes["unchanged"] = scenes["changed"]
            parser = SceneParser(lib, config)
            for t, name in enumerate(FRAMES):
                f = synthetic_frame(
                    lib, scenes[name], T_world_cam=T_world_cam, rng=rng, k=k, stamp=float(t)
                )
                t0 = time.perf_counter()
                est = parser.update(f)
                wall = time.perf_counter() - t0
                per[name].append((wall, est))
                e, h = _errors(est, f, scenes[name], lib)
                err[name][0].extend(e)
                err[name][1].extend(h)
        row = {"objects": n, "k": k, "n_times_k": n * k}
        for name in FRAMES:
            walls = [w for w, _ in per[name]]
            ests = [e for _, e in per[name]]
            shares = [_shares(e) for e in ests]
            row[name] = {
                "sec_per_frame_mean": float(np.mean(walls)),
                "sec_per_frame_max": float(np.max(walls)),
                "hypotheses_tested_mean": float(np.mean([e.hypotheses_tested for e in ests])),
                "unchanged_shortcut": [bool(e.unchanged) for e in ests],
                "stage_share": {s: float(np.mean([sh[s] for sh in shares])) for s in shares[0]},
                "error": {
                    "ssp_mm_mean": float(np.mean([e[0] for e in err[name][0]])),
                    "ssp_deg_mean": float(np.mean([e[1] for e in err[name][0]])),
                    "hypotheses_mm_mean": float(np.mean([e[0] for e in err[name][1]])),
                    "hypotheses_deg_mean": float(np.mean([e[1] for e in err[name][1]])),
                },
            }
        rows.append(row)
    xs = np.array([r["n_times_k"] for r in rows], dtype=float)
    fits = {}
    for name in FRAMES:
        ys = np.array([r[name]["sec_per_frame_mean"] for r in rows])
        if len(xs) >= 2:
            slope, icept = np.polyfit(xs, ys, 1)
            pred = slope * xs + icept
            ss_res = float(((ys - pred) ** 2).sum())
            ss_tot = float(((ys - ys.mean()) ** 2).sum()) or 1.0
            fits[name] = {
                "sec_per_hypothesis": float(slope),
                "intercept_s": float(icept),
                "r2": 1.0 - ss_res / ss_tot,
            }
    return {
        "protocol": "parser-timing",
        "sizes": list(sizes),
        "k": k,
        "repeats": repeats,
        "seed": seed,
        "machine": {
            "python": platform.python_version(),
            "cpu": platform.processor() or "?",
            "threads": 1,
        },
        "rows": rows,
        "linear_fit_vs_n_times_k": fits,
        "targets_s": {"changed": 2.0, "unchanged": 0.2},
    }


def write_report(result: dict, out: Path) -> tuple[Path, Path]:
    """``out/results.json`` and ``out/results.md`` (a table per frame kind)."""
    out.mkdir(parents=True, exist_ok=True)
    j = out / "results.json"
    j.write_text(json.dumps(result, indent=2))
    lines = [
        f"# Parser timing (k = {result['k']}, {result['repeats']} scenes per size, one core)",
        "",
        "| N | frame | s/frame mean | s/frame max | tested | forces | stepping | contacts "
        "| scoring | other | ssp error | hypotheses error |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        for name in FRAMES:
            d = r[name]
            sh = d["stage_share"]
            lines.append(
                f"| {r['objects']} | {name} | {d['sec_per_frame_mean']:.3f} | "
                f"{d['sec_per_frame_max']:.3f} | {d['hypotheses_tested_mean']:.0f} | "
                + " | ".join(f"{100 * sh[s]:.0f} %" for s in (*STAGES, "other"))
                + f" | {d['error']['ssp_mm_mean']:.2f} mm / {d['error']['ssp_deg_mean']:.2f} deg"
                + f" | {d['error']['hypotheses_mm_mean']:.2f} mm / "
                + f"{d['error']['hypotheses_deg_mean']:.2f} deg |"
            )
    lines += ["", "Linear fit of s/frame against N k:", ""]
    for name, f in result["linear_fit_vs_n_times_k"].items():
        lines.append(
            f"- {name}: {1000 * f['sec_per_hypothesis']:.1f} ms per hypothesis, intercept "
            f"{f['intercept_s']:.3f} s, R^2 {f['r2']:.3f}"
        )
    m = out / "results.md"
    m.write_text("\n".join(lines) + "\n")
    return j, m
