"""``ssp refine``, ``ssp estimate`` and ``ssp evaluate``: ssp after a pose estimator, on a BOP
dataset as the toolkit publishes it (:mod:`ssp.io.bop`).

* :func:`refine`: an estimator's output (a BOP19 results CSV or another format of
  :mod:`ssp.io.estimators`, camera frame) becomes ssp's refined BOP19 CSV. Each scene is one
  :func:`ssp.pipeline.run.run` (per-frame JSON, summary, resume) in ``OUT/scenes/<scene_id>/``; the
  scenes' rows are gathered in ``OUT/<method>_<dataset>-<split>.csv``, where ``method`` is the
  input's method name (from its BOP file name) with ``-ssp`` appended.
* :func:`estimate`: the built-in estimator (:mod:`ssp.perception`) over a dataset, every
  hypothesis of every object written as a BOP19 CSV: a stand-in for the user's estimator.
* :func:`evaluate`: the BOP19 average recall (:mod:`ssp.eval.bop_metrics`) of result CSVs
  against the dataset's ground truth, side by side.
* :func:`dataset_models`: the object models of a dataset, when none are given.

The world frame (gravity, the table) is the scene's ``cam_R_w2c`` when it has one, else fitted
to the depth of each frame; never taken from the ground truth.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import ArgumentError, InputError, SSPError
from ssp.geometry import invert
from ssp.io._files import atomic_write_text, write_json
from ssp.io.bop import bop_scenes, dataset_root, open_bop, read_targets
from ssp.io.results import (
    BOP_CSV_HEADER,
    BopCsvWriter,
    bop_csv_name,
    bop_csv_parts,
    bop_model_name,
    read_bop_csv,
)

__all__ = [
    "DatasetModelsError",
    "RefineSummary",
    "check_estimates",
    "dataset_models",
    "estimate",
    "evaluate",
    "refine",
    "refined_method",
]

log = logging.getLogger(__name__)

REFINE_JSON = "refine.json"


def _dataset_name(scenes: Sequence[Path]) -> tuple[str, str]:
    """``(dataset, split)`` names of scene folders ``DATASET/SPLIT/SCENE``."""
    root = dataset_root(scenes[0])
    if root is None:
        return scenes[0].resolve().name, "test"
    return root.name, scenes[0].resolve().parent.name


def refined_method(estimates_path: str | Path) -> str:
    """The method name of the refined CSV: the input's (``METHOD_DATASET-SPLIT.csv``) plus
    ``-ssp``; ``ssp`` when the input's name does not follow the convention."""
    parts = bop_csv_parts(Path(estimates_path).name)
    return f"{parts['method']}-ssp" if parts else "ssp"


@dataclass
class RefineSummary:
    """What :func:`refine` did: per scene its run summary (``scenes``), the gathered CSV, and
    the warnings about the estimates (images the dataset lacks, duplicated rows, units)."""

    csv: Path
    method: str
    scenes: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def done(self) -> bool:
        return all(s["status"] == "finished" for s in self.scenes)

    @property
    def frames_done(self) -> int:
        """Frames refined (over every scene; a refine where this is 0 did nothing)."""
        return sum(int(s.get("done", 0)) for s in self.scenes)

    @property
    def frames(self) -> int:
        return sum(int(s.get("frames", 0)) for s in self.scenes)

    def to_dict(self) -> dict[str, Any]:
        return {"csv": str(self.csv), "method": self.method, "done": self.done,
                "frames": self.frames, "frames_done": self.frames_done,
                "warnings": self.warnings, "scenes": self.scenes}  # fmt: skip


