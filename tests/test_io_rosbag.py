"""ROS 1 / ROS 2 bags and MCAP files in and out (ssp.io.rosbag, ssp.pipeline.bag), on small
synthetic scenes rendered by the simulator and written with rosbags' own writers."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("rosbags")

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402

from ssp.errors import InputError  # noqa: E402
from ssp.geometry import invert  # noqa: E402
from ssp.io.rosbag import (  # noqa: E402
    BagOptions,
    TfBuffer,
    detect_topics,
    open_bag,
    parse_class_map,
    typestore,
)
from ssp.pipeline.bag import write_run_results_bag  # noqa: E402
from ssp.pipeline.run import run  # noqa: E402
from ssp.sim.bop import open_bop, read_bop, simulate_to_disk  # noqa: E402

BASE_S = 1_700_000_000  # bag stamps: this + the scene's stamp
CAM, WORLD = "camera_optical", "world"


@pytest.fixture(scope="module")
def scene_dir(lib, tmp_path_factory):
    (scene,) = simulate_to_disk(
        "structure",
        1,
        5,
        out_dir=tmp_path_factory.mktemp("bop"),
        library=lib,
        stages=2,
        frames_per_stage=1,
        stride=4,
        n_objects=4,
    )
    return Path(scene)


# ------------------------------------------------------------------------------ bag writing
class BagWriter:
    """A ROS 1 (``.bag``), ROS 2 (sqlite3 or mcap folder) bag for tests."""

    def __init__(self, path: Path, storage: str = "ros1") -> None:
        self.ros = 1 if storage == "ros1" else 2
        self.ts = typestore(self.ros)
        self.T = self.ts.types
        if self.ros == 1:
            self.w = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.w = Writer2(path, version=9, storage_plugin=plugin)
        self.w.open()
        self.conns: dict[str, object] = {}

    def header(self, ns: int, frame_id: str = CAM):
        sec, nsec = divmod(int(ns), 1_000_000_000)
        stamp = self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        extra = {"seq": 0} if self.ros == 1 else {}
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **extra)

    def put(self, topic: str, typ: str, ns: int, msg) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, typ, typestore=self.ts)
        ser = self.ts.serialize_ros1 if self.ros == 1 else self.ts.serialize_cdr
        self.w.write(self.conns[topic], int(ns), ser(msg, typ))

    def image(self, topic, ns, arr: np.ndarray, encoding: str, width=None) -> None:
        h, w = arr.shape
        data = np.ascontiguousarray(arr).view(np.uint8).reshape(-1)
        msg = self.T["sensor_msgs/msg/Image"](
            header=self.header(ns),
            height=h,
            width=w if width is None else width,
            encoding=encoding,
            is_bigendian=0,
            step=w * arr.dtype.itemsize,
            data=data,
        )
        self.put(topic, "sensor_msgs/msg/Image", ns, msg)

    def camera_info(self, topic, ns, cam) -> None:
        K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], dtype=float)
        mats = {"K": K, "D": np.zeros(5), "R": np.eye(3).ravel(), "P": np.zeros(12)}
        if self.ros == 2:
            mats = {k.lower(): v for k, v in mats.items()}
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        msg = self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(ns), height=cam.height, width=cam.width,
            distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **mats,
        )  # fmt: skip
        self.put(topic, "sensor_msgs/msg/CameraInfo", ns, msg)

    def cloud(self, topic, ns, pts: np.ndarray, labels: np.ndarray, hw) -> None:
        T = self.T
        rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u2")])
        rec["x"], rec["y"], rec["z"], rec["label"] = pts[:, 0], pts[:, 1], pts[:, 2], labels
        fields = [
            T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1)
            for n, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("label", 12, 4))
        ]
        h, w = hw
        msg = T["sensor_msgs/msg/PointCloud2"](
            header=self.header(ns), height=h, width=w, fields=fields, is_bigendian=False,
            point_step=14, row_step=14 * w, data=rec.view(np.uint8).reshape(-1), is_dense=False,
        )  # fmt: skip
        self.put(topic, "sensor_msgs/msg/PointCloud2", ns, msg)

    def transform(self, parent, child, ns, M):
        T = self.T
        q = Rotation.from_matrix(M[:3, :3]).as_quat()
        return T["geometry_msgs/msg/TransformStamped"](
            header=self.header(ns, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

    def tf(self, topic, ns, transforms) -> None:
        self.put(topic, "tf2_msgs/msg/TFMessage", ns, self.T["tf2_msgs/msg/TFMessage"](transforms))

    def pose(self, M):
        T = self.T
        q = Rotation.from_matrix(M[:3, :3]).as_quat()
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    def detections(self, topic, ns, groups, numbers=None) -> None:
        """``groups``: per detection a list of ``(class, score, T_cam_obj)``."""
        T = self.T
        dets = []
        for i, results in enumerate(groups):
            res = []
            for cls, score, M in results:
                pwc = T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=self.pose(M), covariance=np.zeros(36)
                )
                if self.ros == 1:
                    res.append(
                        T["vision_msgs/msg/ObjectHypothesisWithPose"](
                            id=numbers[cls], score=score, pose=pwc
                        )
                    )
                else:
                    hyp = T["vision_msgs/msg/ObjectHypothesis"](class_id=cls, score=score)
                    res.append(T["vision_msgs/msg/ObjectHypothesisWithPose"](hyp, pwc))
            bbox = T["vision_msgs/msg/BoundingBox3D"](
                center=self.pose(np.eye(4)), size=T["geometry_msgs/msg/Vector3"](x=0, y=0, z=0)
            )
            if self.ros == 1:
                empty = T["sensor_msgs/msg/PointCloud2"](
                    header=self.header(ns), height=0, width=0, fields=[], is_bigendian=False,
                    point_step=0, row_step=0, data=np.zeros(0, np.uint8), is_dense=False,
                )  # fmt: skip
                dets.append(T["vision_msgs/msg/Detection3D"](self.header(ns), res, bbox, empty))
            else:
                dets.append(
                    T["vision_msgs/msg/Detection3D"](self.header(ns), res, bbox, str(i + 1))
                )
        msg = T["vision_msgs/msg/Detection3DArray"](header=self.header(ns), detections=dets)
        self.put(topic, "vision_msgs/msg/Detection3DArray", ns, msg)

    def string(self, topic, ns, text: str) -> None:
        self.put(topic, "std_msgs/msg/String", ns, self.T["std_msgs/msg/String"](data=text))

    def close(self) -> None:
        self.w.close()


def _ns(stamp: float) -> int:
    return BASE_S * 1_000_000_000 + int(round(stamp * 1e9))


def _mask(instance: np.ndarray) -> np.ndarray:
    """BOP instance image (-2 none, -1 table, j object) -> bag mask (0, j + 1)."""
    inst = np.asarray(instance).astype(np.int64)
    return np.where(inst >= 0, inst + 1, 0).astype(np.uint16)


def _groups(scene, k, sf, T_cw, rng=None):
    """Per ground-truth object (mask order) its hypotheses as (class, score, T_cam_obj)."""
    sources = scene.info["hypothesis_sources"][k]
    out = []
    for iid in sf.gt:
        g = [
            (h.class_name, h.score, T_cw @ h.T_world_obj)
            for h, src in zip(sf.hypotheses, sources, strict=True)
            if src == iid
        ]
        out.append(g)
    return out


def write_scene_bag(
    path: Path,
    scene_dir: Path,
    lib,
    storage: str = "ros1",
    *,
    driver: str = "depth",
    hyps: str | None = "json",
    tf: str | None = "static",
    encoding: str = "32FC1",
    corrupt: dict | None = None,
    extra_cloud: bool = False,
) -> dict:
    """Write the BOP scene as a bag; returns facts about it (stamps, numbers)."""
    scene = read_bop(scene_dir, lib)  # SimSequence: ground truth in the world frame
    bw = BagWriter(path, storage)
    T_wc = scene.T_world_cam
    T_cw = invert(T_wc)
    numbers = {c: int(i) for i, c in open_bop(scene_dir, lib).classes.items()}
    corrupt = corrupt or {}
    stamps = []
    if tf == "static":
        bw.tf("/tf_static", _ns(0), [bw.transform(WORLD, CAM, 0, T_wc)])
    for k, sf in enumerate(scene.frames):
        ns = _ns(sf.stamp)
        stamps.append(ns)
        if tf == "chain":  # world -> base (moving, interpolated) -> camera (static)
            T_bc = np.eye(4)
            T_bc[:3, 3] = [0.1, -0.05, 0.2]
            T_wb = T_wc @ invert(T_bc)
            if k == 0:
                bw.tf("/tf_static", ns - 1, [bw.transform("base", CAM, 0, T_bc)])
            samples = []
            for sign, dt in ((-1, -20_000_000), (1, 20_000_000)):
                d = np.eye(4)
                d[:3, :3] = Rotation.from_rotvec([0, 0, sign * 0.05]).as_matrix()
                d[:3, 3] = [sign * 0.03, 0, 0]
                samples.append(bw.transform(WORLD, "base", ns + dt, T_wb @ d))
            bw.tf("/tf", ns - 20_000_000, [samples[0]])
        depth = np.asarray(sf.depth, dtype=np.float32)
        if encoding == "16UC1":
            depth = np.round(depth * 1000).astype(np.uint16)
        mask = _mask(sf.instance)
        if driver == "depth":
            bw.image("/camera/depth/image_rect", ns, depth, encoding)
            bw.camera_info("/camera/depth/camera_info", ns, scene.camera)
            width = scene.camera.width + 3 if corrupt.get("mask_size") == k else None
            mns = ns + corrupt.get("mask_offset", {}).get(k, 0)
            bw.image("/camera/segmentation_mask", mns, mask, "mono16", width=width)
        if driver == "cloud" or extra_cloud:
            pts = scene.camera.backproject(np.asarray(sf.depth, float)).reshape(-1, 3)
            pts[np.asarray(sf.depth).reshape(-1) <= 0] = np.nan
            bw.cloud("/camera/points", ns, pts, mask.reshape(-1), scene.camera.shape)
        if k in corrupt.get("no_hypotheses", ()):
            pass
        elif hyps == "json":
            doc = {
                "frame": "world",
                "hypotheses": [
                    {
                        "class": h.class_name,
                        "score": h.score,
                        "T": np.asarray(h.T_world_obj).tolist(),
                    }
                    for h in sf.hypotheses
                ],
            }
            bw.string("/ssp/hypotheses", ns, json.dumps(doc))
        elif hyps == "detections":
            groups = _groups(scene, k, sf, T_cw)
            if corrupt.get("nan_pose") == k:
                cls, score, M = groups[0][0]
                M = M.copy()
                M[0, 3] = np.nan
                groups[0][0] = (cls, score, M)
            bw.detections("/pose_estimation/output", ns, groups, numbers)
        if tf == "chain":
            bw.tf("/tf", ns + 20_000_000, [samples[1]])
    bw.close()
    return {"stamps": stamps, "numbers": numbers, "scene": scene}


def _objects(out: Path, name: str) -> list[tuple[str, np.ndarray]]:
    """``(class, T_cam_obj)`` of a frame's objects."""
    rec = json.loads((out / "frames" / f"{name}.json").read_text())
    assert rec["status"] == "done", rec.get("error")
    T_cw = invert(np.asarray(rec["T_world_cam"]))
    return [(o["class"], T_cw @ np.asarray(o["T_world_obj"])) for o in rec["objects"]]


