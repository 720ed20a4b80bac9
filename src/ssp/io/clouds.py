"""Point-cloud files (PLY, PCD) to and from :class:`Cloud`.

Fields read (names matched case-insensitively, the first match wins):

* points: ``x y z`` (required; metres, this module does not rescale);
* colours: ``red green blue`` or ``r g b`` (integers 0..255, or floats: 0..1 scaled by 255,
  else 0..255), or a packed ``rgb`` / ``rgba`` field (PCL: the bits ``0xAARRGGBB`` of a
  float32 or uint32);
* normals: ``nx ny nz`` or ``normal_x normal_y normal_z``;
* labels: the first of :data:`LABEL_FIELDS` (integer-valued; floats with integer values are
  accepted, PCD writers often store labels as F);
* viewpoint: the PCD ``VIEWPOINT tx ty tz qw qx qy qz`` header (the sensor pose in the cloud's
  frame); the identity, which every PCD writer puts there when it knows nothing, reads as None.

PLY (``format ascii``, ``binary_little_endian`` and ``binary_big_endian`` 1.0) is parsed and
written here with numpy: the header, then ``np.frombuffer`` of the ``vertex`` rows in a binary
file and :func:`numpy.loadtxt` of them in an ascii one. The well-known Python PLY library,
``plyfile``, is GPL-3.0, incompatible with this package's MIT licence, and trimesh's loader does
not give custom per-vertex fields such as ``label`` (a ``PointCloud`` has colours only; the rest
sits in the private ``metadata["_ply_raw"]``). Elements before ``vertex`` are skipped (in a binary
file only if they have no list properties); elements after it (faces) are not read.

PCD has its own reader and writer here, because the maintained PCD package on PyPI (``pypcd4``
1.5.1, measured 2026) reads PCL's ascii ``rgb`` wrongly (PCL writes that float field as the uint32
integer, pypcd4 parses it as a float32 and loses the low bits: colour (10, 20, 30) with alpha 255
came back as (127, 10, 20)), writes ascii ``rgb`` as ``%.10f`` (every packed colour became 0), and
returns silently fewer points from a truncated file. PCD is a short text header plus one of three
bodies, so a reader that checks every size is little code; ``binary_compressed`` needs LZF, from
the ``lzf`` module (``python-neo-lzf``, the wheel-packaged fork of ``python-lzf``).

Every problem with a file raises :class:`~ssp.errors.CloudFormatError` naming the file and the
problem. Non-finite points are kept (``Frame.validate`` drops them).
"""

from __future__ import annotations

import logging
import os
import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.errors import CloudFormatError
from ssp.io._files import atomic_write_bytes, file_problem

__all__ = ["CLOUD_SUFFIXES", "LABEL_FIELDS", "Cloud", "read_cloud", "write_cloud"]

log = logging.getLogger(__name__)

#: File name endings read and written (lower case).
CLOUD_SUFFIXES = (".ply", ".pcd")
#: Per-point integer fields taken as the label, in order of preference.
LABEL_FIELDS = ("label", "instance", "object", "segment", "class")
_COLOR_FIELDS = (("red", "green", "blue"), ("r", "g", "b"))
_PACKED_COLOR_FIELDS = ("rgb", "rgba")
_NORMAL_FIELDS = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))

_PCD_DTYPES = {
    ("F", 4): "f4",
    ("F", 8): "f8",
    ("U", 1): "u1",
    ("U", 2): "u2",
    ("U", 4): "u4",
    ("U", 8): "u8",
    ("I", 1): "i1",
    ("I", 2): "i2",
    ("I", 4): "i4",
    ("I", 8): "i8",
}
_PCD_HEADER_MAX_LINES = 64
_PCD_PADDING = re.compile(r"^_[0-9]*$")  # PCL pads with fields named "_" (made unique here)
_PCD_VIEWPOINT_IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


@dataclass
class Cloud:
    """A point cloud read from a file.

    Attributes:
        points: ``(N, 3)`` float64, the file's units (metres expected); may hold NaN rows.
        colors: ``(N, 3)`` uint8 RGB, or None.
        labels: ``(N,)`` int64 from the first of :data:`LABEL_FIELDS`, or None.
        normals: ``(N, 3)`` float64, or None.
        viewpoint: ``(4, 4)`` sensor pose in the cloud's frame from a PCD ``VIEWPOINT`` that is
            not the identity, else None.
        fields: names of the file's per-point fields, in file order (PCD padding ``_`` left out).
        label_field: the field ``labels`` came from, or None.
    """

    points: np.ndarray
    colors: np.ndarray | None = None
    labels: np.ndarray | None = None
    normals: np.ndarray | None = None
    viewpoint: np.ndarray | None = None
    fields: tuple[str, ...] = field(default_factory=tuple)
    label_field: str | None = None

    def __len__(self) -> int:
        return len(self.points)


