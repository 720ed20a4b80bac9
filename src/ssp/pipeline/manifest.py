"""The output folder of a run (``docs/formats.md``): what it holds, ``run.json`` (what the run
reads: input files, models, config, options) and ``state.json`` (where to go on), the checks
of a folder for a new run (:func:`check_out_dir`) and of a resume (:func:`prepare_resume`), and
the options a resume takes from ``run.json`` (:meth:`RunOptions.resumed`)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import itertools
import json
import logging
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ssp import __version__
from ssp.config import SSPConfig
from ssp.errors import ArgumentError, OutputLockedError
from ssp.io._files import file_problem, output_error, refuse_link
from ssp.io.bop import MASK_MODES
from ssp.io.rosbag import BagOptions
from ssp.io.tum import TUM_DIR
from ssp.pipeline.inputs import input_files
from ssp.pipeline.sources import FrameSource

__all__ = [
    "FRAMES_DIR",
    "LOCK_FILE",
    "NO_EFFECT",
    "OBJ_IDS_JSON",
    "RUN_JSON",
    "STATE_JSON",
    "SUMMARY_JSON",
    "RunOptions",
    "check_out_dir",
    "differences",
    "file_stamp",
    "library_digests",
    "lock_out_dir",
    "own_files",
    "prepare_fresh",
    "prepare_resume",
    "read_run",
    "read_state",
    "run_manifest",
]

log = logging.getLogger(__name__)

FRAMES_DIR = "frames"
SUMMARY_JSON = "summary.json"
OBJ_IDS_JSON = "obj_ids.json"
RUN_JSON = "run.json"
STATE_JSON = "state.json"
#: The lock a run holds on its output folder while it writes it (:func:`lock_out_dir`).
LOCK_FILE = ".ssp.lock"
RUN_FORMAT, STATE_FORMAT, FORMAT_VERSION = "ssp-run", "ssp-run-state", 1


# ------------------------------------------------------------------------------ run.json
def run_manifest(
    src: Path,
    kind: str,
    library: Mapping,
    cfg: SSPConfig,
    *,
    csv_name: str,
    hypotheses: str,
    classes: Sequence[str] | None,
    method: str,
    scene_id: int,
    models: str | None,
    estimates: Any,
    masks: str,
    period: float | None,
    bag: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """The ``run.json`` of a run of ``src`` (of ``kind``) with these options; a resume must
    find the same (:func:`differences`)."""
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
        "library": library_digests(library),
        "input_files": input_files(src, kind),
    }
    if estimates is not None:
        manifest["input_files"]["estimates"] = file_stamp(Path(estimates.source))
    if masks not in MASK_MODES:  # a detections file: a changed one is another input
        manifest["input_files"]["masks"] = file_stamp(Path(masks))
    return manifest


def file_stamp(p: Path) -> Any:
    """``[size, mtime_ns]`` of a file, or its problem."""
    problem = file_problem(p)
    if problem is not None:
        return problem
    st = p.stat()
    return [st.st_size, st.st_mtime_ns]


def library_digests(library: Mapping) -> dict[str, str]:
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
        if _unstarted(Path(out_dir)):
            raise ArgumentError(
                f"{out_dir}: an ssp run stopped here before it wrote {RUN_JSON} (no frame was "
                "done): nothing to resume; start it again with --overwrite"
            )
        raise ArgumentError(f"{out_dir}: no ssp run here (no {RUN_JSON}): nothing to resume")
    return _read_doc(p, RUN_FORMAT, "ssp run manifest")


def read_state(out: Path) -> dict[str, Any] | None:
    """The ``state.json`` of an output folder (None: the run has committed no frame yet)."""
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


def differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """What differs between the recorded and the current manifest, one phrase each."""
    diffs = []
    for key, what in (("input", "input"), ("kind", "input kind"), ("ssp", "ssp version")):
        if old.get(key) != new.get(key):
            diffs.append(f"{what} {old.get(key)!r} -> {new.get(key)!r}")
    for k, v in new["options"].items():
        if old.get("options", {}).get(k) != v:
            diffs.append(f"option {k} {old.get('options', {}).get(k)!r} -> {v!r}")
    ids = _ids_differences(old.get("obj_ids"), new.get("obj_ids"))
    if ids:
        was, now = old.get("obj_ids_file"), new.get("obj_ids_file")
        diffs.append(
            f"object ids (obj_ids.json) {ids}"
            + (f" (--obj-ids {was!r} -> {now!r})" if was != now else "")
        )
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


def _ids_differences(old: Any, new: Any) -> str:
    """The classes whose BOP ``obj_id`` differ between two ``{"1": "cube", ...}`` maps, in
    words (``""``: the same; an ``old`` None, a run from before ids were recorded, is not
    compared)."""
    if old is None or old == new:
        return ""
    a = {c: k for k, c in old.items()} if isinstance(old, dict) else {}
    b = {c: k for k, c in (new or {}).items()}
    changed = sorted(c for c in a.keys() | b.keys() if a.get(c) != b.get(c))
    shown = ", ".join(f"{c} {a.get(c, 'none')} -> {b.get(c, 'none')}" for c in changed[:5])
    return shown + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")


def _recorded_ids(out: Path, old: dict[str, Any]) -> dict[str, Any]:
    """``old`` (a ``run.json``) with the ids its run wrote: an ``obj_ids.json`` when run.json
    has none (a run of an ssp that did not record them there)."""
    if "obj_ids" in old or not (out / OBJ_IDS_JSON).is_file():
        return old
    try:
        ids = json.loads((out / OBJ_IDS_JSON).read_text(encoding="utf-8")).get("obj_ids")
    except (OSError, ValueError, AttributeError):
        return old
    return {**old, "obj_ids": ids} if isinstance(ids, dict) else old


def _entries(out: Path) -> list[Path]:
    """What ``out`` holds, but the lock of a run (:data:`LOCK_FILE`)."""
    return [p for p in out.iterdir() if p.name != LOCK_FILE]


def _unstarted(out: Path) -> bool:
    """Whether ``out`` holds only what a run that stopped before writing ``run.json`` may have
    left: empty ``frames/`` and ``tum/`` folders, temporary files of atomic writes (and at
    least one of them)."""
    if not out.is_dir() or (out / RUN_JSON).exists():
        return False
    entries = _entries(out)
    for p in entries:
        if p.is_symlink():
            return False
        if p.name in (FRAMES_DIR, TUM_DIR) and p.is_dir():
            if any(not (q.name.startswith(".") and q.name.endswith(".tmp")) for q in p.iterdir()):
                return False
        elif not (p.is_file() and p.name.startswith(".") and p.name.endswith(".tmp")):
            return False
    return bool(entries)


def check_links(out: Path, manifest: Mapping[str, Any] | None = None) -> None:
    """:class:`~ssp.errors.OutputError` when a file or folder a run writes, truncates or deletes
    in ``out`` (its subfolders, the CSV, the JSON files) is a symbolic link: nothing outside the
    output folder is ever touched."""
    names = [FRAMES_DIR, TUM_DIR, RUN_JSON, STATE_JSON, SUMMARY_JSON, OBJ_IDS_JSON, LOCK_FILE]
    if manifest and isinstance(manifest.get("csv"), str):
        names.append(Path(manifest["csv"]).name)
    for name in names:
        refuse_link(out / name, " in the output folder")
    for sub in (FRAMES_DIR, TUM_DIR):
        if (out / sub).is_dir():
            for p in (out / sub).iterdir():
                refuse_link(p, " in the output folder")


@contextlib.contextmanager
def lock_out_dir(out: Path) -> Iterator[None]:
    """Hold ``out``'s lock (an exclusive ``flock`` on ``out/.ssp.lock``, which holds the pid)
    while a run writes it; the folder is created. The lock file is removed on release.

    Raises:
        OutputLockedError: another run holds it (the message names the folder and its pid).
        OutputError: the folder or the lock file cannot be written, or the lock file is a
            symbolic link.
    """
    try:
        import fcntl
    except ImportError:  # Windows: no advisory locks here
        yield
        return
    path = out / LOCK_FILE
    if out.exists() and not out.is_dir():
        raise ArgumentError(f"{out}: the output folder is a file")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(out, exc) from exc
    refuse_link(path, " in the output folder")
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
        except OSError as exc:
            refuse_link(path, " in the output folder")
            raise output_error(path, exc) from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.read(fd, 32).decode("ascii", "replace").strip()
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise output_error(path, exc) from exc
            pid = f" (pid {holder})" if holder.isdigit() else ""
            raise OutputLockedError(
                f"{out}: another ssp run{pid} is writing this output folder; wait for it to "
                "end or stop it, or choose another --out folder"
            ) from None
        try:  # the file may have been removed by a run that released it meanwhile
            same = os.path.samestat(os.fstat(fd), os.stat(path, follow_symlinks=False))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


def own_files(out: Path, manifest: Mapping[str, Any] | None) -> list[Path]:
    """The files an ssp run wrote in ``out`` (and temporary files of atomic writes); never
    the lock (:data:`LOCK_FILE`)."""
    names = [RUN_JSON, STATE_JSON, SUMMARY_JSON, OBJ_IDS_JSON]
    if manifest and isinstance(manifest.get("csv"), str):
        names.append(Path(manifest["csv"]).name)
    files = [out / n for n in names if os.path.lexists(out / n)]
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
    an earlier ssp run); :func:`ssp.pipeline.run.run` checks it too, a command checks it before
    slow work."""
    prepare_fresh(Path(out), overwrite, clear=False)