def _assert_same(a, b, tol=2e-3):
    assert sorted(c for c, _ in a) == sorted(c for c, _ in b)
    for cls, T in a:
        d = min(np.linalg.norm(T[:3, 3] - U[:3, 3]) for c, U in b if c == cls)
        assert d < tol, (cls, d)


# ------------------------------------------------------------------------------ tests
def test_ros1_bag_gives_the_bop_scene_result(lib, scene_dir, tmp_path):
    """Depth 32FC1 + CameraInfo + mask + JSON world hypotheses + tf_static: the same objects
    as the BOP scene the bag was made from."""
    bag = tmp_path / "rec.bag"
    write_scene_bag(bag, scene_dir, lib, "ros1")
    ref = run(scene_dir, lib, tmp_path / "ref", hypotheses="given")
    got = run(bag, lib, tmp_path / "out", hypotheses="given", bag={"world_frame": WORLD})
    assert got.kind == "bag" and got.frames == ref.frames == 2
    assert not got.failed and len(got.done) == 2
    for d in ref.done:
        _assert_same(_objects(tmp_path / "out", d["frame"]), _objects(tmp_path / "ref", d["frame"]))
    manifest = json.loads((tmp_path / "out" / "run.json").read_text())
    assert manifest["kind"] == "bag" and list(manifest["input_files"]) == ["rec.bag"]
    assert manifest["options"]["bag"]["world_frame"] == WORLD
    assert (tmp_path / "out" / "ssp_rec-test.csv").is_file()


