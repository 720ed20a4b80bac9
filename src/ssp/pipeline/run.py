"""``ssp run``: the whole pipeline over recorded frames, with files in and files out.

Inputs (``docs/formats.md``): a folder of PLY/PCD clouds (:func:`ssp.io.folder.open_folder`),
a BOP scene folder written by ``ssp simulate`` (:func:`ssp.sim.bop.open_bop`), or a ROS bag /
MCAP file (:class:`ssp.pipeline.bag.BagSource`), each a :class:`ssp.pipeline.sources.FrameSource`
(:mod:`ssp.pipeline.inputs`). All are read frame by frame: a frame's files are read when its
turn comes, so one unreadable frame fails alone and a long input is never in memory at once.
Each frame goes through the perception front end (:class:`ssp.perception.Perception`; given
hypotheses replace its estimator) and the scene parser. Outputs in ``out``:

* ``frames/<name>.json``: the parser's estimate (:func:`ssp.io.results.frame_record`) plus the
  front end's timings and hypothesis count, or the error of a failed frame;
* ``<method>_<dataset>-test.csv``: BOP19 results (poses in the camera frame, t in mm; in the
  world frame when the camera pose is unknown, as the frame's ``poses_in`` says), under the
  input's BOP ``scene_id`` (``scene_id``: a BOP scene's own, else 1) and the classes' BOP
  ``obj_id`` (``obj_ids``: :func:`ssp.pipeline.inputs.run_object_ids`);
* ``obj_ids.json``: class name -> BOP ``obj_id`` (``{"obj_ids": {"1": "cube", ...}}``);
* ``summary.json``: frames done and failed (with the reason), warnings, objects, times;
* ``run.json``: what the run reads (input files, models, config, options, the scene id and
  object ids), to check a resume;
* ``state.json``: the parser's state and the front end's segment memory
  (:mod:`ssp.perception.reuse`) after the last finished frame, and where to go on;
* ``tum/<object id>.txt``: each object's trajectory in the TUM format (:mod:`ssp.io.tum`),
  written when the run ends (finished or stopped).

**Containment.** Any exception in one frame (reading, perception, parser, formatting its
results) is logged (with its traceback when it is not an :class:`SSPError`: a bug) and the
frame is reported failed in its JSON and in the summary, which counts the unexpected errors
apart; the run goes on with the parser state of the last good frame. ``KeyboardInterrupt``
and ``SystemExit`` stop the run (the outputs stay consistent).

**Crash safety.** Per frame, in this order: its JSON (atomic replace), its CSV rows (fsynced),
then ``state.json`` (atomic; the commit: the frame counts as finished from here), then
``summary.json``. ``run.json`` is written first, then ``frames/``, ``obj_ids.json`` and
``summary.json``, which exist from the start. A run holds a lock on ``out`` while it writes
it (:func:`ssp.pipeline.manifest.lock_out_dir`); nothing is written, truncated or deleted
through a symbolic link in ``out``; a write that fails (a full disk) raises
:class:`ssp.errors.OutputError` naming the file, the committed frames kept. A run stopped at
any point (SIGKILL included) is continued by ``run(..., resume=True)`` (``ssp run --resume
OUT``): the CSV is cut back to the size recorded at the last commit, frame JSONs of frames not
committed are deleted, the parser and the front end's segment memory resume from their saved
state, and the results are those of
an uninterrupted run (only the wall times differ: :data:`ssp.pipeline.summary.TIMING_KEYS`).
The output folder's files and checks: :mod:`ssp.pipeline.manifest`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import ArgumentError, SSPError
from ssp.geometry import invert
from ssp.io._files import atomic_write_text, fsync_dir, read_json, to_jsonable
from ssp.io.results import BopCsvWriter, ObjectIds, bop_csv_name, frame_record, write_json
from ssp.io.tum import TUM_DIR, write_tum
from ssp.parser import SceneParser
from ssp.pipeline.inputs import input_kind, open_source, run_object_ids, run_scene_id
from ssp.pipeline.manifest import (
    FORMAT_VERSION,
    FRAMES_DIR,
    OBJ_IDS_JSON,
    RUN_JSON,
    STATE_FORMAT,
    STATE_JSON,
    SUMMARY_JSON,
    lock_out_dir,
    prepare_fresh,
    prepare_resume,
    read_run,
    run_manifest,
)
from ssp.pipeline.sources import HYPOTHESES_MODES, FrameSource, InputFrame
from ssp.pipeline.summary import RunSummary
from ssp.pipeline.world import RESTARTED

__all__ = ["KEPT_MIN_SCORE", "REJECTED_SCORE_SCALE", "run"]

log = logging.getLogger(__name__)

#: A kept object's row is scored its fit, at least this (an occluded object kept because it
#: holds others up may explain none of its surface: it is still the scene's, above any
#: rejected one).
KEPT_MIN_SCORE = 1e-3
#: A rejected object's row (``rejected_rows``) is scored its fit times this: below every kept
#: object (:data:`KEPT_MIN_SCORE`), so where an object of the class was kept, the kept one is
#: what BOP's evaluation takes.
REJECTED_SCORE_SCALE = 5e-4


def run(
    input_path: str | Path,
    library: Mapping,
    out_dir: str | Path,
    config: SSPConfig | None = None,
    *,
    hypotheses: str = "auto",
    classes: Sequence[str] | None = None,
    method: str = "ssp",
    scene_id: int | None = None,
    obj_ids: str | Path | ObjectIds | Mapping[str, int] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    resume: bool = False,
    overwrite: bool = False,
    models: str | None = None,
    estimates=None,
    masks: str = "auto",
    period: float | None = None,
    bag: Mapping[str, Any] | None = None,
    record: str | Path | None = None,
    rejected_rows: bool = False,
) -> RunSummary:
    """Run perception and the scene parser over every frame of ``input_path``.

    Args:
        input_path: a folder of clouds, a BOP scene folder (module docstring), or a ROS bag
            (``.bag``, ``.mcap``, a ROS 2 bag folder: :mod:`ssp.io.rosbag`).
        library: the object library (every class the input may contain).
        out_dir: output folder: absent or empty, or (``resume``) a stopped run of the same
            input, or (``overwrite``) an earlier run whose files are cleared first.
        config: ssp's settings.
        hypotheses: one of :data:`ssp.pipeline.sources.HYPOTHESES_MODES`.
        classes: the estimator's candidate classes (default: the classes a BOP scene lists,
            else the whole library; fewer classes, faster estimation).
        method: BOP method name (no ``_``).
        scene_id: BOP ``scene_id`` of the CSV rows; None: a BOP scene's own, else
            :data:`ssp.pipeline.inputs.DEFAULT_SCENE_ID` (1). A BOP scene refuses another.
        obj_ids: the BOP ``obj_id`` of each class: an id table (a BOP ``models.json``,
            ``models_info.json`` or ``models/`` folder, an earlier run's ``obj_ids.json``:
            :meth:`ssp.io.results.ObjectIds.from_file`), an :class:`ObjectIds` or a
            ``{class: obj_id}`` mapping, giving an id to every class of ``library``; None:
            the input's own, else the BOP model names of the library (``obj_000005``: 5),
            else the sorted class names (:func:`ssp.pipeline.inputs.run_object_ids`).
            Recorded in ``obj_ids.json`` and ``run.json``: a resume with other ids is refused.
        progress: called as ``progress(done, total, message)`` after each frame.
        resume: continue the run in ``out_dir`` from its saved state (every frame it finished
            is kept; the rest are processed as an uninterrupted run would).
        overwrite: clear an earlier run's files in ``out_dir`` (nothing else is touched).
        models: where ``library`` came from (a model folder, None: built-in), recorded.
        estimates: a BOP scene's hypotheses from an estimator's output file (camera frame,
            :func:`ssp.io.estimators.read_estimates`), instead of its ``hypotheses.json``.
        masks: a BOP scene's segmentation, one of :data:`ssp.io.bop.MASK_MODES`.
        rejected_rows: the results CSV also gets a row for every object the parser rejected
            in a frame, at its best (corrected) pose, scored below every kept object
            (:data:`REJECTED_SCORE_SCALE` x its fit): ``ssp refine`` never drops an object the
            estimator reported (BOP's recall scores a missing object 0, a doubtful one may
            still score); the frame JSON's ``rejected`` entries say why each was doubted.
        period: seconds between images of a published BOP scene (no stamps); default
            :data:`ssp.io.bop.DEFAULT_PERIOD`.
        bag: for a ROS bag / MCAP input, :class:`ssp.io.rosbag.BagOptions` as a dict.
        record: write a 3D recording of the run to this rerun ``.rrd`` file
            (:class:`ssp.viz.record.Recorder`; needs the ``record`` extra): each finished
            frame's cloud, objects, hypotheses, support and terms, failed frames as error
            lines. A resumed run records the frames it processes itself, into the first free
            ``<stem>.<k>.rrd`` next to ``record`` when that exists (the earlier recording is
            kept; ``summary.files`` names the file).

    Raises:
        InputError: the input as a whole cannot be used (missing folder, no frames, bad
            ``scene.json``, classes of ``scene.json`` not in the library), or an ``obj_ids``
            table that cannot be read or misses a class of the library.
        ArgumentError: a bad option, an output folder that holds something else, or a
            resume whose input, models, config or options differ from the recorded ones.
        RecordingError: ``record`` given and rerun is not installed or the file cannot be
            written (:mod:`ssp.viz.record`).
        OutputLockedError: another run is writing ``out_dir``.
        OutputError: a symbolic link in ``out_dir`` where the run writes, or an output that
            cannot be written (a full disk); the message names the file.
    """
    started = time.perf_counter()
    cfg = config if config is not None else SSPConfig()
    if record is not None:
        from ssp.viz.record import check_recording

        check_recording(record)  # rerun installed: checked before any output is written
    src = Path(input_path)
    manifest, source, ids = _open_input(
        src, library, cfg, hypotheses=hypotheses, classes=classes, method=method,
        scene_id=scene_id, obj_ids=obj_ids, models=models, estimates=estimates, masks=masks,
        period=period, bag=bag,
    )  # fmt: skip
    scene_id = manifest["options"]["scene_id"]
    out = Path(out_dir)
    csv_path = out / manifest["csv"]
    if resume and not out.is_dir():
        read_run(out)  # nothing to resume: said before the folder is made for the lock
    with lock_out_dir(out):  # one writer at a time (OutputLockedError for a second one)
        summary, state, parser = _start(out, csv_path, src, manifest, source, ids, library, cfg,
                                        resume=resume, overwrite=overwrite)  # fmt: skip
        summary.started = started
        summary.time("start", time.perf_counter() - started)
        summary.masks = getattr(source, "mask_description", None)
        if record is not None and resume:
            record = _resumed_recording(Path(record))
        if record is not None:
            summary.files.append(str(record))
        _run_frames(out, csv_path, source, parser, summary, state, ids, library, cfg,
                    method=method, scene_id=scene_id, resume=resume, progress=progress,
                    record=record, rejected_rows=rejected_rows)  # fmt: skip
        summary.status = "finished"
        t_end = time.perf_counter()
        write_tum(out)
        summary.time("end", time.perf_counter() - t_end)
        write_json(out / SUMMARY_JSON, summary.to_dict())
    return summary


def _resumed_recording(record: Path) -> Path:
    """Where a resumed run records: ``record`` when it does not exist yet, else the first free
    ``<stem>.<k>.rrd`` next to it (k = 1, 2, ...): the earlier recording is kept."""
    if not record.exists() and not record.is_symlink():
        return record
    k = 1
    while True:
        other = record.with_name(f"{record.stem}.{k}{record.suffix}")
        if not other.exists() and not other.is_symlink():
            log.info("%s exists (the recording before the resume; kept): recording the resumed "
                     "frames in %s", record, other)  # fmt: skip
            return other
        k += 1


def _open_input(
    src: Path,
    library: Mapping,
    cfg: SSPConfig,
    *,
    hypotheses: str,
    classes: Sequence[str] | None,
    method: str,
    scene_id: int | None,
    obj_ids: str | Path | ObjectIds | Mapping[str, int] | None,
    models: str | None,
    estimates: Any,
    masks: str,
    period: float | None,
    bag: Mapping[str, Any] | None,
) -> tuple[dict[str, Any], FrameSource, ObjectIds]:
    """Check the options of :func:`run`, then open its input: ``(run.json, source, ids)``;
    the run's ``scene_id`` and ids are those of ``run.json``."""
    if hypotheses not in HYPOTHESES_MODES:
        raise ArgumentError(
            f"hypotheses must be one of {', '.join(HYPOTHESES_MODES)}, got {hypotheses!r}"
        )
    kind = input_kind(src)
    if kind != "bop" and (masks != "auto" or period is not None or estimates is not None):
        raise ArgumentError(
            f"{src}: masks, period and estimates are options of a BOP scene input, not of a "
            f"{'ROS bag' if kind == 'bag' else 'folder of clouds'}"
        )
    name = src.resolve().stem if kind == "bag" and src.is_file() else src.resolve().name
    csv_name = bop_csv_name(name, method)  # checks the method name
    source = open_source(src, kind, library, cfg, classes, hypotheses, estimates=estimates,
                         masks=masks, period=period, bag=bag)  # fmt: skip
    ids, ids_from = run_object_ids(src, kind, source, library, obj_ids)
    manifest = run_manifest(
        src, kind, library, cfg, csv_name=csv_name, hypotheses=hypotheses, classes=classes,
        method=method, scene_id=run_scene_id(source, scene_id), models=models,
        estimates=estimates, masks=masks, period=period, bag=bag,
    )  # fmt: skip
    given = obj_ids is not None and not isinstance(obj_ids, ObjectIds | Mapping)
    manifest.update(obj_ids=ids.to_json()["obj_ids"], obj_ids_from=ids_from,
                    obj_ids_file=str(Path(obj_ids).resolve()) if given else None)  # fmt: skip
    return manifest, source, ids


