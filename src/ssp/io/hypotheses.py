"""Per-frame pose hypotheses as JSON (``<frame>.hypotheses.json``; docs/formats.md).

::

    {
      "frame": "world",            # or "camera" (OpenCV axes); default "world"
      "units": "m",                # or "mm": applies to translations; default "m"
      "hypotheses": [
        {"class": "mug", "score": 0.9, "t": [0.1, 0.0, 0.05],
         "quat_xyzw": [0, 0, 0, 1], "id": "mug_1"},
        {"class": "box", "t": [...], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        {"class": "box", "T": [[...], [...], [...], [0, 0, 0, 1]]}
      ]
    }

Each hypothesis has ``class`` (str), ``score`` (float, default 1.0), optional ``id`` (a known
instance id), optional ``segment`` (int: the instance segment it was estimated from; hypotheses
of different segments are never taken for one object), and a pose: ``t`` plus a rotation ``R``
(3x3 nested list row-major, or 9 numbers row-major), ``quat_xyzw`` (scipy / ROS order) or
``quat_wxyz``; or instead of all of these ``T`` (4x4, row-major). Several rotation keys may be
given when they agree (within :data:`ROTATION_TOL`): :func:`write_hypotheses` writes both ``R``
and ``quat_xyzw``. Quaternions are normalised; rotation matrices must be orthonormal with det +1
within :data:`ROTATION_TOL` (then they are re-orthonormalised). Unknown keys are ignored with a
warning.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.errors import InputError, InvalidPoseError
from ssp.geometry import nearest_rotation, validate_pose
from ssp.io._files import read_json, write_json
from ssp.scene import Hypothesis

__all__ = [
    "FRAMES",
    "ROTATION_TOL",
    "HypothesisFile",
    "check_rotation",
    "matrix_to_quat_xyzw",
    "parse_hypotheses",
    "read_hypotheses",
    "to_world",
    "write_hypotheses",
]

log = logging.getLogger(__name__)

#: Frames a hypotheses file may be given in.
FRAMES = ("world", "camera")
#: Largest ``|R R^T - I|`` entry (and disagreement between rotation keys) accepted.
ROTATION_TOL = 1e-3
_UNITS = {"m": 1.0, "mm": 1e-3}
_TOP_KEYS = {"frame", "units", "hypotheses"}
_HYP_KEYS = {"class", "score", "id", "segment", "t", "R", "quat_xyzw", "quat_wxyz", "T"}
_ROTATION_KEYS = ("R", "quat_xyzw", "quat_wxyz")


@dataclass
class HypothesisFile:
    """The content of a hypotheses file: poses in ``frame`` (``world`` or ``camera``), metres.

    For ``frame == "camera"`` each ``Hypothesis.T_world_obj`` holds ``T_cam_obj`` until
    :func:`to_world` converts it.
    """

    frame: str
    hypotheses: list[Hypothesis] = field(default_factory=list)


def read_hypotheses(path: str | os.PathLike) -> HypothesisFile:
    """Read a hypotheses JSON file (format in the module docstring).

    Raises:
        InputError: missing file, invalid JSON, a bad value or pose; the message names the
            file and the hypothesis index.
    """
    p = Path(path)
    try:
        return parse_hypotheses(read_json(p, missing="no such file"), str(p))
    except RecursionError:  # json and the checks recurse; a file nested that deep is no input
        raise InputError(f"{p}: invalid JSON: nested too deeply to read") from None


def parse_hypotheses(doc: Any, where: str = "hypotheses") -> HypothesisFile:
    """:func:`read_hypotheses` of an already decoded JSON document; ``where`` names it."""
    if not isinstance(doc, Mapping):
        raise InputError(f"{where}: expected a JSON object with a 'hypotheses' list")
    _warn_unknown(where, doc, _TOP_KEYS)
    frame = doc.get("frame", "world")
    if frame not in FRAMES:
        raise InputError(f"{where}: 'frame' must be 'world' or 'camera', got {frame!r}")
    units = doc.get("units", "m")
    if units not in _UNITS:
        raise InputError(f"{where}: 'units' must be 'm' or 'mm', got {units!r}")
    items = doc.get("hypotheses")
    if not isinstance(items, list):
        raise InputError(f"{where}: 'hypotheses' must be a list")
    unknown: set[str] = set()
    hyps = [
        _parse_one(item, f"{where}: hypothesis {i}", _UNITS[units], unknown)
        for i, item in enumerate(items)
    ]
    if unknown:
        log.warning("%s: ignoring unknown hypothesis keys: %s", where, ", ".join(sorted(unknown)))
    return HypothesisFile(frame=frame, hypotheses=hyps)


def _warn_unknown(where: str, doc: Mapping, known: set[str]) -> None:
    extra = sorted(str(k) for k in doc if k not in known)
    if extra:
        log.warning("%s: ignoring unknown keys: %s", where, ", ".join(extra))


def _parse_one(item: Any, what: str, scale: float, unknown: set[str]) -> Hypothesis:
    """One hypothesis entry; ``scale`` converts translations to metres."""
    if not isinstance(item, Mapping):
        raise InputError(f"{what}: expected a JSON object")
    unknown.update(str(k) for k in item if k not in _HYP_KEYS)
    cls = item.get("class")
    if not isinstance(cls, str) or not cls:
        raise InputError(f"{what}: 'class' must be a non-empty string, got {cls!r}")
    what = f"{what} ({cls!r})"
    score = _finite(item.get("score", 1.0), f"{what}: score")
    iid = item.get("id")
    if iid is not None and (not isinstance(iid, str) or not iid):
        raise InputError(f"{what}: 'id' must be a non-empty string, got {iid!r}")
    seg = item.get("segment")
    if seg is not None and (isinstance(seg, bool) or not isinstance(seg, int)):
        raise InputError(f"{what}: 'segment' must be an integer, got {seg!r}")
    T = _pose(item, what)
    T[:3, 3] *= scale
    return Hypothesis(class_name=cls, T_world_obj=T, score=score, instance_id=iid, segment=seg)


def _pose(item: Mapping, what: str) -> np.ndarray:
    """The 4x4 pose of an entry (translation still in the file's units)."""
    rot_keys = [k for k in _ROTATION_KEYS if k in item]
    if "T" in item:
        if rot_keys or "t" in item:
            others = ", ".join(repr(k) for k in [*rot_keys, "t"] if k in item)
            raise InputError(
                f"{what}: give either 'T' or 't' with a rotation, not 'T' and {others}"
            )
        T = _numbers(item["T"], (4, 4), f"{what}: T")
        if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise InputError(f"{what}: T's last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        T[:3, :3] = check_rotation(T[:3, :3], f"{what}: T")
        return T
    if "t" not in item:
        raise InputError(
            f"{what}: no pose: give 't' with one of 'R', 'quat_xyzw', 'quat_wxyz', or 'T'"
        )
    if not rot_keys:
        raise InputError(f"{what}: 't' without a rotation: add 'R', 'quat_xyzw' or 'quat_wxyz'")
    rotations = [_rotation(item[k], k, f"{what}: {k}") for k in rot_keys]
    for k, R in zip(rot_keys[1:], rotations[1:], strict=True):
        if np.abs(R - rotations[0]).max() > ROTATION_TOL:
            raise InputError(f"{what}: {rot_keys[0]!r} and {k!r} give different rotations")
    T = np.eye(4)
    T[:3, :3] = rotations[0]
    T[:3, 3] = _numbers(item["t"], (3,), f"{what}: t")
    return T


def _rotation(value: Any, key: str, what: str) -> np.ndarray:
    if key == "R":
        arr = _numbers(value, None, what)
        if arr.shape not in ((3, 3), (9,)):
            raise InputError(f"{what}: expected 3x3 (or 9 numbers, row-major), got {arr.shape}")
        return check_rotation(arr.reshape(3, 3), what)
    q = _numbers(value, (4,), what)
    norm = float(np.linalg.norm(q))
    if norm < 1e-6:
        raise InputError(f"{what}: zero quaternion")
    q = q / norm
    xyzw = q if key == "quat_xyzw" else np.roll(q, -1)
    return Rotation.from_quat(xyzw).as_matrix()


def check_rotation(R: np.ndarray, what: str) -> np.ndarray:
    """``R`` re-orthonormalised, or InputError when it is not a rotation within the tolerance."""
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOL or det <= 0:
        raise InputError(
            f"{what}: not a rotation (|R R^T - I| = {err:.2e}, det {det:.3f}; tolerance "
            f"{ROTATION_TOL:g})"
        )
    return nearest_rotation(R)


def _numbers(value: Any, shape: tuple[int, ...] | None, what: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: expected numbers, got {value!r}") from exc
    if shape is not None and arr.shape != shape:
        raise InputError(f"{what}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what}: contains NaN or infinite values")
    return arr


def _finite(value: Any, what: str) -> float:
    if isinstance(value, bool):
        raise InputError(f"{what}: expected a number, got {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: expected a number, got {value!r}") from exc
    if not math.isfinite(out):
        raise InputError(f"{what}: must be finite, got {out}")
    return out


def matrix_to_quat_xyzw(R: np.ndarray) -> list[float]:
    """Unit quaternion ``[x, y, z, w]`` (scipy / ROS order) of a 3x3 rotation, with ``w >= 0``."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    if q[3] < 0:
        q = -q
    return [float(v) for v in q]


def write_hypotheses(
    path: str | os.PathLike, hypotheses: Iterable[Hypothesis], frame: str = "world"
) -> Path:
    """Write hypotheses in the format read by :func:`read_hypotheses` (metres), atomically.

    Each entry has ``class``, ``score``, ``t``, ``R`` (3x3), ``quat_xyzw`` and, when set, ``id``
    and ``segment``.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be 'world' or 'camera', got {frame!r}")
    items = []
    for h in hypotheses:
        T = np.asarray(h.T_world_obj, dtype=np.float64)
        entry: dict[str, Any] = {
            "class": h.class_name,
            "score": float(h.score),
            "t": T[:3, 3].tolist(),
            "R": T[:3, :3].tolist(),
            "quat_xyzw": matrix_to_quat_xyzw(T[:3, :3]),
        }
        if h.instance_id is not None:
            entry["id"] = h.instance_id
        if h.segment is not None:
            entry["segment"] = int(h.segment)
        items.append(entry)
    return write_json(path, {"frame": frame, "units": "m", "hypotheses": items})


def to_world(hypotheses: Iterable[Hypothesis], T_world_cam: np.ndarray) -> list[Hypothesis]:
    """Copies of camera-frame hypotheses (``T_world_obj`` holding ``T_cam_obj``) moved to the
    world frame: ``T_world_obj = T_world_cam @ T_cam_obj``.

    Raises:
        InputError: ``T_world_cam`` is not a rigid 4x4 transform.
    """
    try:
        T_wc = validate_pose(T_world_cam, "T_world_cam")
    except InvalidPoseError as exc:
        raise InputError(str(exc)) from exc
    return [replace(h, T_world_obj=T_wc @ np.asarray(h.T_world_obj, float)) for h in hypotheses]
