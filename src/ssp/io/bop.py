"""Read BOP datasets as the BOP toolkit publishes them, scene by scene and frame by frame.

Layout (bop_toolkit ``docs/bop_datasets_format.md``; ``ssp simulate`` writes the same)::

    DATASET/
      camera.json                   # cx, cy, fx, fy, width, height, depth_scale
      models/models_info.json       # per obj_id: diameter, extents, symmetries (mm)
      models/obj_000001.ply         # meshes, mm
      models.json                   # (ssp, optional) {"obj_ids": {"1": "cube", ...}}
      test/000001/                  # one scene: SPLIT/SCENE_ID
        scene_camera.json           # {im_id: {cam_K, depth_scale, [cam_R_w2c, cam_t_w2c (mm)]}}
        scene_gt.json               # {im_id: [{obj_id, cam_R_m2c, cam_t_m2c (mm)}]} (optional)
        scene_gt_info.json          # {im_id: [{visib_fract, ...}]}                  (optional)
        depth/000000.png            # 16-bit depth, depth_scale mm per unit, 0 = none
        mask_visib/000000_000000.png  # visible mask of the k-th scene_gt entry (optional)

Scenes written by ``ssp simulate`` also hold ``sequence.json`` (stamps, stages, seed),
``hypotheses.json`` (its simulated estimator, world frame, t in mm), ``instance/`` (the
segmentation it simulates) and ``models.json``; published scenes have none of these, and then:

* **stamps** are ``im_id x period`` (``period`` s, default :data:`DEFAULT_PERIOD`);
* the **camera** of each image is its own ``cam_K`` (size from ``DATASET/camera.json``, else
  the depth image);
* the **world frame** is ``cam_R_w2c``/``cam_t_w2c`` when the scene gives them, else None (the
  caller fits the table plane to the depth: never from the ground truth);
* **classes** are ``obj_XXXXXX`` (the model file names:
  :func:`ssp.library.properties.read_bop_models`) unless a ``models.json`` beside the
  scene or the dataset names them;
* ground truth (``scene_gt.json``, ``mask_visib/``) is optional and only for evaluation. Its
  rotations are read as published (:func:`published_rotation`): LM-O's are orthonormal only to
  about 1e-3, so each is replaced by its nearest rotation (SVD), with one warning per file
  when any deviates more than :data:`ROTATION_WARN`; a matrix far from any rotation is an
  error naming the file, image and entry.

:func:`open_bop` reads the JSON files of a scene; :meth:`BopScene.load` reads one frame's images
when it is needed, so a long scene is never in memory at once and one unreadable image fails that
frame alone with an :class:`~ssp.errors.InputError` naming the file. :func:`bop_scenes` lists the
scene folders of a dataset (or the one scene given).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ssp.camera import Camera
from ssp.errors import ArgumentError, InputError
from ssp.geometry import ORTHONORMAL_TOL, nearest_rotation
from ssp.io._files import file_problem, read_json
from ssp.perception.depth import depth_doubt
from ssp.scene import Hypothesis

__all__ = [
    "DEFAULT_PERIOD",
    "DEPTH_SCALE",
    "MASK_MODES",
    "MAX_IMAGE_PIXELS",
    "BopFrame",
    "BopScene",
    "bop_scenes",
    "by_bop_name",
    "dataset_root",
    "is_bop_scene",
    "mask_source",
    "open_bop",
    "published_rotation",
    "read_png",
    "read_targets",
    "rotation_deviation",
]

#: Depth PNG unit written by ssp, mm (0.1 mm: depths up to 6.5 m).
DEPTH_SCALE = 0.1
#: The most pixels of an image (depth, mask) :func:`read_png` decodes: 25 Mpx, about ten times a
#: 4K depth sensor's; a header that claims more is refused before decoding.
MAX_IMAGE_PIXELS = 25_000_000
#: Seconds between consecutive ``im_id`` of a published scene (which has no stamps).
DEFAULT_PERIOD = 1.0 / 30.0
#: A published rotation deviating from orthonormal (max ``|R R^T - I|``) by more than this is
#: re-orthonormalised with a warning: ssp's own tolerance for a pose (``ORTHONORMAL_TOL``,
#: what six printed digits give with a margin). Below it the nearest rotation is taken silently.
ROTATION_WARN = ORTHONORMAL_TOL
#: Farther than this from orthonormal (or a reflection, det < 0) a "rotation" is an error: 0.1
#: is a hundred times LM-O's published error (1e-3) and a matrix that far off (a scale of 5 %,
#: a shear, a transposed or garbled row) is a wrong file, not rounding.
ROTATION_MAX = 0.1
log = logging.getLogger(__name__)

SPLITS = ("test", "val", "train", "train_pbr", "train_real", "train_synt", "test_primesense")


#: What segmentation a run uses on a BOP scene: ``auto`` the one an ssp scene simulates
#: (``instance/``) and none for a published scene; ``gt`` the ground-truth ``mask_visib`` (an
#: upper bound: never the default); ``none`` no masks (the cloud above the table is clustered);
#: ``silhouettes`` the given hypotheses' rendered silhouettes (:mod:`ssp.perception.silhouettes`).
MASK_MODES = ("auto", "gt", "none", "silhouettes")


def mask_source(masks: str, simulated: bool) -> str | None:
    """The ``masks`` argument of :meth:`BopScene.load` for a run's ``masks`` mode (one of
    :data:`MASK_MODES`; ArgumentError otherwise) on a scene ``simulated`` by ssp or not."""
    if masks not in MASK_MODES:
        raise ArgumentError(f"masks must be one of {', '.join(MASK_MODES)}, got {masks!r}")
    return {"gt": "gt", "none": None, "silhouettes": None}.get(
        masks, "scene" if simulated else None
    )


def load_json(path: Path) -> Any:
    """The JSON of ``path`` (:func:`ssp.io._files.read_json`)."""
    return read_json(path)


def read_png(path: Path) -> np.ndarray:
    """The pixels of a PNG; InputError naming the file when it is missing, not a regular
    file (never opened then: a FIFO would block), truncated or corrupt."""
    problem = file_problem(path)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    try:
        size = _png_size(path)
        if size is not None:
            _check_size(path, *size)
        with Image.open(path) as im:  # reads the header only
            _check_size(path, *im.size)
            im.load()
            return np.asarray(im)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: cannot read the image: {exc}") from exc  # PIL: corrupt


def _check_size(path: Path, w: int, h: int) -> None:
    """InputError when an image header claims more than :data:`MAX_IMAGE_PIXELS` pixels."""
    if w * h > MAX_IMAGE_PIXELS:
        raise InputError(
            f"{path}: the image header says {w} x {h} pixels, more than the "
            f"{MAX_IMAGE_PIXELS:,} ssp reads (a corrupt or hostile file?); not decoded"
        )


def _png_size(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG file's IHDR chunk (its first 24 bytes), or None when
    the file is no PNG; read before PIL opens it (PIL refuses a huge one with its own words)."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def rotation_deviation(R: np.ndarray) -> np.ndarray:
    """How far 3x3 matrices ``(..., 3, 3)`` are from orthonormal: ``max |R R^T - I|``."""
    R = np.asarray(R, dtype=float)
    return np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(-2, -1))


def published_rotation(values: Any, where: str) -> np.ndarray:
    """The rotation (3x3) nearest a published one (9 numbers, row-major): the SVD's
    ``U V^T``, so a rotation printed with few digits (LM-O's ground truth: about 1e-3) is a
    rotation again. Warning about it is the caller's (:data:`ROTATION_WARN`: once per file).

    Raises:
        InputError: not 9 finite numbers, a reflection (det < 0) or farther than
            :data:`ROTATION_MAX` from orthonormal; the message starts with ``where`` (file,
            image, row and key, e.g. ``".../scene_gt.json: im_id 3, entry 0: cam_R_m2c"``).
    """
    try:
        M = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        M = np.zeros(0)
    if M.size != 9 or not np.all(np.isfinite(M)):
        raise InputError(f"{where} must be 9 numbers (3x3, row-major, finite), got {values!r:.80}")
    M = M.reshape(3, 3)
    dev, det = float(rotation_deviation(M)), float(np.linalg.det(M))
    if det <= 0 or dev > ROTATION_MAX:
        raise InputError(
            f"{where} is not a rotation (|R R^T - I| = {dev:.2g}, det {det:.3f}; at most "
            f"{ROTATION_MAX:g} off is re-orthonormalised, a reflection never)"
        )
    return nearest_rotation(M)


#: The ``scene_gt.json`` files already warned about (path, modification time): a command opens
#: a scene more than once (its ids, its frames, a refine's check), the warning is once a file.
_WARNED_ROTATIONS: set[tuple[str, int]] = set()


def _warn_rotations(path: Path, scene_gt: Mapping[str, Any]) -> None:
    """One warning when rotations (``cam_R_m2c``) of ``scene_gt.json`` deviate from
    orthonormal by more than :data:`ROTATION_WARN` (malformed entries are left to
    :meth:`BopScene.load`, which names them); once per file and process."""
    try:
        key = (str(path.resolve()), path.stat().st_mtime_ns)
    except OSError:
        return
    if key in _WARNED_ROTATIONS:
        return
    _WARNED_ROTATIONS.add(key)
    found: list[tuple[float, str, int]] = []
    for im, entries in scene_gt.items():
        for j, g in enumerate(entries if isinstance(entries, list) else []):
            try:
                R = np.asarray(g["cam_R_m2c"], dtype=float).reshape(3, 3)
            except (KeyError, TypeError, ValueError):
                continue
            found.append((float(rotation_deviation(R)), str(im), j))
    off = [f for f in found if f[0] > ROTATION_WARN]
    if off:
        worst = max(off)
        log.warning(
            "%s: %d of %d rotations (cam_R_m2c) are orthonormal only to %.1e (worst: im_id %s, "
            "entry %d); each is replaced by its nearest rotation (SVD)",
            path,
            len(off),
            len(found),
            worst[0],
            worst[1],
            worst[2],
        )


#: The BOP19 test targets of a dataset (``DATASET/test_targets_bop19.json``).
TARGETS_FILE = "test_targets_bop19.json"


def read_targets(dataset: str | os.PathLike) -> dict[tuple[int, int], dict[int, int]] | None:
    """``(scene_id, im_id) -> {obj_id: inst_count}`` from the dataset's
    :data:`TARGETS_FILE` (a list of ``{scene_id, im_id, obj_id, inst_count}``), or None when
    the dataset has none.

    Raises:
        InputError: a malformed file (named).
    """
    path = Path(dataset) / TARGETS_FILE
    if not path.is_file():
        return None
    doc = load_json(path)
    out: dict[tuple[int, int], dict[int, int]] = {}
    try:
        for t in doc:
            key = (int(t["scene_id"]), int(t["im_id"]))
            out.setdefault(key, {})[int(t["obj_id"])] = int(t.get("inst_count", 1))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: expected a list of {{scene_id, im_id, obj_id, inst_count}}: "
                         f"{exc!r}") from exc  # fmt: skip
    return out


def is_bop_scene(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a BOP scene folder: a ``scene_camera.json`` and a ``depth/`` folder
    or a ``scene_gt.json``."""
    p = Path(path)
    return (p / "scene_camera.json").is_file() and (
        (p / "depth").is_dir() or (p / "scene_gt.json").is_file()
    )


def dataset_root(scene: str | os.PathLike) -> Path | None:
    """The dataset folder of a scene folder ``DATASET/SPLIT/SCENE`` (the one holding
    ``camera.json`` or ``models/``), or None for a scene on its own."""
    p = Path(scene).resolve()
    root = p.parent.parent
    if (root / "camera.json").is_file() or (root / "models").is_dir():
        return root
    return None


def bop_scenes(path: str | os.PathLike, split: str | None = None) -> list[Path]:
    """The scene folders of ``path``: itself when it is a scene; else those of ``path/SPLIT/``
    (``split``, or the one split folder that holds scenes: ``test`` first), in scene-id order.

    Raises:
        InputError: no scene found, or several splits and none chosen.
    """
    p = Path(path)
    if is_bop_scene(p):
        return [p]
    if not p.is_dir():
        raise InputError(f"{p}: no such folder")

    def scenes_of(d: Path) -> list[Path]:
        found = [s for s in d.iterdir() if s.is_dir() and is_bop_scene(s)] if d.is_dir() else []
        return sorted(found, key=lambda s: (not s.name.isdigit(), s.name))

    if split is not None:
        found = scenes_of(p / split)
        if not found:
            raise InputError(f"{p / split}: no BOP scene folders (SCENE_ID/scene_camera.json)")
        return found
    if scenes_of(p):  # a split folder itself
        return scenes_of(p)
    splits = [d.name for d in sorted(p.iterdir()) if d.is_dir() and scenes_of(d)]
    if not splits:
        raise InputError(
            f"{p}: not a BOP dataset or scene: no SPLIT/SCENE_ID/scene_camera.json below it"
        )
    if "test" in splits:
        return scenes_of(p / "test")
    if len(splits) > 1:
        raise InputError(f"{p}: several splits ({', '.join(splits)}): choose one with --split")
    return scenes_of(p / splits[0])


@dataclass
class BopFrame:
    """One image of a BOP scene, read by :meth:`BopScene.load`.

    Attributes:
        im_id: BOP image id; ``stamp`` its time, s.
        camera: the image's intrinsics.
        T_world_cam: camera pose in the scene's world frame, or None (no world frame given).
        depth: ``(H, W)`` float32, m (0 = no return); None when not read (``load(k,
            depth=False)``).
        instance: ``(H, W)`` int16 segmentation: ``k`` = ``k``-th object, -1 table or
            background with depth, -2 nothing; the simulated segmentation of an ssp scene, the
            ground-truth masks of a published one, None when there are neither.
        gt: ground truth, instance id -> ``(class, T_cam_obj)`` (camera frame, m); empty
            without ``scene_gt.json``. ``visib_fract``: instance id -> visible fraction.
        hypotheses: the scene's own hypotheses (``hypotheses.json``; in the frame
            :attr:`BopScene.hypotheses_frame` says).
        static_group: the stage of an ssp scene (0 for published scenes).
        warnings: what is suspicious about the frame's files (an 8-bit depth image, a depth
            scale that puts the scene at an implausible distance: said once per scene, on the
            first frame it is seen in, and logged).
    """

    im_id: int
    stamp: float
    camera: Camera
    T_world_cam: np.ndarray | None
    depth: np.ndarray | None
    instance: np.ndarray | None
    gt: dict[str, tuple[str, np.ndarray]]
    visib_fract: dict[str, float]
    hypotheses: list[Hypothesis]
    static_group: int = 0
    instance_is_gt: bool = False
    warnings: list[str] = field(default_factory=list)


@dataclass
class BopScene:
    """A BOP scene folder opened by :func:`open_bop`: its metadata, with the frames' images
    read one at a time by :meth:`load`.

    Attributes:
        path: the folder; ``scene_id`` its BOP scene id (the folder name when numeric, else 0).
        classes: ``obj_id -> class name``.
        im_ids: the images in order; ``stamps`` their times (s); ``static_groups`` their stages.
        has_hypotheses: the folder has a ``hypotheses.json``; ``has_world``: every image has
            ``cam_R_w2c``; ``simulated``: written by ``ssp simulate`` (``sequence.json``).
        meta: the ``sequence.json`` of an ssp scene (empty for a published one).
    """

    path: Path
    scene_id: int
    classes: dict[int, str]
    im_ids: list[int]
    stamps: list[float]
    static_groups: list[int]
    has_hypotheses: bool
    has_world: bool
    simulated: bool
    meta: dict = field(default_factory=dict)
    _size: tuple[int, int] | None = field(repr=False, default=None)
    _scene_gt: dict = field(repr=False, default_factory=dict)
    _scene_camera: dict = field(repr=False, default_factory=dict)
    _scene_info: dict = field(repr=False, default_factory=dict)
    _hypotheses: dict = field(repr=False, default_factory=dict)
    _depth_doubted: bool = field(repr=False, default=False)

    def __len__(self) -> int:
        return len(self.im_ids)

    def __iter__(self) -> Iterator[BopFrame]:
        """The frames in order, each read when it is reached."""
        return (self.load(k) for k in range(len(self)))

    @property
    def models(self) -> tuple[str, ...]:
        """The classes the scene may hold: an ssp scene's generator list, else every model of
        the dataset (never read from the ground truth)."""
        if self.meta.get("models"):
            return tuple(self.meta["models"])
        return tuple(self.classes[i] for i in sorted(self.classes))

    def has_entry(self, k: int) -> bool:
        """Whether ``hypotheses.json`` lists the ``k``-th frame (an empty list counts)."""
        return str(self.im_ids[k]) in self._hypotheses

    def camera_of(self, k: int) -> Camera:
        """The intrinsics of the ``k``-th image (its ``cam_K``; size from the dataset)."""
        cam = self._camera_entry(k)
        try:
            K = np.asarray(cam["cam_K"], dtype=float).reshape(3, 3)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{self.path / 'scene_camera.json'}: im_id {self.im_ids[k]}: "
                f"no valid cam_K ({exc!r})"
            ) from exc
        if self._size is not None:
            w, h = self._size
        else:
            h, w = read_png(self._depth_path(k)).shape[:2]
        try:
            return Camera(
                int(w), int(h), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
            )
        except ArgumentError as exc:  # fx = 0, a NaN principal point, ...
            raise InputError(
                f"{self.path / 'scene_camera.json'}: im_id {self.im_ids[k]}: invalid cam_K: {exc}"
            ) from None

    def T_world_cam_of(self, k: int) -> np.ndarray | None:
        """The camera pose of the ``k``-th image from ``cam_R_w2c``/``cam_t_w2c`` (m), or
        None when the scene gives none."""
        cam = self._camera_entry(k)
        if "cam_R_w2c" not in cam:
            return None
        try:
            T_cw = np.eye(4)
            T_cw[:3, :3] = np.asarray(cam["cam_R_w2c"], dtype=float).reshape(3, 3)
            T_cw[:3, 3] = np.asarray(cam["cam_t_w2c"], dtype=float).reshape(3) / 1000.0
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{self.path / 'scene_camera.json'}: im_id {self.im_ids[k]}: "
                f"malformed cam_R_w2c/cam_t_w2c ({exc!r})"
            ) from exc
        if not np.all(np.isfinite(T_cw)):
            raise InputError(
                f"{self.path / 'scene_camera.json'}: im_id {self.im_ids[k]}: "
                "cam_R_w2c/cam_t_w2c are not finite"
            )
        R = T_cw[:3, :3]
        T_wc = np.eye(4)
        T_wc[:3, :3] = R.T
        T_wc[:3, 3] = -R.T @ T_cw[:3, 3]
        return T_wc

    def _camera_entry(self, k: int) -> Mapping[str, Any]:
        try:
            cam = self._scene_camera[str(self.im_ids[k])]
        except KeyError:
            raise InputError(
                f"{self.path / 'scene_camera.json'}: no entry for im_id {self.im_ids[k]}"
            ) from None
        if not isinstance(cam, Mapping):
            raise InputError(
                f"{self.path / 'scene_camera.json'}: im_id {self.im_ids[k]}: not an object"
            )
        return cam

    def _depth_path(self, k: int) -> Path:
        return self.path / "depth" / f"{self.im_ids[k]:06d}.png"

    def load(self, k: int, *, masks: str | None = "scene", depth: bool = True) -> BopFrame:
        """Read the ``k``-th frame (0-based position, not ``im_id``): depth, segmentation,
        ground truth (camera frame) and the scene's hypotheses.

        ``depth=False`` reads no image (``BopFrame.depth`` is None; ``masks`` must be None):
        what an evaluation without VSD needs, on a published dataset without depth images.

        ``masks``: ``"scene"`` the segmentation an ssp scene simulates (``instance/``), else
        the ground-truth ``mask_visib``; ``"gt"`` always ``mask_visib``; None no segmentation.

        Raises:
            InputError: a missing or unreadable image, or a malformed entry of this frame;
                the message names the file. Other frames are unaffected.
        """
        d, im = self.path, self.im_ids[k]
        key = str(im)
        cam_entry = self._camera_entry(k)
        camera = self.camera_of(k)
        T_wc = self.T_world_cam_of(k)
        try:
            gt: dict[str, tuple[str, np.ndarray]] = {}
            for j, g in enumerate(self._scene_gt.get(key, [])):
                T_co = np.eye(4)
                T_co[:3, :3] = published_rotation(
                    g["cam_R_m2c"], f"{d / 'scene_gt.json'}: im_id {im}, entry {j}: cam_R_m2c"
                )
                T_co[:3, 3] = np.asarray(g["cam_t_m2c"], dtype=float).reshape(3) / 1000.0
                cls = self.classes.get(int(g["obj_id"]), f"obj_{int(g['obj_id']):06d}")
                gt[str(g.get("inst_id", f"{cls}_{j}"))] = (cls, T_co)
            ids = list(gt)
            visib = {
                str(e.get("inst_id", ids[j])): float(e["visib_fract"])
                for j, e in enumerate(self._scene_info.get(key, []))
                if j < len(ids)
            }
            depth_scale = float(cam_entry.get("depth_scale", 1.0))
            hl = [self._hypothesis(h) for h in self._hypotheses.get(key, [])]
        except InputError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"{d}: malformed entry of im_id {im}: {exc!r}") from exc
        if not (depth_scale > 0 and np.isfinite(depth_scale)):
            raise InputError(
                f"{d / 'scene_camera.json'}: im_id {im}: depth_scale "
                f"{depth_scale!r} must be a positive number (mm per unit)"
            )
        instance, from_gt = (None, False)
        if not depth:
            if masks is not None:
                raise ArgumentError("a frame's segmentation needs its depth: masks=None")
            image, warnings = None, []
        else:
            image, warnings = self._depth(k, depth_scale, camera, T_wc)
        if image is not None and masks is not None:
            instance, from_gt = self._instance(k, len(ids), image, gt_only=masks == "gt")
        return BopFrame(
            im_id=int(im),
            stamp=self.stamps[k],
            camera=camera,
            T_world_cam=T_wc,
            depth=image,
            instance=instance,
            gt=gt,
            visib_fract=visib,
            hypotheses=hl,
            static_group=self.static_groups[k],
            instance_is_gt=from_gt,
            warnings=warnings,
        )

    def _depth(
        self, k: int, depth_scale: float, camera: Camera, T_wc: np.ndarray | None
    ) -> tuple[np.ndarray, list[str]]:
        """The depth image of frame ``k`` (m, float32) and the warnings about it."""
        raw = read_png(self._depth_path(k))
        if raw.ndim != 2:
            raise InputError(
                f"{self._depth_path(k)}: expected a one-channel depth image, got shape {raw.shape}"
            )
        depth = (raw.astype(np.float64) * depth_scale / 1000.0).astype(np.float32)
        if depth.shape != (camera.height, camera.width):
            raise InputError(
                f"{self._depth_path(k)}: {depth.shape[1]} x {depth.shape[0]} "
                f"pixels, the camera has {camera.width} x {camera.height}"
            )
        return depth, self._doubt_depth(k, raw, depth, depth_scale, T_wc)

    def _doubt_depth(
        self,
        k: int,
        raw: np.ndarray,
        depth: np.ndarray,
        depth_scale: float,
        T_wc: np.ndarray | None,
    ) -> list[str]:
        """The warning (once per scene: the frames after it are not checked) when the depth
        image of frame ``k`` is 8-bit or its depth scale puts the scene at an implausible
        distance (:func:`ssp.perception.depth.depth_doubt`); logged."""
        if self._depth_doubted:
            return []
        origin = None if T_wc is None else float(np.linalg.norm(T_wc[:3, 3]))
        doubt = depth_doubt(
            depth,
            raw_dtype=raw.dtype,
            origin_distance=origin,
            scale_note=f" (depth_scale {depth_scale:g} mm per unit, scene_camera.json)",
        )
        if doubt is None:
            return []
        self._depth_doubted = True
        message = f"{self._depth_path(k)}: {doubt} (said once for the scene)"
        log.warning("%s", message)
        return [message]

    def _instance(
        self, k: int, n_gt: int, depth: np.ndarray, gt_only: bool = False
    ) -> tuple[np.ndarray | None, bool]:
        im = self.im_ids[k]
        inst_path = self.path / "instance" / f"{im:06d}.png"
        if inst_path.exists() and not gt_only:
            instance = (read_png(inst_path).astype(np.int32) - 2).astype(np.int16)
            from_gt = False
        elif (self.path / "mask_visib").is_dir() and n_gt:
            instance = np.where(depth > 0, -1, -2).astype(np.int16)
            for j in range(n_gt):
                m = self.path / "mask_visib" / f"{im:06d}_{j:06d}.png"
                if m.exists():
                    pixels = read_png(m)
                    if pixels.shape != depth.shape:
                        raise InputError(
                            f"{m}: mask of shape {pixels.shape} (height, width[, channels]), "
                            f"the depth image is {depth.shape}"
                        )
                    instance[pixels > 0] = j
            from_gt = True
        else:
            return None, False
        if instance.shape != depth.shape:
            raise InputError(
                f"{inst_path}: shape {instance.shape} differs from the depth image's {depth.shape}"
            )
        return instance, from_gt

    @property
    def hypotheses_frame(self) -> str:
        """The frame of ``hypotheses.json``'s poses: ``"camera"`` when its entries give
        ``cam_R_m2c``/``cam_t_m2c`` (BOP's names; a scene without camera poses), else
        ``"world"`` (``R``/``t``)."""
        for entries in self._hypotheses.values():
            for h in entries:
                return "camera" if isinstance(h, Mapping) and "cam_R_m2c" in h else "world"
        return "world"

    def _hypothesis(self, h: Mapping[str, Any]) -> Hypothesis:
        T = np.eye(4)
        camera = self.hypotheses_frame == "camera"
        T[:3, :3] = np.asarray(h["cam_R_m2c" if camera else "R"], dtype=float).reshape(3, 3)
        T[:3, 3] = np.asarray(h["cam_t_m2c" if camera else "t"], dtype=float) / 1000.0
        return Hypothesis(h.get("class") or self.classes[int(h["obj_id"])], T, float(h["score"]))