# ------------------------------------------------------------------------------------ reading
def read_cloud(path: str | os.PathLike) -> Cloud:
    """Read a ``.ply`` or ``.pcd`` file (see the module docstring for the fields).

    Raises:
        CloudFormatError: missing, unreadable, corrupt or truncated file, unknown extension, no
            ``x y z`` fields, zero points, or a field of the wrong kind.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise CloudFormatError(
            f"{p}: unknown point-cloud extension {p.suffix!r} (expected .ply or .pcd)"
        )
    problem = file_problem(p)
    if problem is not None:
        raise CloudFormatError(f"{p}: {'no such file' if problem == 'does not exist' else problem}")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise CloudFormatError(f"{p}: cannot read: {exc}") from exc
    if not raw:
        raise CloudFormatError(f"{p}: empty file")
    if suffix == ".ply":
        columns, viewpoint = _read_ply(p, raw), None
    else:
        columns, viewpoint = _read_pcd(p, raw)
    return _cloud_from_columns(p, columns, viewpoint)


def _cloud_from_columns(
    path: Path, columns: dict[str, np.ndarray], viewpoint: np.ndarray | None
) -> Cloud:
    """Assemble a :class:`Cloud` from the file's 1-D (or ``(N, count)``) columns."""
    lower = {name.lower(): name for name in reversed(columns)}  # first spelling wins
    xyz = [lower.get(c) for c in ("x", "y", "z")]
    if None in xyz:
        raise CloudFormatError(
            f"{path}: no x, y, z fields (fields: {', '.join(columns) or 'none'})"
        )
    points = np.column_stack([_scalar_column(path, columns, n).astype(np.float64) for n in xyz])
    if len(points) == 0:
        raise CloudFormatError(f"{path}: the cloud has zero points")
    n_bad = int((~np.isfinite(points).all(axis=1)).sum())
    if n_bad:
        log.debug("%s: %d of %d points are not finite", path, n_bad, len(points))

    colors = _colors(path, columns, lower)
    normals = None
    for names in _NORMAL_FIELDS:
        if all(n in lower for n in names):
            normals = np.column_stack(
                [_scalar_column(path, columns, lower[n]).astype(np.float64) for n in names]
            )
            break
    labels, label_field = None, None
    for name in LABEL_FIELDS:
        if name in lower:
            label_field = lower[name]
            labels = _integer_column(path, label_field, _scalar_column(path, columns, label_field))
            break
    return Cloud(
        points=points,
        colors=colors,
        labels=labels,
        normals=normals,
        viewpoint=viewpoint,
        fields=tuple(columns),
        label_field=label_field,
    )


def _scalar_column(path: Path, columns: dict[str, np.ndarray], name: str) -> np.ndarray:
    """Column ``name`` as a 1-D numeric array (CloudFormatError if it has several values)."""
    col = columns[name]
    if col.ndim != 1:
        raise CloudFormatError(
            f"{path}: field {name!r} has {col.shape[1]} values per point, expected 1"
        )
    if not (np.issubdtype(col.dtype, np.number) or col.dtype == np.bool_):
        raise CloudFormatError(f"{path}: field {name!r} is not numeric ({col.dtype})")
    return col


def _integer_column(path: Path, name: str, col: np.ndarray) -> np.ndarray:
    """An integer-valued column as int64 (floats must hold whole finite numbers)."""
    if np.issubdtype(col.dtype, np.integer):
        if col.dtype == np.uint64 and len(col) and col.max() > np.iinfo(np.int64).max:
            raise CloudFormatError(f"{path}: field {name!r} has values beyond int64")
        return col.astype(np.int64)
    col = col.astype(np.float64)
    if not np.all(np.isfinite(col)):
        raise CloudFormatError(f"{path}: label field {name!r} has NaN or infinite values")
    if not np.all(col == np.round(col)):
        raise CloudFormatError(
            f"{path}: label field {name!r} has non-integer values (labels must be integers)"
        )
    if len(col) and np.abs(col).max() > 2**53:
        raise CloudFormatError(f"{path}: label field {name!r} has values too large")
    return col.astype(np.int64)


def _colors(path: Path, columns: dict[str, np.ndarray], lower: dict[str, str]) -> np.ndarray | None:
    """``(N, 3)`` uint8 colours from separate or packed colour fields, or None."""
    for names in _COLOR_FIELDS:
        if all(n in lower for n in names):
            chans = np.column_stack([_scalar_column(path, columns, lower[n]) for n in names])
            return _channels_to_uint8(path, "/".join(lower[n] for n in names), chans)
    for name in _PACKED_COLOR_FIELDS:
        if name in lower:
            bits = _packed_bits(path, lower[name], _scalar_column(path, columns, lower[name]))
            return np.column_stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF]).astype(
                np.uint8
            )
    return None


def _channels_to_uint8(path: Path, what: str, rgb: np.ndarray) -> np.ndarray:
    """``(N, 3)`` colour channels as uint8: integers 0..255; floats scaled by 255 when none
    exceeds 1 (0..1 colours), else rounded (0..255 colours)."""
    if np.issubdtype(rgb.dtype, np.integer):
        if len(rgb) and (rgb.min() < 0 or rgb.max() > 255):
            raise CloudFormatError(
                f"{path}: colour fields {what} have values outside 0..255 "
                f"({rgb.min()}..{rgb.max()})"
            )
        return rgb.astype(np.uint8)
    rgb = rgb.astype(np.float64)
    finite = np.isfinite(rgb)
    if not finite.all():
        log.debug("%s: colour fields %s have non-finite values (set to 0)", path, what)
        rgb = np.where(finite, rgb, 0.0)
    lo, hi = (float(rgb.min()), float(rgb.max())) if len(rgb) else (0.0, 0.0)
    if lo < 0 or hi > 255:
        raise CloudFormatError(f"{path}: colour fields {what} have values outside 0..255")
    scale = 255.0 if hi <= 1.0 else 1.0
    return np.clip(np.round(rgb * scale), 0, 255).astype(np.uint8)


