"""``ssp bench estimator``: the built-in estimator's time per segment and its recall, alone or
side by side with another revision of ssp on the same segments.

The segments are those of Table I's ``--hypotheses estimated`` runs
(:mod:`ssp.eval.estimated`): the rendered, noisy depth of synthetic sequences, segmented by the
instance mask and cleaned by :class:`ssp.perception.Perception`, with their normals
(:meth:`Perception.segment_request`). Only :meth:`HypothesisEstimator.estimate` is timed, after
:meth:`HypothesisEstimator.prepare` (pair tables, grids and compiled kernels): the cost of a
segment once a run is under way. Recall uses :mod:`ssp.eval.estimated`'s thresholds, per
segment: a hypothesis of the segment's object within 1 cm and 10 deg, and the best-scored one.

With ``--compare REV`` the segments are written once and estimated by each code in fresh
processes, alternately (``rounds`` each); the other code's hypotheses come back and are scored
here, so both sides are judged the same way.
"""

from __future__ import annotations

import json
import pickle
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from ssp.config import SSPConfig
from ssp.eval.bench_parser import available_cores, source_tree_of
from ssp.eval.estimated import RECALL_DEG, RECALL_MM, VISIBLE, perceive_frame
from ssp.eval.metrics import pose_error

__all__ = ["bench_estimator", "collect_segments", "compare_estimator", "write_report"]

#: The target of issue 19: seconds per segment.
TARGET_S = 0.05


def collect_segments(
    experiment: str,
    sequences: int,
    seed: int,
    library: Mapping,
    config: SSPConfig,
    progress: Callable[[str], None] | None = None,
    stages: int | None = None,
) -> list[dict]:
    """The estimator's inputs of every ground-truth object's segment of ``sequences``
    synthetic sequences (seeds ``seed, seed + 1, ...``; ``stages``: static scenes of each,
    default Table I's), as plain arrays: ``points``,
    ``normals``, ``classes``, ``camera``, ``single_object``, ``seed``, with ``sequence``,
    ``frame``, ``gt_class``, ``T_gt`` (4, 4) and ``visib_fract``."""
    from ssp.perception.pipeline import Perception
    from ssp.sim.generate import generate_sequence

    rows = []
    for s in range(int(seed), int(seed) + int(sequences)):
        if progress is not None:
            progress(f"rendering sequence {s}")
        seq = generate_sequence(experiment, s, library, stages=stages)
        perception = Perception(library, config, classes=seq.models or None)
        for i, sf in enumerate(seq.frames):
            cam = np.asarray(seq.camera_pose(i), dtype=float)[:3, 3]
            if progress is not None:
                progress(f"segments of sequence {s}, frame {i + 1}/{len(seq)}")
            res = perceive_frame(perception, seq, sf, hypotheses=[])
            present = set(int(x) for x in res.segmentation.segment_ids)
            for k, (gid, (cls, T_gt)) in enumerate(sf.gt.items()):
                if k not in present:
                    continue
                req = perception.segment_request(res.frame.points, res.segmentation, k, cam, True)
                rows.append(
                    {
                        "points": req.points, "normals": req.normals,
                        "classes": list(req.classes), "camera": req.camera,
                        "single_object": req.single_object, "seed": req.seed,
                        "sequence": s, "frame": int(sf.index), "gt_class": cls,
                        "T_gt": np.asarray(T_gt, dtype=float),
                        "visib_fract": float(sf.visib_fract.get(gid, 0.0)),
                    }
                )  # fmt: skip
    return rows


def estimate_segments(segments: list[dict], library: Mapping, config: SSPConfig) -> list[dict]:
    """Per segment: ``seconds`` of :meth:`HypothesisEstimator.estimate` and its hypotheses
    ``[(class, T_world_obj as nested lists)]``, best first. Runs on whichever ssp is imported
    (the ``--compare`` driver runs it on the other revision's code)."""
    from ssp.perception.estimator import HypothesisEstimator

    est = HypothesisEstimator(library, config.perception, seed=config.seed)
    if hasattr(est, "prepare"):  # older revisions build lazily
        est.prepare(sorted({c for seg in segments for c in seg["classes"]}))
    out = []
    for seg in segments:
        t0 = time.perf_counter()
        res = est.estimate(
            seg["points"], seg["normals"], seg["classes"], seg["camera"],
            single_object=seg["single_object"], seed=seg["seed"],
        )  # fmt: skip
        dt = time.perf_counter() - t0
        hyps = [(h.class_name, np.asarray(h.T_world_obj).tolist()) for h in res.hypotheses]
        out.append({"seconds": dt, "hypotheses": hyps})
    return out