def _scene_size(d: Path, meta: Mapping[str, Any]) -> tuple[int, int] | None:
    """``(width, height)`` of the images of scene ``d``: its ``sequence.json``'s camera, else
    the ``camera.json`` of the scene or its dataset, else None (the depth images' size)."""
    if "camera" in meta:
        return (int(meta["camera"]["width"]), int(meta["camera"]["height"]))
    for folder in (d, dataset_root(d)):
        if folder is not None and (folder / "camera.json").is_file():
            return _camera_json_size(folder / "camera.json")
    return None


def _camera_json_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of a dataset's ``camera.json``; InputError naming the file when
    they are not positive integers (at most :data:`MAX_IMAGE_PIXELS` pixels) or when the
    intrinsics it gives (``fx``, ``fy``, ``cx``, ``cy``) are not a camera's."""
    c = load_json(path)
    if not isinstance(c, Mapping):
        raise InputError(f"{path}: expected an object {{width, height, fx, ...}}")
    try:
        w, h = c["width"], c["height"]
    except KeyError as exc:
        raise InputError(f"{path}: no {exc.args[0]!r}") from None
    for name, v in (("width", w), ("height", h)):
        if isinstance(v, bool) or not isinstance(v, int | float) or v != int(v) or v < 1:
            raise InputError(f"{path}: {name} must be a positive number of pixels, got {v!r}")
    if int(w) * int(h) > MAX_IMAGE_PIXELS:
        raise InputError(
            f"{path}: {int(w)} x {int(h)} pixels is more than the {MAX_IMAGE_PIXELS:,} ssp reads"
        )
    for name in ("fx", "fy", "cx", "cy"):
        v = c.get(name)
        if v is None:
            continue
        ok = isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v)
        if not ok or (name in ("fx", "fy") and v <= 0):
            what = "a positive number" if name in ("fx", "fy") else "a finite number"
            raise InputError(f"{path}: {name} must be {what} (pixels), got {v!r}")
    return int(w), int(h)


