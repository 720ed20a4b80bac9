"""Small file helpers shared by :mod:`ssp.io`: atomic writes, JSON conversion, and what is
wrong with a path that should be a regular file."""

from __future__ import annotations

import enum
import errno
import json
import math
import os
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "atomic_write_bytes",
    "atomic_write_text",
    "file_problem",
    "fsync_dir",
    "read_json",
    "to_jsonable",
    "write_json",
]


def file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` is not a readable regular file, as words that follow the path in a message
    (``"is a FIFO ..."``), or None when it is one. Never opens the file (opening a FIFO blocks).
    """
    p = os.fspath(path)
    try:
        st = os.stat(p)  # follows symbolic links
    except FileNotFoundError:
        if os.path.islink(p):
            return f"is a dangling symbolic link (its target {os.readlink(p)!r} does not exist)"
        return "does not exist"
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "is a symbolic link loop (following it never reaches a file)"
        return f"cannot be examined: {exc.strerror or exc}"
    mode = st.st_mode
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a folder, not a file"
    if stat.S_ISFIFO(mode):
        return "is a FIFO (named pipe), not a regular file"
    if stat.S_ISSOCK(mode):
        return "is a socket, not a regular file"
    return "is a device, not a regular file"


def fsync_dir(path: str | os.PathLike) -> None:
    """Flush a folder's entries (new and renamed files) to disk; a no-op where folders cannot
    be opened (Windows)."""
    try:
        fd = os.open(os.fspath(path), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, fsynced, then
    :func:`os.replace` (readers see the old file or the new one, never a partial one).

    The parent folder is created. Returns the path.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return p


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """:func:`atomic_write_bytes` of ``text`` encoded as UTF-8."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def to_jsonable(obj: Any) -> Any:
    """``obj`` with numpy arrays and scalars, tuples, sets, paths and enums turned into JSON types.

    Non-finite floats (NaN, +-inf) become ``None``: strict JSON has no such numbers. Mapping keys
    become strings.
    """
    if isinstance(obj, Mapping):
        return {
            str(k.value if isinstance(k, enum.Enum) else k): to_jsonable(v) for k, v in obj.items()
        }
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, enum.Enum):
        return to_jsonable(obj.value)
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (set, frozenset)):
        return [to_jsonable(v) for v in sorted(obj, key=repr)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> Path:
    """Write ``obj`` as strict JSON (see :func:`to_jsonable`) to ``path`` atomically.

    The parent folder is created. Returns the path.
    """
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def read_json(path: str | os.PathLike, missing: str | None = None) -> Any:
    """The JSON document of ``path``; :class:`~ssp.errors.InputError` naming the file when
    it is missing (``missing``: the words for that, default :func:`file_problem`'s), not a
    regular file (never opened then), unreadable, not UTF-8 or invalid JSON."""
    from ssp.errors import InputError

    p = Path(path)
    problem = file_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {missing if missing and problem == 'does not exist' else problem}")
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:  # removed since the check
        raise InputError(f"{p}: {missing or 'does not exist'}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: invalid JSON: {exc}") from exc
