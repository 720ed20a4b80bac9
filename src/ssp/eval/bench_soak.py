"""``ssp bench soak``: the scene parser over a long synthetic sequence; time and memory per frame.

The sequence is made of cycles of the ``structure`` experiment
(:func:`ssp.sim.generate.generate_sequence` with seeds ``seed, seed + 1, ...``; five stages
seen four times each, so 20 frames of 9-13 blocks built up), one after the other on one time
line: each cycle's first frame replaces every object of the last one, so object ids, physics
worlds and per-object state churn for the whole run. Frames carry the generator's noisy
hypotheses and instance labels. Cycles are generated one at a time: the sequence is never in
memory, so memory growth is the parser's (or the runner's).

Per frame: wall seconds (:meth:`SceneParser.update`; with ``runner=True`` the time between two
progress calls of :func:`ssp.pipeline.run.run`, which reads the frame's files, perceives it with the
given hypotheses, parses it and writes its crash-safe outputs), the resident set size after
it (``VmRSS`` of ``/proc/self/status``; where there is no ``/proc``, the peak of
:func:`resource.getrusage`), the objects in the scene and whether the unchanged-scene shortcut
was taken. The summary: time per frame over the first and the last 100 frames and per block of
100, the RSS after frame 100, after each block and after the last frame, the growth after frame
100 and over the second half (allocations that warm up, such as caches and the allocator's
arenas, are made in the first hundreds of frames), and least-squares slopes of RSS over those
frames (MiB per 1000 frames).
"""

from __future__ import annotations

import json
import logging
import platform
import resource
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.io import write_cloud, write_hypotheses, write_json
from ssp.parser import SceneParser
from ssp.scene import Frame
from ssp.sim.generate import generate_sequence

__all__ = ["WINDOW", "bench_soak", "rss_mib", "soak_frames", "write_report"]

log = logging.getLogger(__name__)

#: Frames at the start and at the end compared by the summary.
WINDOW = 100
CYCLE_STAGES, CYCLE_REPEATS = 5, 4


def rss_mib() -> float:
    """Resident set size of this process now, MiB (``VmRSS``); the peak RSS where there is
    no ``/proc/self/status``."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def soak_frames(library, n: int, seed: int = 0, stride: int = 4) -> Iterator[tuple[Frame, list]]:
    """``n`` frames of the soak sequence (module docstring) with their raw hypotheses, one
    cycle generated at a time; stamps 0, 1, 2, ... s."""
    k, cycle = 0, 0
    while k < n:
        seq = generate_sequence(
            "structure",
            seed + cycle,
            library,
            stages=CYCLE_STAGES,
            frames_per_stage=CYCLE_REPEATS,
            stride=stride,
        )
        for i in range(len(seq)):
            if k == n:
                break
            f = seq.frame(i)
            f.stamp = float(k)
            yield f, seq.frames[i].hypotheses
            k += 1
        cycle += 1


def _window(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "max": float(a.max()),
    }


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Time per frame over the first and last :data:`WINDOW` frames, RSS growth."""
    secs = [r["seconds"] for r in rows]
    rss = np.asarray([r["rss_mib"] for r in rows], dtype=float)
    w = min(WINDOW, len(rows))
    out: dict[str, Any] = {
        "frames": len(rows),
        "failed": sum(bool(r.get("failed")) for r in rows),
        "sec_per_frame_mean": float(np.mean(secs)),
        f"first_{w}": _window(secs[:w]),
        f"last_{w}": _window(secs[-w:]),
        "rss_mib_first_frame": float(rss[0]),
        f"rss_mib_after_{w}": float(rss[w - 1]),
        "rss_mib_end": float(rss[-1]),
        "rss_mib_max": float(rss.max()),
        f"rss_growth_mib_after_{w}": float(rss[-1] - rss[w - 1]),
    }
    if len(rows) > w + 1:
        x = np.arange(w, len(rows), dtype=float)
        out["rss_slope_mib_per_1000_frames"] = float(np.polyfit(x, rss[w:], 1)[0] * 1000.0)
    half = len(rows) // 2
    if len(rows) - half > 1:  # the second half: long after the warm-up
        x = np.arange(half, len(rows), dtype=float)
        out["rss_growth_mib_second_half"] = float(rss[-1] - rss[half - 1])
        out["rss_slope_second_half_mib_per_1000_frames"] = float(
            np.polyfit(x, rss[half:], 1)[0] * 1000.0
        )
    blocks = range(0, len(rows), w)
    out[f"sec_per_frame_by_{w}"] = [float(np.mean(secs[b : b + w])) for b in blocks]
    out[f"rss_mib_by_{w}"] = [float(rss[min(b + w, len(rows)) - 1]) for b in blocks]
    return out


