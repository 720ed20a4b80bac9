"""``ssp run``: the whole pipeline over recorded frames, with files in and files out.

Inputs (``docs/formats.md``): a folder of PLY/PCD clouds (:func:`ssp.io.folder.open_folder`),
a BOP scene folder written by ``ssp simulate`` (:func:`ssp.sim.bop.open_bop`), or a ROS bag /
MCAP file (:func:`ssp.inputs_bag.open_bag_input`). All are read frame by frame: a frame's files
are read when its turn comes, so one unreadable frame fails alone and a long input is never in
memory at once. Each frame goes through the
perception front end (:class:`ssp.perception.Perception`; given hypotheses replace its
estimator) and the scene parser. Outputs in ``out``:

* ``frames/<name>.json``: the parser's estimate (:func:`ssp.io.results.frame_record`) plus the
  front end's timings and hypothesis count, or the error of a failed frame;
* ``<method>_<dataset>-test.csv``: BOP19 results (poses in the camera frame, t in mm; in the
  world frame when the camera pose is unknown, as the frame's ``poses_in`` says);
* ``obj_ids.json``: class name -> BOP ``obj_id``;
* ``summary.json``: frames done and failed (with the reason), warnings, objects, times;
* ``run.json``: what the run reads (input files, models, config, options), to check a resume;
* ``state.json``: the parser's state after the last finished frame, and where to go on;
* ``tum/<object id>.txt``: each object's trajectory in the TUM format (:mod:`ssp.io.tum`),
  written when the run ends (finished or stopped).

**Containment.** Any exception in one frame (reading, perception, parser, formatting its
results) is logged (with its traceback when it is not an :class:`SSPError`: a bug) and the
frame is reported failed in its JSON and in the summary, which counts the unexpected errors
apart; the run goes on with the parser state of the last good frame. ``KeyboardInterrupt``
and ``SystemExit`` stop the run (the outputs stay consistent).

**Crash safety.** Per frame, in this order: its JSON (atomic replace), its CSV rows (fsynced),
then ``state.json`` (atomic; the commit: the frame counts as finished from here), then
``summary.json``. ``summary.json`` and ``obj_ids.json`` exist from the start. A run stopped at
any point (SIGKILL included) is continued by ``run(..., resume=True)`` (``ssp run --resume
OUT``): the CSV is cut back to the size recorded at the last commit, frame JSONs of frames not
committed are deleted, the parser resumes from its saved state, and the results are those of
an uninterrupted run (only the wall times differ: :data:`TIMING_KEYS`).
"""

from __future__ import annotations

import difflib
import hashlib
import itertools
import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ssp import __version__
from ssp.config import SSPConfig
from ssp.errors import ArgumentError, InputError, SSPError
from ssp.geometry import invert
from ssp.io._files import atomic_write_text, file_problem, fsync_dir, to_jsonable
from ssp.io.folder import SCENE_JSON, check_folder, is_bop_scene, open_folder
from ssp.io.results import BopCsvWriter, ObjectIds, bop_csv_name, frame_record, write_json
from ssp.io.tum import TUM_DIR, write_tum
from ssp.parser import SceneParser
from ssp.perception.pipeline import Perception, PerceptionResult

__all__ = [
    "HYPOTHESES_MODES",
    "RUN_JSON",
    "STATE_JSON",
    "TIMING_KEYS",
    "RunSummary",
    "check_out_dir",
    "read_run",
    "run",
]

log = logging.getLogger(__name__)

#: ``auto``: the input's hypotheses when it has them, else the built-in estimator;
#: ``given``: only the input's (a frame without is an error); ``estimated``: always estimate.
HYPOTHESES_MODES = ("auto", "given", "estimated")
FRAMES_DIR = "frames"
SUMMARY_JSON = "summary.json"
OBJ_IDS_JSON = "obj_ids.json"
RUN_JSON = "run.json"
STATE_JSON = "state.json"
RUN_FORMAT, STATE_FORMAT, FORMAT_VERSION = "ssp-run", "ssp-run-state", 1
#: Keys holding wall times, in frame JSONs (also under ``perception``) and summary records:
#: the only values that differ between two runs of one input (or a run and its resume).
TIMING_KEYS = ("seconds", "timings", "perception_s", "parser_s", "sec_per_frame")


