"""Write :class:`SimSequence` in the BOP layout, read it back, and write datasets to disk.

:func:`simulate_to_disk` writes a BOP dataset as the toolkit publishes it
(``docs/bop_datasets_format.md``; read by :mod:`ssp.io.bop`, which reads published datasets
too): ``DATASET/camera.json``, ``DATASET/models/`` (``obj_XXXXXX.ply`` in mm and
``models_info.json`` with the symmetries, :func:`write_bop_models`), ``DATASET/models_eval/``
(the same files: the meshes are already the exact models the toolkit evaluates with),
``DATASET/test_targets_bop19.json`` (the BOP19 test targets, :func:`bop_targets`),
``DATASET/models.json`` (ssp: obj_id -> class) and one scene per sequence in
``DATASET/test/<scene_id:06d>/``. One sequence is one BOP scene folder:

``scene_gt.json``
    ``{im_id: [{obj_id, cam_R_m2c (9 floats, row-major), cam_t_m2c (mm), inst_id}]}``, the
    objects of each frame in the order of ``SimFrame.gt`` (``inst_id`` is our extra key: the
    instance id).
``scene_camera.json``
    ``{im_id: {cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)}}``; each image's
    world-to-camera pose (the same for a static camera, its own along a camera path) gives
    the world frame (z up, table top at z = 0).
``scene_gt_info.json``
    ``{im_id: [{obj_id, inst_id, visib_fract, px_count_visib, px_count_all, bbox_visib}]}``
    (``px_count_all``: pixels of the object rendered alone, when the generator recorded them;
    ``bbox_visib``: ``[x, y, w, h]`` of the visible mask, ``[-1, -1, -1, -1]`` if none).
``camera.json``
    intrinsics of the images: ``width, height, fx, fy, cx, cy, depth_scale``.
``depth/000000.png``
    16-bit depth in units of ``depth_scale`` mm (``DEPTH_SCALE`` = 0.1: 0.1 mm units), 0 = none.
``rgb/000000.png``
    8-bit RGB image of the same size: not a rendering of colour but each class's flat colour
    (:data:`CLASS_COLORS`, the table grey) shaded from the depth image's normals
    (:func:`ssp.sim.render.shade`): no texture, so a stand-in for RGB estimators' input.
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

Files that are not BOP's (``instance/``, ``hypotheses*.json``, ``models.json``,
``sequence.json``, the scene's ``camera.json``) are extra files the toolkit ignores.

Reading streams: :func:`open_bop` reads the JSON files and checks the classes, and
:meth:`BopScene.load` reads one frame's images when it is needed (:mod:`ssp.io.bop`);
:func:`read_bop` reads every frame into a :class:`SimSequence` (for small scenes and tests).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from PIL import Image

from ssp.errors import InputError
from ssp.io import write_json
from ssp.io.bop import DEPTH_SCALE, BopScene, load_json
from ssp.io.bop import open_bop as _open
from ssp.sim.generate import generate_sequence
from ssp.sim.hypotheses import HypothesisNoise
from ssp.sim.render import TABLE, shade
from ssp.sim.sequence import SimFrame, SimSequence

__all__ = [
    "DEPTH_SCALE",
    "BopScene",
    "bop_targets",
    "open_bop",
    "read_bop",
    "sim_frame",
    "simulate_to_disk",
    "write_bop",
    "write_bop_models",
]

FORMAT_VERSION = 1
#: The split folder ``simulate_to_disk`` writes its scenes in.
SPLIT = "test"


def _png(path: Path, array: np.ndarray) -> None:
    Image.fromarray(array).save(path, compress_level=1)


def _bbox(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1]


#: Colours of the classes in ``rgb/`` (by ``obj_id``, cycling), of the table, and of the
#: distractors (objects not in the library).
CLASS_COLORS = (
    (0.85, 0.33, 0.10),
    (0.00, 0.45, 0.74),
    (0.93, 0.69, 0.13),
    (0.47, 0.67, 0.19),
    (0.49, 0.18, 0.56),
    (0.30, 0.75, 0.93),
    (0.64, 0.08, 0.18),
    (0.95, 0.50, 0.70),
)
TABLE_COLOR = (0.72, 0.70, 0.66)
DISTRACTOR_COLOR = (0.45, 0.42, 0.40)


def _rgb(frame: SimFrame, camera, obj_id: Mapping[str, int]) -> np.ndarray:
    """The ``rgb/`` image of a frame (:func:`ssp.sim.render.shade`): each class its colour,
    the table grey, shaded from the frame's depth."""
    colors = {TABLE: TABLE_COLOR}
    for k, (cls, _) in enumerate(frame.gt.values()):
        colors[k] = CLASS_COLORS[(obj_id[cls] - 1) % len(CLASS_COLORS)]
    for k in range(len(frame.gt), len(frame.gt) + len(frame.distractors)):
        colors[k] = DISTRACTOR_COLOR
    return shade(frame.depth, frame.instance, camera, colors)