def _packed_bits(path: Path, name: str, col: np.ndarray) -> np.ndarray:
    """``0xAARRGGBB`` bits (uint32) of a packed colour column (float32 bits or an integer)."""
    if col.dtype == np.float32:
        return np.ascontiguousarray(col).view(np.uint32)
    if np.issubdtype(col.dtype, np.integer):
        return col.astype(np.uint32)
    raise CloudFormatError(
        f"{path}: packed colour field {name!r} must be float32 or an integer type, got {col.dtype}"
    )


# ------------------------------------------------------------------------------------ PLY
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
              "u4": "uint", "f4": "float", "f8": "double"}  # fmt: skip
#: ``format`` of a PLY file -> numpy byte order of its body (None: ascii).
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_PLY_END_HEADER = re.compile(rb"^end_header[ \t\r]*$", re.MULTILINE)
_PLY_COUNT_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}


@dataclass
class _PlyProperty:
    name: str
    code: str  # numpy type code of the value (of each item, for a list)
    count_code: str | None = None  # numpy type code of a list's length; None: a scalar


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[_PlyProperty] = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.count_code is not None for p in self.properties)

    def dtype(self, byte_order: str) -> np.dtype:
        """The record of one row (scalar properties only)."""
        return np.dtype([(p.name, byte_order + p.code) for p in self.properties])


def _read_ply(path: Path, raw: bytes) -> dict[str, np.ndarray]:
    """Columns of the ``vertex`` element of a PLY file (list properties are skipped).

    Elements before ``vertex`` are skipped (in a binary file they must have scalar properties
    only: their rows then have a fixed size); elements after it (faces) are not read.
    """
    byte_order, elements, start = _parse_ply_header(path, raw)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise CloudFormatError(
            f"{path}: PLY file has no 'vertex' element (elements: {', '.join(names) or 'none'})"
        )
    k = names.index("vertex")
    before, vertex = elements[:k], elements[k]
    for p in vertex.properties:
        if p.count_code is not None:
            log.debug("%s: skipping PLY list property %r", path, p.name)
    if byte_order is None:
        return _ply_ascii_vertex(path, raw, start, before, vertex)
    return _ply_binary_vertex(path, raw, start, byte_order, before, vertex)