@pytest.mark.parametrize("storage", ["ros1", "sqlite3", "mcap"])
def test_detection3d_arrays_ros1_and_ros2(lib, scene_dir, tmp_path, storage):
    """vision_msgs Detection3DArray in the ROS 1 (int ids, class map) and ROS 2 (string class
    ids) definitions, camera frame, no world frame (the table gives it)."""
    bag = tmp_path / ("rec.bag" if storage == "ros1" else "rec")
    facts = write_scene_bag(bag, scene_dir, lib, storage, hyps="detections", tf=None)
    opts = {}
    if storage == "ros1":
        opts["class_map"] = {str(i): c for c, i in facts["numbers"].items()}
    b = open_bag(bag, opts, classes=list(lib))
    assert b.ros == (1 if storage == "ros1" else 2)
    assert b.topics.hypotheses == "/pose_estimation/output"
    assert b.topics.mask == "/camera/segmentation_mask" and b.topics.driver == "depth"
    f = next(iter(b.frames())).load()
    sf = facts["scene"].frames[0]
    assert f.hypotheses_frame == "camera" and len(f.hypotheses) == len(sf.hypotheses)
    assert {h.segment for h in f.hypotheses} <= set(range(1, len(sf.gt) + 1))
    np.testing.assert_array_equal(f.depth, sf.depth)
    summary = run(bag, lib, tmp_path / "out", hypotheses="given", bag=opts)
    assert not summary.failed and len(summary.done) == 2
    # the objects the BOP scene gives (same hypotheses, world frame, no segments)
    ref = run(scene_dir, lib, tmp_path / "ref", hypotheses="given")
    for d in ref.done:
        _assert_same(_objects(tmp_path / "out", d["frame"]), _objects(tmp_path / "ref", d["frame"]))
    assert sum(d["objects"] for d in summary.done) >= 3


