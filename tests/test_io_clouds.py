"""Point-cloud files: PLY and PCD round trips, field conventions, and corrupt files."""

from __future__ import annotations

import struct

import lzf
import numpy as np
import plyfile
import pytest
from scipy.spatial.transform import Rotation

from ssp.errors import CloudFormatError
from ssp.io.clouds import read_cloud, write_cloud

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


def _ply(path, data: np.ndarray, text=False, byte_order="<", extra=()):
    elements = [plyfile.PlyElement.describe(data, "vertex"), *extra]
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(str(path))
    return path


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
    faces = np.array([([0, 1, 1],)], dtype=[("vertex_indices", "i4", (3,))])
    c = read_cloud(
        _ply(tmp_path / "m.ply", data, extra=[plyfile.PlyElement.describe(faces, "face")])
    )
    np.testing.assert_array_equal(c.colors, [[0, 128, 255], [255, 51, 0]])


@pytest.mark.parametrize("first", ["vertex", "camera"])
def test_ply_ascii_layouts_agree(tmp_path, first):
    """The numpy fast path (vertex first) and plyfile (another element first) agree."""
    data = np.empty(N, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"),
                              ("blue", "u1"), ("label", "i4")])  # fmt: skip
    data["x"], data["y"], data["z"] = POINTS.T
    data["red"], data["green"], data["blue"] = COLORS.T
    data["label"] = LABELS
    faces = plyfile.PlyElement.describe(
        np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))]), "face"
    )
    cam = plyfile.PlyElement.describe(np.array([(1.5,)], dtype=[("f", "f4")]), "camera")
    elements = [plyfile.PlyElement.describe(data, "vertex"), faces]
    if first == "camera":
        elements.insert(0, cam)
    plyfile.PlyData(elements, text=True).write(str(tmp_path / "a.ply"))
    c = read_cloud(tmp_path / "a.ply")
    np.testing.assert_allclose(c.points, POINTS, rtol=1e-15)
    np.testing.assert_array_equal(c.colors, COLORS)
    np.testing.assert_array_equal(c.labels, LABELS)


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
