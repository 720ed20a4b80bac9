"""ROS 1 / ROS 2 bags and MCAP files in and out, through ``rosbags`` (no ROS install).

Reading (:func:`open_bag`): a ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml``;
sqlite3 or mcap storage) or a bare ``.mcap`` file, opened with
:class:`rosbags.highlevel.AnyReader`. One frame per message of the *driving* topic: a
``sensor_msgs/PointCloud2`` (x, y, z float fields; optional ``label`` field) or a depth
``sensor_msgs/Image`` (``32FC1`` m, ``16UC1``/``mono16`` mm) with its
``sensor_msgs/CameraInfo``. Other topics are matched to a frame by header stamp, the nearest
one within ``sync_tolerance`` (default 50 ms; the nearest CameraInfo whatever the gap):

* instance masks, an ``Image`` (``mono8``/``8UC1``, ``mono16``/``16UC1``, ``32SC1``; 0 =
  background, ``k`` = instance ``k``);
* hypotheses, a ``vision_msgs/Detection3DArray`` (ROS 1 or ROS 2 definitions; every result of a
  detection is a hypothesis of that detection's object) or a ``std_msgs/String`` holding a
  hypotheses file's JSON (:func:`ssp.io.hypotheses.parse_hypotheses`; matched by its bag time,
  a String has no header);
* ``/tf`` and ``/tf_static`` (``tf2_msgs/TFMessage``) for the camera pose in a world frame
  (:class:`TfBuffer`) and for detections in another frame than the camera's.

The bag is read twice, both times as a stream: :func:`open_bag` indexes the header stamps
(and keeps the transforms), :meth:`BagInput.frames` then reads the messages again and holds
the raw bytes of a message only until the frames that use it are read. A frame's messages
are decoded when :meth:`FrameSource.load` is called, so a bad message (wrong encoding, size
mismatch, NaN pose, unknown class) fails that frame alone with an :class:`InputError` naming
the topic, the stamp and the problem.

Writing (:class:`ResultsBagWriter`, :func:`write_results_bag`): per frame a
``geometry_msgs/PoseArray`` and a ``vision_msgs/Detection3DArray`` in the camera frame of the
input frame, with its header stamp, to a ROS 1 bag (``.bag``), an MCAP file (``.mcap``) or a
ROS 2 bag folder (any other name, sqlite3 storage).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ssp.camera import Camera
from ssp.errors import ArgumentError, InputError, SSPError
from ssp.io.hypotheses import parse_hypotheses
from ssp.scene import Hypothesis

__all__ = [
    "BagFrame",
    "BagInput",
    "BagOptions",
    "FrameSource",
    "ResultFrame",
    "ResultObject",
    "ResultsBagWriter",
    "TfBuffer",
    "Topics",
    "bag_paths",
    "detect_topics",
    "is_bag",
    "open_bag",
    "parse_class_map",
    "typestore",
    "write_results_bag",
]

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------ types
#: ``vision_msgs`` as released for ROS 1 (noetic, 0.0.x), and ``tf2_msgs/TFMessage`` that
#: rosbags' ROS 1 store lacks.
ROS1_MSGS = {
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "int64 id\nfloat64 score\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\n"
        "sensor_msgs/PointCloud2 source_cloud\n"
    ),
    "vision_msgs/msg/Detection3DArray": "Header header\nDetection3D[] detections\n",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
}
#: ``vision_msgs`` as released for ROS 2 (humble and later, 4.x).
ROS2_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\n"
        "string id\n"
    ),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nDetection3D[] detections\n",
}

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DETECTIONS = "vision_msgs/msg/Detection3DArray"
STRING = "std_msgs/msg/String"
TF = "tf2_msgs/msg/TFMessage"

_MASK_NAME = re.compile(r"mask|segment|instance|label", re.IGNORECASE)
_DEPTH_NAME = re.compile(r"depth", re.IGNORECASE)
_HYP_NAME = re.compile(r"hypothes|pose_estimation|detection", re.IGNORECASE)
_DEPTH_ENCODINGS = {"32FC1": ("<f4", 1.0), "16UC1": ("<u2", 1e-3), "mono16": ("<u2", 1e-3)}
_MASK_ENCODINGS = {
    "mono8": "u1",
    "8UC1": "u1",
    "mono16": "<u2",
    "16UC1": "<u2",
    "32SC1": "<i4",
}
# PointField datatypes
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}


def typestore(ros: int):
    """A rosbags typestore for ROS ``ros`` (1: noetic, 2: humble) with the ``vision_msgs``
    (and for ROS 1 ``tf2_msgs``) definitions of that ROS version registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if ros not in (1, 2):
        raise ArgumentError(f"ROS version must be 1 or 2, got {ros!r}")
    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in (ROS1_MSGS if ros == 1 else ROS2_MSGS).items():
        types.update(get_types_from_msg(text, name))
    store.register({k: v for k, v in types.items() if k not in store.fielddefs})
    return store


def _complete_types(reader, ros: int) -> None:
    """Register in ``reader.typestore`` the types the bag does not define (from
    :func:`typestore`); the bag's own definitions (ROS 1 connection msgdefs, ROS 2 / MCAP
    schemas) are kept."""
    have = reader.typestore.fielddefs
    extra = {k: v for k, v in typestore(ros).fielddefs.items() if k not in have}
    if extra:
        reader.typestore.register(extra)