def test_ros1_ids_without_class_map_fail_the_frame(lib, scene_dir, tmp_path):
    bag = tmp_path / "rec.bag"
    write_scene_bag(bag, scene_dir, lib, "ros1", hyps="detections", tf=None)
    summary = run(bag, lib, tmp_path / "out", hypotheses="given")
    assert len(summary.failed) == 2
    err = summary.failed[0]["error"]
    assert "/pose_estimation/output" in err and "--class-map" in err and "not in the library" in err


def test_bare_mcap_cloud_and_results_bag(lib, scene_dir, tmp_path):
    """A PointCloud2 (x, y, z, label) in a bare .mcap file; the results bag read back."""
    folder = tmp_path / "rec"
    facts = write_scene_bag(folder, scene_dir, lib, "mcap", driver="cloud", hyps="detections")
    (mcap,) = folder.glob("*.mcap")
    bare = tmp_path / "rec.mcap"
    shutil.move(mcap, bare)
    shutil.rmtree(folder)
    opts = {"world_frame": WORLD}
    summary = run(bare, lib, tmp_path / "out", hypotheses="given", bag=opts)
    assert summary.kind == "bag" and not summary.failed and len(summary.done) == 2
    results = {}
    for suffix in (".bag", ".mcap", ""):
        p = tmp_path / f"results{suffix}"
        write_run_results_bag(tmp_path / "out", bare, p, lib, opts)
        results[suffix] = p
        with AnyReader([p]) as r:
            assert r.is2 == (suffix != ".bag")
            topics = {c.topic: c for c in r.connections}
            assert set(topics) == {"/ssp/poses", "/ssp/detections"}
            poses, dets = [], []
            for conn, t, raw in r.messages():
                msg = r.deserialize(raw, conn.msgtype)
                (poses if conn.topic == "/ssp/poses" else dets).append((t, msg))
        assert [t for t, _ in poses] == facts["stamps"] == [t for t, _ in dets]
        for (t, pa), (_, da), d in zip(poses, dets, summary.done, strict=True):
            stamp = pa.header.stamp.sec * 1_000_000_000 + pa.header.stamp.nanosec
            assert stamp == t and pa.header.frame_id == CAM
            assert len(pa.poses) == len(da.detections) == d["objects"]
            rec = json.loads((tmp_path / "out" / "frames" / f"{d['frame']}.json").read_text())
            T_cw = invert(np.asarray(rec["T_world_cam"]))
            o = rec["objects"][0]
            t_cam = (T_cw @ np.asarray(o["T_world_obj"]))[:3, 3]
            p = pa.poses[0].position
            np.testing.assert_allclose([p.x, p.y, p.z], t_cam, atol=1e-9)
            r0 = da.detections[0].results[0]
            if suffix == ".bag":
                assert r0.id == facts["numbers"][o["class"]] or r0.id >= 1
            else:
                assert r0.hypothesis.class_id == o["class"]
                assert da.detections[0].id == o["id"]
            size = da.detections[0].bbox.size
            assert min(size.x, size.y, size.z) > 0