def refine(
    dataset: str | Path,
    estimates_path: str | Path,
    library: Mapping,
    out_dir: str | Path,
    config: SSPConfig | None = None,
    *,
    fmt: str = "auto",
    split: str | None = None,
    scene_ids: Sequence[int] | None = None,
    method: str | None = None,
    masks: str = "auto",
    period: float | None = None,
    resume: bool = False,
    overwrite: bool = False,
    models: str | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> RefineSummary:
    """Refine an estimator's poses on every scene of ``dataset`` (module docstring).

    Args:
        dataset: a BOP dataset folder, a split folder, or one scene folder.
        estimates_path: the estimator's output (:func:`ssp.io.estimators.read_estimates`).
        library: the models (every class of the dataset).
        out_dir: output folder (new or empty; ``resume``: a stopped refine of the same input;
            ``overwrite``: an earlier one, replaced).
        fmt: the estimates' format (``auto``: detected).
        scene_ids: only these scenes (default: every scene of the split).
        method: the output's BOP method name (default :func:`refined_method`).
        masks, period: as for :func:`ssp.pipeline.run.run`.
        progress: ``progress(done, total, message)`` after each frame of each scene.

    The estimates' warnings (:func:`check_estimates`: scenes and images the dataset lacks;
    the reader's: duplicated rows, metres in a BOP19 CSV) are in ``summary.warnings``. A
    refine where no frame succeeded has ``summary.frames_done == 0``.

    Raises:
        InputError: no scene, an unreadable estimates file, classes not in the library, or
            estimates none of whose images is in the refined scenes.
        ArgumentError: bad options or output folder.
    """
    cfg = config if config is not None else SSPConfig()
    scenes = _select_scenes(dataset, split, scene_ids)
    name, split_name = _dataset_name(scenes)
    method = method or refined_method(estimates_path)
    out = Path(out_dir)
    _check_out(out, resume, overwrite)
    summary = RefineSummary(out / bop_csv_name(name, method, split_name), method)
    _refine_scenes(summary, scenes, estimates_path, library, out, cfg, fmt=fmt, masks=masks,
                   period=period, resume=resume, overwrite=overwrite, models=models,
                   progress=progress)  # fmt: skip
    _gather(summary, out)
    write_json(out / REFINE_JSON, {"format": "ssp-refine", "version": 1,
                                   "estimates": str(Path(estimates_path).resolve()),
                                   **summary.to_dict()})  # fmt: skip
    return summary


def _select_scenes(
    dataset: str | Path, split: str | None, scene_ids: Sequence[int] | None
) -> list[Path]:
    """The scene folders of ``dataset`` (its ``split``), only those of ``scene_ids`` if given.

    Raises:
        InputError: no scene (with one of ``scene_ids``).
    """
    scenes = bop_scenes(dataset, split)
    if scene_ids is not None:
        wanted = {int(s) for s in scene_ids}
        scenes = [s for s in scenes if s.name.isdigit() and int(s.name) in wanted]
        if not scenes:
            raise InputError(f"{dataset}: no scene with id {sorted(wanted)}")
    return scenes


def _refine_scenes(
    summary: RefineSummary,
    scenes: Sequence[Path],
    estimates_path: str | Path,
    library: Mapping,
    out: Path,
    cfg: SSPConfig,
    *,
    fmt: str,
    masks: str,
    period: float | None,
    resume: bool,
    overwrite: bool,
    models: str | None,
    progress: Callable[[int, int, str], None] | None,
) -> None:
    """One run per scene into ``out/scenes/<scene>`` (a scene a resumed refine finished is
    kept), each recorded in ``summary.scenes``."""
    from ssp.io.estimators import read_estimates
    from ssp.pipeline.manifest import read_run
    from ssp.pipeline.run import run  # the parser: only when refining

    first = open_bop(scenes[0])
    est = read_estimates(estimates_path, fmt, dict(first.classes) or None, library=library,
                         scene_id=first.scene_id)  # fmt: skip
    summary.warnings += est.warnings
    summary.warnings += check_estimates(est, scenes, first)
    total = len(scenes)
    for n, scene_path in enumerate(scenes):
        scene = first if n == 0 else open_bop(scene_path)
        if n > 0 and est.format in ("megapose", "foundationpose"):
            # formats without scene ids name the images of the one scene they are for
            est = read_estimates(estimates_path, fmt, dict(scene.classes) or None,
                                 library=library, scene_id=scene.scene_id)  # fmt: skip
        sub = out / "scenes" / scene_path.name
        sub_resume = resume and (sub / "run.json").exists()
        kept = _finished(sub) if resume and sub_resume else None
        if kept is not None:
            log.info("%s: scene %s finished before; kept", out, scene_path.name)
            summary.scenes.append({"scene": scene_path.name, "status": "finished",
                                   "out": str(sub), "input": read_run(sub)["input"],
                                   "frames": kept.get("frames", 0), "done": kept.get("done", 0),
                                   "failed": len(kept.get("failed", []))})  # fmt: skip
            continue

        def report(done: int, frames: int, message: str, n=n) -> None:
            if progress is not None:
                progress(done, frames, f"scene {n + 1}/{total} {message}")

        s = run(
            scene_path,
            library,
            sub,
            cfg,
            hypotheses="given",
            method=summary.method,
            scene_id=scene.scene_id,
            progress=report,
            resume=sub_resume,
            overwrite=overwrite,
            models=models,
            estimates=est,
            masks=masks,
            period=period,
            rejected_rows=True,  # never fewer objects than the estimator reported
        )
        summary.scenes.append({"scene": scene_path.name, "status": s.status, "out": str(sub),
                               "input": s.input, "frames": s.frames, "done": len(s.done),
                               "failed": len(s.failed), "masks": s.masks})  # fmt: skip


def _check_out(out: Path, resume: bool, overwrite: bool) -> None:
    """ArgumentError unless ``out`` can take this refine: new or empty, or an earlier refine
    that ``resume`` continues or ``overwrite`` replaces."""
    if resume and overwrite:
        raise ArgumentError("resume continues a refine; overwrite starts one afresh: not both")
    if out.exists() and not out.is_dir():
        raise ArgumentError(f"{out}: the output folder is a file")
    if not out.exists() or not any(out.iterdir()) or resume or overwrite:
        if resume and not (out / REFINE_JSON).exists() and not (out / "scenes").is_dir():
            raise ArgumentError(f"{out}: no ssp refine here: nothing to resume")
        return
    if (out / REFINE_JSON).exists() or (out / "scenes").is_dir():
        raise ArgumentError(
            f"{out}: the output folder holds an ssp refine: continue it with --resume, replace "
            "it with --overwrite, or choose a new --out folder"
        )
    raise ArgumentError(f"{out}: the output folder is not empty and holds no ssp refine")


def _finished(sub: Path) -> dict[str, Any] | None:
    """The summary of the run in ``sub`` if it finished (its summary says so), else None."""
    try:
        doc = json.loads((sub / "summary.json").read_text())
        return doc if doc["status"] == "finished" else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


#: Image ids shown in a warning about the images an estimates file names (the rest counted).
_SHOWN_IMAGES = 10


def check_estimates(est: Any, scenes: Sequence[Path], first: Any = None) -> list[str]:
    """What an estimator's output names that the dataset lacks: scenes (BOP19, CosyPose) and
    images of the refined ``scenes`` (every format), as warnings (also logged), so that a
    file for another dataset, split or scene, or with other image ids, does not pass as a
    refine with nothing in it. ``first``: ``scenes[0]`` opened, if it is.

    Raises:
        InputError: not one image of the estimates is an image of ``scenes``.
    """
    images = est.images()
    if not images:
        return []
    per_scene = est.format in ("megapose", "foundationpose")  # read again for each scene
    have: dict[int, set[int]] = {}
    for n, path in enumerate(scenes):
        scene = first if n == 0 and first is not None else open_bop(path)
        have[scene.scene_id] = set(scene.im_ids)
    if per_scene:
        union = set().union(*have.values())
        absent = [(s, im) for s, im in images if im not in union]
    else:
        absent = [(s, im) for s, im in images if im not in have.get(s, ())]
    warnings = []
    if not per_scene:
        split = scenes[0].parent  # the scene folders beside the refined ones
        known = {int(p.name) for p in split.iterdir() if p.is_dir() and p.name.isdigit()}
        known |= set(have)
        other = sorted({s for s, _ in images} - known)
        if other:
            warnings.append(f"{est.source}: names scenes the dataset lacks: {other}")
        absent = [(s, im) for s, im in absent if s in have]  # other scenes are not refined
    if absent:
        shown = ", ".join(f"scene {s} image {im}" for s, im in absent[:_SHOWN_IMAGES])
        more = f" and {len(absent) - _SHOWN_IMAGES} more" if len(absent) > _SHOWN_IMAGES else ""
        warnings.append(
            f"{est.source}: {len(absent)} of its images are not in the refined scenes (no "
            f"such im_id): {shown}{more}"
        )
    matched = sum(im in have.get(s, ()) or (per_scene and im in union) for s, im in images)
    if not matched:
        ours = ", ".join(f"scene {s}: im_ids {_ids_text(ims)}" for s, ims in sorted(have.items()))
        theirs = _ids_text([im for _, im in images])
        raise InputError(
            f"{est.source}: none of its {len(images)} images (scenes "
            f"{sorted({s for s, _ in images})}, im_ids {theirs}) is an image of the refined "
            f"scenes ({ours}): estimates of another dataset, split or scene?"
        )
    for w in warnings:
        log.warning("%s", w)
    return warnings


def _ids_text(ids: Any) -> str:
    ids = sorted(set(ids))
    return ", ".join(map(str, ids[:5])) + (f", ... ({len(ids)})" if len(ids) > 5 else "")


def _gather(summary: RefineSummary, out: Path) -> None:
    """Concatenate the scenes' CSVs (header once) into ``summary.csv``."""
    lines = [BOP_CSV_HEADER]
    for s in summary.scenes:
        for p in sorted(Path(s["out"]).glob("*.csv")):
            body = p.read_text(encoding="ascii").splitlines()[1:]
            lines += [ln for ln in body if ln.strip()]
    atomic_write_text(summary.csv, "\n".join(lines) + "\n")


# ------------------------------------------------------------------------------ estimate
def estimate(
    dataset: str | Path,
    library: Mapping,
    out_csv: str | Path,
    config: SSPConfig | None = None,
    *,
    split: str | None = None,
    scene_ids: Sequence[int] | None = None,
    classes: Sequence[str] | None = None,
    masks: str = "auto",
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """The built-in estimator over a dataset: every hypothesis as a BOP19 CSV row (camera
    frame, t in mm; ``time`` the image's perception seconds). A frame that fails is logged,
    reported in the returned ``failed`` list and has no rows.

    ``masks`` as for :func:`ssp.pipeline.run.run`. Returns ``{csv, images, rows, failed}``.
    """
    from ssp.pipeline.bop import BopSource, check_masks  # the front end: only when estimating

    cfg = config if config is not None else SSPConfig()
    check_masks(masks)  # a bad mode or a missing detections file fails before any work
    scenes = bop_scenes(dataset, split)
    if scene_ids is not None:
        scenes = [s for s in scenes if s.name.isdigit() and int(s.name) in set(scene_ids)]
    path = Path(out_csv)
    parts = bop_csv_parts(path.name)
    method = parts["method"] if parts else "ssp"
    report: dict[str, Any] = {"csv": str(path), "images": 0, "rows": 0, "failed": []}
    with BopCsvWriter(path, method) as csv:
        for scene_path in scenes:
            # the frames as ssp run perceives them (masks, estimator), but each camera without
            # a given pose in its own table's world: the rows are in the camera frame, so
            # locating the camera across images (a registration each) would buy nothing
            source = BopSource(scene_path, library, cfg, classes, "estimated", masks=masks,
                               locate=False)  # fmt: skip
            ids = source.object_ids()
            scene_id = open_bop(scene_path).scene_id
            for k, frame in enumerate(source.frames(0)):
                t0 = time.perf_counter()
                try:
                    res, warnings = frame.perceive()
                except SSPError as exc:
                    error = frame.where(str(exc))
                    log.warning("scene %s image %d skipped: %s", scene_path.name, frame.index,
                                error)  # fmt: skip
                    report["failed"].append({"scene": scene_id, "im_id": frame.index,
                                             "error": error})  # fmt: skip
                    continue
                for w in warnings:
                    log.warning("scene %s image %d: %s", scene_path.name, frame.index, w)
                seconds = time.perf_counter() - t0
                T_cw = invert(np.asarray(res.frame.T_world_cam, dtype=float))
                rows = [
                    csv.format_row(
                        scene_id,
                        frame.index,
                        ids[h.class_name],
                        float(h.score),
                        T_cw @ h.T_world_obj,
                        seconds,
                    )  # fmt: skip
                    for h in res.frame.hypotheses
                ]
                csv.write_rows(rows)
                report["images"] += 1
                report["rows"] += len(rows)
                if progress is not None:
                    progress(k + 1, source.total, f"scene {scene_path.name}: {len(rows)} rows")
    return report


# ------------------------------------------------------------------------------ evaluate
def evaluate(
    dataset: str | Path,
    library: Mapping,
    results: Sequence[str | Path],
    *,
    split: str | None = None,
    vsd: bool = True,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """BOP19 AR (VSD, MSSD, MSPD; :class:`ssp.eval.bop_metrics.BopEvaluator`) of each results
    CSV against the ground truth of the dataset's scenes, over the images of the scenes the
    CSVs name (an image a CSV has no row for counts as missed). Returns ``{label: result}``
    in the order given (labels: :func:`result_labels`).

    Raises:
        InputError: a CSV that cannot be read, or a dataset scene without ground truth.
    """
    from ssp.eval.bop_metrics import BopEvaluator

    scenes = {int(p.name): p for p in bop_scenes(dataset, split) if p.name.isdigit()}
    tables = []
    for r in results:
        rows = read_bop_csv(r)
        by_image: dict[tuple[int, int], list] = {}
        for row in rows:
            by_image.setdefault((row["scene_id"], row["im_id"]), []).append(row)
        tables.append((Path(r), by_image))
    wanted = sorted({sid for _, t in tables for sid, _ in t})
    missing = [s for s in wanted if s not in scenes]
    if missing:
        raise InputError(f"{dataset}: the results name scenes {missing} it does not have")
    evaluators = [BopEvaluator(library, vsd=vsd) for _ in tables]
    eye = np.eye(4)
    # the published targets when the dataset has them (as the toolkit takes them)
    targets = read_targets(dataset_root(scenes[wanted[0]])) if wanted else None
    for sid in wanted:
        scene = open_bop(scenes[sid], library)
        if not (scenes[sid] / "scene_gt.json").exists():
            raise InputError(f"{scenes[sid]}: no scene_gt.json: nothing to evaluate against")
        for k, im in enumerate(scene.im_ids):
            f = scene.load(k, masks=None, depth=vsd)  # no depth images needed without VSD
            image_targets = None
            if targets is not None:
                image_targets = {
                    scene.classes.get(o, bop_model_name(o)): n
                    for o, n in targets.get((sid, im), {}).items()
                }
            for (_, by_image), ev in zip(tables, evaluators, strict=True):
                ests = []
                for row in by_image.get((sid, im), []):
                    T = np.eye(4)
                    T[:3, :3], T[:3, 3] = row["R"], row["t"] / 1000.0
                    cls = scene.classes.get(row["obj_id"], f"obj_{row['obj_id']:06d}")
                    if cls not in library:
                        raise InputError(f"obj_id {row['obj_id']} ({cls}) is not in the library")
                    ests.append((cls, T, row["score"]))
                ev.add_frame(f.gt, f.visib_fract, ests, f.camera, eye,
                             depth=f.depth if vsd else None, targets=image_targets)  # fmt: skip
            if progress is not None:
                progress(k + 1, len(scene), f"scene {sid}")
    labels = result_labels([p for p, _ in tables])
    return {lab: ev.result() for lab, ev in zip(labels, evaluators, strict=True)}


def result_labels(paths: Sequence[Path]) -> list[str]:
    """How results files are named in a comparison: their file names, or the paths as given
    when two files share a name (two refines write the same BOP file name)."""
    names = [p.name for p in paths]
    return names if len(set(names)) == len(names) else [str(p) for p in paths]


# ------------------------------------------------------------------------------ models
class DatasetModelsError(ArgumentError):
    """A BOP dataset whose object models are not found: they must be given (``--models``)."""


def dataset_models(dataset: str | Path) -> Path | None:
    """The object models of a BOP dataset when no model folder is given: None (the built-in
    models) when the dataset names its objects after them (``models.json``, as ``ssp
    simulate`` writes), else the dataset's ``models/`` folder.

    Raises:
        DatasetModelsError: the dataset has neither.
    """
    from ssp.library.builtin import builtin_specs

    scene = bop_scenes(dataset)[0]
    root = dataset_root(scene)
    for folder in (scene, root):
        mj = None if folder is None else folder / "models.json"
        if mj is not None and mj.is_file():
            names = set(json.loads(mj.read_text())["obj_ids"].values())
            if names <= {spec.name for spec in builtin_specs()}:
                return None
    if root is not None and (root / "models").is_dir():
        return root / "models"
    raise DatasetModelsError(
        f"{dataset}: no models/ folder in the dataset: give the object models with --models"
    )
