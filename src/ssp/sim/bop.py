"""Read and write :class:`SimSequence` in the BOP scene layout, and write many to disk.

One sequence is one BOP scene folder (bop_toolkit, ``docs/bop_datasets_format.md``):

``scene_gt.json``
    ``{im_id: [{obj_id, cam_R_m2c (9 floats, row-major), cam_t_m2c (mm), inst_id}]}``, the
    objects of each frame in the order of ``SimFrame.gt`` (``inst_id`` is our extra key: the
    instance id).
``scene_camera.json``
    ``{im_id: {cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)}}``; the camera is static, the
    world-to-camera pose gives the world frame (z up, table top at z = 0).
``scene_gt_info.json``
    ``{im_id: [{obj_id, inst_id, visib_fract, px_count_visib, px_count_all, bbox_visib}]}``
    (``px_count_all``: pixels of the object rendered alone, when the generator recorded them;
    ``bbox_visib``: ``[x, y, w, h]`` of the visible mask, ``[-1, -1, -1, -1]`` if none).
``camera.json``
    intrinsics of the images: ``width, height, fx, fy, cx, cy, depth_scale``.
``depth/000000.png``
    16-bit depth in units of ``depth_scale`` mm (``DEPTH_SCALE`` = 0.1: 0.1 mm units), 0 = none.
``mask_visib/000000_000000.png``
    8-bit visible mask (255) of the ``k``-th object of ``scene_gt`` in frame ``im_id``.
``instance/000000.png``
    (not BOP) 16-bit instance image: 0 = no return, 1 = table, ``2 + k`` = ``k``-th object.
``hypotheses.json``
    ``{im_id: [{class, obj_id, score, R (9, row-major), t (mm)}]}``: the pose estimator's
    output, **world frame** (``T_world_obj``), sorted by score; no instance ids.
``hypotheses_gt.json``
    ``{im_id: [inst_id]}``: the source instance of each hypothesis (for evaluation only; the
    parser must not read it).
``models.json``
    ``{"obj_ids": {obj_id: class}, "instances": [{inst_id, class, obj_id}]}``; ``obj_id`` is
    the 1-based index of the class in the library used by the generator.
``sequence.json``
    experiment, seed, scene id, camera, ``T_world_cam`` (m), per frame ``stamp`` and
    ``static_group`` (the stage), model classes, and the generator's ``info``.

Poses and scores are written as JSON floats (shortest round-trip repr), so reading gives the
written values back to float precision; depth comes back within ``depth_scale / 2``.

Reading streams: :func:`open_bop` reads the JSON files and checks the classes, and
:meth:`BopScene.load` reads one frame's images when it is needed, so a long scene is never in
memory at once and one unreadable image (a truncated PNG, a dangling link) fails that frame
alone with an :class:`~ssp.errors.InputError` naming the file. :func:`read_bop` reads every
frame (for small scenes and tests).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ssp.errors import InputError
from ssp.io import write_json
from ssp.io._files import file_problem
from ssp.scene import Hypothesis
from ssp.sim.generate import generate_sequence
from ssp.sim.hypotheses import HypothesisNoise
from ssp.sim.render import Camera
from ssp.sim.sequence import SimFrame, SimSequence

__all__ = ["DEPTH_SCALE", "BopScene", "open_bop", "read_bop", "simulate_to_disk", "write_bop"]

#: Depth PNG unit, mm (0.1 mm: depths up to 6.5 m).
DEPTH_SCALE = 0.1
FORMAT_VERSION = 1


def _load(path: Path):
    """The JSON of ``path``; InputError naming it when it is missing, not a file, or invalid."""
    problem = file_problem(path)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: invalid JSON: {exc}") from exc


def _png(path: Path, array: np.ndarray) -> None:
    Image.fromarray(array).save(path, compress_level=1)


def _read_png(path: Path) -> np.ndarray:
    """The pixels of a PNG; InputError naming the file when it is missing, not a regular
    file (never opened then: a FIFO would block), truncated or corrupt."""
    problem = file_problem(path)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im)
    except (OSError, ValueError, SyntaxError) as exc:  # PIL: truncated, corrupt, unknown
        raise InputError(f"{path}: cannot read the image: {exc}") from exc


def _bbox(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1]


def write_bop(seq: SimSequence, out_dir, scene_id: int = 1) -> Path:
    """Write ``seq`` as a BOP scene folder ``out_dir`` (created; files overwritten).

    Returns the folder path.
    """
    out = Path(out_dir)
    for sub in ("depth", "mask_visib", "instance"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    info = dict(seq.info)
    sources = info.pop("hypothesis_sources", None)
    px_all = info.get("px_count_all")
    lib_classes = list(info.get("library_classes") or seq.models)
    for cls in {c for f in seq.frames for c, _ in f.gt.values()} | {
        h.class_name for f in seq.frames for h in f.hypotheses
    }:
        if cls not in lib_classes:
            lib_classes.append(cls)
    obj_id = {c: i + 1 for i, c in enumerate(lib_classes)}

    cam = seq.camera
    T_wc = np.asarray(seq.T_world_cam, dtype=float)
    T_cw = np.linalg.inv(T_wc)
    cam_entry = {
        "cam_K": [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0],
        "depth_scale": DEPTH_SCALE,
        "cam_R_w2c": T_cw[:3, :3].reshape(-1).tolist(),
        "cam_t_w2c": (T_cw[:3, 3] * 1000.0).tolist(),
    }
    scene_gt, scene_camera, scene_info, hyps, hyps_gt = {}, {}, {}, {}, {}
    instances: dict[str, str] = {}
    for f in seq.frames:
        im = str(f.index)
        scene_camera[im] = cam_entry
        gts, infos = [], []
        inst = np.asarray(f.instance)
        for k, (iid, (cls, T)) in enumerate(f.gt.items()):
            instances.setdefault(iid, cls)
            T_co = T_cw @ np.asarray(T, dtype=float)
            gts.append(
                {
                    "obj_id": obj_id[cls],
                    "cam_R_m2c": T_co[:3, :3].reshape(-1).tolist(),
                    "cam_t_m2c": (T_co[:3, 3] * 1000.0).tolist(),
                    "inst_id": iid,
                }
            )
            mask = inst == k
            _png(out / "mask_visib" / f"{f.index:06d}_{k:06d}.png", mask.astype(np.uint8) * 255)
            n_all = None
            if px_all is not None and f.static_group < len(px_all):
                n_all = px_all[f.static_group].get(iid)
            infos.append(
                {
                    "obj_id": obj_id[cls],
                    "inst_id": iid,
                    "visib_fract": float(f.visib_fract.get(iid, 0.0)),
                    "px_count_visib": int(mask.sum()),
                    "px_count_all": None if n_all is None else int(n_all),
                    "bbox_visib": _bbox(mask),
                }
            )
        scene_gt[im] = gts
        scene_info[im] = infos
        hyps[im] = [
            {
                "class": h.class_name,
                "obj_id": obj_id[h.class_name],
                "score": float(h.score),
                "R": np.asarray(h.T_world_obj, float)[:3, :3].reshape(-1).tolist(),
                "t": (np.asarray(h.T_world_obj, float)[:3, 3] * 1000.0).tolist(),
            }
            for h in f.hypotheses
        ]
        if sources is not None:
            hyps_gt[im] = list(sources[f.index]) if f.index < len(sources) else []
        depth = np.asarray(f.depth, dtype=float)
        units = np.round(depth * 1000.0 / DEPTH_SCALE)
        if units.max(initial=0) > 65535:
            raise ValueError(f"frame {f.index}: depth beyond {65535 * DEPTH_SCALE / 1000} m")
        _png(out / "depth" / f"{f.index:06d}.png", np.where(depth > 0, units, 0).astype(np.uint16))
        _png(out / "instance" / f"{f.index:06d}.png", (inst.astype(np.int32) + 2).astype(np.uint16))

    write_json(out / "scene_gt.json", scene_gt)
    write_json(out / "scene_camera.json", scene_camera)
    write_json(out / "scene_gt_info.json", scene_info)
    write_json(out / "hypotheses.json", hyps)
    if sources is not None:
        write_json(out / "hypotheses_gt.json", hyps_gt)
    write_json(
        out / "camera.json",
        {
            "width": int(cam.width),
            "height": int(cam.height),
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "depth_scale": DEPTH_SCALE,
        },
    )
    write_json(
        out / "models.json",
        {
            "obj_ids": {str(i): c for c, i in obj_id.items()},
            "instances": [
                {"inst_id": iid, "class": cls, "obj_id": obj_id[cls]}
                for iid, cls in instances.items()
            ],
        },
    )
    write_json(
        out / "sequence.json",
        {
            "format": "ssp-bop",
            "format_version": FORMAT_VERSION,
            "experiment": seq.experiment,
            "seed": int(seq.seed),
            "scene_id": int(scene_id),
            "n_frames": len(seq.frames),
            "models": list(seq.models),
            "camera": {
                "width": int(cam.width),
                "height": int(cam.height),
                "fx": cam.fx,
                "fy": cam.fy,
                "cx": cam.cx,
                "cy": cam.cy,
            },
            "T_world_cam": T_wc.tolist(),
            "units": "poses in metres except *_t_* and hypotheses t (mm); depth PNG in "
            "depth_scale mm; hypotheses in the world frame",
            "frames": [
                {"im_id": f.index, "stamp": float(f.stamp), "static_group": int(f.static_group)}
                for f in seq.frames
            ],
            "info": info,
        },
    )
    return out


@dataclass
class BopScene:
    """A BOP scene folder opened by :func:`open_bop`: its metadata, with the frames' images
    read one at a time by :meth:`load`.

    Attributes:
        path: the folder.
        experiment, seed, camera, T_world_cam, models, info: as in :class:`SimSequence`.
        im_ids: BOP ``im_id`` of the frames, in order; ``stamps`` their times (s).
        has_hypotheses: the folder has a ``hypotheses.json``.
    """

    path: Path
    experiment: str
    seed: int
    camera: Camera
    T_world_cam: np.ndarray
    models: tuple[str, ...]
    info: dict
    im_ids: list[int]
    stamps: list[float]
    static_groups: list[int]
    has_hypotheses: bool
    _classes: dict[int, str] = field(repr=False, default_factory=dict)
    _scene_gt: dict = field(repr=False, default_factory=dict)
    _scene_camera: dict = field(repr=False, default_factory=dict)
    _scene_info: dict = field(repr=False, default_factory=dict)
    _hypotheses: dict = field(repr=False, default_factory=dict)

    def __len__(self) -> int:
        return len(self.im_ids)

    def __iter__(self) -> Iterator[SimFrame]:
        """The frames in order, each read when it is reached."""
        return (self.load(k) for k in range(len(self)))

    def has_entry(self, k: int) -> bool:
        """Whether ``hypotheses.json`` lists the ``k``-th frame (an empty list counts)."""
        return str(self.im_ids[k]) in self._hypotheses

    def load(self, k: int) -> SimFrame:
        """Read the ``k``-th frame (0-based position, not ``im_id``): ground truth, depth,
        instance image, hypotheses.

        Raises:
            InputError: a missing or unreadable image, or a frame missing from the scene
                files; the message names the file. Other frames are unaffected.
        """
        d, im = self.path, self.im_ids[k]
        key = str(im)
        try:
            cam = self._scene_camera[key]
            entries = self._scene_gt[key]
        except KeyError:
            raise InputError(f"{d}: im_id {im} is missing from scene_camera.json or "
                             "scene_gt.json") from None  # fmt: skip
        try:
            gt: dict[str, tuple[str, np.ndarray]] = {}
            for j, g in enumerate(entries):
                T_co = np.eye(4)
                T_co[:3, :3] = np.asarray(g["cam_R_m2c"], dtype=float).reshape(3, 3)
                T_co[:3, 3] = np.asarray(g["cam_t_m2c"], dtype=float) / 1000.0
                cls = self._classes[g["obj_id"]]
                gt[g.get("inst_id", f"{cls}_{j}")] = (cls, self.T_world_cam @ T_co)
            ids = list(gt)
            visib = {
                e.get("inst_id", ids[j]): float(e["visib_fract"])
                for j, e in enumerate(self._scene_info.get(key, []))
            }
            depth_scale = float(cam.get("depth_scale", DEPTH_SCALE))
            hl = [_hypothesis(h, self._classes) for h in self._hypotheses.get(key, [])]
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"{d}: malformed entry of im_id {im}: {exc!r}") from exc
        depth = _read_png(d / "depth" / f"{im:06d}.png").astype(np.float64) * depth_scale / 1000.0
        inst_path = d / "instance" / f"{im:06d}.png"
        if inst_path.exists():
            instance = (_read_png(inst_path).astype(np.int32) - 2).astype(np.int16)
        else:  # BOP only: table wherever there is depth, else nothing
            instance = np.where(depth > 0, -1, -2).astype(np.int16)
            for j in range(len(ids)):
                m = d / "mask_visib" / f"{im:06d}_{j:06d}.png"
                if m.exists():
                    instance[_read_png(m) > 0] = j
        if instance.shape != depth.shape:
            raise InputError(
                f"{inst_path}: shape {instance.shape} differs from the depth image's {depth.shape}"
            )
        return SimFrame(
            index=int(im),
            stamp=self.stamps[k],
            gt=gt,
            depth=depth.astype(np.float32),
            instance=instance,
            visib_fract=visib,
            hypotheses=hl,
            static_group=self.static_groups[k],
        )


def _hypothesis(h: Mapping[str, Any], classes: Mapping[int, str]) -> Hypothesis:
    T = np.eye(4)
    T[:3, :3] = np.asarray(h["R"], dtype=float).reshape(3, 3)
    T[:3, 3] = np.asarray(h["t"], dtype=float) / 1000.0
    return Hypothesis(h.get("class") or classes[h["obj_id"]], T, float(h["score"]))


def open_bop(path, library: Mapping) -> BopScene:
    """Open a scene folder written by :func:`write_bop`: read its JSON files (not its images)
    and check its classes.

    ``library`` must know every class of the scene (it is checked, not otherwise used).

    Raises:
        InputError: a missing or invalid JSON file (named), or classes not in ``library``.
    """
    d = Path(path)
    if not (d / "sequence.json").exists():
        raise InputError(
            f"{d}: no sequence.json: ssp reads BOP scenes written by ssp simulate (they hold "
            "the stamps, the camera and T_world_cam)"
        )
    meta = _load(d / "sequence.json")
    scene_gt = _load(d / "scene_gt.json")
    scene_camera = _load(d / "scene_camera.json")
    info_path = d / "scene_gt_info.json"
    scene_info = _load(info_path) if info_path.exists() else {}
    hyp_path = d / "hypotheses.json"
    has_hyps = hyp_path.exists() or hyp_path.is_symlink()
    hyps = _load(hyp_path) if has_hyps else {}
    gt_path = d / "hypotheses_gt.json"
    hyps_gt = _load(gt_path) if gt_path.exists() else None
    models = _load(d / "models.json")
    try:
        classes = {int(k): v for k, v in models["obj_ids"].items()}
        used = {
            "scene_gt.json": {classes[g["obj_id"]] for v in scene_gt.values() for g in v},
            "hypotheses.json": {
                h.get("class") or classes[h["obj_id"]] for v in hyps.values() for h in v
            },
        }
        c = meta["camera"]
        camera = Camera(int(c["width"]), int(c["height"]), c["fx"], c["fy"], c["cx"], c["cy"])
        if "T_world_cam" in meta:
            T_wc = np.asarray(meta["T_world_cam"], dtype=float)
        else:  # static camera: the pose of the first frame
            cam0 = next(iter(scene_camera.values()))
            T_cw = np.eye(4)
            T_cw[:3, :3] = np.asarray(cam0["cam_R_w2c"], dtype=float).reshape(3, 3)
            T_cw[:3, 3] = np.asarray(cam0["cam_t_w2c"], dtype=float) / 1000.0
            T_wc = np.linalg.inv(T_cw)
        frames = meta["frames"]
        im_ids = [int(fm["im_id"]) for fm in frames]
        stamps = [float(fm["stamp"]) for fm in frames]
        groups = [int(fm["static_group"]) for fm in frames]
    except (KeyError, TypeError, ValueError, AttributeError, StopIteration) as exc:
        raise InputError(f"{d}: malformed scene files: {exc!r}") from exc
    for name, names in used.items():
        missing = sorted(c for c in names if c not in library)
        if missing:
            raise InputError(
                f"{d / name}: classes not in the library: {missing} (known: "
                f"{', '.join(library) or 'none'}; object ids in {d / 'models.json'})"
            )
    info = dict(meta.get("info", {}))
    if hyps_gt is not None:
        info["hypothesis_sources"] = [list(hyps_gt.get(str(im), [])) for im in im_ids]
    return BopScene(
        path=d,
        experiment=meta.get("experiment", ""),
        seed=int(meta.get("seed", 0)),
        camera=camera,
        T_world_cam=T_wc,
        models=tuple(meta.get("models", ())),
        info=info,
        im_ids=im_ids,
        stamps=stamps,
        static_groups=groups,
        has_hypotheses=has_hyps,
        _classes=classes,
        _scene_gt=scene_gt,
        _scene_camera=scene_camera,
        _scene_info=scene_info,
        _hypotheses=hyps,
    )


def read_bop(path, library: Mapping) -> SimSequence:
    """Read a scene folder written by :func:`write_bop` back into a :class:`SimSequence`
    (every frame: :func:`open_bop` streams them).

    ``library`` must know every class of the scene (it is checked, not otherwise used).
    Ground-truth poses and hypotheses come back to float precision, depth within
    ``depth_scale / 2``; ``info["hypothesis_sources"]`` is restored from
    ``hypotheses_gt.json`` when present.

    Raises:
        InputError: as :func:`open_bop` and :meth:`BopScene.load`.
    """
    scene = open_bop(path, library)
    return SimSequence(
        experiment=scene.experiment,
        seed=scene.seed,
        camera=scene.camera,
        T_world_cam=scene.T_world_cam,
        frames=list(scene),
        models=scene.models,
        info=scene.info,
    )


#: ``progress(done, total, path)``: called after each sequence is written.
Progress = Callable[[int, int, Path], None]


def simulate_to_disk(
    experiment: str,
    sequences: int,
    seed: int,
    models_dir=None,
    out_dir=".",
    *,
    frames_per_stage: int = 4,
    stages: int | None = None,
    stride: int = 1,
    hypotheses: HypothesisNoise | None = None,
    library: Mapping | None = None,
    progress: Progress | None = None,
    **generate_kwargs,
) -> list[Path]:
    """Generate ``sequences`` sequences (seeds ``seed, seed + 1, ...``) and write each as a
    BOP scene ``out_dir/<experiment>/<i:06d>/`` (``i`` = 0, 1, ...; scene id ``i``).

    Args:
        experiment: ``"isolated"`` or ``"structure"``.
        sequences: how many.
        seed: seed of the first sequence (development 0-99; 1000+ reserved for reporting).
        models_dir: model folder (:meth:`ObjectLibrary.from_folder`), or None for the
            built-in library. ``"structure"`` needs the classes ``cube`` and ``block``.
        out_dir: root folder.
        frames_per_stage, stages, stride, hypotheses, **generate_kwargs: as for
            :func:`ssp.sim.generate.generate_sequence`.
        library: an already loaded library (overrides ``models_dir``).
        progress: ``progress(done, total, path)`` after each sequence.

    Returns:
        The scene folders, in order. Sequences are generated and written one at a time.
    """
    if library is None:
        from ssp.library import ObjectLibrary

        library = (
            ObjectLibrary.builtin() if models_dir is None else ObjectLibrary.from_folder(models_dir)
        )
    root = Path(out_dir) / experiment
    paths = []
    for i in range(int(sequences)):
        t0 = time.perf_counter()
        seq = generate_sequence(
            experiment,
            int(seed) + i,
            library,
            frames_per_stage=frames_per_stage,
            stages=stages,
            stride=stride,
            hypotheses=hypotheses,
            **generate_kwargs,
        )
        seq.info["generate_seconds"] = round(time.perf_counter() - t0, 3)
        p = write_bop(seq, root / f"{i:06d}", scene_id=i)
        paths.append(p)
        if progress is not None:
            progress(i + 1, int(sequences), p)
    return paths