# ------------------------------------------------------------------------------ paths
def is_bag(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a ROS 1 bag (``.bag`` file), an MCAP file (``.mcap``) or a ROS 2
    bag folder (holding ``metadata.yaml``). Never opens a file."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in (".bag", ".mcap")


def bag_paths(path: str | os.PathLike) -> list[Path]:
    """The files a bag is read from: the file itself, or a ROS 2 folder's files."""
    p = Path(path)
    if p.is_dir():
        return sorted(q for q in p.iterdir() if q.is_file() and not q.name.startswith("."))
    return [p]


# ------------------------------------------------------------------------------ options
@dataclass
class BagOptions:
    """How to read a bag. Topics left None are detected (:func:`detect_topics`).

    Attributes:
        topic_cloud, topic_depth, topic_camera_info, topic_mask, topic_hypotheses: topic names.
        world_frame: tf frame id of the world (z up, table top at z = 0); None: the camera
            pose comes from the table plane of each frame.
        class_map: detection class id (as a string) -> library class name.
        sync_tolerance: largest header-stamp difference of a matched message, s.
    """

    topic_cloud: str | None = None
    topic_depth: str | None = None
    topic_camera_info: str | None = None
    topic_mask: str | None = None
    topic_hypotheses: str | None = None
    world_frame: str | None = None
    class_map: dict[str, str] = field(default_factory=dict)
    sync_tolerance: float = 0.05

    def __post_init__(self) -> None:
        if not (self.sync_tolerance >= 0 and np.isfinite(self.sync_tolerance)):
            raise ArgumentError(f"sync_tolerance must be >= 0 s, got {self.sync_tolerance}")
        self.class_map = {str(k): str(v) for k, v in (self.class_map or {}).items()}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> BagOptions:
        if isinstance(d, BagOptions):
            return d
        known = set(cls.__dataclass_fields__)
        extra = sorted(set(d or {}) - known)
        if extra:
            raise ArgumentError(f"unknown bag options: {', '.join(extra)}")
        return cls(**dict(d or {}))


def parse_class_map(text: str | os.PathLike | None) -> dict[str, str]:
    """A class map from ``id=class`` pairs separated by commas, or from a JSON or YAML file
    holding one mapping (``{"3": "mug"}``); ids are compared as strings.

    Raises:
        ArgumentError: unreadable file or a malformed pair.
    """
    if text is None or str(text).strip() == "":
        return {}
    p = Path(text)
    if p.suffix.lower() in (".json", ".yaml", ".yml") or p.is_file():
        try:
            raw = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise ArgumentError(f"{p}: cannot read the class map: {exc}") from exc
        try:
            if p.suffix.lower() == ".json":
                doc = json.loads(raw)
            else:
                import yaml

                doc = yaml.safe_load(raw)
        except Exception as exc:  # JSON or YAML syntax
            raise ArgumentError(f"{p}: invalid class map: {exc}") from exc
        if not isinstance(doc, Mapping) or not all(isinstance(v, str) for v in doc.values()):
            raise ArgumentError(f"{p}: the class map must map ids to class names")
        return {str(k): v for k, v in doc.items()}
    out = {}
    for pair in str(text).split(","):
        if not pair.strip():
            continue
        key, sep, value = pair.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise ArgumentError(f"class map: expected id=class, got {pair.strip()!r}")
        out[key.strip()] = value.strip()
    return out


# ------------------------------------------------------------------------------ topics
@dataclass
class Topics:
    """The topics a bag is read from (None: absent). ``driver`` is ``cloud`` or ``depth``;
    ``hypotheses_kind`` is ``detections`` (Detection3DArray) or ``json`` (String)."""

    driver: str
    cloud: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    mask: str | None = None
    hypotheses: str | None = None
    hypotheses_kind: str | None = None
    tf: tuple[str, ...] = ()

    @property
    def main(self) -> str:
        return self.cloud if self.driver == "cloud" else self.depth  # type: ignore[return-value]


def _pick(what: str, candidates: list[str], option: str, where: str) -> str | None:
    if len(candidates) > 1:
        raise InputError(
            f"{where}: several {what} topics: {', '.join(sorted(candidates))}; choose one "
            f"with {option}"
        )
    return candidates[0] if candidates else None


def _given(topics: Mapping[str, str], name: str, types: Sequence[str], option: str, where: str):
    if name not in topics:
        raise InputError(
            f"{where}: {option} {name}: no such topic; topics: {', '.join(sorted(topics))}"
        )
    if topics[name] not in types:
        raise InputError(
            f"{where}: {option} {name}: its type is {topics[name]}, expected {' or '.join(types)}"
        )
    return name


def detect_topics(
    topics: Mapping[str, str], options: BagOptions, mode: str = "auto", where: str = "bag"
) -> Topics:
    """Resolve the topics to read from ``topics`` (name -> message type) and the options.

    Detected when not given: the only PointCloud2, the only Image named like ``*depth*`` with
    the CameraInfo of its namespace (else the only CameraInfo), the only Image named like
    ``*mask*`` / ``*segment*`` / ``*instance*`` / ``*label*``, the only Detection3DArray (else
    the only String named like ``*hypothes*``), ``/tf`` and ``/tf_static``. A cloud and a depth
    image both present, or two candidates of one role, is ambiguous. ``mode == "estimated"``:
    no hypotheses topic.

    Raises:
        InputError: a given topic is missing or of the wrong type, no frame topic, or an
            ambiguity (the message lists the candidates and the option to choose with).
    """
    o = options
    by_type: dict[str, list[str]] = {}
    for name, typ in topics.items():
        by_type.setdefault(typ, []).append(name)
    images = by_type.get(IMAGE, [])
    if o.topic_cloud is not None and o.topic_depth is not None:
        raise ArgumentError("give --topic-cloud or --topic-depth, not both")
    cloud = depth = None
    if o.topic_cloud is not None:
        cloud = _given(topics, o.topic_cloud, [POINTCLOUD2], "--topic-cloud", where)
    elif o.topic_depth is not None:
        depth = _given(topics, o.topic_depth, [IMAGE], "--topic-depth", where)
    else:
        clouds = by_type.get(POINTCLOUD2, [])
        depths = [t for t in images if _DEPTH_NAME.search(t) and not _MASK_NAME.search(t)]
        if clouds and depths:
            raise InputError(
                f"{where}: both point clouds ({', '.join(sorted(clouds))}) and depth images "
                f"({', '.join(sorted(depths))}): choose one with --topic-cloud or --topic-depth"
            )
        cloud = _pick("PointCloud2", clouds, "--topic-cloud", where)
        depth = _pick("depth Image", depths, "--topic-depth", where)
        if cloud is None and depth is None:
            listed = ", ".join(f"{k} ({v})" for k, v in sorted(topics.items())) or "none"
            raise InputError(
                f"{where}: no sensor_msgs/PointCloud2 topic and no sensor_msgs/Image topic "
                f"named like *depth*; give --topic-cloud or --topic-depth. Topics: {listed}"
            )
    out = Topics(driver="cloud" if cloud is not None else "depth", cloud=cloud, depth=depth)
    if depth is not None:
        if o.topic_camera_info is not None:
            out.camera_info = _given(
                topics, o.topic_camera_info, [CAMERA_INFO], "--topic-camera-info", where
            )
        else:
            infos = by_type.get(CAMERA_INFO, [])
            ns = depth.rsplit("/", 1)[0]
            same = [t for t in infos if t.rsplit("/", 1)[0] == ns]
            out.camera_info = _pick(
                "CameraInfo", same if len(same) == 1 else infos, "--topic-camera-info", where
            )
            if out.camera_info is None:
                raise InputError(
                    f"{where}: depth topic {depth} but no sensor_msgs/CameraInfo topic: the "
                    "intrinsics are needed"
                )
    if o.topic_mask is not None:
        out.mask = _given(topics, o.topic_mask, [IMAGE], "--topic-mask", where)
    else:
        masks = [t for t in images if _MASK_NAME.search(t) and t != depth]
        out.mask = _pick("mask Image", masks, "--topic-mask", where)
    if o.topic_hypotheses is not None:
        out.hypotheses = _given(
            topics, o.topic_hypotheses, [DETECTIONS, STRING], "--topic-hypotheses", where
        )
    elif mode != "estimated":
        dets = by_type.get(DETECTIONS, [])
        out.hypotheses = _pick("Detection3DArray", dets, "--topic-hypotheses", where)
        if out.hypotheses is None:
            strings = [t for t in by_type.get(STRING, []) if _HYP_NAME.search(t)]
            out.hypotheses = _pick("String hypotheses", strings, "--topic-hypotheses", where)
    if out.hypotheses is not None:
        out.hypotheses_kind = "detections" if topics[out.hypotheses] == DETECTIONS else "json"
    out.tf = tuple(t for t in sorted(by_type.get(TF, [])) if t.lstrip("/") in ("tf", "tf_static"))
    return out


# ------------------------------------------------------------------------------ tf
def _pose_matrix(t, q, what: str) -> np.ndarray:
    """4x4 from a translation ``(x, y, z)`` and a quaternion ``(x, y, z, w)``; InputError on
    NaN or a zero quaternion."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(q, dtype=float)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise InputError(f"{what}: NaN or infinite pose")
    n = float(np.linalg.norm(q))
    if n < 1e-6:
        raise InputError(f"{what}: zero quaternion")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / n).as_matrix()
    T[:3, 3] = t
    return T


def _frame_id(name: str) -> str:
    return name.lstrip("/")


class TfBuffer:
    """The transforms of a bag's ``/tf`` and ``/tf_static``, looked up at a stamp.

    Each edge (parent -> child) keeps its samples; a lookup interpolates between the two
    samples around the stamp (linear translation, slerp rotation), takes the first or last
    sample when the stamp lies outside them by at most ``tolerance``, and otherwise fails.
    Static transforms hold at every stamp. A chain goes up from both frames to their common
    ancestor.
    """

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._static: dict[str, np.ndarray] = {}  # child -> T_parent_child
        self._samples: dict[str, list[tuple[int, np.ndarray, np.ndarray]]] = {}
        self._sorted: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def add(self, msg, static: bool, where: str) -> None:
        """Add the transforms of a ``TFMessage`` (bad ones are logged and skipped)."""
        for ts in msg.transforms:
            parent, child = _frame_id(ts.header.frame_id), _frame_id(ts.child_frame_id)
            tr, rot = ts.transform.translation, ts.transform.rotation
            t, q = (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w)
            if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) or not any(q):
                log.warning("%s: transform %s -> %s: invalid; skipped", where, parent, child)
                continue
            known = self._parent.setdefault(child, parent)
            if known != parent:
                log.warning(
                    "%s: frame %s has two parents (%s, %s); the first is kept",
                    where, child, known, parent,
                )  # fmt: skip
                continue
            if static:
                self._static[child] = _pose_matrix(t, q, where)
            else:
                stamp = ts.header.stamp.sec * 1_000_000_000 + ts.header.stamp.nanosec
                self._samples.setdefault(child, []).append((stamp, np.array(t), np.array(q)))
                self._sorted.pop(child, None)

    @property
    def frames(self) -> set[str]:
        return set(self._parent) | set(self._parent.values())

    def _edge(self, child: str, stamp: int, tolerance: int) -> np.ndarray:
        if child in self._static:
            return self._static[child]
        if child not in self._sorted:
            s = sorted(self._samples[child], key=lambda x: x[0])
            self._sorted[child] = (
                np.array([x[0] for x in s], dtype=np.int64),
                np.array([x[1] for x in s]),
                np.array([x[2] / np.linalg.norm(x[2]) for x in s]),
            )
        stamps, ts, qs = self._sorted[child]
        parent = self._parent[child]
        i = int(np.searchsorted(stamps, stamp))
        if i < len(stamps) and stamps[i] == stamp:
            return _pose_matrix(ts[i], qs[i], child)
        if 0 < i < len(stamps):
            a, b = int(stamps[i - 1]), int(stamps[i])
            w = (stamp - a) / (b - a)
            R = Slerp([0.0, 1.0], Rotation.from_quat(qs[i - 1 : i + 1]))([w])[0]
            T = np.eye(4)
            T[:3, :3] = R.as_matrix()
            T[:3, 3] = (1 - w) * ts[i - 1] + w * ts[i]
            return T
        j = 0 if i == 0 else len(stamps) - 1
        gap = abs(int(stamps[j]) - stamp)
        if gap <= tolerance:
            return _pose_matrix(ts[j], qs[j], child)
        raise InputError(
            f"tf {parent} -> {child}: no transform at {_stamp_text(stamp)} (samples from "
            f"{_stamp_text(int(stamps[0]))} to {_stamp_text(int(stamps[-1]))})"
        )

    def _up(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self._parent and len(chain) <= len(self._parent):
            chain.append(self._parent[chain[-1]])
        return chain

    def lookup(self, target: str, source: str, stamp: int, tolerance: int = 0) -> np.ndarray:
        """``T_target_source`` (4x4) at ``stamp`` (ns).

        Raises:
            InputError: the frames are not connected, or an edge has no transform then.
        """
        target, source = _frame_id(target), _frame_id(source)
        if target == source:
            return np.eye(4)
        up_t, up_s = self._up(target), self._up(source)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            known = ", ".join(sorted(self.frames)) or "none"
            raise InputError(
                f"tf: no chain from {target!r} to {source!r} (frames in /tf and /tf_static: "
                f"{known})"
            )

        def to_common(chain: list[str]) -> np.ndarray:
            T = np.eye(4)
            for child in chain[: chain.index(common)]:
                T = self._edge(child, stamp, tolerance) @ T
            return T

        return np.linalg.inv(to_common(up_t)) @ to_common(up_s)


# ------------------------------------------------------------------------------ frames
def _stamp_text(ns: int) -> str:
    s, n = divmod(int(ns), 1_000_000_000)
    return f"{s}.{n:09d} s"


def _header_stamp(msg) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


@dataclass
class BagFrame:
    """One decoded frame (camera frame ``frame_id``, OpenCV axes).

    Attributes:
        kind: ``cloud`` (``points`` ``(N, 3)`` m, ``labels`` ``(N,)`` or None) or ``depth``
            (``depth`` ``(H, W)`` m, 0 = none; ``camera``; ``labels`` ``(H, W)`` or None).
            Labels: -1 = background, ``k >= 1`` = instance ``k``.
        hypotheses: the matched hypotheses (None: no hypotheses message), in
            ``hypotheses_frame`` (``camera``: ``T_world_obj`` holds ``T_cam_obj``).
        T_world_cam: camera pose in the world frame from tf, or None.
    """

    index: int
    stamp_ns: int
    frame_id: str
    kind: str
    points: np.ndarray | None = None
    depth: np.ndarray | None = None
    camera: Camera | None = None
    labels: np.ndarray | None = None
    hypotheses: list[Hypothesis] | None = None
    hypotheses_frame: str = "camera"
    T_world_cam: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def stamp(self) -> float:
        """Header stamp, s."""
        return self.stamp_ns * 1e-9


@dataclass
class _Entry:
    """An indexed message: header stamp (ns; bag time for a String), and the error of a
    message that could not be deserialized."""

    stamp: int
    frame_id: str = ""
    error: str | None = None


@dataclass
class FrameSource:
    """A frame of the bag before decoding: position, header stamp and frame id of its main
    message; :meth:`load` decodes it and its matched messages."""

    index: int
    stamp_ns: int
    frame_id: str
    load: Callable[[], BagFrame]


class BagInput:
    """An indexed bag (:func:`open_bag`): its topics and frames.

    Attributes:
        path: the bag. ``ros``: 1 or 2. ``topics``: the resolved :class:`Topics`.
        entries: the driving topic's messages in bag order (stamp, frame id).
        tf: the bag's transforms.
    """

    def __init__(self, path: Path, options: BagOptions, mode: str, classes) -> None:
        try:
            from rosbags.highlevel import AnyReader, AnyReaderError
        except ImportError as exc:
            raise InputError(
                f"{path}: reading ROS bags needs the rosbags package (>= 0.11): pip install "
                "'sequential-scene-parsing[ros]'"
            ) from exc

        self.path = path
        self.options = options
        self.mode = mode
        self.classes = None if classes is None else set(classes)
        self._tol = int(round(options.sync_tolerance * 1e9))
        self._reader_cls, self._reader_err = AnyReader, AnyReaderError
        with self._open() as reader:
            self.ros = 2 if reader.is2 else 1
            types = {}
            for c in reader.connections:
                types.setdefault(c.topic, c.msgtype)
            self.topics = detect_topics(types, options, mode, str(path))
            self.tf = TfBuffer()
            self._index: dict[str, list[_Entry]] = {}
            self._sorted: dict[str, tuple[np.ndarray, np.ndarray]] = {}
            self._scan(reader)
        self.entries = self._index[self.topics.main]
        if not self.entries:
            raise InputError(f"{path}: topic {self.topics.main} holds no message")
        self._matches = [
            self._match(e, r) for e, r in zip(self.entries, self._ranks(), strict=True)
        ]

    def _ranks(self) -> list[int | None]:
        """Each frame's rank among the frames of the same header stamp (0: the first in bag
        order), None for a frame whose stamp is its own; frames sharing a stamp are warned
        about."""
        seen: dict[int, int] = {}
        self._main_stamps = {e.stamp for e in self.entries}
        ranks = []
        for e in self.entries:
            ranks.append(seen.get(e.stamp, 0))
            seen[e.stamp] = ranks[-1] + 1
        shared = {s: n for s, n in seen.items() if n > 1}
        out = [r if e.stamp in shared else None for e, r in zip(self.entries, ranks, strict=True)]
        if shared:
            first = min(shared)
            log.warning(
                "%s: %d stamps of %s are each on several messages (%d at %s, ...): those frames "
                "get the messages of their stamp in bag order, the k-th frame the k-th",
                self.path, len(shared), self.topics.main, shared[first], _stamp_text(first),
            )  # fmt: skip
        return out

    def __len__(self) -> int:
        return len(self.entries)

    # -- reading
    def _open(self):
        try:
            reader = self._reader_cls([self.path])
            reader.open()
        except (self._reader_err, OSError, ValueError) as exc:
            raise InputError(f"{self.path}: cannot open the bag: {exc}") from exc
        except Exception as exc:  # a corrupt header or index: rosbags raises many kinds
            raise InputError(
                f"{self.path}: cannot open the bag (corrupt?): {type(exc).__name__}: {exc}"
            ) from exc
        try:
            _complete_types(reader, 2 if reader.is2 else 1)
        except Exception as exc:  # the bag's own message definitions are corrupt
            reader.close()
            raise InputError(
                f"{self.path}: cannot read the bag's message definitions (corrupt?): "
                f"{type(exc).__name__}: {exc}"
            ) from exc
        return _Closing(reader)

    def _messages(self, reader, conns) -> Iterator[tuple[Any, int, bytes]]:
        """``reader.messages(connections=conns)``; any error of the bag library while
        reading (a corrupt chunk, record length or index: OverflowError, struct.error, ...) is
        a :class:`_BagReadError` naming the bag."""
        try:
            it = iter(reader.messages(connections=conns))
        except Exception as exc:
            raise _BagReadError(self.path, exc) from exc
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as exc:
                raise _BagReadError(self.path, exc) from exc
            yield item

    def _roles(self) -> dict[str, str]:
        t = self.topics
        roles = {t.main: "main"}
        for role in ("camera_info", "mask", "hypotheses"):
            name = getattr(t, role)
            if name is not None:
                roles[name] = role
        return roles

    def _scan(self, reader) -> None:
        """Index stamps of the frame topics; keep the transforms."""
        roles = self._roles()
        wanted = set(roles) | set(self.topics.tf)
        conns = [c for c in reader.connections if c.topic in wanted]
        for topic in roles:
            self._index[topic] = []
        for conn, bag_ns, raw in self._messages(reader, conns):
            where = f"{self.path}: {conn.topic}"
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic in roles and conn.msgtype != STRING:
                    _header_stamp(msg), _frame_id(msg.header.frame_id)  # a header to index
            except Exception as exc:  # rosbags raises several kinds on a corrupt message
                if conn.topic in roles:
                    self._index[conn.topic].append(
                        _Entry(bag_ns, "", f"cannot deserialize the message: {exc}")
                    )
                else:
                    log.warning("%s at %s: cannot deserialize: %s", where, _stamp_text(bag_ns), exc)
                continue
            if conn.topic in self.topics.tf:
                self.tf.add(msg, conn.topic.lstrip("/") == "tf_static", where)
            elif conn.msgtype == STRING:
                self._index[conn.topic].append(_Entry(bag_ns))
            else:
                self._index[conn.topic].append(
                    _Entry(_header_stamp(msg), _frame_id(msg.header.frame_id))
                )

    def _nearest(
        self, topic: str, stamp: int, tolerance: int | None, rank: int | None = None
    ) -> int | None:
        """Position (in bag order) of the ``topic`` message whose stamp is nearest ``stamp``
        (the earlier one of a tie), None if none lies within ``tolerance`` ns. ``rank``
        given (the frame is the ``rank``-th of several frames of its stamp): the ``rank``-th
        message of that nearest stamp in bag order (or the one following it in time, within
        ``tolerance`` and not of another frame's stamp), so that each frame gets its own and
        not the first frame's; None when there is none."""
        if topic not in self._sorted:
            stamps = np.array([e.stamp for e in self._index.get(topic) or []], dtype=np.int64)
            order = np.argsort(stamps, kind="stable")
            self._sorted[topic] = (stamps[order], order)
        stamps, order = self._sorted[topic]
        if not len(stamps):
            return None
        i = int(np.searchsorted(stamps, stamp))
        near = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
        best = min(near, key=lambda j: (abs(int(stamps[j]) - stamp), int(stamps[j])))
        if tolerance is not None and abs(int(stamps[best]) - stamp) > tolerance:
            return None
        first = int(np.searchsorted(stamps, stamps[best]))  # the first of that stamp
        last = int(np.searchsorted(stamps, stamps[best], side="right"))
        if rank is not None:  # frames share the stamp: pair them in order with its messages
            j = first + rank
            if j >= last and not (
                # a message stamped otherwise (a String's bag time) is the frame's when it
                # follows, within the tolerance, and is no other frame's
                j < len(stamps)
                and abs(int(stamps[j]) - stamp) <= (tolerance or 0)
                and int(stamps[j]) not in self._main_stamps
            ):
                return None
            best = j
        return int(order[best])

    def _match(self, e: _Entry, rank: int | None = None) -> dict[str, int | None]:
        """The messages of the frame of ``e``, the ``rank``-th of its header stamp: frames that
        share a stamp (a driver that stamps late, a paused clock) are paired with the messages
        of that stamp in bag order, each its own, as they were published; a frame with no
        message of its rank has none (a warning when it is read). The CameraInfo holds for
        every frame: the nearest."""
        t = self.topics
        out: dict[str, int | None] = {}
        if t.camera_info is not None:
            out["camera_info"] = self._nearest(t.camera_info, e.stamp, None)
        if t.mask is not None:
            out["mask"] = self._nearest(t.mask, e.stamp, self._tol, rank)
        if t.hypotheses is not None:
            out["hypotheses"] = self._nearest(t.hypotheses, e.stamp, self._tol, rank)
        return out

    def frames(self, start: int = 0) -> Iterator[FrameSource]:
        """The frames from position ``start`` on, in bag order; each is yielded once its
        messages have been read (raw bytes, decoded by :meth:`FrameSource.load`)."""
        if start >= len(self.entries):
            return
        roles = self._roles()
        main = self.topics.main
        # which (topic, position) each frame needs, and the last frame needing each
        need: list[dict[str, tuple[str, int]]] = []
        last_use: dict[tuple[str, int], int] = {}
        for k in range(len(self.entries)):
            d = {"main": (main, k)}
            for role, pos in self._matches[k].items():
                if pos is not None:
                    d[role] = (getattr(self.topics, role), pos)
            need.append(d)
            if k >= start:
                for key in d.values():
                    last_use[key] = k
        held: dict[tuple[str, int], tuple[str, bytes]] = {}
        count = dict.fromkeys(roles, 0)
        k = start
        broken = ""  # why the rest of the bag could not be read
        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic in roles]
            try:
                for conn, _, raw in self._messages(reader, conns):
                    key = (conn.topic, count[conn.topic])
                    count[conn.topic] += 1
                    if key in last_use:
                        held[key] = (conn.msgtype, bytes(raw))
                    while k < len(need) and all(v in held for v in need[k].values()):
                        msgs = {r: (*held[v], v[1]) for r, v in need[k].items()}
                        yield self._source(k, msgs, reader)
                        for v in need[k].values():
                            if last_use.get(v) == k:
                                held.pop(v, None)
                        k += 1
                    if k >= len(need):
                        return
            except _BagReadError as exc:  # the frames from here on fail, the run goes on
                log.warning("%s", exc)
                broken = f" ({exc})"
        yield from self._unread(k, broken)  # the bag ended early (truncated or corrupt)

    def _unread(self, start: int, reason: str) -> Iterator[FrameSource]:
        """The frames from ``start`` on, whose messages the bag did not give (``reason``),
        each failing when it is loaded."""
        for k in range(start, len(self.entries)):
            e = self.entries[k]

            def missing(e=e) -> BagFrame:
                where = f"{self.topics.main} at {_stamp_text(e.stamp)}"
                raise InputError(f"{where}: message not found{reason}")

            yield FrameSource(k, e.stamp, e.frame_id, missing)

    def _source(self, k: int, raw: dict[str, tuple[str, bytes, int]], reader) -> FrameSource:
        e = self.entries[k]
        # the typestore itself, so that a frame can be decoded after the reader is closed
        ts = reader.typestore
        deser = ts.deserialize_cdr if reader.is2 else ts.deserialize_ros1
        return FrameSource(k, e.stamp, e.frame_id, lambda: self._decode_checked(k, raw, deser))

    def _decode_checked(self, k: int, raw: dict[str, tuple[str, bytes, int]], deser) -> BagFrame:
        """:meth:`_decode`; a message that deserialized but lacks the fields of its type (the
        bag's message definitions are corrupt) is an InputError naming the frame."""
        try:
            return self._decode(k, raw, deser)
        except SSPError:
            raise
        except (AttributeError, TypeError, ValueError, OverflowError, IndexError, KeyError) as exc:
            where = f"{self.topics.main} at {_stamp_text(self.entries[k].stamp)}"
            raise InputError(
                f"{where}: malformed message (do the bag's message definitions fit its data?): "
                f"{type(exc).__name__}: {exc}"
            ) from exc

    # -- decoding
    def _decode(self, k: int, raw: dict[str, tuple[str, bytes, int]], deser) -> BagFrame:
        t, e = self.topics, self.entries[k]
        where = f"{t.main} at {_stamp_text(e.stamp)}"
        if e.error:
            raise InputError(f"{where}: {e.error}")
        msg = _deserialize(deser, raw["main"], where)
        frame = BagFrame(index=k, stamp_ns=e.stamp, frame_id=e.frame_id, kind=t.driver)
        if t.driver == "cloud":
            frame.points, labels, organized = _cloud(msg, where)
            frame.labels = labels
        else:
            frame.depth = _depth(msg, where)
            ci = self._matched(raw, "camera_info", deser)
            frame.camera = _camera(ci, frame.depth.shape, f"{t.camera_info}")
            organized = frame.depth.shape
        if t.mask is not None:
            mask = self._matched(raw, "mask", deser)
            if mask is None:
                frame.warnings.append(
                    f"{where}: no {t.mask} message within {self.options.sync_tolerance:g} s: "
                    "the frame is segmented without a mask"
                )
            else:
                lab = _mask(mask, f"{t.mask} at {_stamp_text(_header_stamp(mask))}")
                shape = organized if organized is not None else None
                if shape is None or lab.shape != tuple(shape):
                    raise InputError(
                        f"{t.mask} at {_stamp_text(_header_stamp(mask))}: mask {lab.shape[1]} x "
                        f"{lab.shape[0]} does not fit the "
                        + (
                            "unorganised cloud"
                            if shape is None
                            else f"{t.driver} image {shape[1]} x {shape[0]}"
                        )
                    )
                frame.labels = lab.reshape(-1) if t.driver == "cloud" else lab
        if self.options.world_frame is not None:
            try:
                frame.T_world_cam = self.tf.lookup(
                    self.options.world_frame, e.frame_id, e.stamp, self._tol
                )
            except InputError as exc:
                raise InputError(f"{where}: camera pose: {exc}") from None
        if t.hypotheses is not None:
            hmsg = self._matched(raw, "hypotheses", deser)
            if hmsg is None:
                frame.warnings.append(
                    f"{where}: no {t.hypotheses} message within "
                    f"{self.options.sync_tolerance:g} s: no hypotheses for this frame"
                )
            elif t.hypotheses_kind == "json":
                self._json_hypotheses(frame, hmsg)
            else:
                self._detections(frame, hmsg)
        return frame

    def _matched(self, raw, role: str, deser):
        if role not in raw:
            return None
        topic = getattr(self.topics, role)
        entry = self._index[topic][raw[role][2]]
        where = f"{topic} at {_stamp_text(entry.stamp)}"
        if entry.error:
            raise InputError(f"{where}: {entry.error}")
        return _deserialize(deser, raw[role], where)

    def _class(self, cid: Any, where: str) -> str:
        key = str(cid)
        name = self.options.class_map.get(key, key)
        if self.classes is not None and name not in self.classes:
            import difflib

            close = difflib.get_close_matches(name, sorted(self.classes), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            mapped = f" (mapped from {key!r})" if key in self.options.class_map else ""
            raise InputError(
                f"{where}: class {name!r}{mapped} is not in the library{hint}; map detection "
                "class ids to library classes with --class-map ID=CLASS"
            )
        return name

    def _json_hypotheses(self, frame: BagFrame, msg) -> None:
        topic = self.topics.hypotheses
        where = f"{topic} (bag time {_stamp_text(frame.stamp_ns)})"
        try:
            doc = json.loads(msg.data)
            hf = parse_hypotheses(doc, where)
        except RecursionError:
            raise InputError(f"{where}: invalid JSON: nested too deeply to read") from None
        except json.JSONDecodeError as exc:
            raise InputError(f"{where}: invalid JSON: {exc}") from None
        frame.hypotheses = [
            Hypothesis(
                self._class(h.class_name, where),
                h.T_world_obj,
                h.score,
                h.instance_id,
                h.segment,
            )
            for h in hf.hypotheses
        ]
        frame.hypotheses_frame = hf.frame
        if hf.frame == "world" and frame.T_world_cam is None:
            raise InputError(
                f"{where}: world-frame hypotheses need the camera pose in that world: give "
                "--world-frame (and /tf or /tf_static from it to the camera frame)"
            )

    def _detections(self, frame: BagFrame, msg) -> None:
        where = f"{self.topics.hypotheses} at {_stamp_text(_header_stamp(msg))}"
        det_frame = _frame_id(msg.header.frame_id) or frame.frame_id
        labels = None if frame.labels is None else set(np.unique(frame.labels).tolist())
        hyps: list[Hypothesis] = []
        for i, det in enumerate(msg.detections):
            dw = f"{where}: detection {i}"
            src = _frame_id(det.header.frame_id) or det_frame
            if src == frame.frame_id:
                T_cam_src = np.eye(4)
            else:
                try:
                    T_cam_src = self.tf.lookup(frame.frame_id, src, frame.stamp_ns, self._tol)
                except InputError as exc:
                    raise InputError(f"{dw}: frame {src!r}: {exc}") from None
            det_id = str(getattr(det, "id", "") or "")
            label = int(det_id) if re.fullmatch(r"-?\d+", det_id) else i + 1
            segment = label if labels is not None and label in labels else None
            for j, r in enumerate(det.results):
                rw = f"{dw} result {j}"
                if hasattr(r, "hypothesis"):
                    cid, score = r.hypothesis.class_id, r.hypothesis.score
                else:  # ROS 1 (int64 id) and ROS 2 foxy (string id)
                    cid, score = r.id, r.score
                if not np.isfinite(score):
                    raise InputError(f"{rw}: score {score}")
                p = r.pose.pose
                T = _pose_matrix(
                    (p.position.x, p.position.y, p.position.z),
                    (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w),
                    rw,
                )
                hyps.append(
                    Hypothesis(self._class(cid, rw), T_cam_src @ T, float(score), None, segment)
                )
        frame.hypotheses = hyps
        frame.hypotheses_frame = "camera"


class _BagReadError(InputError):
    """The bag library failed while reading the messages of ``path`` (a corrupt chunk,
    record or index)."""

    def __init__(self, path: Path, exc: Exception) -> None:
        super().__init__(f"{path}: cannot read the bag (corrupt?): {type(exc).__name__}: {exc}")


class _Closing:
    def __init__(self, reader) -> None:
        self.reader = reader

    def __enter__(self):
        return self.reader

    def __exit__(self, *exc) -> None:
        self.reader.close()


def _image(msg, encodings: Mapping[str, Any], what: str, where: str) -> tuple[np.ndarray, Any]:
    """``(H, W)`` array of an ``Image`` of one of ``encodings`` (their value is returned)."""
    enc = str(msg.encoding)
    if enc not in encodings:
        raise InputError(f"{where}: {what} encoding {enc!r}; expected {', '.join(encodings)}")
    spec = encodings[enc]
    dtype = np.dtype(spec[0] if isinstance(spec, tuple) else spec)
    if msg.is_bigendian:
        dtype = dtype.newbyteorder(">")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if h < 1 or w < 1:
        raise InputError(f"{where}: {what} of size {w} x {h}")
    if step < w * dtype.itemsize:
        raise InputError(
            f"{where}: {what} {w} x {h} ({enc}): step {step} bytes is less than a row of "
            f"{w * dtype.itemsize}"
        )
    if data.size < h * step:
        raise InputError(
            f"{where}: {what} {w} x {h} ({enc}, step {step}) needs {h * step} bytes of data, "
            f"the message has {data.size}"
        )
    rows = data[: h * step].reshape(h, step)[:, : w * dtype.itemsize]
    return np.ascontiguousarray(rows).view(dtype).reshape(h, w), spec


def _depth(msg, where: str) -> np.ndarray:
    """Depth ``(H, W)`` float32 m (0 = no return) of a ``32FC1`` (m) or ``16UC1`` (mm) image."""
    arr, (_, scale) = _image(msg, _DEPTH_ENCODINGS, "depth image", where)
    depth = arr.astype(np.float32) * np.float32(scale)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def _mask(msg, where: str) -> np.ndarray:
    """Instance labels ``(H, W)`` int64: -1 = background (0 or negative), ``k`` = instance."""
    arr, _ = _image(msg, _MASK_ENCODINGS, "mask", where)
    lab = arr.astype(np.int64)
    lab[lab <= 0] = -1
    return lab


def _camera(msg, shape: tuple[int, int], where: str) -> Camera:
    """The intrinsics of a ``CameraInfo`` (``K``; ROS 2 ``k``) for images of ``shape``."""
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=float)
    if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0:
        raise InputError(f"{where}: invalid camera matrix K {K.tolist()}")
    h, w = shape
    if (msg.width, msg.height) not in ((0, 0), (w, h)):
        raise InputError(
            f"{where}: CameraInfo is for {msg.width} x {msg.height} images, the depth image "
            f"is {w} x {h}"
        )
    return Camera(int(w), int(h), float(K[0]), float(K[4]), float(K[2]), float(K[5]))