def prepare_fresh(out: Path, overwrite: bool, clear: bool = True) -> None:
    """Make sure ``out`` can take a new run: absent or empty, or an earlier ssp run that
    ``overwrite`` allows to clear (only its own files go; ``clear=False``: only check)."""
    if out.exists() and not out.is_dir():
        raise ArgumentError(f"{out}: the output folder is a file")
    if not out.exists() or not _entries(out):
        return
    if _unstarted(out):  # a run stopped before writing run.json: nothing of it to keep
        if not overwrite:
            raise ArgumentError(
                f"{out}: the output folder holds the start of an ssp run that stopped before "
                f"it wrote {RUN_JSON} (no frame was done): replace it with --overwrite, or "
                "choose a new --out folder"
            )
        if clear:
            _clear(out, None)
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
        state = (read_state(out) if old is not None else None) or {}
        n, total = state.get("next", 0), state.get("total")
        finished = total is not None and n >= total
        of = "" if old is None else f" of {old['input']} ({n} of {total} frames done)"
        again = "" if finished else f"continue it with `ssp run --resume {out}`, "
        raise ArgumentError(
            f"{out}: the output folder already holds {'a finished' if finished else 'an'} ssp "
            f"run{of}: {again}replace it with --overwrite, or choose a new --out folder"
        )
    check_links(out, old)
    if clear:
        _clear(out, old)