def _parse_ply_header(path: Path, raw: bytes) -> tuple[str | None, list[_PlyElement], int]:  # noqa: C901
    """(byte order ``<`` / ``>``, or None for ascii; the elements; the offset of the data)."""
    nl = raw.find(b"\n", 0, 256)
    if not raw.startswith(b"ply") or (nl >= 0 and raw[:nl].strip() != b"ply"):
        raise CloudFormatError(f"{path}: not a PLY file (the first line is not 'ply')")
    end = _PLY_END_HEADER.search(raw)
    if end is None:
        raise CloudFormatError(
            f"{path}: bad PLY header: no 'end_header' line (truncated, or not a PLY file)"
        )
    try:
        text = raw[: end.start()].decode("utf-8")
    except UnicodeDecodeError:
        text = raw[: end.start()].decode("latin-1")  # only comments may hold such bytes
    fmt: str | None = None
    elements: list[_PlyElement] = []
    for lineno, line in enumerate(text.split("\n")[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue

        def bad(problem: str, lineno=lineno, line=line) -> CloudFormatError:
            return CloudFormatError(
                f"{path}: bad PLY header, line {lineno} ({line.strip()!r}): {problem}"
            )

        if words[0] == "format":
            if fmt is not None or elements:
                raise bad("'format' must come once, before the elements")
            if len(words) != 3 or words[1] not in _PLY_FORMATS:
                raise bad(f"expected 'format {' | '.join(_PLY_FORMATS)} 1.0'")
            if words[2] not in ("1.0", "1"):
                raise bad(f"unsupported PLY version {words[2]!r} (expected 1.0)")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not (words[2].isascii() and words[2].isdigit()):
                raise bad("expected 'element <name> <count>'")
            if any(e.name == words[1] for e in elements):
                raise bad(f"a second element {words[1]!r}")
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property":
            if not elements:
                raise bad("a property before any element")
            if len(words) == 3:
                count_type, item_type, name = None, words[1], words[2]
            elif len(words) == 5 and words[1] == "list":
                count_type, item_type, name = words[2], words[3], words[4]
            else:
                raise bad(
                    "expected 'property <type> <name>' or "
                    "'property list <length type> <item type> <name>'"
                )
            for t in (count_type, item_type):
                if t is not None and t not in _PLY_TYPES:
                    raise bad(f"unknown property type {t!r} (known: {', '.join(_PLY_TYPES)})")
            if count_type is not None and _PLY_TYPES[count_type][0] not in "iu":
                raise bad(f"a list's length type must be an integer type, not {count_type!r}")
            props = elements[-1].properties
            if any(p.name == name for p in props):
                raise bad(f"a second property {name!r} in element {elements[-1].name!r}")
            props.append(
                _PlyProperty(name, _PLY_TYPES[item_type], count_type and _PLY_TYPES[count_type])
            )
        else:
            raise bad(f"unknown keyword {words[0]!r}")
    if fmt is None:
        raise CloudFormatError(f"{path}: bad PLY header: no 'format' line")
    return _PLY_FORMATS[fmt], elements, min(end.end() + 1, len(raw))


def _ply_binary_vertex(
    path: Path,
    raw: bytes,
    start: int,
    byte_order: str,
    before: list[_PlyElement],
    vertex: _PlyElement,
) -> dict[str, np.ndarray]:
    """Binary: the elements before ``vertex`` skipped by size, its rows by ``np.frombuffer``."""
    offset = start
    for e in before:
        if e.has_lists:
            raise CloudFormatError(
                f"{path}: element {e.name!r} comes before 'vertex' and has list properties: "
                "skipping it in a binary PLY file is not supported"
            )
        offset += e.count * e.dtype(byte_order).itemsize
    if offset > len(raw):
        raise CloudFormatError(
            f"{path}: truncated: the elements before 'vertex' "
            f"({', '.join(e.name for e in before)}) take {offset - start} bytes, the file has "
            f"{len(raw) - start} after the header"
        )
    if vertex.has_lists:
        return _ply_binary_rows_with_lists(path, raw, offset, byte_order, vertex)
    dtype = vertex.dtype(byte_order)
    need = vertex.count * dtype.itemsize
    if len(raw) - offset < need:
        raise CloudFormatError(
            f"{path}: truncated: {vertex.count} vertices of {dtype.itemsize} bytes take {need} "
            f"bytes, the file has {len(raw) - offset}"
        )
    if vertex.count == 0 or not vertex.properties:
        return {p.name: np.empty(0, p.code) for p in vertex.properties}
    data = np.frombuffer(raw, dtype=dtype, count=vertex.count, offset=offset)
    return {p.name: _native(data[p.name]) for p in vertex.properties}


def _ply_binary_rows_with_lists(
    path: Path, raw: bytes, offset: int, byte_order: str, vertex: _PlyElement
) -> dict[str, np.ndarray]:
    """A binary ``vertex`` element with list properties: the rows differ in size, so they are
    walked in Python to find where each scalar value sits (slow, and rare in point clouds)."""
    steps = [
        (p.name, np.dtype(p.code).itemsize, None, 0)
        if p.count_code is None
        else (None, np.dtype(p.count_code).itemsize,
              struct.Struct(byte_order + _PLY_COUNT_STRUCT[p.count_code]),
              np.dtype(p.code).itemsize)
        for p in vertex.properties
    ]  # fmt: skip
    where: dict[str, list[int]] = {name: [] for name, _, _, _ in steps if name is not None}
    pos, size = offset, len(raw)
    for row in range(vertex.count):
        for name, step, length, item in steps:
            if length is None:
                where[name].append(pos)
                pos += step
                continue
            if pos + step > size:
                pos = size + 1
                break
            (n,) = length.unpack_from(raw, pos)
            if n < 0:
                raise CloudFormatError(f"{path}: vertex {row}: a list of negative length {n}")
            pos += step + n * item
        if pos > size:
            raise CloudFormatError(
                f"{path}: truncated: the data ends in vertex {row} of {vertex.count}"
            )
    buf = np.frombuffer(raw, dtype=np.uint8)
    columns = {}
    for p in vertex.properties:
        if p.count_code is None:
            dt = np.dtype(byte_order + p.code)
            idx = np.asarray(where[p.name], dtype=np.int64)[:, None] + np.arange(dt.itemsize)
            columns[p.name] = _native(buf[idx].reshape(-1).view(dt))
    return columns


def _ply_ascii_vertex(
    path: Path, raw: bytes, start: int, before: list[_PlyElement], vertex: _PlyElement
) -> dict[str, np.ndarray]:
    """Ascii: one row per line (blank lines are ignored); the lines of the elements before
    ``vertex`` are skipped, the vertex rows parsed with :func:`numpy.loadtxt`."""
    lines = raw[start:].decode("latin-1").split("\n")  # any other byte fails as a number
    i = 0
    for e in before:
        need = e.count if e.properties else 0  # a row of no values is a blank line
        while need and i < len(lines):
            need -= bool(lines[i].strip())
            i += 1
        if need:
            raise CloudFormatError(
                f"{path}: truncated: element {e.name!r} has {e.count} rows, the file holds "
                f"{e.count - need}"
            )
    scalars = [p for p in vertex.properties if p.count_code is None]
    if vertex.count == 0 or not scalars:
        return {p.name: np.empty(0, p.code) for p in scalars}
    if vertex.has_lists:
        cells = _ply_ascii_rows_with_lists(path, lines, i, vertex)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # about blank lines and max_rows
            try:
                table = np.loadtxt(
                    lines[i:], dtype=np.float64, comments=None, ndmin=2, max_rows=vertex.count
                )
            except ValueError as exc:
                problem = str(exc).split("; use `usecols`")[0]
                raise CloudFormatError(f"{path}: bad ascii vertex data: {problem}") from exc
        if len(table) < vertex.count:
            raise CloudFormatError(
                f"{path}: truncated: the header declares {vertex.count} vertices, the file holds "
                f"{len(table)}"
            )
        if table.shape[1] != len(scalars):
            raise CloudFormatError(
                f"{path}: the vertex rows have {table.shape[1]} values, the header declares "
                f"{len(scalars)} properties"
            )
        cells = {p.name: table[:, j] for j, p in enumerate(scalars)}
    return {p.name: _ply_ascii_column(path, p, cells[p.name]) for p in scalars}


def _ply_ascii_rows_with_lists(
    path: Path, lines: list[str], i: int, vertex: _PlyElement
) -> dict[str, np.ndarray]:
    """The scalar values of an ascii ``vertex`` element with list properties, row by row."""
    values: dict[str, list[str]] = {p.name: [] for p in vertex.properties if p.count_code is None}
    row = 0
    while row < vertex.count:
        if i >= len(lines):
            raise CloudFormatError(
                f"{path}: truncated: the header declares {vertex.count} vertices, the file holds "
                f"{row}"
            )
        words = lines[i].split()
        i += 1
        if not words:
            continue
        k, complete = 0, True
        for p in vertex.properties:
            if k >= len(words):
                complete = False
                break
            if p.count_code is None:
                values[p.name].append(words[k])
                k += 1
                continue
            try:
                n = int(words[k])
            except ValueError:
                n = -1
            if n < 0:
                raise CloudFormatError(
                    f"{path}: vertex {row}: list {p.name!r} has a bad length {words[k]!r}"
                )
            k += 1 + n
        if not complete or k != len(words):
            raise CloudFormatError(
                f"{path}: vertex {row}: the line has {len(words)} values, "
                + ("too few for its properties" if not complete else f"its properties take {k}")
            )
        row += 1
    columns = {}
    for name, cells in values.items():
        try:
            columns[name] = np.asarray(cells).astype(np.float64)
        except ValueError as exc:
            raise CloudFormatError(
                f"{path}: property {name!r} has a non-numeric value ({exc})"
            ) from exc
    return columns


def _ply_ascii_column(path: Path, prop: _PlyProperty, vals: np.ndarray) -> np.ndarray:
    """Float64 values read from text as the property's type (integers must be whole and in
    the type's range)."""
    if prop.code[0] in "iu":
        if not (np.all(np.isfinite(vals)) and np.all(vals == np.round(vals))):
            raise CloudFormatError(f"{path}: integer property {prop.name!r} has non-integer values")
        info = np.iinfo(prop.code)
        if len(vals) and (vals.min() < info.min or vals.max() > info.max):
            raise CloudFormatError(
                f"{path}: property {prop.name!r} has values outside the range of "
                f"{_PLY_NAMES[prop.code]} ({info.min}..{info.max})"
            )
    with np.errstate(over="ignore"):  # doubles beyond float32 become inf, as in C
        return vals.astype(prop.code)


def _text_rows(fields: list[tuple[str, np.ndarray]]) -> bytes:
    """One line per point, values separated by a space: floats ``%.9g``, integers ``%d``.

    (The rows go through Python numbers and one ``%`` format a row: 3 times faster than
    :func:`numpy.savetxt`, which formats numpy scalars, for the same text.)
    """
    table = np.empty(
        len(fields[0][1]), dtype=[(f"c{i}", a.dtype) for i, (_, a) in enumerate(fields)]
    )
    for i, (_, a) in enumerate(fields):
        table[f"c{i}"] = a
    row = " ".join("%.9g" if a.dtype.kind == "f" else "%d" for _, a in fields)
    return ("\n".join(map(row.__mod__, table.tolist())) + "\n").encode("ascii")


def _write_ply(path: Path, fields: list[tuple[str, np.ndarray]], binary: bool) -> None:
    """Write the ``vertex`` element: ``binary_little_endian``, or ascii (one row a line)."""
    n = len(fields[0][1])
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    header += ["comment written by ssp", f"element vertex {n}"]
    header += [f"property {_PLY_NAMES[a.dtype.str[1:]]} {name}" for name, a in fields]
    header.append("end_header")
    if binary:
        data = np.empty(n, dtype=[(name, "<" + a.dtype.str[1:]) for name, a in fields])
        for name, arr in fields:
            data[name] = arr
        body = data.tobytes()
    else:
        body = _text_rows(fields)
    atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + body)


# ------------------------------------------------------------------------------------ PCD
@dataclass
class _PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    points: int
    viewpoint: tuple[float, ...] | None
    data: str
    offset: int  # byte offset of the body

    def dtype(self) -> np.dtype:
        """The little-endian structured dtype of one point (``binary`` layout)."""
        return np.dtype(
            [
                (name, "<" + _PCD_DTYPES[(t, s)], (c,) if c > 1 else ())
                for name, t, s, c in zip(
                    self.fields, self.types, self.sizes, self.counts, strict=True
                )
            ]
        )


def _read_pcd(path: Path, raw: bytes) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Columns and viewpoint of a PCD file (ascii, binary or binary_compressed)."""
    h = _parse_pcd_header(path, raw)
    if h.points == 0:
        raise CloudFormatError(f"{path}: the cloud has zero points (POINTS 0)")
    body = raw[h.offset :]
    if h.data == "ascii":
        columns = _pcd_ascii(path, h, body)
    elif h.data == "binary":
        columns = _pcd_binary(path, h, body)
    else:
        columns = _pcd_compressed(path, h, body)
    columns = {n: c for n, c in columns.items() if not _PCD_PADDING.match(n)}
    return columns, _viewpoint_matrix(path, h.viewpoint)


def _parse_pcd_header(path: Path, raw: bytes) -> _PcdHeader:
    """Parse the header lines up to and including ``DATA``."""
    entries: dict[str, list[str]] = {}
    offset = 0
    for _ in range(_PCD_HEADER_MAX_LINES):
        end = raw.find(b"\n", offset)
        if end < 0:
            end = len(raw)
        try:
            line = raw[offset:end].decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise CloudFormatError(f"{path}: not a PCD file (header is not text)") from exc
        offset = end + 1
        if line and not line.startswith("#"):
            key, *values = line.split()
            entries[key.upper()] = values
            if key.upper() == "DATA":
                break
        if offset > len(raw):
            break
    if "DATA" not in entries:
        raise CloudFormatError(f"{path}: not a PCD file or its header is cut short (no DATA line)")
    return _pcd_header_from_entries(path, entries, offset)


def _pcd_header_from_entries(path: Path, entries: dict[str, list[str]], offset: int) -> _PcdHeader:
    """Check the header entries and build :class:`_PcdHeader`."""
    fields = entries.get("FIELDS") or entries.get("COLUMNS")
    for key, val in (
        ("FIELDS", fields),
        ("SIZE", entries.get("SIZE")),
        ("TYPE", entries.get("TYPE")),
    ):
        if not val:
            raise CloudFormatError(f"{path}: PCD header has no {key} line")
    n = len(fields)
    try:
        sizes = [int(v) for v in entries["SIZE"]]
        counts = [int(v) for v in entries.get("COUNT", ["1"] * n)]
        width = int(entries["WIDTH"][0]) if "WIDTH" in entries else None
        height = int(entries["HEIGHT"][0]) if "HEIGHT" in entries else 1
        points = int(entries["POINTS"][0]) if "POINTS" in entries else None
        viewpoint = (
            tuple(float(v) for v in entries["VIEWPOINT"]) if "VIEWPOINT" in entries else None
        )
    except (ValueError, IndexError) as exc:
        raise CloudFormatError(f"{path}: PCD header has a malformed number ({exc})") from exc
    types = [t.upper() for t in entries["TYPE"]]
    if not (len(sizes) == len(types) == len(counts) == n):
        raise CloudFormatError(
            f"{path}: PCD header lists {n} fields but {len(sizes)} sizes, {len(types)} types "
            f"and {len(counts)} counts"
        )
    for name, t, s, c in zip(fields, types, sizes, counts, strict=True):
        if (t, s) not in _PCD_DTYPES:
            raise CloudFormatError(f"{path}: field {name!r} has unsupported TYPE {t} SIZE {s}")
        if c < 1:
            raise CloudFormatError(f"{path}: field {name!r} has COUNT {c}")
    if points is None:
        if width is None:
            raise CloudFormatError(f"{path}: PCD header has neither POINTS nor WIDTH")
        points = width * height
    if points < 0:
        raise CloudFormatError(f"{path}: PCD header has POINTS {points}")
    if width is not None and width * height != points:
        log.debug(
            "%s: WIDTH x HEIGHT = %d but POINTS %d (POINTS used)", path, width * height, points
        )
    if viewpoint is not None and len(viewpoint) != 7:
        raise CloudFormatError(f"{path}: VIEWPOINT needs 7 numbers, got {len(viewpoint)}")
    data = entries["DATA"][0].lower() if entries["DATA"] else ""
    if data not in ("ascii", "binary", "binary_compressed"):
        raise CloudFormatError(
            f"{path}: unknown PCD DATA {data!r} (expected ascii, binary or binary_compressed)"
        )
    return _PcdHeader(
        fields=_unique_names(fields),
        sizes=sizes,
        types=types,
        counts=counts,
        points=points,
        viewpoint=viewpoint,
        data=data,
        offset=offset,
    )


def _unique_names(fields: list[str]) -> list[str]:
    """Field names made unique (PCD repeats the padding name ``_``)."""
    seen: dict[str, int] = {}
    out = []
    for name in fields:
        k = seen.get(name, 0)
        seen[name] = k + 1
        out.append(name if k == 0 else f"{name}{'' if name.startswith('_') else '_'}{k}")
    return out


def _pcd_binary(path: Path, h: _PcdHeader, body: bytes) -> dict[str, np.ndarray]:
    dtype = h.dtype()
    need = h.points * dtype.itemsize
    if len(body) < need:
        raise CloudFormatError(
            f"{path}: truncated: {h.points} points need {need} bytes of data, "
            f"the file has {len(body)}"
        )
    data = np.frombuffer(body, dtype=dtype, count=h.points)
    return {name: _native(data[name]) for name in h.fields}


def _pcd_compressed(path: Path, h: _PcdHeader, body: bytes) -> dict[str, np.ndarray]:
    """``binary_compressed``: sizes (2 x uint32), then LZF of the field-major columns."""
    if len(body) < 8:
        raise CloudFormatError(f"{path}: truncated: binary_compressed data has no size header")
    compressed, uncompressed = struct.unpack("<II", body[:8])
    itemsize = h.dtype().itemsize
    if uncompressed != h.points * itemsize:
        raise CloudFormatError(
            f"{path}: binary_compressed size {uncompressed} bytes does not match "
            f"{h.points} points of {itemsize} bytes"
        )
    if uncompressed > 100 * compressed + 1024:  # LZF cannot expand data that much
        raise CloudFormatError(
            f"{path}: corrupt binary_compressed sizes ({compressed} -> {uncompressed} bytes)"
        )
    if len(body) - 8 < compressed:
        raise CloudFormatError(
            f"{path}: truncated: {compressed} compressed bytes announced, {len(body) - 8} present"
        )
    buf = _lzf_decompress(path, body[8 : 8 + compressed], uncompressed)
    columns, offset = {}, 0
    for name, t, s, c in zip(h.fields, h.types, h.sizes, h.counts, strict=True):
        col = np.frombuffer(buf, dtype="<" + _PCD_DTYPES[(t, s)], count=h.points * c, offset=offset)
        offset += h.points * c * s
        columns[name] = _native(col.reshape(h.points, c) if c > 1 else col)
    return columns


def _lzf_decompress(path: Path, data: bytes, size: int) -> bytes:
    try:
        import lzf
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise CloudFormatError(
            f"{path}: binary_compressed PCD needs the lzf module (pip install python-neo-lzf)"
        ) from exc
    try:
        out = lzf.decompress(data, size)
    except (ValueError, SystemError) as exc:
        raise CloudFormatError(f"{path}: corrupt binary_compressed data ({exc})") from exc
    if out is None or len(out) != size:
        raise CloudFormatError(
            f"{path}: corrupt binary_compressed data (decompressed to "
            f"{0 if out is None else len(out)} bytes, expected {size})"
        )
    return out


def _pcd_ascii(path: Path, h: _PcdHeader, body: bytes) -> dict[str, np.ndarray]:
    """One point per line, values separated by white space, ``sum(COUNT)`` values a point."""
    try:
        tokens = body.decode("ascii").split()
    except UnicodeDecodeError as exc:
        raise CloudFormatError(f"{path}: ascii PCD data is not text") from exc
    ncols = sum(h.counts)
    if len(tokens) != h.points * ncols:
        what = "truncated" if len(tokens) < h.points * ncols else "too much data"
        raise CloudFormatError(
            f"{path}: {what}: the header says {h.points} points of {ncols} values "
            f"({h.points * ncols} values), the file has {len(tokens)}"
        )
    table = np.asarray(tokens).reshape(h.points, ncols)
    columns, j = {}, 0
    for name, t, s, c in zip(h.fields, h.types, h.sizes, h.counts, strict=True):
        cells = table[:, j : j + c]
        j += c
        if name.lower() in _PACKED_COLOR_FIELDS and c == 1 and s == 4:
            columns[name] = _ascii_packed_color(path, name, cells[:, 0])
            continue
        columns[name] = _ascii_numbers(path, name, cells, _PCD_DTYPES[(t, s)], c)
    return columns


def _ascii_numbers(path: Path, name: str, cells: np.ndarray, code: str, count: int) -> np.ndarray:
    try:
        vals = cells.astype(np.float64)
    except ValueError as exc:
        raise CloudFormatError(f"{path}: field {name!r} has a non-numeric value ({exc})") from exc
    if code[0] in "ui":
        if not np.all(np.isfinite(vals)) or not np.all(vals == np.round(vals)):
            raise CloudFormatError(f"{path}: integer field {name!r} has non-integer values")
        vals = vals.astype(np.int64)
    return vals if count > 1 else vals[:, 0]


def _ascii_packed_color(path: Path, name: str, cells: np.ndarray) -> np.ndarray:
    """Packed colour bits from ascii: PCL writes the uint32 as an integer even for TYPE F;
    other writers (Open3D) print the float32. Whole numbers in ``[0, 2**32)`` with at least one
    ``>= 1`` are taken as the integer (a packed colour with alpha 0 is a float below 1e-37)."""
    try:
        vals = cells.astype(np.float64)
    except ValueError as exc:
        raise CloudFormatError(f"{path}: field {name!r} has a non-numeric value ({exc})") from exc
    finite = np.isfinite(vals)
    whole = finite.all() and np.all(vals == np.round(vals)) and vals.min() >= 0
    if whole and vals.max() >= 1 and vals.max() < 2**32:
        return vals.astype(np.uint32)
    return vals.astype(np.float32).view(np.uint32)


def _native(col: np.ndarray) -> np.ndarray:
    """A native-byte-order, writable copy."""
    return np.ascontiguousarray(col).astype(col.dtype.newbyteorder("="))


def _viewpoint_matrix(path: Path, vp: tuple[float, ...] | None) -> np.ndarray | None:
    """4x4 pose of ``VIEWPOINT tx ty tz qw qx qy qz``; None if absent, identity or unusable."""
    if vp is None or np.allclose(vp, _PCD_VIEWPOINT_IDENTITY, atol=1e-12):
        return None
    t, (qw, qx, qy, qz) = np.asarray(vp[:3]), vp[3:]
    q = np.array([qx, qy, qz, qw])
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t)) and np.linalg.norm(q) > 1e-9):
        log.warning("%s: ignoring unusable VIEWPOINT %s", path, " ".join(map(str, vp)))
        return None
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    T[:3, 3] = t
    return T


def _write_pcd(path: Path, fields: list[tuple[str, np.ndarray]], binary: bool) -> None:
    """Write an unorganised PCD (``HEIGHT 1``); ``rgb`` float32 columns hold packed bits."""
    n = len(fields[0][1])
    types, sizes = [], []
    for _, arr in fields:
        kind = {"f": "F", "u": "U", "i": "I"}[arr.dtype.kind]
        types.append(kind)
        sizes.append(str(arr.dtype.itemsize))
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by ssp)\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(name for name, _ in fields)}\n"
        f"SIZE {' '.join(sizes)}\n"
        f"TYPE {' '.join(types)}\n"
        f"COUNT {' '.join('1' for _ in fields)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    if binary:
        data = np.empty(n, dtype=[(name, "<" + arr.dtype.str[1:]) for name, arr in fields])
        for name, arr in fields:
            data[name] = arr
        body = data.tobytes()
    else:  # PCL's convention for rgb: the packed bits as an unsigned integer
        body = _text_rows([(f, a.view(np.uint32) if f == "rgb" else a) for f, a in fields])
    atomic_write_bytes(path, header.encode("ascii") + body)


# ------------------------------------------------------------------------------------ writing
def write_cloud(
    path: str | os.PathLike,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    binary: bool = True,
) -> Path:
    """Write a cloud as ``.ply`` or ``.pcd`` (by the extension), atomically.

    Args:
        points: ``(N, 3)`` m, stored as float32 (N >= 1; NaN rows allowed).
        colors: ``(N, 3)`` integers 0..255: PLY ``red green blue`` (uchar); PCD a packed
            float32 ``rgb`` (alpha 0; ascii files hold its uint32 value, as PCL writes it).
        labels: ``(N,)`` integers as ``label``: uint32 when all are >= 0, else int32.
        normals: ``(N, 3)``: PLY ``nx ny nz``, PCD ``normal_x normal_y normal_z`` (float32).
        binary: PLY ``binary_little_endian`` / PCD ``binary``; False: ascii.

    Returns:
        The path. Raises ValueError on arrays of the wrong shape or range,
        :class:`CloudFormatError` on an unknown extension.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise CloudFormatError(
            f"{p}: unknown point-cloud extension {p.suffix!r} (expected .ply or .pcd)"
        )
    pts = _array(points, "points", (None, 3), np.float32)
    n = len(pts)
    if n == 0:
        raise ValueError("points: cannot write a cloud of zero points")
    ply = suffix == ".ply"
    fields: list[tuple[str, np.ndarray]] = [("x", pts[:, 0]), ("y", pts[:, 1]), ("z", pts[:, 2])]
    if normals is not None:
        nrm = _array(normals, "normals", (n, 3), np.float32)
        names = ("nx", "ny", "nz") if ply else ("normal_x", "normal_y", "normal_z")
        fields += [(name, nrm[:, i]) for i, name in enumerate(names)]
    if colors is not None:
        rgb = _color_array(colors, n)
        if ply:
            fields += [(name, rgb[:, i]) for i, name in enumerate(("red", "green", "blue"))]
        else:
            c = rgb.astype(np.uint32)
            fields.append(("rgb", ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)))
    if labels is not None:
        fields.append(("label", _label_array(labels, n)))
    (_write_ply if ply else _write_pcd)(p, fields, binary)
    return p