# ------------------------------------------------------------------------------ summary
@dataclass
class RunSummary:
    """What :func:`run` did (also written to ``summary.json``).

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
        }


# ------------------------------------------------------------------------------ inputs
@dataclass
class _Source:
    """One input frame: its name, index (BOP ``im_id`` or folder position), the files it is
    read from, and a function that reads and perceives it (result and warnings)."""

    name: str
    index: int
    files: tuple[str, ...]
    perceive: Callable[[], tuple[PerceptionResult, list[str]]]

    def where(self, message: str) -> str:
        """The file to name in an error ``message`` that names none: the hypotheses file for
        a problem with a hypothesis (when the frame has one), else the frame's main file."""
        if any(f in message for f in self.files):
            return message
        about_hyp = message.startswith(("hypothesis", "instance id", "invalid pose"))
        f = self.files[1] if about_hyp and len(self.files) > 1 else self.files[0]
        return f"{f}: {message}"


@dataclass
class _Input:
    """An opened input: its kind, frame count, and the frames from position ``start`` on."""

    kind: str
    total: int
    sources: Callable[[int], Iterator[_Source]]


def _unknown_class(name: str, library: Mapping) -> str:
    close = difflib.get_close_matches(name, list(library), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"class {name!r} is not in the library{hint}; known: {', '.join(library) or 'none'}"


def _open_folder_input(path: Path, library: Mapping, perception: Perception, mode: str) -> _Input:
    folder = open_folder(path)
    spec = folder.spec
    scene = path / SCENE_JSON
    for what, mapping in (("classes", spec.classes), ("colors", spec.colors)):
        for key, cls in mapping.items():
            if cls not in library:
                label = f"#{key:06x}" if what == "colors" else str(key)
                raise InputError(f"{scene}: {what}[{label!r}]: {_unknown_class(cls, library)}")

    def make(ff) -> Callable[[], tuple[PerceptionResult, list[str]]]:
        def perceive() -> tuple[PerceptionResult, list[str]]:
            raw = folder.load(ff)
            hyps = None if mode == "estimated" else raw.hypotheses
            if mode == "given" and hyps is None:
                raise InputError(
                    f"{ff.cloud_path}: no hypotheses file {ff.name}.hypotheses.json and "
                    "--hypotheses given"
                )
            for i, h in enumerate(hyps or []):
                if h.class_name not in library:
                    raise InputError(
                        f"{ff.hypotheses_path}: hypothesis {i}: "
                        f"{_unknown_class(h.class_name, library)}"
                    )
            T_wc = spec.T_world_cam
            if T_wc is None and raw.frame == "world":
                T_wc = raw.viewpoint
            result = perception.from_points(
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
            return result, list(raw.warnings)

        return perceive

    def sources(start: int) -> Iterator[_Source]:
        for ff in folder.frames[start:]:
            files = (str(ff.cloud_path),) + (
                (str(ff.hypotheses_path),) if ff.hypotheses_path is not None else ()
            )
            yield _Source(ff.name, ff.index, files, make(ff))

    return _Input("folder", len(folder.frames), sources)


def _open_bop_input(
    path: Path,
    library: Mapping,
    cfg: SSPConfig,
    classes,
    mode: str,
    *,
    estimates=None,
    masks: str = "auto",
    period: float | None = None,
) -> _Input:
    """A BOP scene (``ssp simulate``'s or a published one, :mod:`ssp.io.bop`) as run input.

    Hypotheses come from ``estimates`` (an estimator's output, camera frame, e.g.
    :func:`ssp.io.estimators.read_estimates`; looked up by ``(scene_id, im_id)``), else the
    scene's ``hypotheses.json``, else the built-in estimator (``mode``). The world frame is the
    scene's ``cam_R_w2c`` when every image has one, else the table plane fitted to the depth
    (:class:`ssp.perception.table.TableTracker`: kept while the camera stays put).
    """
    from ssp.io.bop import DEFAULT_PERIOD, mask_source, open_bop
    from ssp.perception.depth import cloud_from_depth
    from ssp.perception.table import TableTracker

    use_masks = mask_source(masks, simulated=True)  # checks ``masks`` before reading
    scene = open_bop(path, library, period=DEFAULT_PERIOD if period is None else period)
    perception = Perception(library, cfg, classes or list(scene.models) or None)
    hyp_file = path / "hypotheses.json"
    given = estimates is not None or scene.has_hypotheses
    if mode == "given" and not given:
        raise InputError(f"{path}: no hypotheses.json and --hypotheses given")
    tracker = None if scene.has_world else TableTracker(cfg.perception.table_distance)
    use_masks = mask_source(masks, scene.simulated)

    def make(k: int) -> Callable[[], tuple[PerceptionResult, list[str]]]:
        def perceive() -> tuple[PerceptionResult, list[str]]:
            im = scene.im_ids[k]
            warnings: list[str] = []
            hyps, hyp_frame = None, "world"
            if mode != "estimated" and estimates is not None:
                hyps, hyp_frame = estimates.for_image(scene.scene_id, im), "camera"
            elif mode != "estimated" and scene.has_hypotheses:
                if scene.has_entry(k):
                    hyps = None  # read with the frame below
                elif mode == "given":
                    raise InputError(f"{hyp_file}: no entry for im_id {im} and --hypotheses given")
                else:
                    warnings.append(
                        f"{hyp_file}: no entry for im_id {im}: its hypotheses were estimated"
                    )
                    log.warning("%s", warnings[-1])
            sf = scene.load(k, masks=use_masks)
            if hyps is None and mode != "estimated" and estimates is None and scene.has_entry(k):
                hyps = list(sf.hypotheses)
            for i, h in enumerate(hyps or []):
                if h.class_name not in library:
                    raise InputError(f"hypothesis {i}: {_unknown_class(h.class_name, library)}")
            if masks == "gt" and sf.instance is not None and sf.instance_is_gt:
                warnings.append("segments from the ground-truth masks (--masks gt)")
            mask = None
            if use_masks and sf.instance is not None:
                mask = np.asarray(sf.instance).astype(np.int64)
                mask[mask < -1] = -1
            T_wc = sf.T_world_cam
            if T_wc is None:
                cloud = cloud_from_depth(sf.depth, sf.camera)
                T_wc, moved = tracker.update(cloud.points)
                if moved:
                    warnings.append(
                        "the table plane moved: the world frame was fitted again (a moving "
                        "camera needs cam_R_w2c/cam_t_w2c in scene_camera.json)"
                    )
            result = perception.from_depth(
                sf.depth,
                sf.camera,
                stamp=sf.stamp,
                T_world_cam=T_wc,
                mask=mask,
                hypotheses=hyps,
                hypotheses_frame=hyp_frame,
            )
            return result, warnings

        return perceive

    def sources(start: int) -> Iterator[_Source]:
        if tracker is not None and start > 0 and tracker.T_world_cam is None:
            # a resumed run: the world frame the frames before ``start`` kept
            for k in range(start):
                try:
                    f = scene.load(k, masks=None)
                    tracker.update(cloud_from_depth(f.depth, f.camera).points)
                except SSPError:
                    pass  # that frame failed in the run too, leaving the frame as it was
        for k in range(start, len(scene)):
            im = scene.im_ids[k]
            hyp = str(estimates.source) if estimates is not None else str(hyp_file)
            # the depth image first (named in an error that names no file), then the files
            # an error may name itself
            files = (str(path / "depth" / f"{im:06d}.png"), hyp,
                     str(path / "scene_camera.json"))  # fmt: skip
            yield _Source(f"{im:06d}", im, files, make(k))

    return _Input("bop", len(scene), sources)


def _input_files(path: Path, kind: str) -> dict[str, Any]:
    """``{relative name: [size, mtime_ns]}`` (or the problem of an entry that is not a regular
    file) of the files the run reads: the input folder's own files, and for a BOP scene those
    of ``depth/``, ``instance/`` and ``mask_visib/``. Never opens a file."""
    if kind == "bag":
        from ssp.inputs_bag import bag_input_files

        return bag_input_files(path)
    out: dict[str, Any] = {}
    folders = [path] + (
        [path / d for d in ("depth", "instance", "mask_visib")] if kind == "bop" else []
    )
    for folder in folders:
        if not folder.is_dir():
            continue
        with os.scandir(folder) as it:
            entries = sorted(it, key=lambda e: e.name)
        for e in entries:
            problem = file_problem(e.path)
            if e.name.startswith(".") or problem == "is a folder, not a file":
                continue
            rel = os.path.relpath(e.path, path)
            if problem is None:
                st = e.stat()
                out[rel] = [st.st_size, st.st_mtime_ns]
            else:
                out[rel] = problem
    return out


def _file_stamp(p: Path) -> Any:
    """``[size, mtime_ns]`` of a file, or its problem."""
    problem = file_problem(p)
    if problem is not None:
        return problem
    st = p.stat()
    return [st.st_size, st.st_mtime_ns]


def _bop_ids(scene: Path, library: Mapping) -> ObjectIds:
    """The BOP ``obj_id`` of each class: the scene's or its dataset's (``models.json``, or
    ``obj_XXXXXX`` model names); classes of the library without one get new ids."""
    from ssp.io.bop import open_bop

    classes = open_bop(scene).classes
    if not classes:
        return ObjectIds.for_input(scene, list(library))
    ids = {cls: oid for oid, cls in classes.items()}
    nxt = max(classes) + 1
    for c in sorted(set(library) - set(ids)):
        ids[c] = nxt
        nxt += 1
    return ObjectIds(ids)


def _library_digests(library: Mapping) -> dict[str, str]:
    """``{class: sha256}`` of what the parser uses of each model (geometry, parts, mass
    properties, friction, samples, symmetries): equal digests, equal results."""
    out = {}
    for name in sorted(library):
        m = library[name]
        h = hashlib.sha256(name.encode())
        arrays = [m.mesh.vertices, m.mesh.faces, m.center_of_mass, m.inertia]
        arrays += [m.surface_points, m.surface_normals, m.interior_points, m.symmetry.discrete]
        for part in m.convex_parts:
            arrays += [part.vertices, part.faces]
        for c in m.symmetry.continuous:
            arrays += [c.axis, c.offset]
        for a in arrays:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())
        h.update(repr((float(m.mass), float(m.friction), len(m.convex_parts))).encode())
        out[name] = h.hexdigest()
    return out


# ------------------------------------------------------------------------------ run folders
def _read_doc(p: Path, fmt: str, what: str) -> dict[str, Any]:
    """The JSON object of ``p`` with ``format == fmt`` and this module's version."""
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ArgumentError(f"{p}: cannot read: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise ArgumentError(f"{p}: not an {what} (format {fmt!r})")
    if doc.get("version") != FORMAT_VERSION:
        raise ArgumentError(
            f"{p}: {what} version {doc.get('version')!r}; this ssp reads {FORMAT_VERSION}"
        )
    return doc


def read_run(out_dir: str | os.PathLike) -> dict[str, Any]:
    """The ``run.json`` of an output folder (what the run reads and its options).

    Raises:
        ArgumentError: the folder holds no ssp run, or its run.json is unreadable.
    """
    p = Path(out_dir) / RUN_JSON
    if not p.is_file():
        raise ArgumentError(f"{out_dir}: no ssp run here (no {RUN_JSON}): nothing to resume")
    return _read_doc(p, RUN_FORMAT, "ssp run manifest")


def _read_state(out: Path) -> dict[str, Any] | None:
    p = out / STATE_JSON
    return _read_doc(p, STATE_FORMAT, "ssp run state") if p.exists() else None


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


#: Settings that do not change the results (a resume may use other values).
NO_EFFECT = frozenset({"search.processes", "perception.processes"})


def _differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """What differs between the recorded and the current manifest, one phrase each."""
    diffs = []
    for key, what in (("input", "input"), ("kind", "input kind"), ("ssp", "ssp version")):
        if old.get(key) != new.get(key):
            diffs.append(f"{what} {old.get(key)!r} -> {new.get(key)!r}")
    for k, v in new["options"].items():
        if old.get("options", {}).get(k) != v:
            diffs.append(f"option {k} {old.get('options', {}).get(k)!r} -> {v!r}")
    a, b = _flat(old.get("config", {})), _flat(new["config"])
    changed = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k) and k not in NO_EFFECT)
    if changed:
        shown = ", ".join(f"{k} {a.get(k)!r} -> {b.get(k)!r}" for k in changed[:4])
        diffs.append("config " + shown + (" ..." if len(changed) > 4 else ""))
    la, lb = old.get("library", {}), new["library"]
    models = sorted(k for k in la.keys() | lb.keys() if la.get(k) != lb.get(k))
    if models:
        diffs.append(f"models {', '.join(models[:6])} differ (--models {old.get('models')!r})")
    fa, fb = old.get("input_files", {}), new["input_files"]
    files = sorted(k for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k))
    if files:
        diffs.append(
            f"input files changed since the run started: {', '.join(files[:5])}"
            + (f" and {len(files) - 5} more" if len(files) > 5 else "")
        )
    return diffs


