"""Point-cloud files: PLY and PCD round trips, field conventions, and corrupt files."""

from __future__ import annotations

import struct

import lzf
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.errors import CloudFormatError
from ssp.io.clouds import _read_ply, read_cloud, write_cloud

RNG = np.random.default_rng(7)
N = 50
POINTS = RNG.uniform(-1.0, 1.0, (N, 3))
COLORS = RNG.integers(0, 256, (N, 3)).astype(np.uint8)
LABELS = RNG.integers(-1, 6, N)
NORMALS = RNG.normal(size=(N, 3))


def _pcd_header(fields, sizes, types, counts, n, data, viewpoint="0 0 0 1 0 0 0") -> bytes:
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT {viewpoint}\nPOINTS {n}\nDATA {data}\n"
    ).encode()


def _packed(rgb: np.ndarray, alpha: int = 0) -> np.ndarray:
    c = rgb.astype(np.uint32)
    return (np.uint32(alpha) << 24) | (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]


_PLY_TYPE = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
             "u4": "uint", "f4": "float", "f8": "double"}  # fmt: skip
_PLY_ALIAS = {"i1": "int8", "u1": "uint8", "i2": "int16", "u2": "uint16", "i4": "int32",
              "u4": "uint32", "f4": "float32", "f8": "float64"}  # fmt: skip
FACES = ("face", [("vertex_indices", [np.array([0, 1, 2], "i4"), np.array([2, 1, 0, 3], "i4")])])


def _ply(path, data: np.ndarray, text=False, byte_order="<", before=(), after=(), aliases=False):
    """Write a PLY file by hand, independently of ``write_cloud``: ``data`` (a structured array)
    is the ``vertex`` element; ``before`` / ``after`` are other elements as ``(name, [(property,
    values)])``, values an array (a scalar property) or a list of arrays (a list property with
    uchar lengths)."""
    names = _PLY_ALIAS if aliases else _PLY_TYPE
    fmt = "ascii" if text else {"<": "binary_little_endian", ">": "binary_big_endian"}[byte_order]
    elements = [*before, ("vertex", [(n, data[n]) for n in data.dtype.names]), *after]
    head = ["ply", f"format {fmt} 1.0", "comment hand-made test file", "obj_info test"]
    body = []
    for name, props in elements:
        n = len(props[0][1])
        head.append(f"element {name} {n}")
        for prop, vals in props:
            if isinstance(vals, np.ndarray):
                head.append(f"property {names[vals.dtype.str[1:]]} {prop}")
            else:
                head.append(f"property list uchar {names[vals[0].dtype.str[1:]]} {prop}")
        for i in range(n):
            row = [v[i : i + 1] if isinstance(v, np.ndarray) else v[i] for _, v in props]
            row = [r if isinstance(v, np.ndarray) else (np.array([len(r)], "u1"), r)
                   for r, (_, v) in zip(row, props, strict=True)]  # fmt: skip
            cells = [c for r in row for c in (r if isinstance(r, tuple) else (r,))]
            if text:
                body.append(" ".join(repr(x) for c in cells for x in c.tolist()).encode() + b"\n")
            else:
                body += [c.astype(byte_order + c.dtype.str[1:]).tobytes() for c in cells]
    path.write_bytes(("\n".join(head) + "\nend_header\n").encode() + b"".join(body))
    return path


def _vertices(n=N, xyz="f8", **extra) -> np.ndarray:
    """``POINTS[:n]`` as ``x y z`` of type ``xyz`` plus ``extra`` fields (name=(type, values))."""
    dt = [(k, xyz) for k in "xyz"] + [(k, t) for k, (t, _) in extra.items()]
    data = np.empty(n, dtype=dt)
    data["x"], data["y"], data["z"] = POINTS[:n].T
    for k, (_, v) in extra.items():
        data[k] = v[:n]
    return data


# ------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("ext", ["ply", "pcd"])
@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_all_fields(tmp_path, ext, binary):
    path = write_cloud(tmp_path / f"c.{ext}", POINTS, COLORS, LABELS, NORMALS, binary=binary)
    c = read_cloud(path)
    assert c.points.dtype == np.float64 and c.points.shape == (N, 3)
    np.testing.assert_allclose(c.points, POINTS, atol=1e-6)  # stored as float32
    np.testing.assert_array_equal(c.colors, COLORS)
    assert c.colors.dtype == np.uint8
    np.testing.assert_array_equal(c.labels, LABELS)
    assert c.labels.dtype == np.int64 and c.label_field == "label"
    np.testing.assert_allclose(c.normals, NORMALS, rtol=1e-6, atol=1e-6)
    assert c.viewpoint is None
    assert c.fields[:3] == ("x", "y", "z") and len(c) == N


