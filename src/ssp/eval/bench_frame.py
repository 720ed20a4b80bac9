"""``ssp bench frame``: whole-frame latency of ``ssp run`` on real-like frames (issue 34).

What a robot waits for is a whole frame: reading its files, depth to points, the table, the
segments, normals and hypotheses, every parser stage and the results. This bench times that
through :func:`ssp.pipeline.run.run`, the code path of ``ssp run``, on:

* **simulated 640 x 480 clutter** (``sim-...``): realistic sequences of both experiments
  (``structure``: 8 blocks built up in 3 stages; ``isolated``: 4 tools, then 8), rendered
  depth with the realistic sensor model and the realistic estimator stream's hypotheses
  (:class:`ssp.sim.realistic.RealisticNoise`, :class:`~ssp.sim.realistic.SceneRealism`),
  written in the BOP layout; four scenarios: masks (the simulated instance segmentation) or
  none (``--masks none``: the cloud above the table is clustered), hypotheses given (the
  stream's) or estimated (the built-in estimator);
* **real captures** (``real-...``, with ``--real-dev``: ``../shared/data/real-dev``): each
  Kinect capture of :mod:`ssp.eval.real_captures` shown ``--repeats`` times as a sequence (a
  robot watching a static scene), with its label field as masks (``labels``) and without
  (``clusters``); hypotheses estimated (the captures come with none).

Per scenario: the median, 95th percentile and worst wall time per frame, from each frame's
end to the next one's (``ssp run``'s progress: reading to writing, everything), without each
run's first frame (reported apart: it builds the estimator's tables once per run); the share
of each stage in the frames' time (from the frame JSONs' ``frame_timings`` and stage timings:
:mod:`ssp.timing`), and issue 34's targets (:data:`TARGETS`). ``--compare REV`` runs the same
inputs with the code of a git revision (or a checkout folder) and this code alternately, each
in a fresh process, and gives both side by side with the ratio (machines are noisy: the ratio
of one run holds where absolute times do not).

This module is also the driver that times a run in the other revision's process
(:data:`_DRIVER`): what it runs there imports only ``ssp.pipeline.run.run``,
``ssp.library.ObjectLibrary`` and ``ssp.config.SSPConfig``.
"""

from __future__ import annotations

import json
import math
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "SCENARIOS",
    "TARGETS",
    "bench_frame",
    "check_targets",
    "markdown_report",
    "prepare_inputs",
    "same_results",
    "summarize",
    "time_scenarios",
    "write_report",
]

#: Simulated scenarios: name -> (masks, hypotheses) as ``ssp run``'s options.
SCENARIOS: dict[str, tuple[str, str]] = {
    "masks, hypotheses given": ("auto", "given"),
    "masks, built-in estimator": ("auto", "estimated"),
    "no masks, hypotheses given": ("none", "given"),
    "no masks, built-in estimator": ("none", "estimated"),
}

#: Issue 34's targets on the simulated frames: scenario -> (statistic, seconds).
TARGETS: dict[str, list[tuple[str, float]]] = {
    "masks, hypotheses given": [("median", 0.3), ("p95", 0.5)],
    "masks, built-in estimator": [("median", 0.6)],
    "no masks, built-in estimator": [("median", 1.0)],
}

#: The simulated sequences: experiment -> generate_sequence keyword arguments (3-8 objects).
SIM_SEQUENCES: dict[str, dict[str, Any]] = {
    "structure": {"stages": 3, "n_objects": 8},
    "isolated": {"stages": 2, "objects_per_stage": 4},
}


