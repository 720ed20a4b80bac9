"""``ssp run``: the whole pipeline over recorded frames, with files in and files out.

Inputs (``docs/formats.md``): a folder of PLY/PCD clouds (:func:`ssp.io.folder.open_folder`)
or a BOP scene folder written by ``ssp simulate`` (:func:`ssp.sim.bop.read_bop`). Each frame
goes through the perception front end (:class:`ssp.perception.Perception`; given hypotheses
replace its estimator) and the scene parser. Outputs in ``out``:

* ``frames/<name>.json``: the parser's estimate (:func:`ssp.io.results.frame_record`) plus the
  front end's timings and hypothesis count;
* ``<method>_<dataset>-test.csv``: BOP19 results (poses in the camera frame, t in mm; in the
  world frame when the camera pose is unknown, as the frame's ``poses_in`` says);
* ``obj_ids.json``: class name -> BOP ``obj_id``;
* ``summary.json``: frames done and failed (with the reason), objects, times.

A frame that cannot be read or perceived, or that the parser rejects, is recorded in the
summary and skipped; the parser's state is untouched by it (:meth:`SceneParser.update`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import InputError, SSPError
from ssp.geometry import invert
from ssp.io.folder import is_bop_scene, open_folder
from ssp.io.results import BopCsvWriter, ObjectIds, bop_csv_name, frame_record, write_json
from ssp.parser import SceneParser
from ssp.perception.pipeline import Perception, PerceptionResult

__all__ = ["HYPOTHESES_MODES", "RunSummary", "run"]

log = logging.getLogger(__name__)

#: ``auto``: the input's hypotheses when it has them, else the built-in estimator;
#: ``given``: only the input's (a frame without is an error); ``estimated``: always estimate.
HYPOTHESES_MODES = ("auto", "given", "estimated")


@dataclass
class RunSummary:
    """What :func:`run` did (also written to ``summary.json``)."""

    input: str
    kind: str
    frames: int = 0
    done: list[dict[str, Any]] = field(default_factory=list)
    failed: list[dict[str, Any]] = field(default_factory=list)
    files: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        secs = [d["seconds"] for d in self.done]
        return {
            "input": self.input,
            "kind": self.kind,
            "frames": self.frames,
            "done": len(self.done),
            "failed": self.failed,
            "sec_per_frame": float(np.mean(secs)) if secs else None,
            "per_frame": self.done,
            "files": self.files,
        }


@dataclass
class _Source:
    """One input frame: its name, 0-based index, and a function that reads and perceives it."""

    name: str
    index: int
    perceive: Callable[[], PerceptionResult]


def _folder_sources(path: Path, perception: Perception, mode: str) -> list[_Source]:
    folder = open_folder(path)
    spec = folder.spec

    def make(ff) -> Callable[[], PerceptionResult]:
        def perceive() -> PerceptionResult:
            raw = folder.load(ff)
            hyps = None if mode == "estimated" else raw.hypotheses
            if mode == "given" and hyps is None:
                raise InputError(f"{ff.name}: no hypotheses file and --hypotheses given")
            T_wc = spec.T_world_cam
            if T_wc is None and raw.frame == "world":
                T_wc = raw.viewpoint
            return perception.from_points(
                raw.points,
                frame=raw.frame,
                stamp=raw.stamp,
                T_world_cam=T_wc,
                labels=raw.labels,
                label_kind=raw.label_kind,
                label_classes=raw.label_classes,
                hypotheses=hyps,
                hypotheses_frame=raw.hypotheses_frame or "world",
            )

        return perceive

    return [_Source(ff.name, ff.index, make(ff)) for ff in folder.frames]


def _bop_sources(path: Path, library, cfg, classes, mode: str) -> list[_Source]:
    from ssp.sim.bop import read_bop

    seq = read_bop(path, library)
    perception = Perception(library, cfg, classes or seq.models or None)
    has_hyps = (path / "hypotheses.json").is_file()
    if mode == "given" and not has_hyps:
        raise InputError(f"{path}: no hypotheses.json and --hypotheses given")

    def make(i: int) -> Callable[[], PerceptionResult]:
        sf = seq.frames[i]

        def perceive() -> PerceptionResult:
            mask = np.asarray(sf.instance).astype(np.int64)
            mask[mask < -1] = -1
            use_given = has_hyps and mode != "estimated"
            return perception.from_depth(
                sf.depth,
                seq.camera,
                stamp=sf.stamp,
                T_world_cam=seq.T_world_cam,
                mask=mask,
                hypotheses=list(sf.hypotheses) if use_given else None,
            )

        return perceive

    return [_Source(f"{sf.index:06d}", sf.index, make(i)) for i, sf in enumerate(seq.frames)]


def run(
    input_path: str | Path,
    library: Mapping,
    out_dir: str | Path,
    config: SSPConfig | None = None,
    *,
    hypotheses: str = "auto",
    classes: Sequence[str] | None = None,
    method: str = "ssp",
    scene_id: int = 1,
    progress: Callable[[int, int, str], None] | None = None,
) -> RunSummary:
    """Run perception and the scene parser over every frame of ``input_path``.

    Args:
        input_path: a folder of clouds or a BOP scene folder (module docstring).
        library: the object library (every class the input may contain).
        out_dir: output folder (created).
        config: ssp's settings.
        hypotheses: one of :data:`HYPOTHESES_MODES`.
        classes: the estimator's candidate classes (default: the classes a BOP scene lists,
            else the whole library; fewer classes, faster estimation).
        method: BOP method name (no ``_``).
        scene_id: BOP ``scene_id`` of the CSV rows.
        progress: called as ``progress(done, total, message)`` after each frame.

    Raises:
        InputError: the input as a whole cannot be used (no frames, bad ``scene.json``).
    """
    cfg = config if config is not None else SSPConfig()
    if hypotheses not in HYPOTHESES_MODES:
        raise ValueError(f"hypotheses must be one of {HYPOTHESES_MODES}, got {hypotheses!r}")
    src = Path(input_path)
    if not src.is_dir():
        raise InputError(f"{src}: not a folder")
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    if is_bop_scene(src):
        sources, kind = _bop_sources(src, library, cfg, classes, hypotheses), "bop"
    else:
        perception = Perception(library, cfg, classes)
        sources, kind = _folder_sources(src, perception, hypotheses), "folder"
    summary = RunSummary(str(src), kind, frames=len(sources))
    ids = ObjectIds.for_input(src, list(library))
    csv_path = out / bop_csv_name(src.resolve().name, method)
    parser = SceneParser(library, cfg)
    with BopCsvWriter(csv_path, method) as csv:
        for n, source in enumerate(sources):
            record = _run_frame(source, parser, csv, ids, scene_id, out)
            (summary.done if "error" not in record else summary.failed).append(record)
            if progress is not None:
                msg = record.get("error") or f"{record['objects']} objects"
                progress(n + 1, len(sources), f"{source.name}: {msg}")
    write_json(out / "obj_ids.json", ids.to_json())
    summary.files = [str(csv_path), str(out / "obj_ids.json"), str(out / "frames")]
    write_json(out / "summary.json", summary.to_dict())
    return summary


def _run_frame(source: _Source, parser: SceneParser, csv, ids, scene_id: int, out: Path) -> dict:
    """Perceive and parse one frame; a record for the summary (with ``error`` on failure)."""
    t0 = time.perf_counter()
    try:
        perceived = source.perceive()
        estimate = parser.update(perceived.frame)
    except (SSPError, ValueError) as exc:  # bad data; anything else is a bug and propagates
        log.warning("frame %s skipped: %s", source.name, exc)
        return {"frame": source.name, "index": source.index, "error": str(exc)}
    seconds = time.perf_counter() - t0
    extra = {
        "perception": {
            "hypotheses": len(perceived.frame.hypotheses),
            "segments": len(perceived.segmentation.segment_ids),
            "timings": perceived.timings,
        },
        "T_world_cam": None
        if perceived.frame.T_world_cam is None
        else perceived.frame.T_world_cam.tolist(),
        "seconds": seconds,
    }
    write_json(
        out / "frames" / f"{source.name}.json",
        frame_record(estimate, name=source.name, index=source.index, extra=extra),
    )
    T_cam_world = (
        np.eye(4) if perceived.frame.T_world_cam is None else invert(perceived.frame.T_world_cam)
    )
    for obj in estimate.objects:
        csv.add(
            scene_id,
            source.index,
            ids[obj.class_name],
            float(obj.fit),
            T_cam_world @ obj.T_world_obj,
            seconds,
        )
    return {
        "frame": source.name,
        "index": source.index,
        "objects": len(estimate.objects),
        "hypotheses": len(perceived.frame.hypotheses),
        "poses_in": "world" if perceived.frame.T_world_cam is None else "camera",
        "perception_s": perceived.timings.get("total", 0.0),
        "parser_s": estimate.timings.get("total", 0.0),
        "seconds": seconds,
    }