def write_bop(seq: SimSequence, out_dir, scene_id: int = 1, camera_pose: bool = True) -> Path:
    """Write ``seq`` as a BOP scene folder ``out_dir`` (created; files overwritten).
    ``camera_pose=False``: as a published test scene of a moving camera, without
    ``cam_R_w2c``/``cam_t_w2c``, the hypotheses in the camera frame (``cam_R_m2c``,
    ``cam_t_m2c``).

    Returns the folder path.
    """
    out = Path(out_dir)
    for sub in ("depth", "mask_visib", "instance", "rgb"):
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
    scene_gt, scene_camera, scene_info, hyps, hyps_gt = {}, {}, {}, {}, {}
    instances: dict[str, str] = {}
    for i, f in enumerate(seq.frames):
        im = str(f.index)
        T_cw = np.linalg.inv(np.asarray(seq.camera_pose(i), dtype=float))
        scene_camera[im] = {
            "cam_K": [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0],
            "depth_scale": DEPTH_SCALE,
        }
        if camera_pose:
            scene_camera[im]["cam_R_w2c"] = T_cw[:3, :3].reshape(-1).tolist()
            scene_camera[im]["cam_t_w2c"] = (T_cw[:3, 3] * 1000.0).tolist()
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
        T_fw = np.eye(4) if camera_pose else T_cw  # the hypotheses' frame from the world
        keys = ("R", "t") if camera_pose else ("cam_R_m2c", "cam_t_m2c")
        hyps[im] = []
        for h in f.hypotheses:
            T_fo = T_fw @ np.asarray(h.T_world_obj, float)
            hyps[im].append({
                "class": h.class_name,
                "obj_id": obj_id[h.class_name],
                "score": float(h.score),
                keys[0]: T_fo[:3, :3].reshape(-1).tolist(),
                keys[1]: (T_fo[:3, 3] * 1000.0).tolist(),
            })  # fmt: skip
        if sources is not None:
            hyps_gt[im] = list(sources[f.index]) if f.index < len(sources) else []
        depth = np.asarray(f.depth, dtype=float)
        units = np.round(depth * 1000.0 / DEPTH_SCALE)
        if units.max(initial=0) > 65535:
            raise ValueError(f"frame {f.index}: depth beyond {65535 * DEPTH_SCALE / 1000} m")
        _png(out / "depth" / f"{f.index:06d}.png", np.where(depth > 0, units, 0).astype(np.uint16))
        _png(out / "instance" / f"{f.index:06d}.png", (inst.astype(np.int32) + 2).astype(np.uint16))
        _png(out / "rgb" / f"{f.index:06d}.png", _rgb(f, cam, obj_id))

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
            "T_world_cam": np.asarray(seq.T_world_cam, dtype=float).tolist(),
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


def open_bop(path, library: Mapping) -> BopScene:
    """Open a scene folder written by :func:`write_bop` (:func:`ssp.io.bop.open_bop`, which
    reads published BOP scenes too); ``library`` must know every class of the scene.

    Raises:
        InputError: a missing or invalid JSON file (named), classes not in ``library``, or a
            scene without ``sequence.json`` (not written by ssp simulate).
    """
    scene = _open(path, library)
    if not scene.simulated:
        raise InputError(
            f"{path}: no sequence.json: not a scene written by ssp simulate (read published "
            "BOP scenes with ssp.io.bop.open_bop)"
        )
    return scene


