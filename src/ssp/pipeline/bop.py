"""A BOP scene (``ssp simulate``'s or a published one, :mod:`ssp.io.bop`) as a
:class:`~ssp.pipeline.sources.FrameSource`, and its classes' BOP ``obj_id``."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import InputError, SSPError
from ssp.io.bop import DEFAULT_PERIOD, mask_source, open_bop
from ssp.io.results import ObjectIds
from ssp.perception.depth import cloud_from_depth
from ssp.perception.pipeline import Perception, PerceptionResult
from ssp.perception.table import TableTracker
from ssp.pipeline.sources import InputFrame, unknown_class

__all__ = ["BOP_FOLDERS", "BopSource", "bop_object_ids"]

log = logging.getLogger(__name__)

#: The folders of a BOP scene a run reads besides the scene's own files.
BOP_FOLDERS = ("depth", "instance", "mask_visib")


class BopSource:
    """The images of a BOP scene as run input.

    Hypotheses come from ``estimates`` (an estimator's output, camera frame, e.g.
    :func:`ssp.io.estimators.read_estimates`; looked up by ``(scene_id, im_id)``), else the
    scene's ``hypotheses.json``, else the built-in estimator (``mode``, one of
    :data:`ssp.pipeline.sources.HYPOTHESES_MODES`). The world frame is the scene's
    ``cam_R_w2c`` when every image has one, else the table plane fitted to the depth
    (:class:`ssp.perception.table.TableTracker`: kept while the camera stays put).
    ``masks`` is one of :data:`ssp.io.bop.MASK_MODES`; ``period`` the seconds between images
    of a scene without stamps (default :data:`ssp.io.bop.DEFAULT_PERIOD`).

    Raises:
        InputError: the scene cannot be read, or ``mode`` is ``given`` and it has no
            hypotheses.
        ArgumentError: a bad ``masks``.
    """

    kind = "bop"

    def __init__(
        self,
        path: Path,
        library: Mapping,
        cfg: SSPConfig,
        classes: Sequence[str] | None,
        mode: str,
        *,
        estimates: Any = None,
        masks: str = "auto",
        period: float | None = None,
    ) -> None:
        mask_source(masks, simulated=True)  # checks ``masks`` before reading
        self.path, self.library, self.mode = path, library, mode
        self.estimates, self.masks = estimates, masks
        self.scene = open_bop(path, library, period=DEFAULT_PERIOD if period is None else period)
        self.perception = Perception(library, cfg, classes or list(self.scene.models) or None)
        self.hyp_file = path / "hypotheses.json"
        given = estimates is not None or self.scene.has_hypotheses
        if mode == "given" and not given:
            raise InputError(f"{path}: no hypotheses.json and --hypotheses given")
        self.tracker = None if self.scene.has_world else TableTracker(cfg.perception.table_distance)
        self.use_masks = mask_source(masks, self.scene.simulated)
        self.total = len(self.scene)

    def frames(self, start: int = 0) -> Iterator[InputFrame]:
        """The images from position ``start`` on (:class:`~ssp.pipeline.sources.FrameSource`);
        the fitted world frame is brought up to ``start`` first."""
        tracker = self.tracker
        if tracker is not None and start > 0 and tracker.T_world_cam is None:
            # a resumed run: the world frame the frames before ``start`` kept
            for k in range(start):
                try:
                    f = self.scene.load(k, masks=None)
                    tracker.update(cloud_from_depth(f.depth, f.camera).points)
                except SSPError:
                    pass  # that frame failed in the run too, leaving the frame as it was
        est = self.estimates
        for k in range(start, len(self.scene)):
            im = self.scene.im_ids[k]
            hyp = str(est.source) if est is not None else str(self.hyp_file)
            # the depth image first (named in an error that names no file), then the files
            # an error may name itself
            files = (str(self.path / "depth" / f"{im:06d}.png"), hyp,
                     str(self.path / "scene_camera.json"))  # fmt: skip
            yield InputFrame(f"{im:06d}", im, files, partial(self._perceive, k))

    def object_ids(self) -> ObjectIds:
        """:func:`bop_object_ids` of the scene."""
        return bop_object_ids(self.path, self.library)

    def _hypotheses(self, k: int, warnings: list[str]) -> tuple[list | None, str]:
        """The hypotheses of image ``k`` known before it is read (None: the scene's, read with
        the image, or estimated) and their frame."""
        im = self.scene.im_ids[k]
        if self.mode != "estimated" and self.estimates is not None:
            return self.estimates.for_image(self.scene.scene_id, im), "camera"
        if self.mode != "estimated" and self.scene.has_hypotheses and not self.scene.has_entry(k):
            if self.mode == "given":
                raise InputError(f"{self.hyp_file}: no entry for im_id {im} and --hypotheses given")
            warnings.append(
                f"{self.hyp_file}: no entry for im_id {im}: its hypotheses were estimated"
            )
            log.warning("%s", warnings[-1])
        return None, "world"

    def _perceive(self, k: int) -> tuple[PerceptionResult, list[str]]:
        warnings: list[str] = []
        hyps, hyp_frame = self._hypotheses(k, warnings)
        sf = self.scene.load(k, masks=self.use_masks)
        warnings.extend(sf.warnings)  # a suspicious depth image (once per scene)
        if (
            hyps is None
            and self.mode != "estimated"
            and self.estimates is None
            and self.scene.has_entry(k)
        ):
            hyps = list(sf.hypotheses)
        for i, h in enumerate(hyps or []):
            if h.class_name not in self.library:
                raise InputError(f"hypothesis {i}: {unknown_class(h.class_name, self.library)}")
        if self.masks == "gt" and sf.instance is not None and sf.instance_is_gt:
            warnings.append("segments from the ground-truth masks (--masks gt)")
        mask = None
        if self.use_masks and sf.instance is not None:
            mask = np.asarray(sf.instance).astype(np.int64)
            mask[mask < -1] = -1
        T_wc = sf.T_world_cam
        if T_wc is None:
            cloud = cloud_from_depth(sf.depth, sf.camera)
            T_wc, moved = self.tracker.update(cloud.points)
            if moved:
                warnings.append(
                    "the table plane moved: the world frame was fitted again (a moving "
                    "camera needs cam_R_w2c/cam_t_w2c in scene_camera.json)"
                )
        result = self.perception.from_depth(
            sf.depth,
            sf.camera,
            stamp=sf.stamp,
            T_world_cam=T_wc,
            mask=mask,
            hypotheses=hyps,
            hypotheses_frame=hyp_frame,
        )
        return result, warnings


def bop_object_ids(scene: Path, library: Mapping) -> ObjectIds:
    """The BOP ``obj_id`` of each class: the scene's or its dataset's (``models.json``, or
    ``obj_XXXXXX`` model names); classes of the library without one get new ids."""
    classes = open_bop(scene).classes
    if not classes:
        return ObjectIds.for_input(scene, list(library))
    ids = {cls: oid for oid, cls in classes.items()}
    nxt = max(classes) + 1
    for c in sorted(set(library) - set(ids)):
        ids[c] = nxt
        nxt += 1
    return ObjectIds(ids)
