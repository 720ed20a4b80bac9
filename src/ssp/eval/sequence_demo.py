"""``ssp demo``: a short synthetic "structure" sequence end to end, every method side by side.

One sequence of blocks and cubes built layer by layer (:func:`ssp.sim.generate.generate_sequence`),
rendered depth with sensor noise and noisy hypotheses, fed to ssp and to the baselines of
Table I (:func:`ssp.eval.table1.run_table1`). Writes into ``out``:

* ``results.json`` / ``results.md``: the comparison table (the Table I layout);
* ``error_vs_visibility.png``, ``error_over_frames.png``;
* ``frames/NNN.png``: the last frame of each static scene, outlines of the truth (white), ssp
  and the pose estimator alone over the depth image;
* ``report.html``: all of it on one page;
* ``run.rrd``: a 3D recording of ssp's run (:mod:`ssp.viz.record`, with the ground truth),
  when rerun is installed (the ``record`` extra); ``ssp view OUT/run.rrd`` opens it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from ssp.config import SSPConfig
from ssp.eval.table1 import run_table1, write_table1
from ssp.library import ObjectLibrary
from ssp.sim.generate import generate_sequence
from ssp.viz.overlay import overlay, save_png
from ssp.viz.report import write_html_report

__all__ = ["RECORDING", "run_sequence_demo"]

log = logging.getLogger(__name__)

#: The demo's 3D recording, in its output folder.
RECORDING = "run.rrd"

#: Methods in the demo's table (the benchmark's, but the costly memoryless parser), and those
#: drawn on the frame images.
METHODS = ("ssp", "estimator", "icp", "ray_slide", "bestfit", "temporal_filter", "icp_filter")
DRAWN = ("estimator", "ssp")


def run_sequence_demo(
    out: Path,
    config: SSPConfig | None = None,
    *,
    experiment: str = "structure",
    seed: int = 1000,
    stages: int = 4,
    frames_per_stage: int = 4,
    stride: int = 1,
    progress: Callable[[str], None] | None = None,
    record: bool = True,
) -> dict:
    """Run the demo; returns the Table I result dict plus ``files``, ``seconds`` and
    ``recording`` (the path of ``run.rrd``, or None: ``record`` off or rerun not installed).
    ``progress(message)``: what it is doing, and after ssp's update of each frame
    ``frame N/TOTAL: ssp kept K objects (S s)``."""
    t0 = time.perf_counter()
    config = config if config is not None else SSPConfig()
    lib = ObjectLibrary.builtin(config.library)
    if progress:
        progress("building the scenes by physics and rendering them")
    seq = generate_sequence(
        experiment, seed, lib, stages=stages, frames_per_stage=frames_per_stage, stride=stride
    )
    last_of_stage = {
        i
        for i, f in enumerate(seq.frames)
        if i + 1 == len(seq.frames) or seq.frames[i + 1].static_group != f.static_group
    }
    outputs: dict[int, dict[str, list]] = {}
    started = [time.perf_counter()]

    def frame_started(_message: str) -> None:  # run_table1's, before each frame
        started[0] = time.perf_counter()

    def keep(_s: int, i: int, method: str, dets) -> None:
        if i in last_of_stage and method in DRAWN:
            outputs.setdefault(i, {})[method] = [(d[0], d[1]) for d in dets]
        if method == "ssp" and progress is not None:
            seconds = time.perf_counter() - started[0]
            progress(f"frame {i + 1}/{len(seq)}: ssp kept {len(dets)} objects ({seconds:.2f} s)")

    out = Path(out)
    with ExitStack() as stack:
        recorder = _recorder(out / RECORDING, lib) if record else None
        on_estimate = None
        if recorder is not None:
            stack.enter_context(recorder)
            last = [None]

            def on_estimate(_s: int, i: int, frame, est) -> None:
                if est is None or est is last[0]:  # the parser rejected this frame
                    recorder.log_failure(i, f"{i:03d}", "ssp skipped the frame (see the log)")
                else:
                    recorder.log_frame(
                        i, frame, est, name=f"{i:03d}", truth=seq.ground_truth(i),
                        camera=seq.camera, depth=seq.frames[i].depth,
                    )  # fmt: skip
                last[0] = est

        result = run_table1(
            [seq], lib, config, METHODS, progress=frame_started, on_output=keep,
            on_estimate=on_estimate,
        )  # fmt: skip
    if progress:
        progress("writing the report")
    files = write_table1(result, out)
    frames = []
    for i in sorted(outputs):
        f = seq.frames[i]
        img = overlay(lib, f.depth, seq.camera, seq.camera_pose(i), list(f.gt.values()), outputs[i])
        caption = f"frame {i}: {len(f.gt)} objects"
        png = save_png(out / "frames" / f"{i:03d}.png", img, caption, ["truth", *DRAWN])
        frames.append((caption, png))
    plots = [p for p in files if p.suffix == ".png"]
    md = next(p for p in files if p.suffix == ".md").read_text()
    page = write_html_report(
        out,
        "ssp demo: a synthetic block structure, ssp against its baselines",
        md,
        plots=plots,
        frames=frames,
        notes=[
            f"Sequence: {experiment}, seed {seed}, {len(seq)} frames "
            f"({stages} static scenes x {frames_per_stage} frames), camera "
            f"{seq.camera.width} x {seq.camera.height}. Rerun: ssp demo --out {out}",
            *(
                [f"3D recording of ssp's run: ssp view {recorder.path}"]
                if recorder is not None
                else []
            ),
        ],
    )
    recording = None if recorder is None else recorder.path
    shown = (*files, *(p for _, p in frames), page, *([recording] if recording else []))
    result["files"] = [str(p) for p in shown]
    result["recording"] = None if recording is None else str(recording)
    result["seconds"] = time.perf_counter() - t0
    return result


def _recorder(path: Path, lib):
    """A :class:`ssp.viz.record.Recorder` of ``path``, or None (logged) without rerun."""
    from ssp.viz.record import Recorder, RecordingError

    try:
        return Recorder(path, lib)
    except RecordingError as exc:
        log.warning("no 3D recording: %s", exc)
        return None