@pytest.mark.parametrize("ext", ["ply", "pcd"])
def test_round_trip_points_only_and_nan_kept(tmp_path, ext):
    pts = POINTS.copy()
    pts[3] = np.nan
    pts[4, 0] = np.inf
    c = read_cloud(write_cloud(tmp_path / f"c.{ext}", pts))
    assert c.colors is None and c.labels is None and c.normals is None
    assert np.isnan(c.points[3]).all() and np.isinf(c.points[4, 0])
    np.testing.assert_allclose(c.points[5:], pts[5:], atol=1e-6)


def test_pcd_ascii_label_signs(tmp_path):
    c = read_cloud(write_cloud(tmp_path / "c.pcd", POINTS[:3], labels=[3, 0, 7], binary=False))
    np.testing.assert_array_equal(c.labels, [3, 0, 7])
    assert "label" in (tmp_path / "c.pcd").read_text()


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_binary_endianness(tmp_path, byte_order):
    data = np.empty(N, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("instance", "i4")])
    data["x"], data["y"], data["z"] = POINTS.T
    data["instance"] = LABELS
    c = read_cloud(_ply(tmp_path / "c.ply", data, byte_order=byte_order))
    np.testing.assert_array_equal(c.points, POINTS)  # float64 in the file: exact
    np.testing.assert_array_equal(c.labels, LABELS)
    assert c.label_field == "instance"


