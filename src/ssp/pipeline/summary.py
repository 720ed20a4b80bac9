"""``summary.json`` of a run: :class:`RunSummary`, what :func:`ssp.pipeline.run.run` did."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ssp.io._files import to_jsonable

__all__ = ["TIMING_KEYS", "RunSummary", "without_timings"]

#: Keys holding wall times, in frame JSONs (also under ``perception``) and summary records:
#: the only values that differ between two runs of one input (or a run and its resume).
TIMING_KEYS = ("seconds", "timings", "perception_s", "parser_s", "sec_per_frame")


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
    _done_text: list[str] = field(default_factory=list, init=False, repr=False)  # JSON per record

    @property
    def unexpected_errors(self) -> int:
        return sum(bool(f.get("unexpected")) for f in self.failed)

    def add(self, frame_json: Mapping[str, Any]) -> dict[str, Any]:
        """Add a finished frame from its ``frames/<name>.json`` content (so that a resumed
        run rebuilds the summary of the frames done before it stopped); returns its record."""
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
        self.done.append(record)
        return record

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
        }