def _own_files(out: Path, manifest: Mapping[str, Any] | None) -> list[Path]:
    """The files an ssp run wrote in ``out`` (and temporary files of atomic writes)."""
    names = [RUN_JSON, STATE_JSON, SUMMARY_JSON, OBJ_IDS_JSON]
    if manifest and isinstance(manifest.get("csv"), str):
        names.append(Path(manifest["csv"]).name)
    files = [out / n for n in names if (out / n).exists()]
    files += [p for p in out.glob(".*.tmp")]
    frames = out / FRAMES_DIR
    if frames.is_dir():
        files += sorted(frames.glob("*.json")) + sorted(frames.glob(".*.tmp"))
    tum = out / TUM_DIR
    if tum.is_dir():
        files += sorted(tum.glob("*.txt")) + sorted(tum.glob(".*.tmp"))
    return files


def check_out_dir(out: str | os.PathLike, overwrite: bool = False) -> None:
    """ArgumentError unless ``out`` can take a new run (absent, empty, or with ``overwrite``
    an earlier ssp run); :func:`run` checks it too, a command checks it before slow work."""
    _prepare_fresh(Path(out), overwrite, clear=False)


def _prepare_fresh(out: Path, overwrite: bool, clear: bool = True) -> None:
    """Make sure ``out`` can take a new run: absent or empty, or an earlier ssp run that
    ``overwrite`` allows to clear (only its own files go; ``clear=False``: only check)."""
    if out.exists() and not out.is_dir():
        raise ArgumentError(f"{out}: the output folder is a file")
    if not out.exists() or not any(out.iterdir()):
        return
    if not (out / RUN_JSON).exists():
        raise ArgumentError(
            f"{out}: the output folder is not empty and holds no ssp run ({RUN_JSON}); "
            "choose a new or empty --out folder"
        )
    try:
        old = read_run(out)
    except ArgumentError:
        old = None
    if not overwrite:
        state = (_read_state(out) if old is not None else None) or {}
        n, total = state.get("next", 0), state.get("total")
        finished = total is not None and n >= total
        of = "" if old is None else f" of {old['input']} ({n} of {total} frames done)"
        again = "" if finished else f"continue it with `ssp run --resume {out}`, "
        raise ArgumentError(
            f"{out}: the output folder already holds {'a finished' if finished else 'an'} ssp "
            f"run{of}: {again}replace it with --overwrite, or choose a new --out folder"
        )
    if not clear:
        return
    for p in _own_files(out, old):
        p.unlink()
    for sub in (out / FRAMES_DIR, out / TUM_DIR):
        if sub.is_dir() and not any(sub.iterdir()):
            sub.rmdir()
    log.info("%s: cleared the earlier run's files", out)