def _score(segments: list[dict], runs: list[dict], library: Mapping) -> list[dict]:
    """Per segment: ``seconds``, ``recalled`` (a hypothesis within the thresholds) and
    ``top1`` (the best-scored one is)."""
    rows = []
    for seg, run in zip(segments, runs, strict=True):
        sym = library[seg["gt_class"]].symmetry
        ok = []
        for cls, T in run["hypotheses"]:
            if cls != seg["gt_class"]:
                ok.append(False)
                continue
            dt, dr = pose_error(seg["T_gt"], np.asarray(T), sym)
            ok.append(dt <= RECALL_MM and dr <= RECALL_DEG)
        rows.append({"seconds": run["seconds"], "recalled": any(ok), "top1": bool(ok and ok[0])})
    return rows


def _summary(segments: list[dict], rows: list[dict]) -> dict:
    secs = np.array([r["seconds"] for r in rows])
    vis = np.array([s["visib_fract"] >= VISIBLE for s in segments], dtype=bool)
    rec = np.array([r["recalled"] for r in rows], dtype=bool)
    top = np.array([r["top1"] for r in rows], dtype=bool)
    return {
        "segments": len(rows),
        "sec_per_segment_mean": float(secs.mean()) if len(secs) else None,
        "sec_per_segment_median": float(np.median(secs)) if len(secs) else None,
        "sec_per_segment_p95": float(np.percentile(secs, 95)) if len(secs) else None,
        "recall": float(rec.mean()) if len(rec) else None,
        "recall_visible": float(rec[vis].mean()) if vis.any() else None,
        "top1_recall_visible": float(top[vis].mean()) if vis.any() else None,
    }


def _machine() -> dict:
    return {
        "python": platform.python_version(),
        "cpu": platform.processor() or "?",
        "cores_available": available_cores(),
    }


def bench_estimator(
    experiment: str = "isolated",
    sequences: int = 3,
    seed: int = 1000,
    library: Mapping | None = None,
    config: SSPConfig | None = None,
    progress: Callable[[str], None] | None = None,
    stages: int | None = None,
) -> dict:
    """Time per segment and recall of this code's estimator (module docstring)."""
    from ssp.library import ObjectLibrary

    cfg = config if config is not None else SSPConfig()
    lib = library if library is not None else ObjectLibrary.builtin()
    segments = collect_segments(experiment, sequences, seed, lib, cfg, progress, stages)
    if progress is not None:
        progress(f"estimating {len(segments)} segments")
    rows = _score(segments, estimate_segments(segments, lib, cfg), lib)
    return {
        "protocol": "estimator-timing", "experiment": experiment, "sequences": sequences,
        "seed": seed, "machine": _machine(), "target_s": TARGET_S,
        "this": _summary(segments, rows),
    }  # fmt: skip


_DRIVER = """
import json, pickle, sys, importlib.util
src, here, path = sys.argv[1], sys.argv[2], sys.argv[3]
sys.path.insert(0, src)
spec = importlib.util.spec_from_file_location("ssp_bench_estimator_driver", here)
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
from ssp.config import SSPConfig
from ssp.library import ObjectLibrary
segments = pickle.load(open(path, "rb"))
runs = mod.estimate_segments(segments, ObjectLibrary.builtin(), SSPConfig())
print("RESULT " + json.dumps(runs))
"""


