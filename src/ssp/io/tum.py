"""Object trajectories of a run in the TUM format: ``OUT/tum/<object id>.txt``.

One file per object instance, one line per frame the object is in the scene::

    # ssp object cube_0 (class cube): timestamp tx ty tz qx qy qz qw; world frame, m
    0.1 0.12 -0.03 0.025 0.0 0.0 0.3826834323650898 0.9238795325112867

``timestamp`` is the frame's ``stamp`` (s) from its ``frames/<name>.json`` record
(:func:`ssp.io.results.frame_record`: ``SceneEstimate.stamp``, the input frame's time); the pose
is the object's ``T_world_obj`` (m; quaternion x, y, z, w with w >= 0) in the run's world frame
(the camera frame when the run knew no camera pose: the record's ``T_world_cam`` is null).
Objects kept although unseen (``ephemeral``) are in; removed and rejected ones are not; failed
frames add no line. Tools such as ``evo`` read these files (``evo_traj tum OUT/tum/*.txt``).

:func:`write_tum` builds every file from a run's frame records (call it at the end of a run, or
to rebuild after a resume); :class:`TumWriter` appends one frame's record at a time.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ssp.errors import InputError
from ssp.io._files import atomic_write_text
from ssp.io.hypotheses import matrix_to_quat_xyzw

__all__ = ["TUM_DIR", "TumWriter", "read_frame_records", "tum_line", "tum_stamp", "write_tum"]

log = logging.getLogger(__name__)

#: Folder of the trajectories inside a run's output folder.
TUM_DIR = "tum"
FRAMES_DIR = "frames"
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")


def tum_stamp(stamp: float) -> str:
    """A timestamp (s) as written: fixed-point, the fewest decimals (at most 9: a ROS stamp's
    nanoseconds) that give the stamp within half a nanosecond or one float step
    (``1700000000.1``, ``0.033333333``, ``0.0``), never the float noise of ``stamp_ns *
    1e-9`` (``1700000000.1000001``); evo and the TUM scripts read it as a float."""
    stamp = float(stamp)
    tol = max(0.5e-9, math.ulp(stamp))
    for decimals in range(1, 10):
        text = f"{stamp:.{decimals}f}"
        if abs(float(text) - stamp) <= tol:
            break
    if "." in text:
        text = text.rstrip("0")
    return text + "0" if text.endswith(".") else text


def tum_line(stamp: float, T_world_obj: np.ndarray) -> str:
    """``"timestamp tx ty tz qx qy qz qw"`` (s, m; w >= 0) of a 4x4 pose, without a newline:
    the stamp to the nanosecond (:func:`tum_stamp`), the pose's numbers exact (``repr``)."""
    T = np.asarray(T_world_obj, dtype=np.float64)
    vals = [*T[:3, 3].tolist(), *matrix_to_quat_xyzw(T[:3, :3])]
    return " ".join([tum_stamp(stamp), *(repr(v) for v in vals)])


