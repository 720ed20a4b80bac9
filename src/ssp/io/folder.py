"""An input folder of frames for ``ssp run`` (docs/formats.md).

Layout::

    INPUT/
      scene.json                   # optional, see below
      frame1.ply                   # one cloud per frame: *.ply or *.pcd directly in INPUT,
      frame1.hypotheses.json       #   ordered by natural sort of the file name (frame2 < frame10);
      frame2.pcd                   #   optional hypotheses <stem>.hypotheses.json beside a cloud
      frame10.ply

Files starting with ``.``, sub-folders and other files are ignored. A frame's ``name`` is its
cloud's file name without the extension (two clouds with one stem are an error). A ``.ply`` /
``.pcd`` entry that is not a regular file (a dangling symbolic link, a link loop, a FIFO, a
device) is still a frame, in its place in the order: reading it fails with the reason, so the
stamps and indices of the other frames never shift.

``scene.json`` (every key optional; an unknown key is an error naming the closest known one):

``frame``
    ``"camera"`` (default): clouds are in the sensor frame (OpenCV axes, m); ``"world"``: z up,
    table top at z = 0.
``T_world_cam``
    4x4 camera pose (m). With ``"camera"`` clouds it is used instead of fitting the table; with
    ``"world"`` clouds it is the camera pose for visibility reasoning.
``period``
    seconds between frames (default 0.1): frame ``i`` has stamp ``i * period``. Or:
``stamps``
    ``{file name or stem: seconds}`` for every frame, non-decreasing in frame order.
``labels``
    ``"instance"`` (default): the cloud's label field holds instance ids; ``"class"``: it holds
    class ids, named by ``classes``.
``classes``
    ``{label value (string): class name}``; required for ``"class"`` labels; with ``"instance"``
    labels it optionally names the class of some instance labels.
``colors``
    ``{"#rrggbb": class name}``: colour-coded classes (exact colour match); a point whose colour
    is not listed is background. Labels then come from the colours, not from a label field.
``background_labels``
    label values that mean table / background (default ``[0]``); negative labels always do.
``camera_axes``
    the axes of ``"camera"`` clouds: ``"opencv"`` (default: x right, y down, z forward) or
    ``"opengl"`` (x right, y up, z backward, as PCL's Kinect tutorial clouds); ``"opengl"``
    clouds (and their camera-frame hypotheses) are turned to OpenCV axes when read.
"""

from __future__ import annotations

import difflib
import logging
import math
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ssp.errors import CloudFormatError, InputError, InvalidPoseError
from ssp.geometry import validate_pose
from ssp.io._files import file_problem, read_json
from ssp.io.bop import is_bop_scene
from ssp.io.clouds import CLOUD_SUFFIXES, read_cloud
from ssp.io.hypotheses import read_hypotheses
from ssp.scene import MM_CLOUD_MEDIAN, Hypothesis

__all__ = [
    "HYPOTHESES_SUFFIX",
    "FolderInput",
    "FrameFile",
    "RawFrame",
    "SceneSpec",
    "check_folder",
    "is_bop_scene",
    "natural_key",
    "open_folder",
    "read_scene_json",
]

log = logging.getLogger(__name__)

#: ``<stem>`` + this is the hypotheses file of cloud ``<stem>.ply`` / ``<stem>.pcd``.
HYPOTHESES_SUFFIX = ".hypotheses.json"
SCENE_JSON = "scene.json"
_SCENE_KEYS = (
    "frame",
    "T_world_cam",
    "period",
    "stamps",
    "labels",
    "classes",
    "colors",
    "background_labels",
    "camera_axes",
)
#: ``camera_axes`` value -> the rotation from those axes to OpenCV's.
CAMERA_AXES = {"opencv": np.eye(3), "opengl": np.diag([1.0, -1.0, -1.0])}
_HEX_COLOR = re.compile(r"^#([0-9a-fA-F]{6})$")