def _cloud(msg, where: str) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int] | None]:
    """``(points (N, 3) m, labels (N,) or None, (H, W) when organised)`` of a PointCloud2
    (float ``x``, ``y``, ``z``; optional ``label``: 0 = background)."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in "xyz" if n not in fields]
    if missing:
        raise InputError(
            f"{where}: PointCloud2 without field(s) {', '.join(missing)} (fields: "
            f"{', '.join(fields) or 'none'})"
        )
    names, formats, offsets = [], [], []
    for n in ("x", "y", "z", "label"):
        f = fields.get(n)
        if f is None:
            continue
        if f.datatype not in _FIELD_TYPES or (n in "xyz" and f.datatype not in (7, 8)):
            raise InputError(f"{where}: PointCloud2 field {n!r} has datatype {f.datatype}")
        if int(getattr(f, "count", 1)) != 1:
            raise InputError(f"{where}: PointCloud2 field {n!r} has count {f.count}")
        dt = np.dtype(_FIELD_TYPES[f.datatype])
        names.append(n)
        formats.append(dt.newbyteorder(">") if msg.is_bigendian else dt)
        offsets.append(int(f.offset))
    h, w = int(msg.height), int(msg.width)
    step, row = int(msg.point_step), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    ends = [o + np.dtype(f).itemsize for o, f in zip(offsets, formats, strict=True)]
    if step < max(ends) or row < w * step or data.size < h * row:
        raise InputError(
            f"{where}: PointCloud2 {w} x {h} (point_step {step}, row_step {row}) needs "
            f"{h * row} bytes of data, the message has {data.size}"
        )
    rows = np.ascontiguousarray(data[: h * row].reshape(h, row)[:, : w * step])
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rec = rows.reshape(-1).view(dtype)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    labels = None
    if "label" in names:
        lab = rec["label"]
        if not np.all(np.isfinite(lab)):
            raise InputError(f"{where}: PointCloud2 label field holds NaN")
        labels = lab.astype(np.int64)
        labels[labels <= 0] = -1
    return pts, labels, ((h, w) if h > 1 else None)


def _deserialize(deser, item: tuple, where: str):
    msgtype, raw = item[0], item[1]
    try:
        return deser(raw, msgtype)
    except Exception as exc:  # a corrupt message
        raise InputError(f"{where}: cannot deserialize the {msgtype} message: {exc}") from None


def open_bag(
    path: str | os.PathLike,
    options: BagOptions | Mapping[str, Any] | None = None,
    mode: str = "auto",
    classes: Iterable[str] | None = None,
) -> BagInput:
    """Open and index a bag (module docstring): topics, frame stamps, transforms.

    Args:
        mode: ``auto``, ``given`` or ``estimated`` (no hypotheses topic is read).
        classes: the library's class names (a detection class must be one, after the
            options' ``class_map``); None: not checked.

    Raises:
        InputError: the bag cannot be opened, a topic cannot be chosen, or the driving topic
            is empty.
    """
    p = Path(path)
    if not os.path.lexists(p):
        raise InputError(f"{p}: no such bag")
    if not is_bag(p):
        raise InputError(f"{p}: not a bag (.bag, .mcap, or a folder with metadata.yaml)")
    return BagInput(p, BagOptions.from_dict(options), mode, classes)


# ------------------------------------------------------------------------------ writing
@dataclass
class ResultObject:
    """One object of a results frame: ``T_cam_obj`` (4x4, m) in the frame's camera frame.

    ``number`` is the ROS 1 ``ObjectHypothesisWithPose.id`` (int64; e.g. the BOP ``obj_id``);
    ``bbox`` is ``(T_cam_box (4x4), size (3,) m)`` of the model's bounding box, or None.
    """

    id: str
    class_name: str
    T_cam_obj: np.ndarray
    score: float
    number: int = 0
    bbox: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class ResultFrame:
    """The objects of one frame, stamped with the input frame's header (``stamp_ns``,
    ``frame_id``: the camera frame the poses are in)."""

    stamp_ns: int
    frame_id: str
    objects: list[ResultObject] = field(default_factory=list)


class ResultsBagWriter:
    """Write results to a new bag: ``.bag`` ROS 1, ``.mcap`` an MCAP file (ROS 2 CDR), any
    other path a ROS 2 bag folder (sqlite3). Per frame a ``geometry_msgs/PoseArray`` on
    ``poses_topic`` and a ``vision_msgs/Detection3DArray`` on ``detections_topic``, bag time =
    header stamp. Use as a context manager.

    Raises:
        ArgumentError: ``path`` exists.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        poses_topic: str = "/ssp/poses",
        detections_topic: str = "/ssp/detections",
    ) -> None:
        self.path = Path(path)
        if os.path.lexists(self.path):
            raise ArgumentError(f"{self.path}: exists; the results bag must be a new path")
        self.ros = 1 if self.path.suffix.lower() == ".bag" else 2
        self.ts = typestore(self.ros)
        self._tmp: Path | None = None
        if self.ros == 1:
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            target = self.path
            plugin = StoragePlugin.SQLITE3
            if self.path.suffix.lower() == ".mcap":
                self._tmp = Path(tempfile.mkdtemp(prefix=".ssp-bag-", dir=self.path.parent))
                target, plugin = self._tmp / "bag", StoragePlugin.MCAP
            self._writer = Writer(target, version=9, storage_plugin=plugin)
        self._writer.open()
        self._poses = self._writer.add_connection(
            poses_topic, "geometry_msgs/msg/PoseArray", typestore=self.ts
        )
        self._dets = self._writer.add_connection(detections_topic, DETECTIONS, typestore=self.ts)
        self._seq = 0

    def __enter__(self) -> ResultsBagWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _serialize(self, msg, typ: str) -> bytes:
        if self.ros == 1:
            return self.ts.serialize_ros1(msg, typ)
        return self.ts.serialize_cdr(msg, typ)

    def _header(self, stamp_ns: int, frame_id: str):
        T = self.ts.types
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if self.ros == 1:
            return T["std_msgs/msg/Header"](seq=self._seq, stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _pose(self, M: np.ndarray):
        T = self.ts.types
        q = Rotation.from_matrix(np.asarray(M, float)[:3, :3]).as_quat()
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    def write(self, frame: ResultFrame) -> None:
        """Write one frame's PoseArray and Detection3DArray."""
        T = self.ts.types
        header = self._header(frame.stamp_ns, frame.frame_id)
        poses = [self._pose(o.T_cam_obj) for o in frame.objects]
        pa = T["geometry_msgs/msg/PoseArray"](header=header, poses=poses)
        dets = []
        for o, pose in zip(frame.objects, poses, strict=True):
            pwc = T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
            if self.ros == 1:
                result = T["vision_msgs/msg/ObjectHypothesisWithPose"](
                    id=int(o.number), score=float(o.score), pose=pwc
                )
            else:
                hyp = T["vision_msgs/msg/ObjectHypothesis"](
                    class_id=o.class_name, score=float(o.score)
                )
                result = T["vision_msgs/msg/ObjectHypothesisWithPose"](hypothesis=hyp, pose=pwc)
            box_pose, size = (o.T_cam_obj, np.zeros(3)) if o.bbox is None else o.bbox
            bbox = T["vision_msgs/msg/BoundingBox3D"](
                center=self._pose(box_pose),
                size=T["geometry_msgs/msg/Vector3"](x=size[0], y=size[1], z=size[2]),
            )
            if self.ros == 1:
                cloud = T[POINTCLOUD2](
                    header=header, height=0, width=0, fields=[], is_bigendian=False,
                    point_step=0, row_step=0, data=np.zeros(0, np.uint8), is_dense=False,
                )  # fmt: skip
                det = T["vision_msgs/msg/Detection3D"](
                    header=header, results=[result], bbox=bbox, source_cloud=cloud
                )
            else:
                det = T["vision_msgs/msg/Detection3D"](
                    header=header, results=[result], bbox=bbox, id=str(o.id)
                )
            dets.append(det)
        da = T[DETECTIONS](header=header, detections=dets)
        t = int(frame.stamp_ns)
        self._writer.write(self._poses, t, self._serialize(pa, "geometry_msgs/msg/PoseArray"))
        self._writer.write(self._dets, t, self._serialize(da, DETECTIONS))
        self._seq += 1

    def close(self) -> None:
        """Finish the bag (for ``.mcap``: move the MCAP file to ``path``)."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        writer.close()
        if self._tmp is not None:
            (mcap,) = list((self._tmp / "bag").glob("*.mcap"))
            os.replace(mcap, self.path)
            shutil.rmtree(self._tmp, ignore_errors=True)


def write_results_bag(
    path: str | os.PathLike, frames: Iterable[ResultFrame], **topics: str
) -> Path:
    """Write ``frames`` with :class:`ResultsBagWriter` (``topics``: its topic names)."""
    with ResultsBagWriter(path, **topics) as w:
        for f in frames:
            w.write(f)
    return Path(path)