def _prepare_resume(
    out: Path, manifest: dict[str, Any], csv_path: Path, inp: _Input
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Check that ``out`` holds a resumable run of the same input, models, config and options,
    cut its CSV back to the last committed frame and delete uncommitted frame JSONs; returns
    the saved state (empty if the run stopped before its first commit) and the frame JSONs of
    the committed frames, in order."""
    old = read_run(out)
    diffs = _differences(old, manifest)
    if diffs:
        raise ArgumentError(
            f"{out}: cannot resume: the run was started with other inputs: "
            + "; ".join(diffs)
            + ". Resume with the same input, --models, --config and options, or start a new "
            "run in a new --out folder"
        )
    state = _read_state(out)
    if state is None:  # stopped before its first commit: start over (run.json is kept)
        for p in _own_files(out, old):
            if p.name != RUN_JSON:
                p.unlink()
        return {}, []
    size = int(state.get("csv_bytes", 0))
    have = csv_path.stat().st_size if csv_path.exists() else 0
    if have < size:
        raise ArgumentError(
            f"{csv_path}: {have} bytes, but the run had written {size}: the output folder was "
            "modified; start a new run"
        )
    with open(csv_path, "r+b") as f:
        f.truncate(size)
    names = [src.name for src in itertools.islice(inp.sources(0), int(state["next"]))]
    for p in _own_files(out, old):
        stale = p.parent.name == FRAMES_DIR and p.suffix == ".json" and p.stem not in names
        if stale or p.name.endswith(".tmp"):
            log.info("%s: not committed before the run stopped; removed", p)
            p.unlink()
    records = []
    for name in names:
        p = out / FRAMES_DIR / f"{name}.json"
        try:
            records.append(json.loads(p.read_text(encoding="utf-8")))
        except (OSError, ValueError) as exc:
            raise ArgumentError(
                f"{p}: the result of a finished frame cannot be read ({exc}): the output "
                "folder was modified; start a new run"
            ) from exc
    return state, records


# ------------------------------------------------------------------------------ run
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
    resume: bool = False,
    overwrite: bool = False,
    models: str | None = None,
    estimates=None,
    masks: str = "auto",
    period: float | None = None,
    bag: Mapping[str, Any] | None = None,
    record: str | Path | None = None,
) -> RunSummary:
    """Run perception and the scene parser over every frame of ``input_path``.

    Args:
        input_path: a folder of clouds, a BOP scene folder (module docstring), or a ROS bag
            (``.bag``, ``.mcap``, a ROS 2 bag folder: :mod:`ssp.io.rosbag`).
        library: the object library (every class the input may contain).
        out_dir: output folder: absent or empty, or (``resume``) a stopped run of the same
            input, or (``overwrite``) an earlier run whose files are cleared first.
        config: ssp's settings.
        hypotheses: one of :data:`HYPOTHESES_MODES`.
        classes: the estimator's candidate classes (default: the classes a BOP scene lists,
            else the whole library; fewer classes, faster estimation).
        method: BOP method name (no ``_``).
        scene_id: BOP ``scene_id`` of the CSV rows.
        progress: called as ``progress(done, total, message)`` after each frame.
        resume: continue the run in ``out_dir`` from its saved state (every frame it finished
            is kept; the rest are processed as an uninterrupted run would).
        overwrite: clear an earlier run's files in ``out_dir`` (nothing else is touched).
        models: where ``library`` came from (a model folder, None: built-in), recorded.
        estimates: a BOP scene's hypotheses from an estimator's output file (camera frame,
            :func:`ssp.io.estimators.read_estimates`), instead of its ``hypotheses.json``.
        masks: a BOP scene's segmentation, one of :data:`ssp.io.bop.MASK_MODES`.
        period: seconds between images of a published BOP scene (no stamps); default
            :data:`ssp.io.bop.DEFAULT_PERIOD`.
        bag: for a ROS bag / MCAP input, :class:`ssp.io.rosbag.BagOptions` as a dict.
        record: write a 3D recording of the run to this rerun ``.rrd`` file
            (:class:`ssp.viz.record.Recorder`; needs the ``record`` extra): each finished
            frame's cloud, objects, hypotheses, support and terms, failed frames as error
            lines. A resumed run records the frames it processes itself.

    Raises:
        InputError: the input as a whole cannot be used (missing folder, no frames, bad
            ``scene.json``, classes of ``scene.json`` not in the library).
        ArgumentError: a bad option, an output folder that holds something else, or a
            resume whose input, models, config or options differ from the recorded ones.
        RecordingError: ``record`` given and rerun is not installed or the file cannot be
            written (:mod:`ssp.viz.record`).
    """
    cfg = config if config is not None else SSPConfig()
    if record is not None:
        from ssp.viz.record import check_recording

        check_recording(record)  # rerun installed: checked before any output is written
    if hypotheses not in HYPOTHESES_MODES:
        raise ArgumentError(
            f"hypotheses must be one of {', '.join(HYPOTHESES_MODES)}, got {hypotheses!r}"
        )
    src = Path(input_path)
    from ssp.io.rosbag import BagOptions, is_bag  # imports no rosbags

    kind = "bag" if is_bag(src) else None
    if kind is None:
        check_folder(src)
        kind = "bop" if is_bop_scene(src) else "folder"
    if kind != "bop" and (masks != "auto" or period is not None or estimates is not None):
        raise ArgumentError(
            f"{src}: masks, period and estimates are options of a BOP scene input, not of a "
            f"{'ROS bag' if kind == 'bag' else 'folder of clouds'}"
        )
    name = src.resolve().stem if kind == "bag" and src.is_file() else src.resolve().name
    csv_name = bop_csv_name(name, method)  # checks the method name
    out = Path(out_dir)
    manifest = {
        "format": RUN_FORMAT,
        "version": FORMAT_VERSION,
        "ssp": __version__,
        "input": str(src.resolve()),
        "kind": kind,
        "models": None if models is None else str(models),
        "options": {
            "hypotheses": hypotheses,
            "classes": None if classes is None else list(classes),
            "method": method,
            "scene_id": int(scene_id),
            "estimates": None if estimates is None else str(Path(estimates.source).resolve()),
            "masks": masks,
            "period": period,
            **({"bag": BagOptions.from_dict(bag).to_dict()} if kind == "bag" else {}),
        },
        "csv": csv_name,
        "config": cfg.to_dict(),
        "library": _library_digests(library),
        "input_files": _input_files(src, kind),
    }
    if estimates is not None:
        manifest["input_files"]["estimates"] = _file_stamp(Path(estimates.source))
    if kind == "bag":
        from ssp.inputs_bag import open_bag_input

        inp = open_bag_input(src, library, cfg, classes, hypotheses, bag)
        ids = ObjectIds.for_input(src, list(library))
    elif kind == "bop":
        inp = _open_bop_input(src, library, cfg, classes, hypotheses, estimates=estimates,
                              masks=masks, period=period)  # fmt: skip
        ids = _bop_ids(src, library)
    else:
        inp = _open_folder_input(src, library, Perception(library, cfg, classes), hypotheses)
        ids = ObjectIds.for_input(src, list(library))
    csv_path = out / csv_name
    if resume:
        state, finished = _prepare_resume(out, manifest, csv_path, inp)
    else:
        _prepare_fresh(out, overwrite)
        state, finished = {}, []
    (out / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
    summary = RunSummary(str(src), inp.kind, frames=inp.total)
    summary.files = [str(csv_path), str(out / OBJ_IDS_JSON), str(out / FRAMES_DIR),
                     str(out / TUM_DIR)]  # fmt: skip
    for frame_json in finished:
        summary.add(frame_json)
    start = int(state.get("next", 0))
    if "parser" in state:
        parser = SceneParser.from_state(library, state["parser"], cfg)
    else:
        parser = SceneParser(library, cfg)
    if not resume:
        write_json(out / RUN_JSON, manifest)
    write_json(out / OBJ_IDS_JSON, ids.to_json())
    write_json(out / SUMMARY_JSON, summary.to_dict())
    fsync_dir(out)
    if start:
        log.info("%s: resuming at frame %d of %d", out, start, inp.total)
    run_state = {
        "format": STATE_FORMAT,
        "version": FORMAT_VERSION,
        "total": inp.total,
        "resumes": int(state.get("resumes", -1)) + 1,
    }
    from ssp.viz.record import RunRecording  # rerun itself only when recording

    with BopCsvWriter(csv_path, method, append=resume) as csv, RunRecording(record, library) as rec:
        committed_parser = parser.state()

        def commit(n_next: int, parser_state: dict[str, Any]) -> None:
            """The frames before ``n_next`` are finished once this atomic write is done."""
            doc = {**run_state, "next": n_next, "csv_bytes": csv.sync(), "parser": parser_state}
            write_json(out / STATE_JSON, doc, indent=None)

        try:
            if not state:
                commit(0, committed_parser)
            for n, source in enumerate(inp.sources(start), start=start):
                kept: dict[str, Any] = {}
                frame_json, lines = _run_frame(source, parser, csv, ids, scene_id, kept)
                failed = frame_json["status"] == "failed"
                if failed and parser.state() != committed_parser:
                    # it failed after the parser took it: go on from the last good frame
                    parser = SceneParser.from_state(library, committed_parser, cfg)
                write_json(out / FRAMES_DIR / f"{source.name}.json", frame_json)
                csv.write_rows(lines)
                parser_state = parser.state()
                commit(n + 1, parser_state)
                committed_parser = parser_state
                done = summary.add(frame_json)
                atomic_write_text(out / SUMMARY_JSON, summary.to_json())
                rec.add(n, source.name, frame_json, **kept)
                if progress is not None:
                    msg = done.get("error") or f"{done['objects']} objects"
                    progress(n + 1, inp.total, f"{source.name}: {msg}")
        except BaseException as exc:
            # the summary holds the committed frames only; --resume continues from there
            summary.status = "stopped" if isinstance(exc, Exception) else "interrupted"
            try:
                write_tum(out)  # the committed frames' trajectories
                write_json(out / SUMMARY_JSON, summary.to_dict())
            except Exception:  # the original error matters more
                log.exception("could not write %s", out / SUMMARY_JSON)
            raise
    summary.status = "finished"
    write_tum(out)
    write_json(out / SUMMARY_JSON, summary.to_dict())
    return summary


def _run_frame(
    source: _Source,
    parser: SceneParser,
    csv: BopCsvWriter,
    ids: ObjectIds,
    scene_id: int,
    kept: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """Perceive and parse one frame: ``(frame JSON, CSV lines)``. Nothing is written here;
    a failure anywhere gives a frame JSON with ``status: failed`` and no lines. ``kept``
    receives the ``perceived`` result and the parser's ``estimate`` of a frame that succeeds."""
    t0 = time.perf_counter()
    warnings: list[str] = []
    try:
        perceived, warnings = source.perceive()
        estimate = parser.update(perceived.frame)
        seconds = time.perf_counter() - t0
        if kept is not None:
            kept.update(perceived=perceived, estimate=estimate)
        frame = perceived.frame
        T_cam_world = np.eye(4) if frame.T_world_cam is None else invert(frame.T_world_cam)
        lines = [
            csv.format_row(
                scene_id,
                source.index,
                ids[obj.class_name],
                float(obj.fit),
                T_cam_world @ obj.T_world_obj,
                seconds,
            )
            for obj in estimate.objects
        ]
        extra = {
            "status": "done",
            "perception": {
                "hypotheses": len(frame.hypotheses),
                "segments": len(perceived.segmentation.segment_ids),
                "timings": perceived.timings,
            },
            "T_world_cam": None if frame.T_world_cam is None else frame.T_world_cam.tolist(),
            "seconds": seconds,
        }
        frame_json = frame_record(estimate, name=source.name, index=source.index, extra=extra)
        # one list of doubts: the input's and the front end's, then the parser's
        frame_json["warnings"] = [*warnings, *frame_json["warnings"]]
        # a segment the parser got no hypothesis for: say what the front end made of it
        for label, verdict in perceived.verdicts.items():
            key = str(label)
            if frame_json["segments"].get(key, "").startswith("no object"):
                frame_json["segments"][key] = f"no object: {verdict}"
        return to_jsonable(frame_json), lines
    except Exception as exc:
        return _failure(source, exc, warnings, time.perf_counter() - t0), []


def _failure(
    source: _Source, exc: Exception, warnings: list[str], seconds: float
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