def test_tf_chain_interpolated(lib, scene_dir, tmp_path):
    """world -> base on /tf (two samples around each frame, interpolated) -> camera on
    /tf_static: the same camera pose, so the same objects, as the static transform."""
    a, b = tmp_path / "static.bag", tmp_path / "chain.bag"
    write_scene_bag(a, scene_dir, lib, "ros1", tf="static")
    facts = write_scene_bag(b, scene_dir, lib, "ros1", tf="chain")
    bag = open_bag(b, {"world_frame": WORLD})
    f = next(iter(bag.frames())).load()
    np.testing.assert_allclose(f.T_world_cam, facts["scene"].T_world_cam, atol=1e-9)
    run(a, lib, tmp_path / "a", hypotheses="given", bag={"world_frame": WORLD})
    run(b, lib, tmp_path / "b", hypotheses="given", bag={"world_frame": WORLD})
    for name in ("000000", "000001"):
        _assert_same(_objects(tmp_path / "a", name), _objects(tmp_path / "b", name), 1e-4)
    # an unknown world frame fails every frame, naming the frames tf knows
    s = run(b, lib, tmp_path / "c", hypotheses="given", bag={"world_frame": "map"})
    assert len(s.failed) == 2 and "no chain" in s.failed[0]["error"]


def test_tf_buffer_lookup():
    ts = typestore(2)
    T = ts.types

    def tfm(parent, child, ns, x, yaw):
        q = Rotation.from_rotvec([0, 0, yaw]).as_quat()
        sec, nsec = divmod(ns, 1_000_000_000)
        return T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=parent
            ),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=x, y=0.0, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

    buf = TfBuffer()
    buf.add(T["tf2_msgs/msg/TFMessage"]([tfm("/map", "base", 0, 0.0, 0.0)]), False, "t")
    buf.add(T["tf2_msgs/msg/TFMessage"]([tfm("map", "base", 100, 1.0, 0.2)]), False, "t")
    buf.add(T["tf2_msgs/msg/TFMessage"]([tfm("base", "cam", 0, 0.5, 0.0)]), True, "t")
    M = buf.lookup("map", "cam", 50)
    np.testing.assert_allclose(M[:3, 3], [0.5 + 0.5 * np.cos(0.1), 0.5 * np.sin(0.1), 0], atol=1e-9)
    yaw = Rotation.from_matrix(M[:3, :3]).as_rotvec()[2]
    assert yaw == pytest.approx(0.1)
    np.testing.assert_allclose(buf.lookup("cam", "map", 50), np.linalg.inv(M), atol=1e-12)
    assert buf.lookup("map", "cam", 110, tolerance=20)[0, 3] > 1.0  # last sample, in tolerance
    with pytest.raises(InputError, match="no transform"):
        buf.lookup("map", "cam", 200, tolerance=20)
    with pytest.raises(InputError, match="no chain"):
        buf.lookup("odom", "cam", 50)