def test_ply_rgb_short_names_float_colors_and_mesh(tmp_path):
    data = np.empty(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")] + [(k, "f4") for k in "rgb"])
    data["x"], data["y"], data["z"] = 0.0, 0.5, 1.0
    data["r"], data["g"], data["b"] = [0.0, 1.0], [0.5, 0.2], [1.0, 0.0]
    c = read_cloud(_ply(tmp_path / "m.ply", data, after=[FACES]))
    np.testing.assert_array_equal(c.colors, [[0, 128, 255], [255, 51, 0]])


@pytest.mark.parametrize("first", ["vertex", "camera"])
def test_ply_ascii_layouts_agree(tmp_path, first):
    """Vertex first, or after another element (whose lines are skipped): the same cloud."""
    data = _vertices(red=("u1", COLORS[:, 0]), green=("u1", COLORS[:, 1]),
                     blue=("u1", COLORS[:, 2]), label=("i4", LABELS))  # fmt: skip
    cam = ("camera", [("f", np.array([1.5], "f4")), ("k", [np.array([1, 2], "i2")])])
    before = [cam] if first == "camera" else []
    c = read_cloud(_ply(tmp_path / "a.ply", data, text=True, before=before, after=[FACES]))
    np.testing.assert_allclose(c.points, POINTS, rtol=1e-15)
    np.testing.assert_array_equal(c.colors, COLORS)
    np.testing.assert_array_equal(c.labels, LABELS)


@pytest.mark.parametrize("fmt", ["<", ">", "ascii"])
@pytest.mark.parametrize("aliases", [False, True], ids=["names", "aliases"])
def test_ply_every_scalar_type(tmp_path, fmt, aliases):
    """Every PLY type, by its name or its alias, reads with its own numpy type and exact values."""
    rng = np.random.default_rng(1)
    extra = {}
    for code in _PLY_TYPE:
        if code[0] == "f":
            vals = rng.normal(size=N).astype(code) * 1000
        else:
            info = np.iinfo(code)
            vals = rng.integers(info.min, int(info.max) + 1, N, dtype=np.int64).astype(code)
            vals[:2] = info.min, info.max
        extra[f"p_{code}"] = (code, vals)
    data = _vertices(**extra)
    path = _ply(tmp_path / "t.ply", data, text=fmt == "ascii", byte_order=fmt[0], aliases=aliases)
    assert read_cloud(path).fields == data.dtype.names
    columns = _read_ply(path, path.read_bytes())  # the columns themselves, not only the Cloud
    for code in _PLY_TYPE:
        col = columns[f"p_{code}"]
        assert col.dtype == np.dtype(code) and col.dtype.isnative
        np.testing.assert_array_equal(col, extra[f"p_{code}"][1])


@pytest.mark.parametrize("fmt", ["<", ">", "ascii"])
def test_ply_double_coordinates_exact(tmp_path, fmt):
    pts = POINTS.copy()
    pts[0] = [1e-300, -1e300, np.pi]
    pts[1] = np.nan
    data = np.empty(N, dtype=[(k, "f8") for k in "xyz"])
    data["x"], data["y"], data["z"] = pts.T
    c = read_cloud(_ply(tmp_path / "d.ply", data, text=fmt == "ascii", byte_order=fmt[0]))
    assert c.points.dtype == np.float64
    np.testing.assert_array_equal(c.points, pts)  # float64 in the file: bit for bit


@pytest.mark.parametrize("fmt", ["<", ">", "ascii"])
def test_ply_scalar_element_before_and_faces_after(tmp_path, fmt):
    data = _vertices(xyz="f4", nx=("f4", NORMALS[:, 0]), ny=("f4", NORMALS[:, 1]),
                     nz=("f4", NORMALS[:, 2]), instance=("i2", LABELS))  # fmt: skip
    camera = ("camera", [("fx", np.array([525.0, 1.0, 2.0])), ("w", np.array([640, 1, 2], "u2")),
                         ("flag", np.array([1, 0, 1], "i1"))])  # fmt: skip
    path = _ply(tmp_path / "s.ply", data, text=fmt == "ascii", byte_order=fmt[0], before=[camera],
                after=[FACES])  # fmt: skip
    c = read_cloud(path)
    np.testing.assert_array_equal(c.points, POINTS.astype("f4"))
    np.testing.assert_array_equal(c.normals, NORMALS.astype("f4"))
    np.testing.assert_array_equal(c.labels, LABELS)
    assert c.label_field == "instance" and c.fields == data.dtype.names


@pytest.mark.parametrize("fmt", ["<", ">", "ascii"])
def test_ply_list_property_in_vertex_is_skipped(tmp_path, fmt):
    lists = [np.arange(i % 4, dtype="i4") for i in range(N)]
    data = _vertices(xyz="f4")
    text = fmt == "ascii"
    path = tmp_path / "l.ply"
    _ply(path, data, text=text, byte_order=fmt[0], after=[FACES])
    # the same vertex element with a list property between y and z, built on the first file
    head, body = path.read_bytes().split(b"end_header\n")
    head = head.replace(b"property float z", b"property list uchar int idx\nproperty float z")
    rows = []
    for i, lst in enumerate(lists):
        x, y, z = (data[k][i : i + 1] for k in "xyz")
        cells = [x, y, np.array([len(lst)], "u1"), lst, z]
        if text:
            rows.append(" ".join(repr(v) for cell in cells for v in cell.tolist()).encode() + b"\n")
        else:
            rows += [cell.astype(fmt + cell.dtype.str[1:]).tobytes() for cell in cells]
    faces = body[N * 12 :] if not text else b"".join(body.splitlines(True)[N:])
    path.write_bytes(head + b"end_header\n" + b"".join(rows) + faces)
    c = read_cloud(path)
    np.testing.assert_array_equal(c.points, POINTS.astype("f4"))
    assert c.fields == ("x", "y", "z")
    cut = b"".join(rows[:-1]) if text else b"".join(rows)[:-3]  # the last vertex incomplete
    path.write_bytes(head + b"end_header\n" + cut)
    _assert_bad(path, "truncated")


def test_ply_list_element_before_vertex(tmp_path):
    material = ("material", [("ids", [np.array([1, 2, 3], "i4")]), ("s", np.array([9], "i4"))])
    data = _vertices()
    c = read_cloud(_ply(tmp_path / "a.ply", data, text=True, before=[material]))
    np.testing.assert_allclose(c.points, POINTS, rtol=1e-15)  # ascii: its lines are skipped
    for bo in "<>":
        _assert_bad(_ply(tmp_path / "b.ply", data, byte_order=bo, before=[material]),
                    "'material'.*list properties.*not supported")  # fmt: skip


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_truncated_binary(tmp_path, byte_order):
    camera = ("camera", [("fx", np.array([525.0, 1.0]))])
    path = _ply(tmp_path / "t.ply", _vertices(), byte_order=byte_order, before=[camera])
    full = path.read_bytes()
    vertex_bytes = N * 24
    path.write_bytes(full[:-1])
    _assert_bad(path, rf"truncated: {N} vertices of 24 bytes take {vertex_bytes} bytes")
    path.write_bytes(full[: -vertex_bytes - 1])  # inside the camera element
    _assert_bad(path, "truncated: the elements before 'vertex' \\(camera\\)")
    path.write_bytes(full[: full.index(b"end_header") + 5])  # inside the header
    _assert_bad(path, "no 'end_header'")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ((b"format ascii 1.0\n", b""), "no 'format' line"),
        ((b"ascii 1.0", b"ascii 2.0"), "unsupported PLY version"),
        ((b"ascii 1.0", b"binary_middle_endian 1.0"), "expected 'format"),
        ((b"float z", b"half z"), "unknown property type 'half'"),
        ((b"float z", b"list float int z"), "length type must be an integer"),
        ((b"float z", b"float x"), "a second property 'x'"),
        ((b"vertex 2", b"vertex -2"), "expected 'element <name> <count>'"),
        ((b"vertex 2", b"point 2"), "no 'vertex' element \\(elements: point\\)"),
        ((b"end_header", b"weird line\nend_header"), "unknown keyword 'weird'"),
        ((b"ply\n", b"plx\n"), "not a PLY file"),
        ((b"4 5 6\n", b""), "truncated: the header declares 2 vertices, the file holds 1"),
        ((b"4 5 6", b"4 5"), "number of columns changed"),
        ((b"4 5 6", b"4 x 6"), "could not convert string 'x'"),
        ((b"float z", b"uchar z"), None),  # 3 and 6: fine as uchar
        ((b"4 5 6", b"4 5 6.5"), "integer property 'z' has non-integer values"),
        ((b"4 5 6", b"4 5 256"), "outside the range of uchar"),
    ],
)
def test_ply_bad_header_and_ascii_data(tmp_path, change, match):
    text = (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n1 2 3\n4 5 6\n")  # fmt: skip
    if change[1] in (b"4 5 6.5", b"4 5 256"):
        text = text.replace(b"float z", b"uchar z")
    p = tmp_path / "h.ply"
    p.write_bytes(text.replace(*change))
    if match is None:
        np.testing.assert_array_equal(read_cloud(p).points, [[1, 2, 3], [4, 5, 6]])
    else:
        _assert_bad(p, match)


def test_ply_crlf_blank_lines_and_comments(tmp_path):
    p = tmp_path / "w.ply"
    p.write_bytes(b"ply\r\ncomment made on windows\r\nformat ascii 1.0\r\nobj_info x\r\n"
                  b"element vertex 2\r\nproperty double x\r\nproperty double y\r\n"
                  b"property double z\r\nend_header\r\n1 2 3\r\n\r\n4\t5 6\r\n")  # fmt: skip
    np.testing.assert_array_equal(read_cloud(p).points, [[1, 2, 3], [4, 5, 6]])


def test_ply_written_header_and_body(tmp_path):
    """``write_cloud`` writes a plain little-endian vertex element (readable by any PLY reader)."""
    p = write_cloud(tmp_path / "w.ply", POINTS[:3], COLORS[:3], [1, 2, 3])
    head, body = p.read_bytes().split(b"end_header\n")
    assert head.decode().splitlines() == [
        "ply", "format binary_little_endian 1.0", "comment written by ssp", "element vertex 3",
        "property float x", "property float y", "property float z", "property uchar red",
        "property uchar green", "property uchar blue", "property uint label",
    ]  # fmt: skip
    dtype = [(k, "<f4") for k in "xyz"] + [(k, "u1") for k in ("red", "green", "blue")]
    rows = np.frombuffer(body, dtype=[*dtype, ("label", "<u4")])
    np.testing.assert_array_equal(rows["y"], POINTS[:3, 1].astype("f4"))
    np.testing.assert_array_equal(rows["label"], [1, 2, 3])


def test_label_field_order_and_float_labels(tmp_path):
    dt = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("segment", "i4"), ("object", "f4")]
    data = np.zeros(3, dtype=dt)
    data["segment"], data["object"] = [1, 2, 3], [4.0, 5.0, -1.0]
    c = read_cloud(_ply(tmp_path / "c.ply", data, text=True))
    assert c.label_field == "object"  # "object" comes before "segment"
    np.testing.assert_array_equal(c.labels, [4, 5, -1])
    data["object"][0] = 0.5
    with pytest.raises(CloudFormatError, match="non-integer"):
        read_cloud(_ply(tmp_path / "bad.ply", data))