def _classes(d: Path) -> dict[int, str]:
    """``obj_id -> class`` from a ``models.json`` in the scene or its dataset, else the ids
    of ``models/models_info.json`` as ``obj_XXXXXX`` (empty when neither exists)."""
    root = dataset_root(d)
    for folder in (d, root):
        if folder is not None and (folder / "models.json").is_file():
            doc = load_json(folder / "models.json")
            try:
                return {int(k): str(v) for k, v in doc["obj_ids"].items()}
            except (KeyError, TypeError, ValueError, AttributeError) as exc:
                raise InputError(f"{folder / 'models.json'}: malformed obj_ids: {exc!r}") from exc
    if root is not None and (root / "models" / "models_info.json").is_file():
        info = load_json(root / "models" / "models_info.json")
        if isinstance(info, Mapping):
            return {int(k): f"obj_{int(k):06d}" for k in info if str(k).isdigit()}
    return {}


def by_bop_name(classes: Mapping[int, str], library: Mapping | None) -> dict[str, str]:
    """``class -> obj_XXXXXX`` for the classes of ``classes`` (``obj_id -> class``, named by a
    ``models.json``, as ``ssp simulate`` writes) that are not in ``library`` but whose BOP
    model name is: a library read from the dataset's own ``models/`` folder names its models
    by obj_id. Empty without a library."""
    if library is None:
        return {}
    return {
        c: f"obj_{i:06d}"
        for i, c in classes.items()
        if c not in library and f"obj_{i:06d}" in library
    }


