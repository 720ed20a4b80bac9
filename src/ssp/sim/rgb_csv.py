"""A simulated RGB estimator's BOP19 results CSV for a BOP dataset with ground truth (``ssp
estimate DATA --noise rgb``): the hypotheses of :class:`ssp.sim.realistic.RealisticStream`
with :meth:`RealisticNoise.rgb <ssp.sim.realistic.RealisticNoise.rgb>` (MegaPose-like,
measured on LM-O) drawn at each image's ground truth, in the camera frame, with their scores.

The stream runs in each image's camera frame (``T_world_cam`` the identity), one stream per
scene over its images in order, so a static camera on a static scene sees a persistent error,
as an RGB estimator's is. The stream's randomness derives from ``seed`` and the scene id.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ssp.errors import InputError
from ssp.io.bop import bop_scenes, open_bop
from ssp.io.results import BopCsvWriter, bop_csv_parts
from ssp.sim.realistic import RealisticNoise, RealisticStream

__all__ = ["rgb_estimates"]

log = logging.getLogger(__name__)


def rgb_estimates(
    dataset: str | Path,
    library: Mapping,
    out_csv: str | Path,
    *,
    seed: int = 0,
    noise: RealisticNoise | None = None,
    split: str | None = None,
    scene_ids: Sequence[int] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Write a BOP19 CSV of simulated RGB-estimator hypotheses for every image of the
    dataset's scenes (module docstring); rows in the camera frame (t in mm), ``time`` -1.

    Args:
        dataset: a BOP dataset, split or scene folder with ``scene_gt.json`` and
            ``scene_gt_info.json`` (visible fractions; missing: 1).
        library: class name -> model, holding every class of the ground truth.
        out_csv: the CSV to write (``METHOD_DATASET-SPLIT.csv``; METHOD ``rgb`` otherwise).
        seed: non-negative; the same seed and dataset give the same file.
        noise: the stream (default :meth:`RealisticNoise.rgb`).
        scene_ids: only these scenes.

    Returns:
        ``{csv, images, rows, targets, missed}`` (targets: ground-truth instances; missed:
        those without a hypothesis).

    Raises:
        InputError: no scene, or a scene without ``scene_gt.json`` (before anything is
            written).
    """
    noise = noise if noise is not None else RealisticNoise.rgb()
    scenes = [s for s in bop_scenes(dataset, split) if s.name.isdigit()]
    if scene_ids is not None:
        scenes = [s for s in scenes if int(s.name) in set(scene_ids)]
    if not scenes:
        raise InputError(f"{dataset}: no BOP scene (a folder with scene_camera.json) in it")
    no_gt = [str(s) for s in scenes if not (s / "scene_gt.json").is_file()]
    if no_gt:
        raise InputError(
            f"{', '.join(no_gt)}: no scene_gt.json: the simulated RGB estimator draws its "
            "errors around the ground truth"
        )
    path = Path(out_csv)
    parts = bop_csv_parts(path.name)
    report: dict[str, Any] = {"csv": str(path), "images": 0, "rows": 0, "targets": 0, "missed": 0}
    with BopCsvWriter(path, parts["method"] if parts else "rgb") as csv:
        for scene_path in scenes:
            scene = open_bop(scene_path, library)
            ids = {name: oid for oid, name in scene.classes.items()}
            stream = RealisticStream(
                library,
                noise,
                int(np.random.SeedSequence([int(seed), scene.scene_id]).generate_state(1)[0]),
                classes=[c for c in ids if c in library],
                T_world_cam=np.eye(4),
            )
            for k in range(len(scene)):
                f = scene.load(k, masks=None, depth=False)  # ground truth only: no image needed
                visib = {oid: f.visib_fract.get(oid, 1.0) for oid in f.gt}
                drawn = stream.draw(k, f.gt, visib)
                rows = [
                    csv.format_row(
                        scene.scene_id,
                        f.im_id,
                        ids[d.hypothesis.class_name],
                        d.hypothesis.score,
                        d.hypothesis.T_world_obj,
                    )  # fmt: skip
                    for d in drawn
                ]
                csv.write_rows(rows)
                found = {d.source for d in drawn}
                report["images"] += 1
                report["rows"] += len(rows)
                report["targets"] += len(f.gt)
                report["missed"] += sum(1 for oid in f.gt if oid not in found)
                if progress is not None:
                    progress(k + 1, len(scene), f"scene {scene_path.name}: {len(rows)} rows")
    log.info("%d rows for %d images: %s", report["rows"], report["images"], path)
    return report
