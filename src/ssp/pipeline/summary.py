"""``summary.json`` of a run: :class:`RunSummary`, what :func:`ssp.pipeline.run.run` did."""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ssp.io._files import to_jsonable

__all__ = ["RUN_PARTS", "TIMING_KEYS", "RunSummary", "without_timings"]

#: Keys holding wall times, in frame JSONs (also under ``perception``) and summary records:
#: the only values that differ between two runs of one input (or a run and its resume).
TIMING_KEYS = (
    "seconds",
    "timings",
    "frame_timings",
    "perception_s",
    "parser_s",
    "write_s",
    "sec_per_frame",
)

#: The parts of a run's wall time (``summary.json`` ``timings.parts``): opening the input and
#: the output folder, each frame's front end, parser and results record (a failed frame's
#: time: ``failed``), writing each frame's files (frame JSON, CSV rows, state, summary,
#: recording), the trajectories at the end, and ``other`` (what none of them holds).
RUN_PARTS = ("start", "perception", "parser", "results", "failed", "writing", "end")


def without_timings(obj: Any, drop: tuple[str, ...] = ()) -> Any:
    """``obj`` (JSON-like: dicts, lists, values) without its wall times (:data:`TIMING_KEYS`)
    and the keys in ``drop``, at every level: what two runs of one input, or a run and its
    resume, must agree on."""
    if isinstance(obj, dict):
        return {k: without_timings(v, drop) for k, v in obj.items() if k not in TIMING_KEYS + drop}
    if isinstance(obj, list):
        return [without_timings(v, drop) for v in obj]
    return obj


@dataclass
class RunSummary:
    """What :func:`ssp.pipeline.run.run` did (also written to ``summary.json``).

    ``done`` and ``failed`` hold one record per frame (``failed``: ``frame``, ``index``,
    ``error``, ``error_type``, ``unexpected``); ``unexpected_errors`` counts the failures that
    are not :class:`SSPError` (bugs); ``warnings`` holds ``{frame, warning}``; ``status`` is
    ``running``, ``finished``, ``interrupted`` (KeyboardInterrupt, SystemExit) or ``stopped``
    (an error outside any frame, such as a full disk).
    """

    input: str
    kind: str
    frames: int = 0
    done: list[dict[str, Any]] = field(default_factory=list)
    failed: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[dict[str, str]] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    status: str = "running"
    #: which masks the frames got, in words (None: the input says nothing of masks)
    masks: str | None = None
    #: ``time.perf_counter()`` when the run started (its wall time is counted from here)
    started: float = field(default_factory=time.perf_counter)
    #: wall seconds per part of the run (:data:`RUN_PARTS`), of this process's frames
    parts: dict[str, float] = field(default_factory=dict)
    #: exclusive wall seconds per stage, summed over this process's frames: ``perception``
    #: (:attr:`ssp.perception.PerceptionResult.timings`) and ``parser``
    #: (:attr:`ssp.parser.SceneEstimate.timings`)
    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    _done_text: list[str] = field(default_factory=list, init=False, repr=False)  # JSON per record

    @property
    def unexpected_errors(self) -> int:
        return sum(bool(f.get("unexpected")) for f in self.failed)

    def add(self, frame_json: Mapping[str, Any], write_s: float | None = None) -> dict[str, Any]:
        """Add a finished frame from its ``frames/<name>.json`` content (so that a resumed
        run rebuilds the summary of the frames done before it stopped); returns its record.
        ``write_s``: the seconds its files took (frame JSON, CSV rows, state), when known."""
        name = frame_json["name"]
        self.warnings.extend({"frame": name, "warning": w} for w in frame_json.get("warnings", []))
        if frame_json.get("status") == "failed":
            record = {
                "frame": name,
                "index": frame_json["index"],
                "error": frame_json["error"],
                "error_type": frame_json["error_type"],
                "unexpected": frame_json["unexpected"],
            }
            self.failed.append(record)
            return record
        T_wc = frame_json.get("T_world_cam")
        record = {
            "frame": name,
            "index": frame_json["index"],
            "objects": len(frame_json["objects"]),
            "hypotheses": frame_json["perception"]["hypotheses"],
            "poses_in": "world" if T_wc is None else "camera",
            "perception_s": frame_json["perception"]["timings"].get("total", 0.0),
            "parser_s": frame_json["timings"].get("total", 0.0),
            "seconds": frame_json["seconds"],
        }
        if write_s is not None:
            record["write_s"] = float(write_s)
        self.done.append(record)
        return record

    def time(self, part: str, seconds: float) -> None:
        """Add ``seconds`` of wall time to ``part`` (one of :data:`RUN_PARTS`)."""
        if part not in RUN_PARTS:
            raise ValueError(f"part must be one of {RUN_PARTS}, got {part!r}")
        self.parts[part] = self.parts.get(part, 0.0) + float(seconds)

    def time_frame(self, frame_json: Mapping[str, Any]) -> None:
        """Add the wall times of a frame this process ran (its ``frame_timings`` and stages;
        a failed frame's ``seconds`` as ``failed``)."""
        if frame_json.get("status") == "failed":
            self.time("failed", frame_json.get("seconds", 0.0))
            return
        ft = frame_json["frame_timings"]
        for part in ("perception", "parser", "results"):
            self.time(part, ft[part])
        for group, timings in (
            ("perception", frame_json["perception"]["timings"]),
            ("parser", frame_json["timings"]),
        ):
            sums = self.stages.setdefault(group, {})
            for stage, sec in timings.items():
                if stage != "total":
                    sums[stage] = sums.get(stage, 0.0) + float(sec)

    def timings(self) -> dict[str, Any]:
        """The run's wall time so far (``wall``, s) and its ``parts`` (:data:`RUN_PARTS` and
        ``other``, what none holds: they add up to ``wall``), with the stage sums
        (:attr:`stages`)."""
        wall = time.perf_counter() - self.started
        parts = {p: self.parts[p] for p in RUN_PARTS if p in self.parts}
        parts["other"] = wall - sum(parts.values())
        return {"wall": wall, "parts": parts, "stages": self.stages}

    def to_json(self) -> str:
        """:meth:`to_dict` as compact JSON; the per-frame records are serialised once each, so
        writing the summary after every frame costs a string join, not a re-encoding."""
        self._done_text += [
            json.dumps(r, allow_nan=False) for r in self.done[len(self._done_text) :]
        ]
        head = {k: v for k, v in self.to_dict().items() if k != "per_frame"}
        text = json.dumps(to_jsonable(head), allow_nan=False)
        return f'{text[:-1]}, "per_frame": [{", ".join(self._done_text)}]}}\n'

    def to_dict(self) -> dict[str, Any]:
        secs = [d["seconds"] for d in self.done]
        return {
            "status": self.status,
            "input": self.input,
            "kind": self.kind,
            "frames": self.frames,
            "done": len(self.done),
            "failed": self.failed,
            "unexpected_errors": self.unexpected_errors,
            "warnings": self.warnings,
            "sec_per_frame": float(np.mean(secs)) if secs else None,
            "per_frame": self.done,
            "files": self.files,
            "masks": self.masks,
            "timings": self.timings(),
        }