def _clear(out: Path, old: Mapping[str, Any] | None) -> None:
    """Delete the files of the earlier run in ``out`` (:func:`own_files`; links themselves,
    never what they point to) and its empty subfolders."""
    for p in own_files(out, old):
        p.unlink()
    for sub in (out / FRAMES_DIR, out / TUM_DIR):
        if sub.is_dir() and not sub.is_symlink() and not any(sub.iterdir()):
            sub.rmdir()
    log.info("%s: cleared the earlier run's files", out)


def _truncate(path: Path, size: int) -> None:
    """Cut ``path`` back to ``size`` bytes, never through a symbolic link."""
    try:
        fd = os.open(path, os.O_WRONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError as exc:
        refuse_link(path, " in the output folder")
        raise output_error(path, exc) from exc
    try:
        os.ftruncate(fd, size)
    except OSError as exc:
        raise output_error(path, exc) from exc
    finally:
        os.close(fd)


def prepare_resume(
    out: Path, manifest: dict[str, Any], csv_path: Path, source: FrameSource
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Check that ``out`` holds a resumable run of the same input, models, config and options,
    cut its CSV back to the last committed frame and delete uncommitted frame JSONs; returns
    the saved state (empty if the run stopped before its first commit) and the frame JSONs of
    the committed frames, in order."""
    old = read_run(out)
    check_links(out, old)
    diffs = differences(_recorded_ids(out, old), manifest)
    if diffs:
        raise ArgumentError(
            f"{out}: cannot resume: the run was started with other inputs: "
            + "; ".join(diffs)
            + ". Resume with the same input, --models, --config and options, or start a new "
            "run in a new --out folder"
        )
    state = read_state(out)
    if state is None:  # stopped before its first commit: start over (run.json is kept)
        for p in own_files(out, old):
            if p.name != RUN_JSON:
                p.unlink()
        return {}, []
    size = int(state.get("csv_bytes", 0))
    refuse_link(csv_path, " in the output folder")
    have = csv_path.stat().st_size if csv_path.exists() else 0
    if have < size:
        raise ArgumentError(
            f"{csv_path}: {have} bytes, but the run had written {size}: the output folder was "
            "modified; start a new run"
        )
    _truncate(csv_path, size)
    names = [fr.name for fr in itertools.islice(source.frames(0), int(state["next"]))]
    for p in own_files(out, old):
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


# ------------------------------------------------------------------------------ options
@dataclass
class RunOptions:
    """The options of a run that a resume may leave out (None: not given): the input, the
    model folder (None also: the built-in models), the :func:`ssp.pipeline.run.run` options
    ``hypotheses``, ``method``, ``classes``, ``bag`` (empty: not given), ``masks``,
    ``period``, ``scene_id`` and ``obj_ids`` (an id table file; None for a new run: the
    input's own scene id and ids)."""

    input: Path | None = None
    models: Path | None = None
    hypotheses: str | None = None
    method: str | None = None
    classes: list[str] | None = None
    bag: dict[str, Any] = field(default_factory=dict)
    masks: str | None = None
    period: float | None = None
    scene_id: int | None = None
    obj_ids: Path | None = None

    def fresh(self) -> RunOptions:
        """These options for a new run: the defaults of those not given."""
        return replace(
            self,
            hypotheses=self.hypotheses or "auto",
            method=self.method or "ssp",
            masks=self.masks or "auto",
        )

    def resumed(self, manifest: Mapping[str, Any]) -> RunOptions:
        """These options for a resume of the run whose ``run.json`` is ``manifest``
        (:func:`read_run`): each one not given is the recorded one."""
        opts = manifest["options"]
        models = self.models
        if models is None and manifest.get("models") is not None:
            models = Path(manifest["models"])
        return RunOptions(
            input=self.input if self.input is not None else Path(manifest["input"]),
            models=models,
            hypotheses=self.hypotheses or opts["hypotheses"],
            method=self.method or opts["method"],
            classes=self.classes if self.classes is not None else opts["classes"],
            bag=self.bag or opts.get("bag") or {},
            masks=self.masks or opts.get("masks", "auto"),
            period=self.period if self.period is not None else opts.get("period"),
            scene_id=self.scene_id if self.scene_id is not None else opts.get("scene_id"),
            obj_ids=self.obj_ids if self.obj_ids is not None else _path(manifest, "obj_ids_file"),
        )


def _path(manifest: Mapping[str, Any], key: str) -> Path | None:
    value = manifest.get(key)
    return None if value is None else Path(value)