def test_corrupt_messages_fail_their_frame_only(lib, scene_dir, tmp_path):
    bag = tmp_path / "rec"
    facts = write_scene_bag(
        bag, scene_dir, lib, "sqlite3", hyps="detections", tf=None,
        corrupt={"mask_size": 0, "nan_pose": 1},
    )  # fmt: skip
    summary = run(bag, lib, tmp_path / "out", hypotheses="given")
    assert not summary.done and len(summary.failed) == 2
    e0, e1 = (f["error"] for f in summary.failed)
    assert e0.startswith(f"{bag}: /camera/segmentation_mask at {BASE_S}.")
    assert e0.endswith("mask 163 x 120 (mono16): step 320 bytes is less than a row of 326")
    assert "/pose_estimation/output" in e1 and "NaN" in e1 and "detection 0 result 0" in e1
    assert not any(f["unexpected"] for f in summary.failed)
    # in auto mode a frame without a hypotheses message is estimated, with a warning
    del facts


def test_16uc1_depth_and_missing_hypotheses(lib, scene_dir, tmp_path):
    bag = tmp_path / "rec.bag"
    write_scene_bag(bag, scene_dir, lib, "ros1", hyps=None, encoding="16UC1")
    b = open_bag(bag)
    f = next(iter(b.frames())).load()
    sf = read_bop(scene_dir, lib).frames[0]
    assert np.abs(f.depth - sf.depth).max() <= 5e-4 + 1e-6
    assert f.hypotheses is None and f.T_world_cam is None
    s = run(bag, lib, tmp_path / "out", hypotheses="given")
    assert len(s.failed) == 2 and "no hypotheses topic" in s.failed[0]["error"]


def test_auto_detection_and_ambiguity(lib, scene_dir, tmp_path):
    pc, img, ci, det = (
        "sensor_msgs/msg/PointCloud2",
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/CameraInfo",
        "vision_msgs/msg/Detection3DArray",
    )
    topics = {
        "/cam/depth/image": img,
        "/cam/depth/camera_info": ci,
        "/cam/color/camera_info": ci,
        "/cam/color/image_raw": img,
        "/seg/mask": img,
        "/pose_estimation/output": det,
        "/tf": "tf2_msgs/msg/TFMessage",
        "/tf_static": "tf2_msgs/msg/TFMessage",
    }
    t = detect_topics(topics, BagOptions())
    assert (t.driver, t.depth, t.camera_info, t.mask) == (
        "depth",
        "/cam/depth/image",
        "/cam/depth/camera_info",
        "/seg/mask",
    )
    assert t.hypotheses == "/pose_estimation/output" and t.tf == ("/tf", "/tf_static")
    assert detect_topics(topics, BagOptions(), mode="estimated").hypotheses is None
    with pytest.raises(InputError, match="--topic-cloud or --topic-depth"):
        detect_topics({**topics, "/cam/points": pc}, BagOptions())
    t = detect_topics({**topics, "/cam/points": pc}, BagOptions(topic_cloud="/cam/points"))
    assert t.driver == "cloud" and t.camera_info is None
    with pytest.raises(InputError, match=r"/a/mask, /seg/mask; choose one with --topic-mask"):
        detect_topics({**topics, "/a/mask": img}, BagOptions())
    with pytest.raises(InputError, match="--topic-hypotheses"):
        detect_topics({**topics, "/other": det}, BagOptions())
    with pytest.raises(InputError, match="no such topic"):
        detect_topics(topics, BagOptions(topic_mask="/nope"))
    with pytest.raises(InputError, match="expected sensor_msgs/msg/Image"):
        detect_topics(topics, BagOptions(topic_mask="/cam/depth/camera_info"))
    with pytest.raises(InputError, match="no sensor_msgs/PointCloud2"):
        detect_topics({"/x": ci}, BagOptions())
    # on a real bag: a cloud and a depth image are ambiguous; the error reaches run()
    bag = tmp_path / "both.bag"
    write_scene_bag(bag, scene_dir, lib, "ros1", extra_cloud=True)
    with pytest.raises(InputError, match="/camera/points"):
        run(bag, lib, tmp_path / "out")
    s = run(bag, lib, tmp_path / "out2", bag={"topic_depth": "/camera/depth/image_rect",
                                               "world_frame": WORLD})  # fmt: skip
    assert len(s.done) == 2