def test_pcd_pcl_ascii_rgb_integer_with_alpha(tmp_path):
    rgb = np.array([[10, 20, 30], [255, 128, 0]], dtype=np.uint8)
    vals = _packed(rgb, alpha=255)  # PCL writes the uint32 even though TYPE is F
    body = "".join(f"{i} {i} {i} {v}\n" for i, v in enumerate(vals))
    p = tmp_path / "pcl.pcd"
    p.write_bytes(
        _pcd_header("x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1", 2, "ascii") + body.encode()
    )
    np.testing.assert_array_equal(read_cloud(p).colors, rgb)


def test_pcd_float_text_rgb(tmp_path):
    rgb = np.array([[10, 20, 30], [255, 128, 0]], dtype=np.uint8)
    floats = _packed(rgb).view(np.float32)  # Open3D prints the float (alpha 0: tiny numbers)
    body = "".join(f"0 0 1 {v:.9g}\n" for v in floats)
    p = tmp_path / "o3d.pcd"
    p.write_bytes(
        _pcd_header("x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1", 2, "ascii") + body.encode()
    )
    np.testing.assert_array_equal(read_cloud(p).colors, rgb)


def test_pcd_binary_rgba_uint_and_viewpoint(tmp_path):
    rgb = COLORS[:4]
    data = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "<u4")])
    data["x"], data["y"], data["z"] = POINTS[:4].T
    data["rgba"] = _packed(rgb, alpha=255)
    q_xyzw = Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_quat()
    vp = f"0.1 0.2 0.3 {q_xyzw[3]} {q_xyzw[0]} {q_xyzw[1]} {q_xyzw[2]}"  # tx ty tz qw qx qy qz
    p = tmp_path / "b.pcd"
    p.write_bytes(
        _pcd_header("x y z rgba", "4 4 4 4", "F F F U", "1 1 1 1", 4, "binary", vp) + data.tobytes()
    )
    c = read_cloud(p)
    np.testing.assert_array_equal(c.colors, rgb)
    np.testing.assert_allclose(
        c.viewpoint[:3, :3], Rotation.from_quat(q_xyzw).as_matrix(), atol=1e-9
    )
    np.testing.assert_allclose(c.viewpoint[:3, 3], [0.1, 0.2, 0.3])