# ------------------------------------------------------------------------------ the inputs
def prepare_inputs(
    work: Path,
    *,
    sequences: int = 1,
    seed: int = 1000,
    frames_per_stage: int = 4,
    real_dev: Path | None = None,
    repeats: int = 5,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Write the bench's inputs in ``work`` and return its runs: ``{scenario, input, models
    (None: built-in), masks, hypotheses, kind}`` (module docstring). Simulated sequences:
    ``sequences`` per experiment, seeds ``seed, seed + 1, ...``."""
    from ssp.config import SSPConfig
    from ssp.library import ObjectLibrary
    from ssp.sim.bop import write_bop
    from ssp.sim.generate import generate_sequence
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    if real_dev is not None:
        _check_real_dev(Path(real_dev))  # before the simulation, not after
    library = ObjectLibrary.builtin(SSPConfig().library)
    runs: list[dict[str, Any]] = []
    for experiment, kwargs in SIM_SEQUENCES.items():
        for i in range(sequences):
            if progress is not None:
                progress(f"simulating {experiment} {i + 1}/{sequences}")
            scene = work / "sim" / experiment / f"{i:06d}"
            if not (scene / "scene_gt.json").exists():
                seq = generate_sequence(
                    experiment, seed + i, library, frames_per_stage=frames_per_stage,
                    hypotheses=RealisticNoise(), realism=SceneRealism(), **kwargs,
                )  # fmt: skip
                write_bop(seq, scene, scene_id=i)
            for name, (masks, hyps) in SCENARIOS.items():
                runs.append({"scenario": f"sim {experiment}: {name}", "input": str(scene),
                             "models": None,
                             "masks": masks, "hypotheses": hyps, "kind": "sim"})  # fmt: skip
    if real_dev is not None:
        runs += _real_runs(Path(real_dev), work / "real", repeats)
    return runs


def _check_real_dev(data: Path) -> None:
    """ArgumentError unless ``data`` holds the real captures' folders."""
    from ssp.errors import ArgumentError
    from ssp.eval.real_captures import MILK, MOSD

    if not (data / MOSD).is_dir() or not (data / MILK).is_dir():
        raise ArgumentError(
            f"--real-dev {data}: expected the real captures' folder (../shared/data/real-dev) "
            f"with {MOSD}/ and {MILK}/ in it"
        )


def _real_runs(data: Path, work: Path, repeats: int) -> list[dict[str, Any]]:
    """The real captures as runs of ``repeats`` frames each (links to the capture).

    Raises:
        ArgumentError: ``data`` is not the real captures' folder.
    """
    from ssp.eval.real_captures import milk_captures, mosd_captures

    _check_real_dev(data)

    runs = []
    for r in mosd_captures(data, work, None) + milk_captures(data, work, None):
        src = Path(r["input"])
        clouds = sorted(p for p in src.iterdir() if p.suffix in (".pcd", ".ply"))
        seq = work / "sequences" / r["capture"].replace(" ", "-")
        seq.mkdir(parents=True, exist_ok=True)
        for k in range(repeats):
            link = seq / f"{k:06d}{clouds[0].suffix}"
            if not link.is_symlink() and not link.exists():
                link.symlink_to(clouds[0].resolve())
        if (src / "scene.json").exists():
            (seq / "scene.json").write_text((src / "scene.json").read_text(), encoding="utf-8")
        masks = "labels" if r["capture"].endswith("labels") else "none"
        runs.append({"scenario": f"real: {r['capture']}", "input": str(seq),
                     "models": str(r["models"]), "masks": masks, "hypotheses": "estimated",
                     "kind": "real"})  # fmt: skip
    return runs


