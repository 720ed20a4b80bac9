"""``ssp run`` on a ROS bag or MCAP file (:mod:`ssp.io.rosbag`): a
:class:`~ssp.pipeline.sources.FrameSource` of its frames, and the results bag written from a
run's output folder."""

from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Iterator, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import InputError, SSPError
from ssp.geometry import invert
from ssp.io.results import ObjectIds
from ssp.io.rosbag import (
    BagOptions,
    ResultFrame,
    ResultObject,
    bag_paths,
    open_bag,
    write_results_bag,
)
from ssp.perception.depth import cloud_from_depth
from ssp.perception.pipeline import Perception, PerceptionResult
from ssp.pipeline.sources import Committed, InputFrame
from ssp.pipeline.world import CameraLocator
from ssp.timing import StageTimer

__all__ = ["BagSource", "bag_input_files", "write_run_results_bag"]

log = logging.getLogger(__name__)


class BagSource:
    """The frames of a bag for :func:`ssp.pipeline.run.run`: named ``000000``, ``000001``, ...
    (the position of the driving topic's message), BOP ``im_id`` = that position. Without a
    camera pose from tf, the world frame is the table's, kept while the camera stays put.

    Raises:
        InputError: the bag cannot be opened or its topics cannot be chosen.
    """

    kind = "bag"

    def __init__(
        self,
        path: Path,
        library: Mapping,
        cfg: SSPConfig,
        classes: Sequence[str] | None,
        mode: str,
        options: BagOptions | Mapping[str, Any] | None = None,
    ) -> None:
        self.path, self.library, self.mode = path, library, mode
        self.bag = open_bag(path, options, mode=mode, classes=list(library))
        self.perception = Perception(library, cfg, classes)
        self.topics = self.bag.topics
        # no camera pose from tf: the camera located in the first frame's table frame
        self.locator = CameraLocator(cfg.perception.table_distance)
        self.total = len(self.bag)
        self._said_no_masks = False

    def frames(self, start: int = 0, committed: Committed | None = None) -> Iterator[InputFrame]:
        """The frames from position ``start`` on (:class:`~ssp.pipeline.sources.FrameSource`);
        a camera without pose is located up to ``start`` first, from the ``committed``
        records of the frames before."""
        files = (str(self.path),)  # the bag (file or ROS 2 folder) is named in a frame's errors
        if start > 0 and not self.locator.started:
            for fs in itertools.islice(self.bag.frames(0), start):
                rec = committed(f"{fs.index:06d}") if committed else None
                if rec is None or rec.get("T_world_cam") is None:
                    continue  # that frame failed in the run too
                try:
                    self.locator.replay(self._camera_points(fs.load()), rec)
                except SSPError:
                    pass  # unreadable now, though the run read it: left out of the map
        for fs in self.bag.frames(start):
            yield InputFrame(f"{fs.index:06d}", fs.index, files, partial(self._perceive, fs))

    def object_ids(self) -> ObjectIds:
        """The ids of the bag's folder's ``models.json``, else in the library's order."""
        return ObjectIds.for_input(self.path, list(self.library))

    @staticmethod
    def _camera_points(f) -> np.ndarray:
        if f.kind == "depth":
            return cloud_from_depth(f.depth, f.camera).points
        return np.asarray(f.points, dtype=float)

    def _world(self, f, warnings: list[str], timer: StageTimer) -> tuple[np.ndarray, dict | None]:
        """``(T_world_cam, how it was found)``: tf's (checked), else the locator's."""
        with timer("world frame"):
            if f.T_world_cam is not None:
                return f.T_world_cam, self.locator.check(self._camera_points(f), f.T_world_cam,
                                                         warnings)  # fmt: skip
            return self.locator.locate(self._camera_points(f), warnings)

    def _no_masks(self, f, warnings: list[str]) -> None:
        """Say once per run (log and the frame's warnings, so the summary) that the bag has no
        mask topic and the frames are segmented by clustering, much less exactly."""
        if self._said_no_masks or f.labels is not None or self.topics.mask is not None:
            return
        self._said_no_masks = True
        what = "and its clouds no label field " if f.kind == "cloud" else ""
        warnings.append(
            f"{self.path}: no instance mask topic {what}(give one with --topic-mask): the "
            "frames are segmented by clustering the cloud above the table, much less exactly "
            "than with masks"
        )
        log.warning("%s", warnings[-1])

    def _perceive(self, fs) -> tuple[PerceptionResult, list[str]]:
        timer = StageTimer()  # the frame's: reading and the world frame here
        with timer("read"):
            f = fs.load()
        warnings = list(f.warnings)
        for w in warnings:
            log.warning("%s", w)
        self._no_masks(f, warnings)
        hyps = None if self.mode == "estimated" else f.hypotheses
        if self.mode == "given" and hyps is None:
            topics = self.topics
            raise InputError(
                f"{topics.main} at {f.stamp_ns * 1e-9:.9f} s: no hypotheses message"
                + (f" on {topics.hypotheses}" if topics.hypotheses else " (no hypotheses topic)")
                + " and --hypotheses given"
            )
        T_wc, camera_fix = self._world(f, warnings, timer)
        if f.kind == "depth":
            result = self.perception.from_depth(
                f.depth,
                f.camera,
                stamp=f.stamp,
                T_world_cam=T_wc,
                mask=f.labels,
                hypotheses=hyps,
                hypotheses_frame=f.hypotheses_frame,
                timer=timer,
            )
        else:
            result = self.perception.from_points(
                f.points,
                frame="camera",
                stamp=f.stamp,
                T_world_cam=T_wc,
                labels=f.labels,
                label_kind="instance",
                hypotheses=hyps,
                hypotheses_frame=f.hypotheses_frame,
                timer=timer,
            )
        result.camera_fix = camera_fix
        return result, warnings