def sim_frame(scene: BopScene, k: int) -> SimFrame:
    """The ``k``-th frame of an ssp scene as a :class:`SimFrame` (ground truth in the scene's
    world frame, through this image's camera pose)."""
    f = scene.load(k)
    T_wc = scene.T_world_cam_of(k)
    return SimFrame(
        index=f.im_id,
        stamp=f.stamp,
        gt={iid: (cls, T_wc @ T_co) for iid, (cls, T_co) in f.gt.items()},
        depth=f.depth,
        instance=f.instance,
        visib_fract=f.visib_fract,
        hypotheses=f.hypotheses,
        static_group=f.static_group,
        T_world_cam=None if T_wc is None else np.array(T_wc, dtype=float),
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
    meta = scene.meta
    info = dict(meta.get("info", {}))
    gt_path = scene.path / "hypotheses_gt.json"
    if gt_path.exists():
        hyps_gt = load_json(gt_path)
        info["hypothesis_sources"] = [list(hyps_gt.get(str(im), [])) for im in scene.im_ids]
    return SimSequence(
        experiment=meta.get("experiment", ""),
        seed=int(meta.get("seed", 0)),
        camera=scene.camera_of(0),
        T_world_cam=scene.T_world_cam_of(0),
        frames=[sim_frame(scene, k) for k in range(len(scene))],
        models=scene.models,
        info=info,
    )


def write_bop_models(library: Mapping, classes, out_dir) -> Path:
    """Write the models of ``classes`` (``obj_id`` = 1-based position) as a BOP ``models/``
    folder: ``obj_XXXXXX.ply`` (mm) and ``models_info.json`` (diameter, bounding box, declared
    symmetries; mm), as the BOP toolkit publishes them. Returns the folder."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = {}
    for i, cls in enumerate(classes, start=1):
        model = library[cls]
        mesh = model.mesh.copy()
        mesh.apply_scale(1000.0)
        mesh.export(out / f"obj_{i:06d}.ply", encoding="binary")
        lo, hi = mesh.bounds
        entry = {
            "diameter": float(model.diameter) * 1000.0,
            "min_x": float(lo[0]),
            "min_y": float(lo[1]),
            "min_z": float(lo[2]),
            "size_x": float(hi[0] - lo[0]),
            "size_y": float(hi[1] - lo[1]),
            "size_z": float(hi[2] - lo[2]),
        }
        entry.update(model.symmetry.to_bop(scale=1000.0))
        info[str(i)] = entry
    write_json(out / "models_info.json", info)
    return out


#: Ground-truth instances less visible than this are not test targets (BOP19; the same
#: threshold as :data:`ssp.eval.bop_metrics.MIN_VISIB`).
TARGET_MIN_VISIB = 0.1
#: The dataset's list of test targets, as the BOP toolkit's evaluation reads it.
TARGETS_JSON = "test_targets_bop19.json"


def bop_targets(scene_dir, scene_id: int) -> list[dict]:
    """The BOP19 test targets of a scene folder: per image and ``obj_id``, ``inst_count``
    ground-truth instances at least :data:`TARGET_MIN_VISIB` visible (``scene_gt_info.json``),
    as ``{scene_id, im_id, obj_id, inst_count}`` sorted by ``im_id`` and ``obj_id``."""
    info = load_json(Path(scene_dir) / "scene_gt_info.json")
    targets = []
    for im in sorted(info, key=int):
        counts: dict[int, int] = {}
        for entry in info[im]:
            if entry["visib_fract"] >= TARGET_MIN_VISIB:
                counts[int(entry["obj_id"])] = counts.get(int(entry["obj_id"]), 0) + 1
        targets += [
            {"scene_id": int(scene_id), "im_id": int(im), "obj_id": o, "inst_count": n}
            for o, n in sorted(counts.items())
        ]
    return targets


def _copy_models(src: Path, dst: Path) -> None:
    """``models_eval/``: the files of ``models/`` (the meshes are already the exact models)."""
    import shutil

    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.iterdir()):
        if f.is_file():
            shutil.copyfile(f, dst / f.name)


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
    camera_pose: bool = True,
    **generate_kwargs,
) -> list[Path]:
    """Generate ``sequences`` sequences (seeds ``seed, seed + 1, ...``) and write each as a
    BOP scene ``out_dir/<experiment>/test/<i:06d>/`` (``i`` = 0, 1, ...; scene id ``i``).

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
        camera_pose: write the camera poses (:func:`write_bop`).

    Returns:
        The scene folders ``out_dir/<experiment>/test/<i:06d>``, in order. Sequences are
        generated and written one at a time. ``out_dir/<experiment>`` is a BOP dataset as the
        toolkit publishes it (module docstring): ``camera.json``, ``models/``,
        ``models_eval/``, ``test_targets_bop19.json`` (rewritten after each scene) and
        ``test/``.
    """
    if library is None:
        from ssp.library import ObjectLibrary

        library = (
            ObjectLibrary.builtin() if models_dir is None else ObjectLibrary.from_folder(models_dir)
        )
    root = Path(out_dir) / experiment
    paths = []
    targets: list[dict] = []
    classes: list[str] | None = None
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
        p = write_bop(seq, root / SPLIT / f"{i:06d}", scene_id=i, camera_pose=camera_pose)
        if classes is None:  # the dataset's files, once: every scene shares the library
            classes = [c for _, c in sorted(load_json(p / "models.json")["obj_ids"].items(),
                                            key=lambda kv: int(kv[0]))]  # fmt: skip
            write_bop_models(library, classes, root / "models")
            _copy_models(root / "models", root / "models_eval")
            write_json(root / "models.json", load_json(p / "models.json"))
            write_json(root / "camera.json", load_json(p / "camera.json"))
        targets += bop_targets(p, i)
        write_json(root / TARGETS_JSON, targets)  # every scene written so far
        paths.append(p)
        if progress is not None:
            progress(i + 1, int(sequences), p)
    return paths