def _renamed_entries(entries: Any, renamed: Mapping[str, str]) -> Any:
    """``hypotheses.json`` entries of one image with their ``class`` renamed (``renamed``);
    anything malformed as it is (the reader names it)."""
    if not isinstance(entries, list):
        return entries
    return [
        {**h, "class": renamed[h["class"]]}
        if isinstance(h, Mapping) and isinstance(h.get("class"), str) and h["class"] in renamed
        else h
        for h in entries
    ]


def open_bop(path, library: Mapping | None = None, *, period: float = DEFAULT_PERIOD) -> BopScene:
    """Open a BOP scene folder (module docstring): read its JSON files (not its images).

    Args:
        path: the scene folder ``DATASET/SPLIT/SCENE_ID`` (or a scene on its own).
        library: when given, every class of the scene's ground truth and hypotheses must be
            in it (checked here, so a run fails before its first frame); a class a
            ``models.json`` names that it lacks is its BOP model ``obj_XXXXXX`` when it has
            that (the dataset's own ``models/`` folder).
        period: seconds between consecutive ``im_id`` when the scene has no stamps.

    Raises:
        InputError: a missing or invalid JSON file (named), or classes not in ``library``.
    """
    d = Path(path)
    if not (d / "scene_camera.json").is_file():
        raise InputError(f"{d}: not a BOP scene folder (no scene_camera.json)")
    if not (period > 0 and np.isfinite(period)):
        raise InputError(f"period must be a positive number of seconds, got {period!r}")
    scene_camera = load_json(d / "scene_camera.json")
    gt_path, info_path = d / "scene_gt.json", d / "scene_gt_info.json"
    scene_gt = load_json(gt_path) if gt_path.exists() else {}
    scene_info = load_json(info_path) if info_path.exists() else {}
    hyp_path = d / "hypotheses.json"
    has_hyps = hyp_path.exists() or hyp_path.is_symlink()
    hyps = load_json(hyp_path) if has_hyps else {}
    simulated = (d / "sequence.json").exists()
    meta = load_json(d / "sequence.json") if simulated else {}
    for name, doc in (
        ("scene_camera.json", scene_camera),
        ("scene_gt.json", scene_gt),
        ("scene_gt_info.json", scene_info),
        ("hypotheses.json", hyps),
    ):
        if not isinstance(doc, Mapping):
            raise InputError(f"{d / name}: expected an object {{im_id: ...}}")
    classes = _classes(d)
    renamed = by_bop_name(classes, library)
    if renamed:  # the dataset's own models/ folder given: its models are named by obj_id
        classes = {i: renamed.get(c, c) for i, c in classes.items()}
        if meta.get("models"):
            meta = {**meta, "models": [renamed.get(c, c) for c in meta["models"]]}
        hyps = {k: _renamed_entries(v, renamed) for k, v in hyps.items()}
    _warn_rotations(gt_path, scene_gt)
    try:
        if simulated:
            frames = meta["frames"]
            im_ids = [int(fm["im_id"]) for fm in frames]
            stamps = [float(fm["stamp"]) for fm in frames]
            groups = [int(fm.get("static_group", 0)) for fm in frames]
        else:
            im_ids = sorted(int(k) for k in scene_camera)
            stamps = [im * float(period) for im in im_ids]
            groups = [0] * len(im_ids)
        used = {
            "scene_gt.json": {int(g["obj_id"]) for v in scene_gt.values() for g in v},
            "hypotheses.json": {
                h.get("class") or int(h["obj_id"]) for v in hyps.values() for h in v
            },
        }
        size = _scene_size(d, meta)
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"{d}: malformed scene files: {exc!r}") from exc
    if not im_ids:
        raise InputError(f"{d / 'scene_camera.json'}: no images")
    for name, ids in used.items():
        unknown = sorted(str(i) for i in ids if isinstance(i, int) and i not in classes)
        if unknown and classes:
            raise InputError(
                f"{d / name}: obj_ids {unknown} have no model (known: {sorted(classes)})"
            )
        if library is None:
            continue
        names = {classes.get(i, f"obj_{i:06d}") if isinstance(i, int) else i for i in ids}
        missing = sorted(c for c in names if c not in library)
        if missing:
            root = dataset_root(d)
            models = (
                f" ({root / 'models'})"
                if root is not None and (root / "models").is_dir()
                else ""
            )  # fmt: skip
            raise InputError(
                f"{d / name}: classes not in the library: {missing} (known: "
                f"{', '.join(library) or 'none'}); give the dataset's models with --models"
                f"{models}"
            )
    has_world = all(
        isinstance(scene_camera.get(str(im)), Mapping) and "cam_R_w2c" in scene_camera[str(im)]
        for im in im_ids
    )
    return BopScene(
        path=d,
        scene_id=int(d.name) if d.name.isdigit() else int(meta.get("scene_id", 0)),
        classes=classes,
        im_ids=im_ids,
        stamps=stamps,
        static_groups=groups,
        has_hypotheses=has_hyps,
        has_world=has_world,
        simulated=simulated,
        meta=meta,
        _size=size,
        _scene_gt=scene_gt,
        _scene_camera=scene_camera,
        _scene_info=scene_info,
        _hypotheses=hyps,
    )