def _compressed_pcd(path, n=N, cut=0):
    """A binary_compressed PCD built by hand (field-major, as PCL writes it), with a padding
    field and a field of COUNT 2."""
    cols = [
        POINTS[:n, 0].astype("<f4"),
        POINTS[:n, 1].astype("<f4"),
        POINTS[:n, 2].astype("<f4"),
        np.zeros(n, "<u1"),
        _packed(COLORS[:n]).view("<f4"),
        np.arange(2 * n, dtype="<f4").reshape(n, 2),
        LABELS[:n].astype("<i4"),
    ]
    raw = b"".join(np.ascontiguousarray(c).tobytes() for c in cols)
    comp = lzf.compress(raw)
    header = _pcd_header(
        "x y z _ rgb extra label",
        "4 4 4 1 4 4 4",
        "F F F U F F I",
        "1 1 1 1 1 2 1",
        n,
        "binary_compressed",
    )
    blob = header + struct.pack("<II", len(comp), len(raw)) + comp
    path.write_bytes(blob[: len(blob) - cut])
    return path


def test_pcd_binary_compressed(tmp_path):
    c = read_cloud(_compressed_pcd(tmp_path / "c.pcd"))
    np.testing.assert_allclose(c.points, POINTS, atol=1e-6)
    np.testing.assert_array_equal(c.colors, COLORS)
    np.testing.assert_array_equal(c.labels, LABELS)
    assert c.fields == ("x", "y", "z", "rgb", "extra", "label")


# ------------------------------------------------------------------------------ bad files
def _assert_bad(path, match=None):
    with pytest.raises(CloudFormatError, match=match) as err:
        read_cloud(path)
    assert str(path) in str(err.value)


