"""A folder of PLY/PCD clouds (:func:`ssp.io.folder.open_folder`, ``docs/formats.md``) as a
:class:`~ssp.pipeline.sources.FrameSource`."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from functools import partial
from pathlib import Path

from ssp.config import SSPConfig
from ssp.errors import InputError
from ssp.io.folder import SCENE_JSON, FrameFile, open_folder
from ssp.io.results import ObjectIds
from ssp.perception.pipeline import Perception, PerceptionResult
from ssp.pipeline.sources import Committed, InputFrame, unknown_class
from ssp.timing import StageTimer

__all__ = ["FolderSource", "open_folder_source"]


class FolderSource:
    """The frames of a folder of clouds, each with its hypotheses file when it has one.

    ``mode`` is one of :data:`ssp.pipeline.sources.HYPOTHESES_MODES`; ``perception`` is the
    front end the frames go through.

    Raises:
        InputError: no frames, a bad ``scene.json``, or classes of ``scene.json`` not in the
            library.
    """

    kind = "folder"

    def __init__(self, path: Path, library: Mapping, perception: Perception, mode: str) -> None:
        self.path = path
        self.library = library
        self.perception = perception
        self.mode = mode
        self.folder = open_folder(path)
        self.spec = self.folder.spec
        scene = path / SCENE_JSON
        for what, mapping in (("classes", self.spec.classes), ("colors", self.spec.colors)):
            for key, cls in mapping.items():
                if cls not in library:
                    label = f"#{key:06x}" if what == "colors" else str(key)
                    raise InputError(f"{scene}: {what}[{label!r}]: {unknown_class(cls, library)}")
        self.total = len(self.folder.frames)

    def frames(self, start: int = 0, committed: Committed | None = None) -> Iterator[InputFrame]:
        """The frames from position ``start`` on (:class:`~ssp.pipeline.sources.FrameSource`)."""
        for ff in self.folder.frames[start:]:
            files = (str(ff.cloud_path),) + (
                (str(ff.hypotheses_path),) if ff.hypotheses_path is not None else ()
            )
            yield InputFrame(ff.name, ff.index, files, partial(self._perceive, ff))

    def object_ids(self) -> ObjectIds:
        """The folder's ``models.json`` ids, else ids in the library's order."""
        return ObjectIds.for_input(self.path, list(self.library))

    def _perceive(self, ff: FrameFile) -> tuple[PerceptionResult, list[str]]:
        timer = StageTimer()  # the frame's: reading here
        with timer("read"):
            raw = self.folder.load(ff)
        hyps = None if self.mode == "estimated" else raw.hypotheses
        if self.mode == "given" and hyps is None:
            raise InputError(
                f"{ff.cloud_path}: no hypotheses file {ff.name}.hypotheses.json and "
                "--hypotheses given"
            )
        for i, h in enumerate(hyps or []):
            if h.class_name not in self.library:
                raise InputError(
                    f"{ff.hypotheses_path}: hypothesis {i}: "
                    f"{unknown_class(h.class_name, self.library)}"
                )
        T_wc = self.spec.T_world_cam
        if T_wc is None and raw.frame == "world":
            T_wc = raw.viewpoint
        result = self.perception.from_points(
            raw.points,
            frame=raw.frame,
            stamp=raw.stamp,
            T_world_cam=T_wc,
            labels=raw.labels,
            label_kind=raw.label_kind,
            label_classes=raw.label_classes,
            hypotheses=hyps,
            hypotheses_frame=raw.hypotheses_frame or "world",
            timer=timer,
        )
        return result, list(raw.warnings)


def open_folder_source(
    path: Path, library: Mapping, cfg: SSPConfig, classes: Sequence[str] | None, mode: str
) -> FolderSource:
    """A folder of clouds as run input, perceived with ``classes`` as the estimator's candidate
    classes (None: the whole library)."""
    return FolderSource(path, library, Perception(library, cfg, classes), mode)
