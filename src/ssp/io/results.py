"""Result files of ``ssp run``: per-frame JSON records, the BOP19 results CSV, object ids.

* :func:`frame_record` / :func:`write_json`: ``OUT/frames/<name>.json``.
* :class:`BopCsvWriter`: ``OUT/<method>_<dataset>-<split>.csv`` in the BOP19 format
  (bop_toolkit ``docs/bop_challenge_2019.md``): header ``scene_id,im_id,obj_id,score,R,t,time``,
  ``R`` the 9 row-major entries of the model-to-camera rotation and ``t`` the model-to-camera
  translation in **mm**, space-separated; ``time`` the seconds spent on the whole image (the
  same on every row of the image), -1 if unknown. :func:`read_bop_csv` reads it back (the
  first bad line fails it), :func:`scan_bop_csv` line by line (bad lines apart).
* :class:`ObjectIds`: class name -> BOP ``obj_id``, written as ``OUT/obj_ids.json``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ssp.errors import ArgumentError, InputError, InvalidPoseError, UnknownObjectError
from ssp.geometry import validate_pose
from ssp.io._files import file_problem, output_error, refuse_link, to_jsonable, write_json
from ssp.io.hypotheses import matrix_to_quat_xyzw

if TYPE_CHECKING:
    from ssp.parser import SceneEstimate

__all__ = [
    "BOP_CSV_HEADER",
    "BopCsvLine",
    "BopCsvWriter",
    "ObjectIds",
    "bop_csv_name",
    "bop_model_name",
    "bop_csv_parts",
    "frame_record",
    "read_bop_csv",
    "scan_bop_csv",
    "to_jsonable",
    "write_json",
]

log = logging.getLogger(__name__)

BOP_CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
#: The files of a BOP id table (:meth:`ObjectIds.from_file`).
MODELS_JSON, MODELS_INFO_JSON = "models.json", "models_info.json"
_BOP_MODEL = re.compile(r"^obj_(\d+)$")
_BOP_NAME = re.compile(r"^(?P<method>[^_]+)_(?P<dataset>[^_-]+)-(?P<split>[^_]+)\.csv$")


# ------------------------------------------------------------------------------ frame records
def frame_record(
    estimate: SceneEstimate, *, name: str, index: int, extra: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """JSON-ready record of one frame's estimate.

    Everything in ``estimate.to_dict()``, plus ``name`` (the frame's name) and ``index`` (its
    0-based position in the input), plus for each object (also the removed and rejected ones)
    ``R`` (3x3),
    ``t`` (m) and ``quat_xyzw`` of ``T_world_obj``. ``extra`` keys are added at the top level.

    Raises:
        ValueError: an ``extra`` key that the record already has.
    """
    rec: dict[str, Any] = {"name": str(name), "index": int(index)}
    rec.update(estimate.to_dict())
    for key in ("objects", "removed", "rejected"):
        rec[key] = [_with_pose_parts(o) for o in rec[key]]
    for key, value in (extra or {}).items():
        if key in rec:
            raise ValueError(f"extra key {key!r} would overwrite the record's own {key!r}")
        rec[key] = value
    return rec


def _with_pose_parts(obj: dict[str, Any]) -> dict[str, Any]:
    T = np.asarray(obj["T_world_obj"], dtype=np.float64)
    out = dict(obj)
    out["R"] = T[:3, :3].tolist()
    out["t"] = T[:3, 3].tolist()
    out["quat_xyzw"] = matrix_to_quat_xyzw(T[:3, :3])
    return out


# ------------------------------------------------------------------------------ BOP CSV
def bop_csv_name(dataset: str, method: str = "ssp", split: str = "test") -> str:
    """``METHOD_DATASET-SPLIT.csv``, the name the BOP toolkit parses; ``_`` and ``-`` are
    removed from ``dataset`` (the toolkit splits the name on them)."""
    _check_method(method)
    clean = re.sub(r"[_\-\s]", "", dataset)
    if not clean:
        raise ValueError(f"dataset name {dataset!r} is empty once '_' and '-' are removed")
    if not split or "_" in split:
        raise ValueError(f"split must be non-empty without '_', got {split!r}")
    return f"{method}_{clean}-{split}.csv"


def bop_csv_parts(name: str) -> dict[str, str] | None:
    """``{method, dataset, split}`` of a BOP results file name ``METHOD_DATASET-SPLIT.csv``,
    or None when the name does not follow the convention."""
    m = _BOP_NAME.match(name)
    return None if m is None else m.groupdict()


def _check_method(method: str) -> None:
    """ArgumentError (a ValueError) unless ``method`` can be the METHOD of a BOP file name."""
    if not isinstance(method, str) or not method:
        raise ArgumentError("BOP method name must be a non-empty string")
    if "_" in method:
        raise ArgumentError(
            f"BOP method name {method!r} must not contain '_' (files are "
            f"METHOD_DATASET-SPLIT.csv): try {method.replace('_', '')!r}"
        )
    if re.search(r"[\s,/\\]", method):
        raise ArgumentError(f"BOP method name {method!r} must not contain spaces, ',' or slashes")


class BopCsvWriter:
    """Stream rows of a BOP19 results CSV (format in the module docstring).

    The header is written on opening; rows are line-buffered, so every row added is on disk
    even if the run dies later. Use as a context manager or call :meth:`close`. With
    ``append=True`` an existing file (a resumed run's, already cut to its last whole frame)
    is continued, the header written only if it is empty. :meth:`sync` makes the rows
    durable and returns the file's size, which a resumed run cuts the file back to. With
    ``nofollow=True`` a ``path`` that is a symbolic link is refused, never written through
    (:class:`~ssp.errors.OutputError`). A write that fails (a full disk) raises
    :class:`~ssp.errors.OutputError` naming the file.
    """

    def __init__(
        self, path: str | os.PathLike, method: str, *, append: bool = False, nofollow: bool = False
    ) -> None:
        _check_method(method)
        self.path = Path(path)
        self.method = method
        m = _BOP_NAME.match(self.path.name)
        if m is None or m["method"] != method:
            log.warning(
                "%s: the BOP toolkit expects a file named %s_DATASET-SPLIT.csv", self.path, method
            )
        flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC)
        if nofollow:
            flags |= getattr(os, "O_NOFOLLOW", 0)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, flags, 0o666)
        except OSError as exc:
            if nofollow:
                refuse_link(self.path)
            raise output_error(self.path, exc) from exc
        self._f = open(fd, "a", encoding="ascii", newline="\n", buffering=1)  # noqa: SIM115
        if self._f.tell() == 0:
            self._write(BOP_CSV_HEADER + "\n")
        self._times: dict[tuple[int, int], float] = {}
        self.rows = 0

    def add(self, *row: Any, **kw: Any) -> None:
        """Add one estimate: ``add(scene_id, im_id, obj_id, score, T_cam_obj, time=None)``,
        arguments as for :meth:`format_row`.

        Raises:
            ValueError: closed writer, a bad id, score, pose or time.
        """
        self.write_rows([self.format_row(*row, **kw)])

    def format_row(
        self,
        scene_id: int,
        im_id: int,
        obj_id: int,
        score: float,
        T_cam_obj: np.ndarray,
        time: float | None = None,
    ) -> str:
        """The CSV line of one estimate, validated but not written (a caller that must write a
        frame's rows all or none formats them first): ``T_cam_obj`` (4x4, m) is the
        model-to-camera pose; ``time`` (s) the whole image's processing time, None or negative
        for unknown (-1); every row of one ``(scene_id, im_id)`` must carry the same time.

        Raises:
            ValueError: a bad id, score, pose or time.
        """
        ids = [_nonneg_int(v, k) for v, k in ((scene_id, "scene_id"), (im_id, "im_id"))]
        oid = _nonneg_int(obj_id, "obj_id")
        if oid < 1:
            raise ValueError(f"obj_id must be >= 1, got {obj_id}")
        s = float(score)
        if not math.isfinite(s):
            raise ValueError(f"score must be finite, got {score}")
        t_img = -1.0 if time is None or float(time) < 0 else float(time)
        if not math.isfinite(t_img):
            raise ValueError(f"time must be finite, got {time}")
        try:
            T = validate_pose(T_cam_obj, "T_cam_obj")
        except InvalidPoseError as exc:
            raise ValueError(str(exc)) from exc
        key = (ids[0], ids[1])
        if self._times.get(key, t_img) != t_img:
            raise ValueError(
                f"scene {key[0]} image {key[1]}: time {t_img} differs from the {self._times[key]} "
                "of its earlier rows (BOP wants the whole image's time on every row)"
            )
        R = " ".join(repr(float(v)) for v in T[:3, :3].reshape(-1))
        t = " ".join(repr(float(v)) for v in T[:3, 3] * 1000.0)
        return f"{ids[0]},{ids[1]},{oid},{s!r},{R},{t},{t_img!r}\n"

    def write_rows(self, lines: Iterable[str]) -> None:
        """Write lines made by :meth:`format_row`."""
        if self._f.closed:
            raise ValueError(f"{self.path}: writer is closed")
        for line in lines:
            scene_id, im_id, *_rest, t_img = line.rstrip("\n").split(",")
            self._times.setdefault((int(scene_id), int(im_id)), float(t_img))
            self._write(line)
            self.rows += 1

    def _write(self, text: str) -> None:
        try:
            self._f.write(text)
        except OSError as exc:
            raise output_error(self.path, exc) from exc

    def flush(self) -> None:
        """Flush buffered rows to the operating system (rows are line-buffered anyway)."""
        if not self._f.closed:
            try:
                self._f.flush()
            except OSError as exc:
                raise output_error(self.path, exc) from exc

    def sync(self) -> int:
        """Flush and fsync the rows written so far; returns the file's size in bytes."""
        try:
            self._f.flush()
            os.fsync(self._f.fileno())
            return self._f.tell()
        except OSError as exc:
            raise output_error(self.path, exc) from exc

    def close(self) -> None:
        """Flush and close; further :meth:`add` calls raise. Closing twice is harmless."""
        if not self._f.closed:
            try:
                self._f.close()
            except OSError as exc:
                raise output_error(self.path, exc) from exc

    @property
    def closed(self) -> bool:
        return self._f.closed

    def __enter__(self) -> BopCsvWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _nonneg_int(value: Any, what: str) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < 0:
        raise ValueError(f"{what} must be a non-negative integer, got {value!r}")
    return int(value)


def read_bop_csv(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Rows of a BOP19 results CSV: ``scene_id, im_id, obj_id`` (int), ``score, time`` (float),
    ``R`` (3x3 ndarray), ``t`` ((3,) ndarray, **mm** as in the file).

    Raises:
        InputError: a missing or unreadable file, a bad header, or any malformed row (the
            message names the file and line). :func:`scan_bop_csv` reads past bad rows.
    """
    rows = []
    for line in scan_bop_csv(path):
        if line.error is not None:
            raise InputError(f"{line.where}: {line.error}")
        rows.append(line.row)
    return rows


@dataclass(frozen=True)
class BopCsvLine:
    """One data line of a BOP19 results CSV, as :func:`scan_bop_csv` parsed it.

    ``where`` is ``"<file>:<line number>"``; ``ids`` the ``(scene_id, im_id)`` when the first
    two columns are integers (else None); ``row`` the parsed row (as :func:`read_bop_csv`
    returns them) or None, and then ``error`` says what is wrong.
    """

    where: str
    ids: tuple[int, int] | None
    row: dict[str, Any] | None
    error: str | None = None


def scan_bop_csv(path: str | os.PathLike) -> Iterator[BopCsvLine]:
    """The data lines of a BOP19 results CSV, each parsed on its own (a malformed line yields a
    :class:`BopCsvLine` with its ``error``; the rest are still read). Blank lines are skipped.

    Values are only parsed, not judged (a NaN or a matrix that is no rotation passes).

    Raises:
        InputError: the file is missing, unreadable, not ASCII, or its first line is not the
            BOP19 header.
    """
    p = Path(path)
    problem = file_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {'no such file' if problem == 'does not exist' else problem}")
    try:
        lines = p.read_text(encoding="ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not a BOP19 results CSV (not ASCII text: {exc})") from exc
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc}") from exc
    if not lines or lines[0].strip() != BOP_CSV_HEADER:
        raise InputError(f"{p}: not a BOP19 results CSV (header must be {BOP_CSV_HEADER!r})")
    for n, line in enumerate(lines[1:], start=2):
        if line.strip():
            yield _parse_bop_line(line, f"{p}:{n}")


def _parse_bop_line(line: str, where: str) -> BopCsvLine:
    parts = line.split(",")
    try:
        ids: tuple[int, int] | None = (int(parts[0]), int(parts[1]))
    except (ValueError, IndexError):
        ids = None
    if len(parts) != 7:
        return BopCsvLine(where, ids, None, f"expected 7 columns, got {len(parts)}")
    for col, n, what in ((4, 9, "R must be 9 numbers (3x3, row-major)"), (5, 3, "t must be 3")):
        if len(parts[col].split()) != n:
            return BopCsvLine(where, ids, None, f"{what}, got {len(parts[col].split())}")
    try:
        row = {
            "scene_id": int(parts[0]),
            "im_id": int(parts[1]),
            "obj_id": int(parts[2]),
            "score": float(parts[3]),
            "R": np.array(parts[4].split(), dtype=float).reshape(3, 3),
            "t": np.array(parts[5].split(), dtype=float).reshape(3),
            "time": float(parts[6]),
        }
    except ValueError as exc:
        return BopCsvLine(where, ids, None, f"malformed row ({exc})")
    return BopCsvLine(where, ids, row)


# ------------------------------------------------------------------------------ object ids
class ObjectIds:
    """A stable class name -> BOP ``obj_id`` (int >= 1) mapping.

    Build it with :meth:`from_classes` (1-based order of the sorted names),
    :meth:`from_models_json` (a BOP ``models.json`` ``obj_ids`` map, as written by
    ``ssp simulate``), :meth:`for_input` (the latter when the input folder has one),
    :meth:`from_file` (any BOP id table: ``models.json``, ``models_info.json``, a ``models/``
    folder) or :meth:`from_bop_names` (``obj_000005``: 5).
    """

    def __init__(self, ids: Mapping[str, int]) -> None:
        seen: dict[int, str] = {}
        for cls, oid in ids.items():
            if not isinstance(cls, str) or not cls:
                raise ValueError(f"class names must be non-empty strings, got {cls!r}")
            if isinstance(oid, bool) or not isinstance(oid, (int, np.integer)) or oid < 1:
                raise ValueError(f"obj_id of {cls!r} must be an integer >= 1, got {oid!r}")
            if int(oid) in seen:
                raise ValueError(f"obj_id {oid} is given to both {seen[int(oid)]!r} and {cls!r}")
            seen[int(oid)] = cls
        self._ids = {cls: seen_id for seen_id, cls in sorted(seen.items())}

    @classmethod
    def from_classes(cls, classes: Iterable[str]) -> ObjectIds:
        """``obj_id`` = 1-based position of the class in the sorted unique names."""
        return cls({c: i + 1 for i, c in enumerate(sorted(set(classes)))})

    @classmethod
    def from_models_json(cls, path: str | os.PathLike, classes: Iterable[str] = ()) -> ObjectIds:
        """The ``obj_ids`` map (``{"1": "cube", ...}``) of a BOP ``models.json``.

        ``classes`` missing from it get new ids after the largest, in sorted order.

        Raises:
            InputError: unreadable file, no ``obj_ids``, or ids that are not integers >= 1,
                or one class under two ids.
        """
        p = Path(path)
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"{p}: cannot read: {exc}") from exc
        raw = doc.get("obj_ids") if isinstance(doc, Mapping) else None
        if not isinstance(raw, Mapping):
            raise InputError(f'{p}: no \'obj_ids\' object ({{"1": "class", ...}})')
        ids: dict[str, int] = {}
        for key, name in raw.items():
            try:
                oid = int(key)
            except ValueError as exc:
                raise InputError(f"{p}: obj_id {key!r} is not an integer") from exc
            if not isinstance(name, str) or not name:
                raise InputError(f"{p}: obj_id {key}: class must be a non-empty string")
            if name in ids:
                raise InputError(f"{p}: class {name!r} has two obj_ids ({ids[name]}, {oid})")
            ids[name] = oid
        next_id = max(ids.values(), default=0) + 1
        for c in sorted(set(classes) - set(ids)):
            log.info("%s: class %r has no obj_id; giving it %d", p, c, next_id)
            ids[c] = next_id
            next_id += 1
        try:
            return cls(ids)
        except ValueError as exc:
            raise InputError(f"{p}: {exc}") from exc

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> ObjectIds:
        """The ids of a BOP id table, as given to ``ssp run --obj-ids``:

        * a JSON file with an ``obj_ids`` map (``{"1": "cube", ...}``): a BOP ``models.json``
          as ``ssp simulate`` writes it, or the ``obj_ids.json`` of an earlier run;
        * a BOP ``models_info.json`` (``{"1": {"diameter": ...}, ...}``): obj_id ``k`` is the
          class ``obj_{k:06d}`` (the name ssp gives the model ``obj_00000k.ply``);
        * a BOP ``models/`` folder: its ``models_info.json``, else its ``models.json``, else
          its mesh files named ``obj_<digits>`` (``obj_000005.ply``: obj_id 5).

        Raises:
            InputError: a missing or unreadable file, or one that holds none of these (the
                message names the file and what is wrong).
        """
        p = Path(path)
        if p.is_dir():
            for name in (MODELS_INFO_JSON, MODELS_JSON):
                if (p / name).is_file():
                    return cls.from_file(p / name)
            ids = _bop_mesh_ids(p)
            if not ids:
                raise InputError(
                    f"{p}: no {MODELS_INFO_JSON}, no {MODELS_JSON} and no obj_<digits> mesh "
                    "files: not a BOP models folder"
                )
            try:
                return cls(ids)
            except ValueError as exc:
                raise InputError(f"{p}: {exc}") from exc
        problem = file_problem(p)
        if problem is not None:
            raise InputError(f"{p}: {'no such file' if problem == 'does not exist' else problem}")
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"{p}: cannot read: {exc}") from exc
        if isinstance(doc, Mapping) and "obj_ids" in doc:
            return cls.from_models_json(p)
        if isinstance(doc, Mapping) and doc and all(isinstance(v, Mapping) for v in doc.values()):
            ids: dict[str, int] = {}
            for key in doc:
                if not str(key).isdigit() or int(key) < 1:
                    raise InputError(f"{p}: obj_id {key!r} is not an integer >= 1")
                ids[bop_model_name(int(key))] = int(key)
            try:
                return cls(ids)
            except ValueError as exc:
                raise InputError(f"{p}: {exc}") from exc
        raise InputError(
            f'{p}: not an id table: expected {{"obj_ids": {{"1": "class", ...}}}} (a BOP '
            f'{MODELS_JSON}) or a BOP {MODELS_INFO_JSON} ({{"1": {{"diameter": ...}}, ...}})'
        )

    @classmethod
    def from_bop_names(cls, classes: Iterable[str]) -> ObjectIds | None:
        """The ids the names say when every class is named as a BOP model
        (``obj_000005``: obj_id 5, the model ``obj_000005.ply`` of a BOP ``models/`` folder);
        None when one is not (or two name one id)."""
        ids = {}
        for c in classes:
            m = _BOP_MODEL.match(c)
            if m is None or int(m[1]) < 1:
                return None
            ids[c] = int(m[1])
        if not ids or len(set(ids.values())) != len(ids):
            return None
        return cls(ids)

    def missing(self, classes: Iterable[str]) -> list[str]:
        """The ``classes`` that have no obj_id here, sorted."""
        return sorted(set(classes) - set(self._ids))

    @classmethod
    def for_input(cls, folder: str | os.PathLike, classes: Iterable[str]) -> ObjectIds:
        """:meth:`from_models_json` of ``folder/models.json`` if it exists, else
        :meth:`from_classes`."""
        mj = Path(folder) / "models.json"
        return cls.from_models_json(mj, classes) if mj.is_file() else cls.from_classes(classes)

    def __getitem__(self, class_name: str) -> int:
        try:
            return self._ids[class_name]
        except KeyError:
            raise UnknownObjectError(
                f"class {class_name!r} has no BOP obj_id (known: {', '.join(self._ids) or 'none'})"
            ) from None

    def __contains__(self, class_name: object) -> bool:
        return class_name in self._ids

    def __len__(self) -> int:
        return len(self._ids)

    def __iter__(self) -> Iterator[str]:
        return iter(self._ids)

    def __repr__(self) -> str:
        return f"ObjectIds({self._ids!r})"

    def class_of(self, obj_id: int) -> str:
        """The class of ``obj_id`` (UnknownObjectError if none)."""
        for c, i in self._ids.items():
            if i == obj_id:
                return c
        raise UnknownObjectError(f"no class has obj_id {obj_id}")

    def as_dict(self) -> dict[str, int]:
        """``class -> obj_id``, by increasing id."""
        return dict(self._ids)

    def to_json(self) -> dict[str, Any]:
        """``{"obj_ids": {"1": "cube", ...}}``, the shape of a BOP ``models.json`` (readable by
        :meth:`from_models_json`)."""
        return {"obj_ids": {str(i): c for c, i in self._ids.items()}}


def bop_model_name(obj_id: int) -> str:
    """The class name of BOP obj_id ``obj_id``: its model's file name ``obj_XXXXXX``."""
    return f"obj_{int(obj_id):06d}"


def _bop_mesh_ids(folder: Path) -> dict[str, int]:
    """``{class: obj_id}`` of the ``obj_<digits>.*`` mesh files in ``folder`` (the class is the
    file name without its extension, as ssp names a model)."""
    out: dict[str, int] = {}
    for p in sorted(folder.iterdir()):
        m = _BOP_MODEL.match(p.stem)
        if m is not None and p.suffix.lower() in (".obj", ".ply", ".stl") and int(m[1]):
            out[p.stem] = int(m[1])
    return out