def bench_soak(
    frames: int = 1000,
    *,
    seed: int = 0,
    stride: int = 4,
    config: SSPConfig | None = None,
    runner: bool = False,
    work_dir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the soak (module docstring); returns the result dict (``per_frame`` and
    ``summary``).

    Args:
        frames: sequence length.
        seed: seed of the first cycle.
        stride: render every ``stride``-th pixel (4: 160 x 120).
        config: ssp's settings.
        runner: go through :func:`ssp.pipeline.run.run` (files in, files out) instead of calling
            the parser directly; the input folder and the run's outputs are written under
            ``work_dir`` (a temporary folder, deleted, when None).
        progress: ``progress(done, total)`` after each frame.
    """
    from ssp.library import ObjectLibrary

    cfg = config if config is not None else SSPConfig()
    library = ObjectLibrary.builtin(cfg.library)
    t0 = time.perf_counter()
    rows = (
        _soak_runner(library, cfg, frames, seed, stride, work_dir, progress)
        if runner
        else _soak_parser(library, cfg, frames, seed, stride, progress)
    )
    return {
        "protocol": "soak",
        "frames": frames,
        "seed": seed,
        "stride": stride,
        "runner": runner,
        "cycle_frames": CYCLE_STAGES * CYCLE_REPEATS,
        "seconds": time.perf_counter() - t0,
        "platform": {"python": platform.python_version(), "machine": platform.machine()},
        "summary": summarize(rows),
        "per_frame": rows,
    }


def _soak_parser(library, cfg, frames, seed, stride, progress) -> list[dict[str, Any]]:
    parser = SceneParser(library, cfg)
    rows = []
    for k, (frame, _) in enumerate(soak_frames(library, frames, seed, stride)):
        t = time.perf_counter()
        try:
            est = parser.update(frame)
        except Exception as exc:  # reported in the row; the soak goes on as a run would
            log.warning("soak frame %d failed: %r", k, exc)
            est = None
        seconds = time.perf_counter() - t
        rows.append(
            {
                "frame": k,
                "seconds": seconds,
                "rss_mib": rss_mib(),
                "objects": None if est is None else len(est.objects),
                "unchanged": None if est is None else est.unchanged,
                "failed": est is None,
            }
        )
        if progress is not None:
            progress(k + 1, frames)
    return rows


def _soak_runner(library, cfg, frames, seed, stride, work_dir, progress) -> list[dict[str, Any]]:
    from ssp.pipeline.run import run

    root = Path(work_dir) if work_dir is not None else Path(tempfile.mkdtemp(prefix="ssp-soak-"))
    src = root / "input"
    try:
        src.mkdir(parents=True, exist_ok=True)
        T_wc = None
        for k, (frame, hyps) in enumerate(soak_frames(library, frames, seed, stride)):
            write_cloud(src / f"f{k:06d}.ply", frame.points, labels=frame.labels + 1)
            write_hypotheses(src / f"f{k:06d}.hypotheses.json", hyps)
            T_wc = frame.T_world_cam
        write_json(src / "scene.json", {"frame": "world", "T_world_cam": T_wc, "period": 1.0})
        rows: list[dict[str, Any]] = []
        last = [time.perf_counter()]

        def on_frame(done: int, total: int, message: str) -> None:
            now = time.perf_counter()
            rows.append({"frame": done - 1, "seconds": now - last[0], "rss_mib": rss_mib()})
            last[0] = now
            if progress is not None:
                progress(done, total)

        last[0] = time.perf_counter()
        summary = run(src, library, root / "run", cfg, hypotheses="given", progress=on_frame)
        failed = {f["index"] for f in summary.failed}
        objects = {d["index"]: d["objects"] for d in summary.done}
        for r in rows:
            r["failed"] = r["frame"] in failed
            r["objects"] = objects.get(r["frame"])
        return rows
    finally:
        if work_dir is None:
            shutil.rmtree(root, ignore_errors=True)


def write_report(result: dict[str, Any], out: str | Path) -> Path:
    """``out/results.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    return path