def test_unknown_extension_missing_and_empty(tmp_path):
    (tmp_path / "c.xyz").write_text("1 2 3\n")
    _assert_bad(tmp_path / "c.xyz", "extension")
    _assert_bad(tmp_path / "missing.ply", "no such file")
    (tmp_path / "e.pcd").write_bytes(b"")
    _assert_bad(tmp_path / "e.pcd", "empty")
    with pytest.raises(CloudFormatError, match="extension"):
        write_cloud(tmp_path / "c.txt", POINTS)


def test_no_xyz_and_zero_points(tmp_path):
    data = np.zeros(3, dtype=[("a", "f4"), ("b", "f4"), ("c", "f4")])
    _assert_bad(_ply(tmp_path / "noxyz.ply", data), "no x, y, z")
    empty = np.zeros(0, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    _assert_bad(_ply(tmp_path / "zero.ply", empty), "zero points")
    p = tmp_path / "zero.pcd"
    p.write_bytes(_pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 0, "binary"))
    _assert_bad(p, "zero points")
    p = tmp_path / "noxyz.pcd"
    p.write_bytes(_pcd_header("a b c", "4 4 4", "F F F", "1 1 1", 1, "ascii") + b"1 2 3\n")
    _assert_bad(p, "no x, y, z")


def test_non_numeric_and_garbage(tmp_path):
    p = tmp_path / "t.pcd"
    p.write_bytes(_pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 1, "ascii") + b"1 2 abc\n")
    _assert_bad(p, "non-numeric")
    p = tmp_path / "t.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n1 2 abc\n")  # fmt: skip
    _assert_bad(p)
    for name in ("g.ply", "g.pcd"):
        (tmp_path / name).write_bytes(bytes(range(256)) * 8)
        _assert_bad(tmp_path / name)
    p = tmp_path / "f16.pcd"
    p.write_bytes(_pcd_header("x y z", "2 2 2", "F F F", "1 1 1", 1, "binary") + b"\0" * 6)
    _assert_bad(p, "unsupported TYPE")
    p = tmp_path / "count.pcd"
    p.write_bytes(_pcd_header("x y z", "4 4 4", "F F F", "3 1 1", 1, "ascii") + b"1 2 3 4 5\n")
    _assert_bad(p, "values per point")


@pytest.mark.parametrize(
    "make",
    [
        lambda d: write_cloud(d / "b.ply", POINTS, COLORS, LABELS),
        lambda d: write_cloud(d / "b.pcd", POINTS, COLORS, LABELS),
        lambda d: _compressed_pcd(d / "c.pcd"),
    ],
    ids=["ply-binary", "pcd-binary", "pcd-compressed"],
)
def test_every_truncation_of_a_binary_file_is_reported(tmp_path, make):
    full = make(tmp_path).read_bytes()
    p = tmp_path / ("t" + make(tmp_path).suffix)
    for cut in range(1, len(full), 11):
        p.write_bytes(full[: len(full) - cut])
        with pytest.raises(CloudFormatError):
            read_cloud(p)


@pytest.mark.parametrize("ext", ["ply", "pcd"])
def test_truncated_ascii_never_crashes(tmp_path, ext):
    full = write_cloud(tmp_path / f"a.{ext}", POINTS[:5], COLORS[:5], LABELS[:5], binary=False)
    data = full.read_bytes()
    p = tmp_path / f"t.{ext}"
    for cut in range(1, len(data), 7):
        p.write_bytes(data[: len(data) - cut])
        try:
            read_cloud(p)
        except CloudFormatError:
            pass


def test_truncated_ascii_pcd_rows_reported(tmp_path):
    p = tmp_path / "t.pcd"
    p.write_bytes(_pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 3, "ascii") + b"1 2 3\n4 5 6\n")
    _assert_bad(p, "truncated")


def test_write_rejects_bad_arrays(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_cloud(tmp_path / "a.ply", np.zeros((4, 2)))
    with pytest.raises(ValueError, match="zero points"):
        write_cloud(tmp_path / "a.ply", np.zeros((0, 3)))
    with pytest.raises(ValueError, match="0..255"):
        write_cloud(tmp_path / "a.ply", POINTS, colors=COLORS * 2.0)
    with pytest.raises(ValueError, match="labels"):
        write_cloud(tmp_path / "a.pcd", POINTS, labels=np.zeros(N - 1))