def test_class_map_parsing(tmp_path):
    assert parse_class_map("1=cube, 2=block") == {"1": "cube", "2": "block"}
    p = tmp_path / "map.json"
    p.write_text(json.dumps({"3": "mug"}))
    assert parse_class_map(p) == {"3": "mug"}
    y = tmp_path / "map.yaml"
    y.write_text("4: drill\nobj_5: wrench\n")
    assert parse_class_map(y) == {"4": "drill", "obj_5": "wrench"}
    with pytest.raises(ValueError, match="id=class"):
        parse_class_map("1:cube")


def test_cli_run_bag_with_results_bag_and_resume(lib, scene_dir, tmp_path):
    from typer.testing import CliRunner

    from ssp.cli import app

    bag = tmp_path / "rec.bag"
    write_scene_bag(bag, scene_dir, lib, "ros1")
    out, res = tmp_path / "out", tmp_path / "res.mcap"
    args = ["run", str(bag), "--out", str(out), "--hypotheses", "given"]
    r = CliRunner().invoke(app, [*args, "--world-frame", WORLD, "--results-bag", str(res)])
    assert r.exit_code == 0, r.output
    assert "2 of 2 frames done" in r.output and res.is_file()
    with AnyReader([res]) as reader:
        assert sum(c.msgcount for c in reader.connections) == 4
    # resume takes the recorded bag options; other ones are refused
    r = CliRunner().invoke(app, ["run", "--resume", str(out)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["run", "--resume", str(out), "--world-frame", "map"])
    assert r.exit_code == 1 and "world_frame" in r.output
    # bag options on a folder input are refused before anything runs
    r = CliRunner().invoke(app, ["run", str(scene_dir), "--world-frame", WORLD])
    assert r.exit_code != 0 and "ROS bag input" in r.output


def test_sync_tolerance(lib, scene_dir, tmp_path):
    """A mask 30 ms off is matched (tolerance 50 ms), one 80 ms off is not (the frame is
    segmented without it, with a warning); a frame without hypotheses is estimated in auto
    mode (warning) and fails in given mode."""
    bag = tmp_path / "rec.bag"
    corrupt = {"mask_offset": {0: 30_000_000, 1: 80_000_000}, "no_hypotheses": {1}}
    write_scene_bag(bag, scene_dir, lib, "ros1", corrupt=corrupt)
    b = open_bag(bag, {"world_frame": WORLD})
    f0, f1 = (fs.load() for fs in b.frames())
    assert f0.labels is not None and f1.labels is None
    assert f0.hypotheses and f1.hypotheses is None
    assert any("segmentation_mask" in w and "0.05 s" in w for w in f1.warnings)
    assert any("/ssp/hypotheses" in w for w in f1.warnings)
    wider = open_bag(bag, {"world_frame": WORLD, "sync_tolerance": 0.1})
    assert all(fs.load().labels is not None for fs in wider.frames())
    s = run(bag, lib, tmp_path / "auto", classes=["cube", "block"], bag={"world_frame": WORLD})
    assert [d["frame"] for d in s.done] == ["000000", "000001"]
    assert any("/ssp/hypotheses" in w["warning"] for w in s.warnings)
    s = run(bag, lib, tmp_path / "given", hypotheses="given", bag={"world_frame": WORLD})
    assert [f["frame"] for f in s.failed] == ["000001"] and len(s.done) == 1