def bag_input_files(path: Path) -> dict[str, Any]:
    """``{relative name: [size, mtime_ns]}`` of the files a bag is read from."""
    base = path if path.is_dir() else path.parent
    out: dict[str, Any] = {}
    for p in bag_paths(path):
        st = p.stat()
        out[str(p.relative_to(base))] = [st.st_size, st.st_mtime_ns]
    return out


def write_run_results_bag(
    out_dir: str | Path,
    bag_path: str | Path,
    results_path: str | Path,
    library: Mapping,
    options: BagOptions | Mapping[str, Any] | None = None,
) -> Path:
    """Write the results bag of a finished (or stopped) run of ``bag_path`` in ``out_dir``:
    per frame done, the objects of ``frames/<name>.json`` in the camera frame (the input
    frame's ``frame_id``) with the input header stamp (:class:`ssp.io.rosbag.ResultsBagWriter`).
    Failed frames get no message. ``library`` gives the bounding boxes; ``obj_ids.json`` the
    ROS 1 integer class ids."""
    out = Path(out_dir)
    bag = open_bag(bag_path, options, mode="estimated")
    ids_doc = json.loads((out / "obj_ids.json").read_text(encoding="utf-8"))
    numbers = {cls: int(i) for i, cls in ids_doc.get("obj_ids", {}).items()}

    def frames() -> Iterator[ResultFrame]:
        for k, e in enumerate(bag.entries):
            p = out / "frames" / f"{k:06d}.json"
            if not p.is_file():
                continue
            rec = json.loads(p.read_text(encoding="utf-8"))
            if rec.get("status") == "failed" or rec.get("T_world_cam") is None:
                continue
            T_cw = invert(np.asarray(rec["T_world_cam"], dtype=float))
            objects = []
            for o in rec["objects"]:
                T_co = T_cw @ np.asarray(o["T_world_obj"], dtype=float)
                bbox = None
                model = library.get(o["class"]) if hasattr(library, "get") else None
                if model is not None:
                    lo, hi = np.asarray(model.mesh.bounds, dtype=float)
                    T_ob = np.eye(4)
                    T_ob[:3, 3] = (lo + hi) / 2
                    bbox = (T_co @ T_ob, hi - lo)
                objects.append(
                    ResultObject(
                        id=str(o["id"]),
                        class_name=o["class"],
                        T_cam_obj=T_co,
                        score=float(o.get("fit") or 0.0),
                        number=numbers.get(o["class"], 0),
                        bbox=bbox,
                    )
                )
            yield ResultFrame(e.stamp, e.frame_id, objects)

    return write_results_bag(results_path, frames())