# ------------------------------------------------------------------------------ the timing
def time_scenarios(args: dict[str, Any]) -> dict[str, Any]:
    """Run every run of ``args["runs"]`` (:func:`prepare_inputs`) with the ssp imported here,
    into ``args["out"]/<k>``; per run, each frame's wall time (end of one frame to the end of
    the next; the first from the call) and what its frame JSON says. Runs in the process of
    the code being timed (:data:`_DRIVER`); uses only APIs every revision has."""
    import shutil

    from ssp.config import SSPConfig
    from ssp.library import ObjectLibrary
    from ssp.pipeline.run import run

    cfg = SSPConfig()
    processes = int(args.get("processes", 1))
    if processes > 1:  # as ssp run --processes: the estimator's segments and the search's tests
        cfg.perception.processes = cfg.search.processes = processes
    libraries: dict[str | None, Any] = {}
    out_root = Path(args["out"])
    results = []
    for k, r in enumerate(args["runs"]):
        models = r["models"]
        if models not in libraries:
            libraries[models] = (
                ObjectLibrary.builtin() if models is None else ObjectLibrary.from_folder(models)
            )
        out = out_root / f"{k:03d}"
        if out.exists():
            shutil.rmtree(out)
        stamps: list[float] = []
        t0 = time.perf_counter()
        opts: dict[str, Any] = {"hypotheses": r["hypotheses"]}
        if r["kind"] == "sim":
            opts["masks"] = r["masks"]

        def stamp(done: int, total: int, message: str, stamps: list[float] = stamps) -> None:
            stamps.append(time.perf_counter())

        run(r["input"], libraries[models], out, cfg, progress=stamp, **opts)
        walls = [b - a for a, b in zip([t0, *stamps[:-1]], stamps, strict=True)]
        frames = []
        for wall, path in zip(walls, sorted((out / "frames").glob("*.json")), strict=False):
            doc = json.loads(path.read_text())
            frames.append({
                "name": path.stem,
                "wall": wall,
                "status": doc.get("status"),
                "objects": len(doc.get("objects") or []),
                "seconds": doc.get("seconds"),
                "frame_timings": doc.get("frame_timings"),
                "perception": (doc.get("perception") or {}).get("timings"),
                "parser": doc.get("timings"),
            })  # fmt: skip
        results.append({"scenario": r["scenario"], "input": r["input"], "frames": frames})
    return {"runs": results, "machine": _machine()}