def read_frame_records(run_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The frame records of a run (``run_dir/frames/*.json``), ordered by their ``index``
    (input order), failed frames included; each gets ``_path`` (its file, for messages).

    Raises:
        InputError: no ``frames`` folder, or a record that cannot be read (named).
    """
    frames = Path(run_dir) / FRAMES_DIR
    if not frames.is_dir():
        raise InputError(f"{frames}: no such folder (not an ssp run output folder?)")
    records = []
    for p in sorted(frames.glob("*.json")):
        try:
            rec = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"{p}: cannot read the frame record: {exc}") from exc
        if not isinstance(rec, Mapping) or not isinstance(rec.get("index"), int):
            raise InputError(f"{p}: not a frame record (no integer 'index')")
        records.append((rec["index"], p, rec))
    records.sort(key=lambda r: r[0])
    return [dict(rec, _path=str(p)) for _, p, rec in records]


def _frame_poses(record: Mapping[str, Any]) -> tuple[float, list[tuple[str, Any, np.ndarray]]]:
    """``(stamp, [(id, class, T_world_obj)])`` of a done frame record (no objects for a
    failed one). InputError for a done frame without a finite stamp or a malformed object."""
    if record.get("status", "done") != "done":
        return math.nan, []
    where = record.get("_path") or f"frame {record.get('name')!r}"
    stamp = record.get("stamp")
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float)) or not math.isfinite(stamp):
        raise InputError(f"{where}: no finite 'stamp' (s), got {stamp!r}")
    objects = []
    for i, obj in enumerate(record.get("objects", [])):
        oid = obj.get("id") if isinstance(obj, Mapping) else None
        try:
            T = np.asarray(obj.get("T_world_obj"), dtype=np.float64)
        except (AttributeError, TypeError, ValueError):
            T = np.zeros(0)
        if not isinstance(oid, str) or not oid or T.shape != (4, 4):
            raise InputError(f"{where}: objects[{i}]: no 'id' or no 4x4 'T_world_obj'")
        objects.append((oid, obj.get("class"), T))
    return float(stamp), objects


def _header(oid: str, cls: Any) -> str:
    return f"# ssp object {oid} (class {cls}): timestamp tx ty tz qx qy qz qw; world frame, m"


class _Names:
    """Object id -> file name: unsafe characters replaced, clashes numbered ``~2``, ``~3``."""

    def __init__(self) -> None:
        self._names: dict[str, str] = {}

    def __call__(self, oid: str) -> str:
        name = self._names.get(oid)
        if name is None:
            base = _UNSAFE.sub("_", oid)
            base = "_" + base if base.startswith(".") else base
            name, n = base, 1
            while name in self._names.values():
                n += 1
                name = f"{base}~{n}"
            self._names[oid] = name
        return name


class TumWriter:
    """Append frames to the TUM files of ``out_dir/tum/`` (``out_dir``: a run's output folder),
    one :meth:`add` per frame record, in the run's frame order.

    ``fresh=True`` deletes the ``*.txt`` files already in ``tum/`` (an earlier write's); with
    ``fresh=False`` lines are appended to them (a resumed run: first :func:`write_tum` the
    frames it kept, then append). File names are the object ids with characters other than
    letters, digits, ``.``, ``_`` and ``-`` replaced by ``_`` (a clash gets ``~2``, ``~3``, ...
    in order of first appearance).
    """

    def __init__(self, out_dir: str | os.PathLike, *, fresh: bool = True) -> None:
        self.dir = Path(out_dir) / TUM_DIR
        self.dir.mkdir(parents=True, exist_ok=True)
        if fresh:
            for p in self.dir.glob("*.txt"):
                p.unlink()
        self._names = _Names()
        self._last: dict[str, float] = {}

    def path(self, object_id: str) -> Path:
        """The file of ``object_id``."""
        return self.dir / f"{self._names(object_id)}.txt"

    def add(self, record: Mapping[str, Any]) -> list[Path]:
        """Append one frame record's objects (a failed frame adds nothing); returns the files
        appended to.

        Raises:
            InputError: a done frame without a finite ``stamp``, or an object without ``id`` or
                a 4x4 ``T_world_obj``.
        """
        stamp, objects = _frame_poses(record)
        written = []
        for oid, cls, T in objects:
            last = self._last.get(oid)
            if last is not None and stamp < last:
                log.warning("%s: stamp %r before the previous %r", oid, stamp, last)
            self._last[oid] = stamp
            p = self.path(oid)
            head = not p.exists() or p.stat().st_size == 0
            with open(p, "a", encoding="ascii", newline="\n") as f:
                f.write((_header(oid, cls) + "\n" if head else "") + tum_line(stamp, T) + "\n")
            written.append(p)
        return written


def write_tum(
    run_dir: str | os.PathLike, records: Iterable[Mapping[str, Any]] | None = None
) -> dict[str, Path]:
    """Write ``run_dir/tum/<object id>.txt`` for every object of a run, from its frame records
    (default: :func:`read_frame_records` of ``run_dir``), in the order given; earlier TUM
    files of ``tum/`` are replaced or deleted. Each file is written atomically. Returns
    ``{object id: file}``.

    Raises:
        InputError: a record that cannot be read, or a done frame without a stamp.
    """
    recs = read_frame_records(run_dir) if records is None else list(records)
    lines: dict[str, list[str]] = {}
    for rec in recs:
        stamp, objects = _frame_poses(rec)
        for oid, cls, T in objects:
            lines.setdefault(oid, [_header(oid, cls)]).append(tum_line(stamp, T))
    folder = Path(run_dir) / TUM_DIR
    folder.mkdir(parents=True, exist_ok=True)
    names = _Names()
    out = {oid: folder / f"{names(oid)}.txt" for oid in lines}
    for old in folder.glob("*.txt"):
        if old not in out.values():
            old.unlink()
    for oid, body in lines.items():
        atomic_write_text(out[oid], "\n".join(body) + "\n")
    return out