# ------------------------------------------------------------------------------ scene.json
@dataclass(frozen=True, eq=False)
class SceneSpec:
    """The validated ``scene.json`` of an input folder (defaults when there is none).

    Attributes:
        frame: ``"camera"`` or ``"world"``: the frame of the clouds.
        T_world_cam: ``(4, 4)`` camera pose, m, or None.
        period: s between frames (used when ``stamps`` is None).
        stamps: ``{file name or stem: s}``, or None.
        labels: ``"instance"`` or ``"class"``: what the label field holds.
        classes: ``{label value: class name}``.
        colors: ``{0xRRGGBB: class name}``.
        background_labels: label values that mean background (besides negative ones).
        camera_axes: ``"opencv"`` or ``"opengl"``: the axes of camera-frame clouds.
    """

    frame: str = "camera"
    T_world_cam: np.ndarray | None = None
    period: float = 0.1
    stamps: dict[str, float] | None = None
    labels: str = "instance"
    classes: dict[int, str] = field(default_factory=dict)
    colors: dict[int, str] = field(default_factory=dict)
    background_labels: frozenset[int] = frozenset({0})
    camera_axes: str = "opencv"

    @classmethod
    def from_dict(cls, doc: Any, where: str = SCENE_JSON) -> SceneSpec:
        """Validate a decoded ``scene.json``; InputError naming ``where`` and the key."""
        if not isinstance(doc, Mapping):
            raise InputError(f"{where}: expected a JSON object")
        for key in doc:
            if key not in _SCENE_KEYS:
                close = difflib.get_close_matches(str(key), _SCENE_KEYS, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise InputError(
                    f"{where}: unknown key {key!r}{hint}; known keys: {', '.join(_SCENE_KEYS)}"
                )
        frame = doc.get("frame", "camera")
        if frame not in ("camera", "world"):
            raise InputError(f"{where}: 'frame' must be 'camera' or 'world', got {frame!r}")
        axes = doc.get("camera_axes", "opencv")
        if axes not in CAMERA_AXES:
            raise InputError(
                f"{where}: 'camera_axes' must be 'opencv' (x right, y down, z forward) or "
                f"'opengl' (x right, y up, z backward), got {axes!r}"
            )
        if axes != "opencv" and frame != "camera":
            raise InputError(f"{where}: 'camera_axes' applies to 'frame': 'camera' clouds only")
        labels = doc.get("labels", "instance")
        if labels not in ("instance", "class"):
            raise InputError(f"{where}: 'labels' must be 'instance' or 'class', got {labels!r}")
        classes = _classes(doc.get("classes", {}), where)
        colors = _colors(doc.get("colors", {}), where)
        background = _background(doc.get("background_labels", [0]), where)
        if labels == "class" and not classes and not colors:
            raise InputError(f"{where}: 'labels': 'class' needs 'classes' ({{label: class name}})")
        if colors and ("classes" in doc or "labels" in doc):
            raise InputError(
                f"{where}: give either 'colors' (colour-coded classes) or 'labels'/'classes' "
                "(a label field), not both"
            )
        both = sorted(set(classes) & background)
        if both:
            raise InputError(
                f"{where}: label values {both} are in both 'classes' and 'background_labels'"
            )
        if "period" in doc and "stamps" in doc:
            raise InputError(f"{where}: give either 'period' or 'stamps', not both")
        return cls(
            frame=frame,
            T_world_cam=_pose(doc.get("T_world_cam"), where),
            period=_period(doc.get("period", 0.1), where),
            stamps=_stamps(doc["stamps"], where) if "stamps" in doc else None,
            labels=labels,
            classes=classes,
            colors=colors,
            background_labels=background,
            camera_axes=axes,
        )


def read_scene_json(path: str | os.PathLike) -> SceneSpec:
    """Read and validate a ``scene.json`` (InputError if unreadable or invalid)."""
    p = Path(path)
    return SceneSpec.from_dict(read_json(p), str(p))


def _int_key(key: Any, what: str) -> int:
    try:
        return int(str(key).strip())
    except ValueError as exc:
        raise InputError(f"{what}: label value {key!r} is not an integer") from exc


def _class_name(name: Any, what: str) -> str:
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{what}: class name must be a non-empty string, got {name!r}")
    return name


def _classes(raw: Any, where: str) -> dict[int, str]:
    if not isinstance(raw, Mapping):
        raise InputError(f"{where}: 'classes' must be an object {{label value: class name}}")
    return {
        _int_key(k, f"{where}: classes"): _class_name(v, f"{where}: classes[{k!r}]")
        for k, v in raw.items()
    }


def _colors(raw: Any, where: str) -> dict[int, str]:
    if not isinstance(raw, Mapping):
        raise InputError(f"{where}: 'colors' must be an object {{\"#rrggbb\": class name}}")
    out = {}
    for k, v in raw.items():
        m = _HEX_COLOR.match(str(k).strip())
        if m is None:
            raise InputError(f"{where}: colour {k!r} is not of the form '#rrggbb'")
        packed = int(m.group(1), 16)
        if packed in out:
            raise InputError(f"{where}: colour {k!r} is listed twice")
        out[packed] = _class_name(v, f"{where}: colors[{k!r}]")
    return out


def _background(raw: Any, where: str) -> frozenset[int]:
    if not isinstance(raw, list):
        raise InputError(f"{where}: 'background_labels' must be a list of integers")
    out = set()
    for v in raw:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v:
            raise InputError(f"{where}: background label {v!r} is not an integer")
        out.add(int(v))
    return frozenset(out)


def _pose(raw: Any, where: str) -> np.ndarray | None:
    if raw is None:
        return None
    try:
        return validate_pose(raw, f"{where}: T_world_cam")
    except InvalidPoseError as exc:
        raise InputError(str(exc)) from exc


def _seconds(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{what} must be a finite number of seconds, got {v!r}")
    return float(v)


def _period(raw: Any, where: str) -> float:
    p = _seconds(raw, f"{where}: 'period'")
    if p <= 0:
        raise InputError(f"{where}: 'period' must be > 0 s, got {p}")
    return p


def _stamps(raw: Any, where: str) -> dict[str, float]:
    if not isinstance(raw, Mapping):
        raise InputError(f"{where}: 'stamps' must be an object {{file name: seconds}}")
    return {str(k): _seconds(v, f"{where}: stamps[{k!r}]") for k, v in raw.items()}


# ------------------------------------------------------------------------------ frames
@dataclass(frozen=True)
class FrameFile:
    """One frame of an input folder: ``index`` (0-based, natural-sort order), ``name`` (the
    cloud's stem), its cloud, its hypotheses file or None, ``stamp`` (s; NaN for an entry
    that cannot be read and has no stamp), and ``problem``: why the cloud entry is not a
    regular file (:func:`ssp.io._files.file_problem`), None when it is one."""

    index: int
    name: str
    cloud_path: Path
    hypotheses_path: Path | None
    stamp: float
    problem: str | None = None


@dataclass
class RawFrame:
    """One frame as read from disk, before perception.

    Attributes:
        name, index, stamp: as in :class:`FrameFile` (stamp in s).
        cloud_path: the cloud file.
        points: ``(N, 3)`` float64, m, in ``frame`` (the scene's ``frame``); may hold NaN rows.
        labels: ``(N,)`` int64, -1 = background, ``>= 0`` = segment label (the file's values,
            or class indices for colour-coded classes); None without labels.
        label_kind: ``"instance"`` (a label is one object), ``"class"`` (a label is a class;
            several objects may share it), or None.
        label_classes: class name of label values when known (``"class"`` labels, colours, or
            ``classes`` given for instance labels), else None.
        colors: ``(N, 3)`` uint8 or None.
        viewpoint: ``(4, 4)`` sensor pose from a PCD ``VIEWPOINT``, or None.
        hypotheses: hypotheses from ``<name>.hypotheses.json`` (m) or None when there is none.
        hypotheses_frame: ``"world"`` or ``"camera"`` (then each ``T_world_obj`` holds
            ``T_cam_obj``; see :func:`ssp.io.hypotheses.to_world`), None without hypotheses.
        frame: ``"camera"`` or ``"world"``: the frame of ``points``.
        warnings: what is suspicious but not fatal (a colour map that matches no point), for
            the frame's output.
    """

    name: str
    index: int
    stamp: float
    cloud_path: Path
    points: np.ndarray
    labels: np.ndarray | None
    label_kind: str | None
    label_classes: dict[int, str] | None
    colors: np.ndarray | None
    viewpoint: np.ndarray | None
    hypotheses: list[Hypothesis] | None
    hypotheses_frame: str | None
    frame: str
    warnings: list[str] = field(default_factory=list)


def natural_key(name: str) -> tuple:
    """Sort key: digit runs compare as numbers, the rest case-insensitively
    (``frame2 < frame10``); the name itself breaks ties."""
    parts = re.split(r"([0-9]+)", name)
    key = tuple((0, int(p)) if p[:1].isdigit() else (1, p.lower()) for p in parts if p)
    return (key, name)


@dataclass
class FolderInput:
    """An opened input folder: its :class:`SceneSpec` and frames (see :func:`open_folder`)."""

    path: Path
    spec: SceneSpec
    frames: list[FrameFile]

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[FrameFile]:
        return iter(self.frames)

    def load(self, frame: FrameFile | int) -> RawFrame:
        """Read one frame's cloud and hypotheses.

        Raises:
            CloudFormatError: the cloud is not a regular file (:attr:`FrameFile.problem`),
                cannot be read, has no finite point, or looks like millimetres.
            InputError: bad hypotheses file, label values not in ``classes``, or colours
                required but missing. Every message names the file; other frames are unaffected.
        """
        ff = self.frames[frame] if isinstance(frame, int) else frame
        if ff.problem is not None:
            raise CloudFormatError(f"{ff.cloud_path}: {ff.problem}")
        cloud = read_cloud(ff.cloud_path)
        _check_metres(ff.cloud_path, cloud.points)
        points = cloud.points
        R = CAMERA_AXES[self.spec.camera_axes]
        if self.spec.camera_axes != "opencv":
            points = points @ R.T
        warnings: list[str] = []
        labels, kind, label_classes = _labels(self.spec, ff.cloud_path, cloud, warnings)
        hyps, hframe = None, None
        if ff.hypotheses_path is not None:
            hf = read_hypotheses(ff.hypotheses_path)
            hyps, hframe = hf.hypotheses, hf.frame
            if self.spec.camera_axes != "opencv" and hframe == "camera":
                D = np.eye(4)
                D[:3, :3] = R
                hyps = [replace(h, T_world_obj=D @ h.T_world_obj) for h in hyps]
        return RawFrame(
            name=ff.name,
            index=ff.index,
            stamp=ff.stamp,
            cloud_path=ff.cloud_path,
            points=points,
            labels=labels,
            label_kind=kind,
            label_classes=label_classes,
            colors=cloud.colors,
            viewpoint=cloud.viewpoint,
            hypotheses=hyps,
            hypotheses_frame=hframe,
            frame=self.spec.frame,
            warnings=warnings,
        )


def open_folder(path: str | os.PathLike) -> FolderInput:
    """List the frames of an input folder and read its ``scene.json`` (layout: module doc).

    Raises:
        InputError: not a folder, no frame files, two clouds with one stem, invalid
            ``scene.json``, or ``stamps`` that miss a readable frame, name no frame, or
            decrease.
    """
    root = Path(path)
    check_folder(root)
    scene = root / SCENE_JSON
    spec = read_scene_json(scene) if os.path.lexists(scene) else SceneSpec()
    clouds = sorted(
        (
            p
            for p in root.iterdir()
            if p.suffix.lower() in CLOUD_SUFFIXES and not p.name.startswith(".") and not p.is_dir()
        ),
        key=lambda p: natural_key(p.name),
    )
    problems = {p: file_problem(p) for p in clouds}
    if not clouds:
        hint = (
            " (it looks like a BOP scene folder: read it as a BOP sequence)"
            if is_bop_scene(root)
            else ""
        )
        raise InputError(f"{root}: no frames: no .ply or .pcd files in the folder{hint}")
    stems: dict[str, Path] = {}
    for p in clouds:
        if p.stem in stems:
            raise InputError(f"{root}: {stems[p.stem].name} and {p.name} are one frame name")
        stems[p.stem] = p
    stamps = _frame_stamps(root, spec, clouds, problems)
    frames = []
    for i, (p, stamp) in enumerate(zip(clouds, stamps, strict=True)):
        hyp = root / f"{p.stem}{HYPOTHESES_SUFFIX}"
        if problems[p] is not None:
            log.warning("%s: %s; that frame will be reported failed", p, problems[p])
        # any entry of that name counts (a broken one fails the frame when it is read)
        frames.append(
            FrameFile(i, p.stem, p, hyp if os.path.lexists(hyp) else None, stamp, problems[p])
        )
    for h in root.glob(f"*{HYPOTHESES_SUFFIX}"):
        if h.name[: -len(HYPOTHESES_SUFFIX)] not in stems:
            log.warning(
                "%s: no cloud %s.ply / .pcd for it; ignored", h, h.name[: -len(HYPOTHESES_SUFFIX)]
            )
    log.debug("%s: %d frames", root, len(frames))
    return FolderInput(path=root, spec=spec, frames=frames)


def check_folder(root: Path) -> None:
    """InputError unless ``root`` is an existing folder (the message says which it is)."""
    if root.is_dir():
        return
    if not os.path.lexists(root):
        raise InputError(f"{root}: the input folder does not exist")
    problem = file_problem(root)
    raise InputError(f"{root}: not a folder: it {problem or 'is a file'}")


def _frame_stamps(
    root: Path, spec: SceneSpec, clouds: list[Path], problems: Mapping[Path, str | None]
) -> list[float]:
    """Stamps (s) of the frames in order, from ``period`` or ``stamps``; an entry that cannot
    be read needs no stamp (NaN)."""
    if spec.stamps is None:
        return [i * spec.period for i in range(len(clouds))]
    where = f"{root / SCENE_JSON}: stamps"
    names = {p.name for p in clouds} | {p.stem for p in clouds}
    stray = sorted(k for k in spec.stamps if k not in names)
    if stray:
        raise InputError(f"{where}: no frame file for {', '.join(map(repr, stray))}")
    out, missing = [], []
    for p in clouds:
        s = spec.stamps.get(p.name, spec.stamps.get(p.stem))
        if s is None and problems.get(p) is None:
            missing.append(p.name)
        out.append(math.nan if s is None else s)
    if missing:
        raise InputError(f"{where}: no stamp for {', '.join(missing)}")
    good = [k for k in range(len(out)) if not math.isnan(out[k])]
    for j, k in zip(good[:-1], good[1:], strict=True):
        a, b, pa, pb = out[j], out[k], clouds[j], clouds[k]
        if b < a:
            raise InputError(
                f"{where}: {pb.name} ({b} s) is earlier than {pa.name} ({a} s); frames are "
                "processed in natural-sort order of their names"
            )
    return out


# ------------------------------------------------------------------------------ per frame
def _check_metres(path: Path, points: np.ndarray) -> None:
    finite = np.isfinite(points).all(axis=1)
    if not finite.any():
        raise CloudFormatError(f"{path}: no finite points (all {len(points)} are NaN or infinite)")
    median = float(np.median(np.linalg.norm(points[finite], axis=1)))
    if median > MM_CLOUD_MEDIAN:
        raise CloudFormatError(
            f"{path}: median distance from the origin is {median:.1f} m; the cloud looks like "
            "millimetres (ssp reads metres): divide the coordinates by 1000"
        )


def _labels(
    spec: SceneSpec, path: Path, cloud, warnings: list[str]
) -> tuple[np.ndarray | None, str | None, dict[int, str] | None]:
    """``(labels with -1 background, label kind, label classes)`` of one cloud; suspicious
    findings are appended to ``warnings``."""
    if spec.colors:
        return _color_labels(spec, path, cloud, warnings)
    if cloud.labels is None:
        return None, None, None
    raw = cloud.labels
    bg = (raw < 0) | np.isin(raw, np.fromiter(spec.background_labels, dtype=np.int64))
    labels = np.where(bg, -1, raw).astype(np.int64)
    values = [int(v) for v in np.unique(labels[labels >= 0])]
    if spec.labels == "class":
        unknown = [v for v in values if v not in spec.classes]
        if unknown:
            raise InputError(
                f"{path}: label values {unknown} (field {cloud.label_field!r}) are in neither "
                "'classes' nor 'background_labels' of scene.json"
            )
        return labels, "class", {v: spec.classes[v] for v in values}
    named = {v: spec.classes[v] for v in values if v in spec.classes} if spec.classes else None
    return labels, "instance", named


def _color_labels(
    spec: SceneSpec, path: Path, cloud, warnings: list[str]
) -> tuple[np.ndarray, str, dict[int, str]]:
    """Class labels from colour-coded points: label = index of the class in the sorted names.
    A colour map that matches no point is a warning naming the cloud's most common colours."""
    if cloud.colors is None:
        raise InputError(f"{path}: scene.json lists 'colors' but the cloud has no colour fields")
    if cloud.labels is not None:
        log.info("%s: labels come from colours; field %r ignored", path, cloud.label_field)
    names = sorted(set(spec.colors.values()))
    index = {c: i for i, c in enumerate(names)}
    keys = np.array(sorted(spec.colors), dtype=np.int64)
    vals = np.array([index[spec.colors[int(k)]] for k in keys], dtype=np.int64)
    c = cloud.colors.astype(np.int64)
    packed = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    pos = np.clip(np.searchsorted(keys, packed), 0, len(keys) - 1)
    hit = keys[pos] == packed
    labels = np.where(hit, vals[pos], -1)
    if not hit.any():
        colours, counts = np.unique(packed, return_counts=True)
        top = colours[np.argsort(-counts, kind="stable")[:5]]
        msg = (
            f"{path}: no point has a colour of scene.json 'colors' "
            f"({', '.join(f'#{int(k):06x}' for k in keys)}), so the frame has no object "
            f"segments; its most common colours are {', '.join(f'#{int(c):06x}' for c in top)}"
        )
        log.warning("%s", msg)
        warnings.append(msg)
    present = sorted({int(v) for v in np.unique(labels[labels >= 0])})
    return labels, "class", {v: names[v] for v in present}
