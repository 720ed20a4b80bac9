"""Bad inputs that crashed, hung or passed silently (issue 35), in the outcomes of the
bad-input matrix (tests/test_bad_input.py): an **error** (the input as a whole: a typed
:class:`SSPError` naming the file and the problem), a **skipped frame** (reported failed with
the file and the problem, the other frames as without it), a **warning** (said once per run),
**bounded** work.

* a corrupt MCAP (a record length, the message definitions, a chunk that fails while the
  frames are read);
* ``fx = 0``, a PNG header claiming 20000 x 20000 pixels, a mask of the wrong size,
  a ``camera.json`` that is not a camera's;
* a YAML alias bomb, a value echoed in full, a timestep or window that makes a frame endless;
* an 8-bit depth PNG, a depth scale 10x off;
* a cloud with no table (an object's face taken for the table).
"""

from __future__ import annotations

import json
import logging
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.camera import Camera
from ssp.config import load_config
from ssp.errors import ConfigError, InputError, TableNotFoundError
from ssp.geometry import invert, transform_points
from ssp.io.bop import open_bop
from ssp.io.clouds import write_cloud
from ssp.io.hypotheses import write_hypotheses
from ssp.perception.table import table_frame
from ssp.pipeline.run import run
from ssp.scene import Hypothesis
from ssp.sim.bop import simulate_to_disk
from ssp.sim.generate import generate_sequence


def _load(p: Path):
    return json.loads(p.read_text())