def _machine() -> dict[str, Any]:
    import os

    return {"python": platform.python_version(), "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine()}  # fmt: skip


_DRIVER = """
import json, sys
tree, here, args = sys.argv[1], sys.argv[2], sys.argv[3]
sys.path.insert(0, tree)
import importlib.util
spec = importlib.util.spec_from_file_location("ssp_bench_frame_driver", here)
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
res = mod.time_scenarios(json.loads(args))
print("RESULT " + json.dumps(res))
"""


def _in_process(tree: str, args: dict[str, Any], name: str) -> dict[str, Any]:
    """:func:`time_scenarios` in a fresh process running the ssp of ``tree`` (a ``src``)."""
    import os
    import subprocess
    import sys

    from ssp.errors import SSPError

    env = {**os.environ, "PYTHONPATH": tree}
    p = subprocess.run(
        [sys.executable, "-c", _DRIVER, tree, str(Path(__file__).resolve()), json.dumps(args)],
        capture_output=True, text=True, env=env, check=False,
    )  # fmt: skip
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    if p.returncode or not line:
        raise SSPError(f"the frame bench failed with {name}: {p.stderr.strip()[-2000:]}")
    return json.loads(line[-1][len("RESULT ") :])


def bench_frame(
    out: Path,
    *,
    sequences: int = 1,
    seed: int = 1000,
    frames_per_stage: int = 4,
    real_dev: Path | None = None,
    repeats: int = 5,
    compare: str | None = None,
    rounds: int = 1,
    processes: int = 1,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Write the inputs in ``out/inputs``, time them (``out/runs``) with this code, and with
    ``compare`` (a git revision or checkout folder) alternately, ``rounds`` times each, every
    time in a fresh process; returns the result :func:`write_report` writes. ``processes``:
    as ``ssp run --processes`` (both codes)."""
    import tempfile

    from ssp.eval.bench_parser import source_tree_of

    out = Path(out)
    runs = prepare_inputs(out / "inputs", sequences=sequences, seed=seed,
                          frames_per_stage=frames_per_stage, real_dev=real_dev,
                          repeats=repeats, progress=progress)  # fmt: skip
    this_tree = str(Path(__file__).resolve().parents[2])
    revision = _revision(Path(this_tree))  # before the runs: the code they time
    timed: dict[str, list[dict[str, Any]]] = {"this": [], "rev": []}
    with tempfile.TemporaryDirectory(prefix="ssp-compare-") as tmp:
        rev_tree, remove = (None, lambda: None)
        if compare is not None:
            src, remove = source_tree_of(compare, Path(tmp) / "tree")
            rev_tree = str(src)
        try:
            for r in range(rounds):
                sides = [("rev", rev_tree)] if rev_tree is not None else []
                for tag, tree in [*sides, ("this", this_tree)]:
                    name = compare if tag == "rev" else "this code"
                    if progress is not None:
                        progress(f"round {r + 1}/{rounds}: {name}, {len(runs)} runs")
                    args = {"runs": runs, "out": str(out / "runs" / tag), "processes": processes}
                    timed[tag].append(_in_process(str(tree), args, str(name)))
        finally:
            remove()
    result: dict[str, Any] = {
        "protocol": "frame-latency",
        "sequences": sequences, "seed": seed, "frames_per_stage": frames_per_stage,
        "real_dev": None if real_dev is None else str(real_dev), "repeats": repeats,
        "rounds": rounds, "compare": compare, "processes": processes,
        "machine": timed["this"][0]["machine"],
        "this": summarize(timed["this"]),
    }  # fmt: skip
    if compare is not None:
        result["rev"] = summarize(timed["rev"])
        result["rev_machine"] = timed["rev"][0]["machine"]
        result["same_results"] = same_results(runs, out / "runs" / "rev", out / "runs" / "this")
    result["revision"] = revision
    result["targets"] = check_targets(result["this"])
    result["command"] = {"sequences": str(sequences), "seed": str(seed),
                         "real-dev": None if real_dev is None else str(real_dev),
                         "repeats": str(repeats), "compare": compare, "rounds": str(rounds),
                         "processes": str(processes)}  # fmt: skip
    return result


def same_results(runs: list[dict[str, Any]], rev_dir: Path, this_dir: Path) -> dict[str, str]:
    """Per scenario, whether the two codes' outputs of its runs (the last round's) are the
    same: the frame JSONs without wall times (:func:`ssp.pipeline.summary.without_timings`)
    and the CSV rows without their time column; ``"identical"``, else how many frames differ
    and the first."""
    from ssp.pipeline.summary import without_timings

    out: dict[str, list[str]] = {}
    for k, r in enumerate(runs):
        a, b = Path(rev_dir) / f"{k:03d}", Path(this_dir) / f"{k:03d}"
        differ = []
        names = sorted({p.name for p in [*a.glob("frames/*.json"), *b.glob("frames/*.json")]})
        for name in names:
            docs = [
                without_timings(json.loads(p.read_text())) if p.exists() else None
                for p in (a / "frames" / name, b / "frames" / name)
            ]
            if docs[0] != docs[1]:
                differ.append(Path(name).stem)
        rows = [
            sorted(
                line.rsplit(",", 1)[0]
                for p in d.glob("*.csv")
                for line in p.read_text().splitlines()
            )
            for d in (a, b)
        ]
        if rows[0] != rows[1] and not differ:
            differ.append("CSV rows")
        out.setdefault(r["scenario"], []).extend(f"{Path(r['input']).name}/{n}" for n in differ)
    return {
        sc: "identical" if not d else f"{len(d)} frame(s) differ, first {d[0]}"
        for sc, d in out.items()
    }


def _revision(tree: Path) -> str | None:
    """The git revision of the checkout holding ``tree`` (``+`` when it has uncommitted
    changes), or None outside a checkout."""
    import subprocess

    try:
        git = ["git", "-C", str(tree)]
        run = {"capture_output": True, "text": True, "check": True}
        head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], **run).stdout.strip()
        dirty = subprocess.run([*git, "status", "--porcelain", "--", "."], **run).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+" if dirty else "")


# ------------------------------------------------------------------------------ the numbers
def _percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (linear interpolation, as numpy's default)."""
    import numpy as np

    return float(np.percentile(np.asarray(values, dtype=float), q)) if values else math.nan


def summarize(rounds: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scenario, over every round and run: frames, median / p95 / worst wall seconds of
    the frames after each run's first, the first frames' median, the objects per frame, and
    each stage's share of the frames' time (exclusive stages: ``perception/<stage>``,
    ``parser/<stage>``, ``results``, and ``writing and other``, the rest of the wall time;
    empty for a revision without frame timings)."""
    by: dict[str, dict[str, Any]] = {}
    for rnd in rounds:
        for run in rnd["runs"]:
            s = by.setdefault(
                run["scenario"],
                {"walls": [], "first": [], "objects": [], "failed": 0, "stages": {}},
            )
            for i, f in enumerate(run["frames"]):
                if f["status"] != "done":
                    s["failed"] += 1
                    continue
                if i == 0:
                    s["first"].append(f["wall"])
                    continue
                s["walls"].append(f["wall"])
                s["objects"].append(f["objects"])
                _add_stages(s, f)
    rows = []
    for scenario, s in by.items():
        walls = s["walls"]
        total = sum(walls)
        shares = {k: v / total for k, v in s["stages"].items()} if s["stages"] and total else {}
        if shares:
            shares["writing and other"] = 1.0 - sum(shares.values())
        rows.append({
            "scenario": scenario,
            "frames": len(walls),
            "failed": s["failed"],
            "objects": [min(s["objects"], default=0), max(s["objects"], default=0)],
            "median": _percentile(walls, 50),
            "p95": _percentile(walls, 95),
            "max": max(walls, default=math.nan),
            "mean": total / len(walls) if walls else math.nan,
            "first_median": _percentile(s["first"], 50),
            "shares": dict(sorted(shares.items(), key=lambda kv: -kv[1])),
        })  # fmt: skip
    return rows


def _add_stages(s: dict[str, Any], f: dict[str, Any]) -> None:
    """Add frame ``f``'s exclusive stage seconds to ``s["stages"]`` (when it has them)."""
    ft = f.get("frame_timings")
    if not ft:
        return
    st = s["stages"]
    for group in ("perception", "parser"):
        for stage, sec in (f.get(group) or {}).items():
            if stage not in ("total", "lanes"):
                st[f"{group}/{stage}"] = st.get(f"{group}/{stage}", 0.0) + float(sec)
    for part in ("results", "other"):
        st[part] = st.get(part, 0.0) + float(ft.get(part, 0.0))


def check_targets(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Issue 34's targets (:data:`TARGETS`) against each simulated scenario's row (each
    experiment apart: a median over both would hide the slower one). A scenario with a
    failed frame meets none: a frame that raised is not a fast frame."""
    out = []
    for row in rows:
        if not row["scenario"].startswith("sim "):
            continue
        name = row["scenario"].split(": ", 1)[1]
        for stat, limit in TARGETS.get(name, []):
            got = row[stat]
            out.append({"scenario": row["scenario"], "statistic": stat, "target_s": limit,
                        "seconds": got, "failed": row["failed"],
                        "met": bool(got <= limit and not row["failed"])})  # fmt: skip
    return out


# ------------------------------------------------------------------------------ the report
def write_report(result: dict[str, Any], out: Path) -> list[Path]:
    """``out/results.json``, ``out/results.md`` and ``out/shares.png`` (the stage shares)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    j = out / "results.json"
    j.write_text(json.dumps(result, indent=1, allow_nan=True), encoding="utf-8")
    m = out / "results.md"
    m.write_text(markdown_report(result), encoding="utf-8")
    files = [j, m]
    png = _plot(result["this"], out / "shares.png")
    if png is not None:
        files.append(png)
    return files


def _ms(x: float) -> str:
    return "-" if x is None or math.isnan(x) else f"{1000 * x:.0f}"


def markdown_report(result: dict[str, Any]) -> str:
    """``results.md``: the latency table (side by side with ``compare``'s when given), then
    issue 34's targets."""
    cmp = result.get("compare")
    machine = result["machine"]
    lines = [
        f"# Whole-frame latency (`ssp bench frame`, code {result.get('revision') or '?'}): "
        f"{machine['cpus']} CPUs, Python "
        f"{machine['python']}; {result['sequences']} sequence(s) per experiment from seed "
        f"{result['seed']}, {result['rounds']} round(s), {result.get('processes', 1)} "
        "process(es) per run",
        "",
        "Wall milliseconds per frame, reading to writing, without each run's first frame "
        "(first: its median).",
        "",
    ]
    if cmp is None:
        lines += ["| scenario | frames | failed | objects | median | p95 | worst | first | "
                  "top stages |", "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in result["this"]:
            lines.append(
                f"| {r['scenario']} | {r['frames']} | {r['failed']} | "
                f"{r['objects'][0]}-{r['objects'][1]} | "
                f"{_ms(r['median'])} | {_ms(r['p95'])} | {_ms(r['max'])} | "
                f"{_ms(r['first_median'])} | {_top(r['shares'])} |"
            )
    else:
        rev = {r["scenario"]: r for r in result["rev"]}
        same = result.get("same_results", {})
        lines += [f"| scenario | frames | failed {cmp} / this | median {cmp} | median this | "
                  f"speed-up | p95 {cmp} | p95 this | speed-up | results | top stages (this) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in result["this"]:
            o = rev.get(r["scenario"], {})
            lines.append(
                f"| {r['scenario']} | {r['frames']} | {o.get('failed', '-')} / {r['failed']} | "
                f"{_ms(o.get('median', math.nan))} | "
                f"{_ms(r['median'])} | {_ratio(o.get('median'), r['median'])} | "
                f"{_ms(o.get('p95', math.nan))} | {_ms(r['p95'])} | "
                f"{_ratio(o.get('p95'), r['p95'])} | {same.get(r['scenario'], '-')} | "
                f"{_top(r['shares'])} |"
            )
    if result.get("targets"):
        lines += ["", "Issue 34's targets (this code):", "",
                  "| scenario | statistic | target ms | ms | failed frames | met |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        for t in result["targets"]:
            lines.append(
                f"| {t['scenario']} | {t['statistic']} | {_ms(t['target_s'])} | "
                f"{_ms(t['seconds'])} | {t.get('failed', 0)} | {'yes' if t['met'] else 'no'} |"
            )
    return "\n".join(lines) + "\n"


def _ratio(old: float | None, new: float) -> str:
    if old is None or not new or math.isnan(old) or math.isnan(new):
        return "-"
    return f"{old / new:.2f}x"


def _top(shares: dict[str, float], n: int = 4) -> str:
    return ", ".join(f"{k} {100 * v:.0f} %" for k, v in list(shares.items())[:n]) or "-"


def _plot(rows: list[dict[str, Any]], path: Path) -> Path | None:
    """A horizontal stacked bar per scenario: the mean frame split by stage (the stages that
    hold at least 3 % of some scenario's time; the rest as ``other stages``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["shares"]]
    if not rows:
        return None
    keys = sorted({k for r in rows for k, v in r["shares"].items() if v >= 0.03},
                  key=lambda k: -max(r["shares"].get(k, 0.0) for r in rows))  # fmt: skip
    fig, ax = plt.subplots(figsize=(10, 0.6 * len(rows) + 2))
    cmap = plt.get_cmap("tab20")
    for i, r in enumerate(rows):
        left = 0.0
        for j, k in enumerate([*keys, "other stages"]):
            if k == "other stages":
                v = max(0.0, 1.0 - sum(r["shares"].get(x, 0.0) for x in keys))
            else:
                v = max(0.0, r["shares"].get(k, 0.0))
            width = 1000 * v * r["mean"]
            ax.barh(i, width, left=left, color=cmap(j % 20), label=k if i == 0 else None)
            left += width
    ax.set_yticks(range(len(rows)), [r["scenario"] for r in rows])
    ax.invert_yaxis()
    ax.set_xlabel("mean wall ms per frame (after each run's first)")
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
