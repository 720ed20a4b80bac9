"""``ssp bench stream``: the realistic estimator stream beside the built-in estimator it is
calibrated to.

On the same synthetic scenes (the paper's protocol: static scenes, clean instance masks), the
built-in perception front end (:func:`ssp.eval.estimated.estimate_sequence`) and the realistic
stream (:class:`ssp.sim.realistic.RealisticStream`, its default :class:`RealisticNoise`) each
propose hypotheses; :mod:`ssp.eval.stream_stats` measures both the same way (top-1 errors and
gross rate, wrong classes, persistence of errors and of gross failures, dropouts). Use
development seeds (0-99).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path

from ssp.config import SSPConfig
from ssp.eval.estimated import estimate_sequence
from ssp.eval.stream_stats import stream_records, summarize_stream
from ssp.pipeline.executor import Parallel, done_messages, map_items
from ssp.sim.generate import generate_sequence
from ssp.sim.realistic import RealisticNoise, RealisticStream

__all__ = ["run_stream_calibration", "write_stream_calibration"]


def run_stream_calibration(
    experiment: str,
    seeds: Sequence[int],
    library,
    config: SSPConfig | None = None,
    noise: RealisticNoise | None = None,
    progress: Callable[[str], None] | None = None,
    parallel: Parallel | None = None,
) -> dict:
    """Both sources' statistics on the sequences of ``seeds`` (module docstring).

    ``progress`` gets a message per seed as it starts (serial) or ends (in parallel);
    ``parallel``: how the seeds are run (:mod:`ssp.pipeline.executor`), the result is the serial
    one.
    """
    cfg = config if config is not None else SSPConfig()
    noise = noise if noise is not None else RealisticNoise()
    parallel = parallel if parallel is not None else Parallel()
    seeds = [int(s) for s in seeds]
    work = partial(
        _seed_records,
        experiment=experiment,
        config=cfg,
        noise=noise,
        progress=progress if parallel.serial else None,
    )
    done = done_messages(progress, parallel)
    parts = map_items(
        work,
        seeds,
        shared=library,
        parallel=parallel,
        names=[f"seed {s}" for s in seeds],
        progress=done,
    )
    est_records = [r for est, _ in parts for r in est]
    stream_records_ = [r for _, stream in parts for r in stream]
    return {
        "protocol": "stream",
        "experiment": experiment,
        "seeds": [int(s) for s in seeds],
        "estimator": summarize_stream(est_records),
        "stream": summarize_stream(stream_records_),
        "noise": noise.to_dict(),
    }


def _seed_records(
    seed: int,
    library,
    *,
    experiment: str,
    config: SSPConfig,
    noise: RealisticNoise,
    progress: Callable[[str], None] | None = None,
) -> tuple[list[dict], list[dict]]:
    """The built-in estimator's and the realistic stream's records on the sequence of
    ``seed`` (a work item of :func:`run_stream_calibration`)."""
    if progress is not None:
        progress(f"seed {seed}: scenes and the built-in estimator")
    seq = generate_sequence(experiment, seed, library)
    est, _ = estimate_sequence(seq, library, config)
    stream = RealisticStream(library, noise, seed, classes=seq.models)
    frames = []
    for sf in seq.frames:
        labels = {g: k for k, g in enumerate(sf.gt)}
        drawn = stream.draw(sf.index, sf.gt, sf.visib_fract, segments=labels)
        frames.append(replace(sf, hypotheses=[d.hypothesis for d in drawn]))
    return stream_records(est, library), stream_records(replace(seq, frames=frames), library)


_ROWS = (
    ("top-1 gross (> 1 cm / 10 deg or wrong class)", ("top1", "gross"), 100, "%"),
    ("top-1 of the wrong class", ("top1", "wrong_class"), 100, "%"),
    ("top-1 error when not gross, mean mm", ("top1", "trans_mm_mean"), 1, ""),
    ("top-1 error when not gross, mean deg", ("top1", "rot_deg_mean"), 1, ""),
    ("hypotheses per object", ("hypotheses", "per_object"), 1, ""),
    ("hypotheses gross", ("hypotheses", "gross"), 100, "%"),
    ("persistent share of the top-1 error", ("persistence", "bias_share_mean"), 100, "%"),
    ("gross top-1 after a gross top-1", ("persistence", "gross_after_gross"), 100, "%"),
    ("visible objects without hypotheses", ("dropout_rate",), 100, "%"),
)


def _get(d: dict, path: tuple[str, ...]):
    for k in path:
        d = d.get(k) if isinstance(d, dict) else None
    return d


def write_stream_calibration(result: dict, out_dir: str | Path) -> list[Path]:
    """``results.json`` and ``results.md`` (the two columns side by side) in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    j = out / "results.json"
    j.write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        f"# Realistic stream vs the built-in estimator: {result['experiment']}, seeds "
        f"{result['seeds'][0]}-{result['seeds'][-1]}",
        "",
        "| | built-in estimator | realistic stream |",
        "|---|---|---|",
    ]
    for label, path, scale, unit in _ROWS:
        cells = []
        for src in ("estimator", "stream"):
            v = _get(result[src], path)
            cells.append("n/a" if v is None else f"{scale * v:.{1 if unit else 2}f}{unit}")
        lines.append(f"| {label} | {cells[0]} | {cells[1]} |")
    m = out / "results.md"
    m.write_text("\n".join(lines) + "\n")
    return [j, m]