# ------------------------------------------------------------------------------ 1. bags
def _cloud_mcap(path: Path, n: int = 3, npts: int = 500) -> Path:
    """A bare ``.mcap`` of ``n`` PointCloud2 messages (random points 0.6 m in front)."""
    pytest.importorskip("rosbags")
    from rosbags.rosbag2 import StoragePlugin, Writer

    from ssp.io.rosbag import typestore

    ts = typestore(2)
    T = ts.types
    tmp = path.with_suffix(".d")
    w = Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP)
    w.open()
    conn = w.add_connection("/camera/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
    rng = np.random.default_rng(0)
    for k in range(n):
        ns = 1_700_000_000_000_000_000 + k * 100_000_000
        sec, nsec = divmod(ns, 1_000_000_000)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        pts = rng.uniform(-0.1, 0.1, (npts, 3)).astype("<f4")
        pts[:, 2] += 0.6
        fields = [
            T["sensor_msgs/msg/PointField"](name=a, offset=o, datatype=7, count=1)
            for a, o in (("x", 0), ("y", 4), ("z", 8))
        ]
        msg = T["sensor_msgs/msg/PointCloud2"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam"), height=1,
            width=npts, fields=fields, is_bigendian=False, point_step=12, row_step=12 * npts,
            data=pts.view(np.uint8).reshape(-1), is_dense=True,
        )  # fmt: skip
        w.write(conn, ns, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    w.close()
    (mcap,) = tmp.glob("*.mcap")
    shutil.move(mcap, path)
    shutil.rmtree(tmp)
    return path


@pytest.fixture(scope="module")
def mcap(tmp_path_factory) -> Path:
    return _cloud_mcap(tmp_path_factory.mktemp("bag") / "rec.mcap")


def _damaged(mcap: Path, tmp: Path, edit) -> Path:
    p = tmp / "bad.mcap"
    p.write_bytes(edit(mcap.read_bytes()))
    return p


def _length_overflow(data: bytes) -> bytes:
    """A record length of the first chunk set to 2^63 - 1 (rosbags: OverflowError)."""
    b = bytearray(data)
    b[97:105] = b"\xff\xff\xff\xff\xff\xff\xff\x7f"
    return bytes(b)


def test_corrupt_mcap_record_length_is_an_input_error(lib, mcap, tmp_path):
    """A corrupt index or record length: the input fails as a whole, typed, naming the bag
    (was: an uncaught OverflowError and no summary)."""
    bad = _damaged(mcap, tmp_path, _length_overflow)
    with pytest.raises(InputError) as err:
        run(bad, lib, tmp_path / "out", hypotheses="estimated")
    assert str(bad) in str(err.value) and "cannot read the bag" in str(err.value)
    assert "OverflowError" in str(err.value)


def test_corrupt_mcap_message_definitions_fail_each_frame(lib, mcap, tmp_path):
    """Message definitions that do not fit the data (a field renamed): each frame fails with
    an InputError naming the bag, the run finishes and writes its summary."""
    bad = _damaged(mcap, tmp_path, lambda b: b.replace(b"uint32 offset", b"uint32 offsxt"))
    out = tmp_path / "out"
    summary = run(bad, lib, out, hypotheses="estimated")
    assert len(summary.failed) == 3 and not summary.done
    for f in summary.failed:
        assert not f["unexpected"] and f["error_type"] == "InputError", f
        assert str(bad) in f["error"] and "malformed message" in f["error"], f["error"]
    assert _load(out / "summary.json")["status"] == "finished"


def test_mcap_failing_while_frames_are_read_fails_the_rest(lib, mcap, tmp_path, monkeypatch):
    """The bag library fails on the second reading (a chunk read while the frames are
    decoded): the frames from there on fail naming the bag and the error, the run finishes."""
    from rosbags.highlevel import AnyReader

    real = AnyReader.messages
    calls = []

    def flaky(self, *a, **kw):
        calls.append(1)
        for i, item in enumerate(real(self, *a, **kw)):
            if len(calls) > 1 and i == 1:
                raise OverflowError("Python int too large to convert to C ssize_t")
            yield item

    monkeypatch.setattr(AnyReader, "messages", flaky)
    out = tmp_path / "out"
    summary = run(mcap, lib, out, hypotheses="estimated")
    failed = {f["frame"]: f for f in summary.failed}
    assert set(failed) >= {"000001", "000002"}
    for name in ("000001", "000002"):
        f = failed[name]
        assert not f["unexpected"] and f["error_type"] == "InputError", f
        assert str(mcap) in f["error"] and "cannot read the bag" in f["error"], f["error"]
        assert "OverflowError" in f["error"]
    assert _load(out / "summary.json")["status"] == "finished"


# ------------------------------------------------------------------------------ 2, 4. BOP scenes
@pytest.fixture(scope="module")
def bop(lib, tmp_path_factory):
    """A BOP dataset of one three-frame scene: ``(dataset root, scene folder)``."""
    root = tmp_path_factory.mktemp("bop")
    (scene,) = simulate_to_disk("structure", 1, 3, out_dir=root, library=lib, stages=3,
                                frames_per_stage=1, stride=8, n_objects=3)  # fmt: skip
    scene = Path(scene)
    assert (scene.parent.parent / "camera.json").is_file()
    return scene.parent.parent, scene


def _copy(bop, tmp_path: Path) -> tuple[Path, Path]:
    root, scene = bop
    dst = tmp_path / "ds"
    shutil.copytree(root, dst)
    return dst, dst / scene.relative_to(root)


def _edit_json(p: Path, edit) -> None:
    doc = _load(p)
    edit(doc)
    p.write_text(json.dumps(doc))


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_claiming(width: int, height: int) -> bytes:
    """A small PNG file whose header claims ``width`` x ``height`` 16-bit pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", ihdr)
        + _png_chunk(b"IDAT", zlib.compress(b"\x00" * 64))
        + _png_chunk(b"IEND", b"")
    )


def _fx_zero(scene: Path) -> None:
    _edit_json(scene / "scene_camera.json", lambda d: d["1"]["cam_K"].__setitem__(0, 0.0))


def _huge_depth(scene: Path) -> None:
    (scene / "depth" / "000001.png").write_bytes(_png_claiming(20000, 20000))


def _small_mask_visib(scene: Path) -> None:
    from PIL import Image

    (m,) = sorted((scene / "mask_visib").glob("000001_000000.png"))
    Image.fromarray(np.zeros((7, 5), dtype=np.uint8)).save(m)


BOP_FRAMES = [
    ("cam-K-fx-zero", _fx_zero, ("scene_camera.json", "im_id 1", "cam_K", "fx=0"), "auto"),
    ("depth-png-header-20000x20000", _huge_depth,
     ("depth/000001.png", "20000 x 20000", "not decoded"), "auto"),
    ("mask-visib-wrong-size", _small_mask_visib,
     ("mask_visib/000001_000000.png", "(7, 5)", "the depth image is"), "gt"),
]  # fmt: skip


@pytest.mark.parametrize("case", BOP_FRAMES, ids=lambda c: c[0])
def test_bad_bop_frame_is_a_clear_frame_failure(case, lib, bop, tmp_path):
    """Each was a raw traceback (an unexpected ValueError, DecompressionBombError,
    IndexError): now a typed frame failure naming the file and the problem; the other frames
    are done."""
    name, damage, needles, masks = case
    _, scene = _copy(bop, tmp_path)
    damage(scene)
    summary = run(scene, lib, tmp_path / "out", masks=masks)
    assert [(f["frame"], f["index"]) for f in summary.failed] == [("000001", 1)]
    (failed,) = summary.failed
    assert not failed["unexpected"] and failed["error_type"] == "InputError", failed
    for needle in needles:
        assert needle in failed["error"], (needle, failed["error"])
    assert [d["frame"] for d in summary.done] == ["000000", "000002"]


CAMERA_JSON = [
    ("fx-zero", {"fx": 0.0}, ("camera.json", "fx must be a positive number", "0.0")),
    ("width-zero", {"width": 0}, ("camera.json", "width must be a positive number", "0")),
    ("huge", {"width": 20000, "height": 20000}, ("camera.json", "20000 x 20000")),
]


@pytest.mark.parametrize("case", CAMERA_JSON, ids=lambda c: c[0])
def test_bad_camera_json_is_an_input_error(case, lib, bop, tmp_path):
    """A published scene's camera.json (here the scene's own; no sequence.json) is read when
    the scene is opened: a bad one fails the input (was: ignored, or every frame an
    unexpected ValueError)."""
    name, values, needles = case
    root, scene = _copy(bop, tmp_path)
    (scene / "sequence.json").unlink()  # a published scene: its size from camera.json
    _edit_json(scene / "camera.json", lambda d: d.update(values))
    with pytest.raises(InputError) as err:
        run(scene, lib, tmp_path / "out")
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))
    assert not (tmp_path / "out").exists()


def test_camera_intrinsics_are_checked_with_a_typed_error():
    from ssp.errors import ArgumentError

    for bad in (dict(fx=0.0), dict(fy=float("inf")), dict(cx=float("nan"))):
        kw = dict(width=4, height=3, fx=100.0, fy=100.0, cx=1.5, cy=1.0) | bad
        with pytest.raises(ArgumentError):
            Camera(**kw)


def _depth_8bit(scene: Path) -> None:
    from PIL import Image

    for p in sorted((scene / "depth").glob("*.png")):
        raw = np.asarray(Image.open(p)).astype(np.float64)
        Image.fromarray(np.clip(raw / 100, 0, 255).astype(np.uint8)).save(p)
    _edit_json(scene / "scene_camera.json",
               lambda d: [v.update(depth_scale=10.0) for v in d.values()])  # fmt: skip


def _depth_scale_10x(scene: Path) -> None:
    doc = _load(scene / "scene_camera.json")
    for v in doc.values():
        v["depth_scale"] *= 10
    (scene / "scene_camera.json").write_text(json.dumps(doc))


DEPTH_DOUBTS = [
    ("8-bit-depth-png", _depth_8bit, ("depth/000000.png", "8-bit")),
    ("depth-scale-10x", _depth_scale_10x, ("depth/000000.png", "depth scale", "depth_scale 1 ")),
]


@pytest.mark.parametrize("case", DEPTH_DOUBTS, ids=lambda c: c[0])
def test_suspicious_depth_is_said_once_per_run(case, lib, bop, tmp_path, caplog):
    """An 8-bit depth PNG, a depth scale 10x off: one warning for the run (logged, and in the
    first frame's warnings), naming the file and what is suspicious (was: none)."""
    name, damage, needles = case
    _, scene = _copy(bop, tmp_path)
    damage(scene)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        run(scene, lib, tmp_path / "out", hypotheses="given")
    logged = [
        r.getMessage() for r in caplog.records if "(said once for the scene)" in r.getMessage()
    ]
    assert len(logged) == 1, logged
    for needle in needles:
        assert needle in logged[0], (needle, logged[0])
    rec = _load(tmp_path / "out" / "frames" / "000000.json")
    if rec["status"] == "done":
        assert logged[0] in rec["warnings"]
    s = open_bop(scene)
    assert [len(s.load(k).warnings) for k in range(len(s))] == [1, 0, 0]


def test_good_depth_raises_no_doubt(bop):
    s = open_bop(bop[1])
    assert all(not s.load(k).warnings for k in range(len(s)))


# ------------------------------------------------------------------------------ 3. config files
def _alias_bomb(levels: int = 6) -> str:
    names = "abcdefghij"
    lines = ["x:", '  a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels):
        lines.append(f"  {names[i]}: &{names[i]} [" + ",".join(["*" + names[i - 1]] * 9) + "]")
    return "\n".join(lines) + f"\nphysics:\n  timestep: *{names[levels - 1]}\n"


CONFIG_CASES = [
    ("alias-bomb", _alias_bomb(), ("YAML aliases", "alias bomb")),
    ("self-alias", "x: &a [1, *a]\n", ("YAML aliases", "refer to themselves")),
    ("long-value-echoed", "physics:\n  timestep: '" + "9" * 5000 + "'\n",
     ("physics.timestep", "...")),
    ("timestep-1e-7", "physics:\n  timestep: 1.0e-7\n",
     ("physics.timestep", "search.settle_with_forces", "simulation steps", "at least")),
    ("final-settle-hours", "search:\n  final_settle: 3600\n",
     ("search.final_settle", "simulation steps")),
    ("solver-iterations-1e9", "physics:\n  solver_iterations: 1000000000\n",
     ("physics.solver_iterations", "less than or equal to")),
]  # fmt: skip


@pytest.mark.parametrize("case", CONFIG_CASES, ids=lambda c: c[0])
def test_config_that_would_hang_is_one_short_line(case, tmp_path):
    """Refused with one short line naming the file and the field (was: an alias bomb echoed
    in full, > 200 s; a timestep that let no frame finish)."""
    name, text, needles = case
    path = tmp_path / "ssp.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert str(path) in msg and len(msg.splitlines()) == 1 and len(msg) < 600, msg[:1000]
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_yaml_anchors_within_the_bound_still_work(tmp_path):
    path = tmp_path / "ssp.yaml"
    path.write_text("base: &b {timestep: 0.004}\nphysics:\n  <<: *b\n")
    with pytest.raises(ConfigError, match="unknown setting"):  # 'base' is no section
        load_config(path)
    path.write_text("physics:\n  solimp: &s [0.99, 0.999, 0.001, 0.5, 2.0]\n")
    assert load_config(path).physics.solimp == (0.99, 0.999, 0.001, 0.5, 2.0)


# ------------------------------------------------------------------------------ 5. no table
def _box_cloud(size: float = 0.3, n: int = 20000, seed: int = 0) -> np.ndarray:
    """The visible faces of a ``size`` m box 1 m in front of the camera (camera frame)."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("xy", [25, 35], degrees=True).as_matrix()
    c = np.array([0.0, 0.0, 1.0])
    faces = []
    for axis in range(3):
        for sign in (-1, 1):
            normal = R[:, axis] * sign
            centre = c + normal * size / 2
            if normal @ -centre <= 0:  # faces away from the camera
                continue
            uv = rng.uniform(-size / 2, size / 2, (n, 2))
            a, b = (R[:, k] for k in range(3) if k != axis)
            faces.append(centre + uv[:, :1] * a + uv[:, 1:] * b)
    return np.vstack(faces)


def test_table_frame_refuses_an_objects_face():
    with pytest.raises(TableNotFoundError, match="face of an object"):
        table_frame(_box_cloud())


@pytest.fixture(scope="module")
def camera_folder(lib, tmp_path_factory):
    """Frames 0 and 2 of a block structure as camera-frame clouds without a camera pose (the
    world frame is fitted to the table), with camera-frame hypotheses; and their run."""
    seq = generate_sequence("structure", 3, lib, stages=3, frames_per_stage=1, stride=8,
                            n_objects=3)  # fmt: skip
    d = tmp_path_factory.mktemp("camera_folder")
    T_cw = invert(seq.T_world_cam)
    for i in (0, 2):
        f = seq.frame(i)
        write_cloud(d / f"f{i}.ply", transform_points(T_cw, f.points), labels=f.labels + 1)
        hyps = [Hypothesis(h.class_name, T_cw @ h.T_world_obj, h.score)
                for h in seq.frames[i].hypotheses]  # fmt: skip
        write_hypotheses(d / f"f{i}.hypotheses.json", hyps, frame="camera")
    (d / "scene.json").write_text(json.dumps({"frame": "camera",
                                              "stamps": {"f0": 0.0, "f2": 1.0}}))  # fmt: skip
    ref = tmp_path_factory.mktemp("camera_ref") / "out"
    summary = run(d, lib, ref, hypotheses="given")
    assert len(summary.done) == 2 and not summary.failed
    return d, ref


def test_a_cloud_without_a_table_is_refused_and_changes_nothing(lib, camera_folder, tmp_path):
    """A frame whose cloud shows no table (one big box): refused, saying the plane is an
    object's face and what to give, rather than a world frame on that face; the parser's
    state is as without the frame."""
    src, ref = camera_folder
    d = tmp_path / "in"
    shutil.copytree(src, d)
    write_cloud(d / "f1.ply", _box_cloud())
    write_hypotheses(d / "f1.hypotheses.json", [], frame="camera")
    stamps = {"f0": 0.0, "f1": 0.5, "f2": 1.0}
    (d / "scene.json").write_text(json.dumps({"frame": "camera", "stamps": stamps}))
    out = tmp_path / "out"
    summary = run(d, lib, out, hypotheses="given")
    assert [f["frame"] for f in summary.failed] == ["f1"]
    (failed,) = summary.failed
    assert failed["error_type"] == "TableNotFoundError" and not failed["unexpected"]
    for needle in ("f1.ply", "no table", "face of an object", "camera pose"):
        assert needle in failed["error"], (needle, failed["error"])
    assert _load(out / "state.json")["parser"] == _load(ref / "state.json")["parser"]
