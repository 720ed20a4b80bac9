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
    "file_mode",
    "file_problem",
    "fsync_dir",
    "output_error",
    "refuse_link",
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


def file_mode() -> int:
    """The permissions of a new file under the process's umask (``0o666 & ~umask``: 0644 under
    umask 022), as :func:`open` gives them; read from ``/proc`` where it can be."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # no other way to read it: set and put back at once
    os.umask(mask)
    return 0o666 & ~mask


def output_error(path: str | os.PathLike, exc: OSError) -> OSError:
    """``exc`` (raised while writing ``path``) as an :class:`~ssp.errors.OutputError` whose
    message is one line naming the file (``exc`` itself when it is one already)."""
    from ssp.errors import OutputError

    if isinstance(exc, OutputError):
        return exc
    err = OutputError(f"{os.fspath(path)}: cannot write: {exc.strerror or exc}")
    err.errno = exc.errno
    return err


def refuse_link(path: str | os.PathLike, what: str = "") -> None:
    """:class:`~ssp.errors.OutputError` when ``path`` is a symbolic link (never followed: ssp
    writes, truncates and deletes nothing through a link); nothing when it is anything else or
    absent."""
    from ssp.errors import OutputError

    p = os.fspath(path)
    if os.path.islink(p):
        raise OutputError(
            f"{p}: is a symbolic link (to {os.readlink(p)!r}){what}; ssp writes, truncates and "
            "deletes nothing through a link: remove the link, or choose a new --out folder"
        )


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, fsynced, then
    :func:`os.replace` (readers see the old file or the new one, never a partial one). The file
    gets the permissions the umask gives new files (:func:`file_mode`), not the owner-only ones
    of a temporary file.

    The parent folder is created. Returns the path.

    Raises:
        OutputError: the file cannot be written (a full disk, no permission); the message
            names ``path``, the file being written.
    """
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except OSError as exc:
        raise output_error(p, exc) from exc
    try:
        with os.fdopen(fd, "wb") as f:
            if hasattr(os, "fchmod"):  # not on Windows, where files have no such mode
                os.fchmod(f.fileno(), file_mode())
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise output_error(p, exc) from exc
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
        # a finite numeric array's list holds JSON types already: no second pass over it
        if obj.dtype.kind in "biu" or (obj.dtype.kind == "f" and np.isfinite(obj).all()):
            return obj.tolist()
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