def _array(values, what: str, shape: tuple[int | None, int], dtype) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not a numeric array ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != shape[1] or (shape[0] is not None and len(arr) != shape[0]):
        want = f"({'N' if shape[0] is None else shape[0]}, {shape[1]})"
        raise ValueError(f"{what}: expected shape {want}, got {arr.shape}")
    return arr.astype(dtype)


def _color_array(colors, n: int) -> np.ndarray:
    arr = _array(colors, "colors", (n, 3), np.float64)
    if not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 255:
        raise ValueError("colors: values must be finite integers in 0..255")
    if not np.all(arr == np.round(arr)):
        raise ValueError("colors: values must be integers 0..255 (not floats 0..1)")
    return arr.astype(np.uint8)


def _label_array(labels, n: int) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.shape != (n,):
        raise ValueError(f"labels: expected shape ({n},), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        f = arr.astype(np.float64)
        if not (np.all(np.isfinite(f)) and np.all(f == np.round(f))):
            raise ValueError("labels: values must be integers")
        arr = f.astype(np.int64)
    arr = arr.astype(np.int64)
    if arr.min() >= 0 and arr.max() <= np.iinfo(np.uint32).max:
        return arr.astype(np.uint32)
    if arr.min() >= np.iinfo(np.int32).min and arr.max() <= np.iinfo(np.int32).max:
        return arr.astype(np.int32)
    raise ValueError("labels: values must fit in 32 bits")