def compare_estimator(
    rev: str,
    experiment: str = "isolated",
    sequences: int = 3,
    seed: int = 1000,
    rounds: int = 1,
    progress: Callable[[str], None] | None = None,
    stages: int | None = None,
) -> dict:
    """:func:`bench_estimator` with this code and with the code of ``rev`` (a git revision or
    a checkout folder) on the same segments, alternately in fresh processes: both summaries,
    the speed-up (``rev`` / this code, of the mean) and the segments one recalls and the other
    does not."""
    from ssp.errors import SSPError
    from ssp.library import ObjectLibrary

    cfg = SSPConfig()
    lib = ObjectLibrary.builtin()
    segments = collect_segments(experiment, sequences, seed, lib, cfg, progress, stages)
    here = str(Path(__file__).resolve())
    current = str(Path(__file__).resolve().parents[2])
    runs: dict[str, list] = {"rev": [], "this": []}
    with tempfile.TemporaryDirectory(prefix="ssp-compare-") as tmp:
        path = Path(tmp) / "segments.pkl"
        path.write_bytes(pickle.dumps(segments))
        src, remove = source_tree_of(rev, Path(tmp) / "tree")
        try:
            for r in range(rounds):
                for tag, tree in (("rev", str(src)), ("this", current)):
                    name = rev if tag == "rev" else "this code"
                    if progress is not None:
                        progress(f"round {r + 1}/{rounds}: {name}, {len(segments)} segments")
                    p = subprocess.run(
                        [sys.executable, "-c", _DRIVER, tree, here, str(path)],
                        capture_output=True, text=True,
                    )  # fmt: skip
                    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
                    if p.returncode or not line:
                        raise SSPError(
                            f"the estimator bench failed with {name}: {p.stderr.strip()[-2000:]}"
                        )
                    runs[tag].append(json.loads(line[-1][len("RESULT ") :]))
        finally:
            remove()
    scored = {}
    for tag in ("rev", "this"):
        rows = _score(segments, runs[tag][0], lib)
        secs = np.mean([[run[i]["seconds"] for run in runs[tag]] for i in range(len(rows))], 1)
        for row, s in zip(rows, secs, strict=True):
            row["seconds"] = float(s)
        scored[tag] = rows
    rev_sum, this_sum = _summary(segments, scored["rev"]), _summary(segments, scored["this"])
    where = [f"{s['sequence']}/{s['frame']}/{s['gt_class']}" for s in segments]
    pairs = list(zip(where, scored["rev"], scored["this"], strict=True))
    return {
        "protocol": "estimator-timing-compare", "rev": rev, "rounds": rounds,
        "experiment": experiment, "sequences": sequences, "seed": seed,
        "machine": _machine(), "target_s": TARGET_S, "rev_summary": rev_sum, "this": this_sum,
        "speedup": rev_sum["sec_per_segment_mean"] / this_sum["sec_per_segment_mean"],
        "recalled_by_rev_only": [w for w, a, b in pairs if a["recalled"] and not b["recalled"]],
        "recalled_by_this_only": [w for w, a, b in pairs if b["recalled"] and not a["recalled"]],
    }  # fmt: skip


def write_report(result: dict, out: Path) -> tuple[Path, Path]:
    """``out/results.json`` and ``out/results.md`` (``compare.*`` for a comparison)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = "compare" if "rev" in result else "results"
    j = out / f"{stem}.json"
    j.write_text(json.dumps(result, indent=2))
    m = result["machine"]
    head = (
        f"# Estimator: {result['experiment']}, {result['sequences']} sequences from seed "
        f"{result['seed']} (Python {m['python']}, {m['cores_available']} cores available)"
    )
    cols = [("this code", result["this"])]
    if "rev" in result:
        cols.insert(0, (result["rev"], result["rev_summary"]))
        head += f"; {result['rounds']} rounds each, alternating"
    lines = [head, "", "| | " + " | ".join(c for c, _ in cols) + " |",
             "|---|" + "---|" * len(cols)]  # fmt: skip
    for key, what in (
        ("segments", "segments"),
        ("sec_per_segment_mean", "s per segment, mean"),
        ("sec_per_segment_median", "s per segment, median"),
        ("sec_per_segment_p95", "s per segment, p95"),
        ("recall", "recall (1 cm / 10 deg, any of the k)"),
        ("recall_visible", f"recall, objects >= {VISIBLE:.0%} visible"),
        ("top1_recall_visible", "best-scored recall, same objects"),
    ):
        vals = [s[key] for _, s in cols]
        fmt = "{}" if key == "segments" else "{:.4f}"
        lines.append(
            f"| {what} | " + " | ".join("-" if v is None else fmt.format(v) for v in vals) + " |"
        )
    if "rev" in result:
        lines += [
            "",
            f"Speed-up ({result['rev']} / this code, mean): {result['speedup']:.2f}x.",
            f"Recalled by {result['rev']} only ({len(result['recalled_by_rev_only'])}): "
            + (", ".join(result["recalled_by_rev_only"]) or "none"),
            f"Recalled by this code only ({len(result['recalled_by_this_only'])}): "
            + (", ".join(result["recalled_by_this_only"]) or "none"),
        ]
    mean = result["this"]["sec_per_segment_mean"]
    lines += ["", f"Target (issue 19): <= {TARGET_S} s per segment on this machine: "
              + ("met" if mean is not None and mean <= TARGET_S else "not met") + "."]  # fmt: skip
    p = out / f"{stem}.md"
    p.write_text("\n".join(lines) + "\n")
    return j, p