def _start(
    out: Path,
    csv_path: Path,
    src: Path,
    manifest: dict[str, Any],
    source: FrameSource,
    ids: ObjectIds,
    library: Mapping,
    cfg: SSPConfig,
    *,
    resume: bool,
    overwrite: bool,
) -> tuple[RunSummary, dict[str, Any], SceneParser]:
    """Make ``out`` ready for the run of ``src`` (a new one, or the resume of the one there)
    and write the files that exist from the start: ``(summary, saved state, parser)``; the
    saved state is empty when the run starts from its first frame."""
    if resume:
        state, finished = prepare_resume(out, manifest, csv_path, source)
    else:
        prepare_fresh(out, overwrite)
        state, finished = {}, []
        # run.json first: a folder without it holds nothing of the run but empty folders and
        # temporary files (an --overwrite replaces them)
        write_json(out / RUN_JSON, manifest)
    (out / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
    summary = RunSummary(str(src), source.kind, frames=source.total)
    summary.files = [str(csv_path), str(out / OBJ_IDS_JSON), str(out / FRAMES_DIR),
                     str(out / TUM_DIR)]  # fmt: skip
    for frame_json in finished:
        summary.add(frame_json)
    if "parser" in state:
        parser = SceneParser.from_state(library, state["parser"], cfg)
    else:
        parser = SceneParser(library, cfg)
    write_json(out / OBJ_IDS_JSON, ids.to_json())
    write_json(out / SUMMARY_JSON, summary.to_dict())
    fsync_dir(out)
    return summary, state, parser


def _run_frames(
    out: Path,
    csv_path: Path,
    source: FrameSource,
    parser: SceneParser,
    summary: RunSummary,
    state: dict[str, Any],
    ids: ObjectIds,
    library: Mapping,
    cfg: SSPConfig,
    *,
    method: str,
    scene_id: int,
    resume: bool,
    progress: Callable[[int, int, str], None] | None,
    record: str | Path | None,
    rejected_rows: bool = False,
) -> None:
    """Parse the frames from the saved state on, committing each (module docstring); on any
    exception, the summary says the run stopped, the trajectories are written, and the
    exception goes on."""
    start = int(state.get("next", 0))
    if start:
        log.info("%s: resuming at frame %d of %d", out, start, source.total)
        source.perception.memory.restore(state.get("segments", []))  # none in older states
    run_state = {
        "format": STATE_FORMAT,
        "version": FORMAT_VERSION,
        "total": source.total,
        "resumes": int(state.get("resumes", -1)) + 1,
    }
    from ssp.viz.record import RunRecording  # rerun itself only when recording

    with (
        BopCsvWriter(csv_path, method, append=resume, nofollow=True) as csv,
        RunRecording(record, library) as rec,
    ):
        committed_parser = parser.state()

        def commit(n_next: int, parser_state: dict[str, Any]) -> None:
            """The frames before ``n_next`` are finished once this atomic write is done."""
            doc = {**run_state, "next": n_next, "csv_bytes": csv.sync(), "parser": parser_state,
                   "segments": source.perception.memory.state()}  # fmt: skip
            write_json(out / STATE_JSON, doc, indent=None)

        def committed(name: str) -> dict[str, Any] | None:
            """A committed frame's JSON (a resumed source's history)."""
            p = out / FRAMES_DIR / f"{name}.json"
            return read_json(p) if p.is_file() and not p.is_symlink() else None

        try:
            if not state:
                commit(0, committed_parser)
            for n, frame in enumerate(source.frames(start, committed), start=start):
                kept: dict[str, Any] = {}
                frame_json, lines = _run_frame(
                    frame, parser, csv, ids, scene_id, kept, rejected_rows=rejected_rows
                )
                failed = frame_json["status"] == "failed"
                if failed and parser.state() != committed_parser:
                    # it failed after the parser took it: go on from the last good frame
                    parser = SceneParser.from_state(library, committed_parser, cfg)
                t_write = time.perf_counter()
                write_json(out / FRAMES_DIR / f"{frame.name}.json", frame_json)
                csv.write_rows(lines)
                parser_state = parser.state()
                commit(n + 1, parser_state)
                committed_parser = parser_state
                done = summary.add(frame_json, write_s=time.perf_counter() - t_write)
                summary.time_frame(frame_json)
                summary.time("writing", time.perf_counter() - t_write)
                t_write = time.perf_counter()
                atomic_write_text(out / SUMMARY_JSON, summary.to_json())
                rec.add(n, frame.name, frame_json, **kept)
                summary.time("writing", time.perf_counter() - t_write)
                if progress is not None:
                    msg = done.get("error") or f"{done['objects']} objects"
                    progress(n + 1, source.total, f"{frame.name}: {msg}")
        except BaseException as exc:
            # the summary holds the committed frames only; --resume continues from there
            summary.status = "stopped" if isinstance(exc, Exception) else "interrupted"
            try:
                write_tum(out)  # the committed frames' trajectories
                write_json(out / SUMMARY_JSON, summary.to_dict())
            except Exception as err:  # the original error matters more: one line for this one
                log.warning("the stopped run's summary and trajectories: %s", err)
            raise


def _run_frame(
    source: InputFrame,
    parser: SceneParser,
    csv: BopCsvWriter,
    ids: ObjectIds,
    scene_id: int,
    kept: dict[str, Any] | None = None,
    *,
    rejected_rows: bool = False,
) -> tuple[dict[str, Any], list[str]]:
    """Perceive and parse one frame: ``(frame JSON, CSV lines)``. Nothing is written here;
    a failure anywhere gives a frame JSON with ``status: failed`` and no lines. ``kept``
    receives the ``perceived`` result and the parser's ``estimate`` of a frame that succeeds;
    ``rejected_rows``: as for :func:`run`."""
    t0 = time.perf_counter()
    warnings: list[str] = []
    try:
        perceived, warnings = source.perceive()
        if (perceived.camera_fix or {}).get("how") == RESTARTED:
            parser.reset(keep_ids=True)  # its objects are in the world frame the camera lost
        estimate = parser.update(perceived.frame)
        seconds = time.perf_counter() - t0  # the CSV's time: from reading to the estimate
        t_results = time.perf_counter()
        if kept is not None:
            kept.update(perceived=perceived, estimate=estimate)
        frame = perceived.frame
        T_cam_world = np.eye(4) if frame.T_world_cam is None else invert(frame.T_world_cam)
        lines = [
            csv.format_row(
                scene_id,
                source.index,
                ids[obj.class_name],
                max(float(obj.fit), KEPT_MIN_SCORE),
                T_cam_world @ obj.T_world_obj,
                seconds,
            )
            for obj in estimate.objects
        ]
        if rejected_rows:
            lines += [
                csv.format_row(
                    scene_id,
                    source.index,
                    ids[r.class_name],
                    REJECTED_SCORE_SCALE * float(r.evidence.get("fit", 0.0)),
                    T_cam_world @ r.T_world_obj,
                    seconds,
                )
                for r in estimate.rejected
            ]
        extra = {
            "status": "done",
            "perception": {
                "hypotheses": len(frame.hypotheses),
                "segments": len(perceived.segmentation.segment_ids),
                "reused": sum(r.reused for r in perceived.segments.values()),
                "timings": perceived.timings,
            },
            "T_world_cam": None if frame.T_world_cam is None else frame.T_world_cam.tolist(),
            "camera": perceived.camera_fix,
        }
        frame_json = frame_record(estimate, name=source.name, index=source.index, extra=extra)
        # one list of doubts: the input's and the front end's, then the parser's
        frame_json["warnings"] = [*warnings, *frame_json["warnings"]]
        # a segment the parser got no hypothesis for: say what the front end made of it
        for label, verdict in perceived.verdicts.items():
            key = str(label)
            if frame_json["segments"].get(key, "").startswith("no object"):
                frame_json["segments"][key] = f"no object: {verdict}"
        frame_json = to_jsonable(frame_json)
        frame_json.update(_frame_timings(t0, t_results, perceived.timings, estimate.timings))
        return frame_json, lines
    except Exception as exc:
        return _failure(source, exc, warnings, time.perf_counter() - t0), []


def _frame_timings(
    t0: float, t_results: float, perception: Mapping[str, float], parser: Mapping[str, float]
) -> dict[str, Any]:
    """A frame's ``seconds`` (wall, from reading its files to its results record) and
    ``frame_timings``: that time's parts, the front end's (reading included), the parser's,
    the results record's, and ``other`` (between them); they add up to ``seconds``."""
    now = time.perf_counter()
    total = now - t0
    parts = {
        "perception": float(perception.get("total", 0.0)),
        "parser": float(parser.get("total", 0.0)),
        "results": now - t_results,
    }
    parts["other"] = total - sum(parts.values())
    return {"seconds": total, "frame_timings": {**parts, "total": total}}


def _failure(
    source: InputFrame, exc: Exception, warnings: list[str], seconds: float
) -> dict[str, Any]:
    """The frame JSON of a frame that failed with ``exc`` (logged here)."""
    unexpected = not isinstance(exc, SSPError)
    message = source.where(str(exc) or repr(exc))
    if unexpected:
        log.error("frame %s failed with an unexpected %s", source.name, type(exc).__name__,
                  exc_info=exc)  # fmt: skip
    else:
        log.warning("frame %s skipped: %s", source.name, message)
    return {
        "name": source.name,
        "index": source.index,
        "status": "failed",
        "error": message,
        "error_type": type(exc).__name__,
        "unexpected": unexpected,
        "warnings": warnings,
        "seconds": seconds,
    }
