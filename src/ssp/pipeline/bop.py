"""A BOP scene (``ssp simulate``'s or a published one, :mod:`ssp.io.bop`) as a
:class:`~ssp.pipeline.sources.FrameSource`, and its classes' BOP ``obj_id``."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import ArgumentError, InputError, SSPError
from ssp.geometry import invert
from ssp.io.bop import DEFAULT_PERIOD, MASK_MODES, BopFrame, by_bop_name, mask_source, open_bop
from ssp.io.detections import (
    Detection,
    Detections,
    SceneDetections,
    instance_labels,
    match_segments,
    read_detections,
)
from ssp.io.results import ObjectIds
from ssp.perception.depth import cloud_from_depth, labels_at
from ssp.perception.pipeline import Perception, PerceptionResult
from ssp.perception.silhouettes import silhouette_detections
from ssp.pipeline.sources import Committed, InputFrame, unknown_class
from ssp.pipeline.world import CameraLocator
from ssp.timing import StageTimer

__all__ = ["BOP_FOLDERS", "BopSource", "bop_object_ids", "check_masks"]

log = logging.getLogger(__name__)

#: The folders of a BOP scene a run reads besides the scene's own files.
BOP_FOLDERS = ("depth", "instance", "mask_visib")


def check_masks(masks: str) -> Path | None:
    """The detections file ``masks`` names (None: one of :data:`ssp.io.bop.MASK_MODES`).

    Raises:
        ArgumentError: neither a mode nor an existing file.
    """
    if masks in MASK_MODES:
        return None
    p = Path(masks).expanduser()
    if not p.is_file():
        raise ArgumentError(
            f"masks must be one of {', '.join(MASK_MODES)} or a detections file (BOP "
            f"segmentation results JSON), got {masks!r}: "
            + ("not a file" if p.exists() else "no such file")
        )
    return p


class BopSource:
    """The images of a BOP scene as run input.

    Hypotheses come from ``estimates`` (an estimator's output, camera frame, e.g.
    :func:`ssp.io.estimators.read_estimates`; looked up by ``(scene_id, im_id)``), else the
    scene's ``hypotheses.json``, else the built-in estimator (``mode``, one of
    :data:`ssp.pipeline.sources.HYPOTHESES_MODES`). The world frame is the scene's
    ``cam_R_w2c`` when every image has one (checked against the data:
    :meth:`ssp.pipeline.world.CameraLocator.check`), else the first image's table, each image's
    camera located in it (:class:`ssp.pipeline.world.CameraLocator`); with ``locate`` False
    (single-frame work: the estimator alone), each image's own table.
    ``masks`` is one of :data:`ssp.io.bop.MASK_MODES` or the path of a detector's instance
    masks (a BOP segmentation results file, :mod:`ssp.io.detections`; ``mask_min_score``
    drops its detections scoring below it): each image's detections are its instance labels,
    each label's class the detection's, and each given hypothesis takes the label of the
    detection of its class it overlaps (:func:`ssp.io.detections.match_segments`); an image
    without detections has no masks (a warning of the frame). ``mask_description`` says in
    words which masks the frames get. ``period`` is the seconds between images of a scene
    without stamps (default :data:`ssp.io.bop.DEFAULT_PERIOD`).

    Raises:
        InputError: the scene cannot be read, ``mode`` is ``given`` and it has no
            hypotheses, or the detections file cannot be read or has no usable detection of
            the scene.
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
        mask_min_score: float = 0.0,
        locate: bool = True,
    ) -> None:
        det_file = check_masks(masks)  # checks ``masks`` before reading
        self.locate = locate
        self.path, self.library, self.mode = path, library, mode
        self.estimates, self.masks = estimates, masks
        self.scene = open_bop(path, library, period=DEFAULT_PERIOD if period is None else period)
        self.perception = Perception(library, cfg, classes or list(self.scene.models) or None)
        self.hyp_file = path / "hypotheses.json"
        given = estimates is not None or self.scene.has_hypotheses
        if mode == "given" and not given:
            raise InputError(f"{path}: no hypotheses.json and --hypotheses given")
        self.locator = CameraLocator(cfg.perception.table_distance)  # locates or checks
        #: m: how far from a silhouette's rendered depth its pixels may be (the correction's reach)
        self.max_gap = cfg.correction.max_shift
        self.detections: SceneDetections | None = None
        if det_file is None:
            self.use_masks = mask_source(masks, self.scene.simulated)
        else:
            self.use_masks = None  # the scene's own segmentation is not read
            self.detections = self._read_detections(det_file, mask_min_score)
        self.mask_description = self._describe_masks(det_file, mask_min_score)
        self.total = len(self.scene)

    def _read_detections(self, det_file: Path, min_score: float) -> SceneDetections:
        """The detections of this scene in ``det_file`` (:mod:`ssp.io.detections`)."""
        sc = self.scene
        sizes = {}
        for k, im in enumerate(sc.im_ids):
            cam = sc.camera_of(k)
            sizes[im] = (cam.height, cam.width)
        classes = {oid: c for oid, c in sc.classes.items() if c in self.library}
        dets = _detections_file(str(det_file.resolve()), *_stamp(det_file))
        return dets.for_scene(sc.scene_id, sizes, classes, min_score=min_score)

    def _describe_masks(self, det_file: Path | None, min_score: float) -> str:
        """Which masks the frames get, in words."""
        if det_file is not None:
            low = f", scores of at least {min_score:g}" if min_score > 0 else ""
            return f"detections: {det_file}{low}"
        if self.use_masks is None:
            return {
                "none": "none (--masks none)",
                "silhouettes": "the hypotheses' rendered silhouettes (--masks silhouettes)",
            }.get(self.masks, "--masks auto: a published scene's only masks are its ground truth's")
        if self.use_masks == "gt":
            return "ground truth (mask_visib)"
        return "the simulated segmentation (instance/), else mask_visib"

    def frames(self, start: int = 0, committed: Committed | None = None) -> Iterator[InputFrame]:
        """The images from position ``start`` on (:class:`~ssp.pipeline.sources.FrameSource`);
        a camera without pose is located up to ``start`` first, from the ``committed``
        records of the frames before."""
        loc = self.locator
        if start > 0 and not loc.started:
            for k in range(start):  # a resumed run: the world frame the frames before left
                rec = committed(f"{self.scene.im_ids[k]:06d}") if committed else None
                if rec is None or rec.get("T_world_cam") is None:
                    continue  # that frame failed in the run too, leaving the locator as it was
                try:
                    f = self.scene.load(k, masks=None)
                except SSPError:
                    continue  # unreadable now, though the run read it: left out of the map
                loc.replay(cloud_from_depth(f.depth, f.camera).points, rec)
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
        timer = StageTimer()  # the frame's: reading, world frame, masks and cloud here
        with timer("read"):
            hyps, hyp_frame = self._hypotheses(k, warnings)
            sf = self.scene.load(k, masks=self.use_masks)
            warnings.extend(sf.warnings)  # a suspicious depth image (once per scene)
            if (
                hyps is None
                and self.mode != "estimated"
                and self.estimates is None
                and self.scene.has_entry(k)
            ):
                hyps, hyp_frame = list(sf.hypotheses), self.scene.hypotheses_frame
            for i, h in enumerate(hyps or []):
                if h.class_name not in self.library:
                    raise InputError(f"hypothesis {i}: {unknown_class(h.class_name, self.library)}")
        if self.masks == "gt" and sf.instance is not None and sf.instance_is_gt:
            warnings.append("segments from the ground-truth masks (--masks gt)")
        mask = None
        if self.use_masks and sf.instance is not None:
            mask = np.asarray(sf.instance).astype(np.int64)
            mask[mask < -1] = -1
        with timer("cloud"):  # the points once: the world frame's fit and the front end's
            cloud = cloud_from_depth(sf.depth, sf.camera)
        T_wc = sf.T_world_cam
        with timer("world frame"):
            if T_wc is None and not self.locate:
                T_wc, camera_fix = self.locator.own_table(cloud.points)
            elif T_wc is None:
                T_wc, camera_fix = self.locator.locate(cloud.points, warnings)
            else:
                camera_fix = self.locator.check(cloud.points, T_wc, warnings)
        label_classes = None
        if self.detections is not None:
            with timer("masks"):
                dets, notes = self.detections.frame(sf.im_id)
                for note in notes:
                    log.warning("%s", note)
                warnings.extend(notes)
                mask, label_classes, hyps = self._instance_masks(dets, sf, hyps, hyp_frame, T_wc)
        elif mask is None and self.masks != "none":
            if hyps and self.masks == "silhouettes":
                with timer("masks"):
                    T_cf = None if hyp_frame == "camera" else invert(T_wc)
                    ids = {c: oid for oid, c in self.scene.classes.items()}
                    dets = silhouette_detections(
                        hyps, self.library, ids, sf.camera, sf.depth, T_cf, im_id=sf.im_id,
                        max_gap=self.max_gap,
                    )  # fmt: skip
                    mask, label_classes, hyps = self._instance_masks(
                        dets, sf, hyps, hyp_frame, T_wc
                    )
            warnings.append(
                "no masks: segments from the hypotheses' rendered silhouettes (--masks FILE: a "
                "detector's instance masks)"
                if mask is not None
                else f"no masks ({self.mask_description}): the cloud above the table is "
                "clustered, clutter may become objects (--masks FILE: a detector's instance masks)"
            )
        with timer("cloud"):
            labels = None if mask is None else labels_at(mask, sf.camera, cloud.pixels)
        result = self.perception.from_points(
            cloud.points,
            frame="camera",
            stamp=sf.stamp,
            T_world_cam=T_wc,
            labels=labels,
            label_classes=label_classes,
            hypotheses=hyps,
            hypotheses_frame=hyp_frame,
            timer=timer,
        )
        result.camera, result.depth = sf.camera, sf.depth  # for the recording
        result.camera_fix = camera_fix
        return result, warnings

    def _instance_masks(
        self,
        dets: list[Detection],
        sf: BopFrame,
        hyps: list | None,
        hyp_frame: str,
        T_wc: np.ndarray,
    ) -> tuple[np.ndarray | None, dict[int, str] | None, list | None]:
        """The instance labels ``(H, W)`` of frame ``sf``'s detections ``dets`` (a detector's
        or the hypotheses' silhouettes), each label's class, and the hypotheses with the label
        of their detection (``segment``); no labels when there is no detection."""
        if not dets:
            return None, None, hyps
        inst = instance_labels(dets, sf.depth.shape)
        class_of = self.scene.classes
        label_classes = {i: class_of[d.obj_id] for i, d in enumerate(inst.detections)}
        if hyps:
            T_cam_frame = None if hyp_frame == "camera" else invert(T_wc)
            hyps, n = match_segments(
                hyps, inst, class_of, self.library, sf.camera, sf.depth, T_cam_frame
            )
            log.info("im_id %d: %d of %d hypotheses on a detection of their class (%d "
                     "detections)", sf.im_id, n, len(hyps), len(dets))  # fmt: skip
        return inst.labels.astype(np.int64), label_classes, hyps


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_mtime_ns, st.st_size


@lru_cache(maxsize=2)
def _detections_file(path: str, mtime_ns: int, size: int) -> Detections:
    """:func:`read_detections` of ``path``, read once while the file is unchanged (a refine
    opens one scene source per scene, each reading the same file)."""
    return read_detections(path)


def bop_object_ids(scene: Path, library: Mapping) -> ObjectIds:
    """The BOP ``obj_id`` of each class: the scene's or its dataset's (``models.json``, or
    ``obj_XXXXXX`` model names); classes of the library without one get new ids."""
    classes = open_bop(scene).classes
    if not classes:
        return ObjectIds.for_input(scene, list(library))
    renamed = by_bop_name(classes, library)  # the dataset's own models/ folder: obj_XXXXXX
    ids = {renamed.get(cls, cls): oid for oid, cls in classes.items()}
    nxt = max(classes) + 1
    for c in sorted(set(library) - set(ids)):
        ids[c] = nxt
        nxt += 1
    return ObjectIds(ids)
