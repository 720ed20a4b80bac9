"""Which :class:`~ssp.pipeline.sources.FrameSource` reads an input path, and the files it is
read from (recorded in ``run.json`` to check a resume).

Kinds: ``bag`` (a ROS 1 bag, an MCAP file or a ROS 2 bag folder: :mod:`ssp.pipeline.bag`),
``bop`` (a BOP scene folder: :mod:`ssp.pipeline.bop`), ``folder`` (a folder of PLY/PCD
clouds: :mod:`ssp.pipeline.folder`). A new input format adds its source module and its
branch in each function here.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ssp.config import SSPConfig
from ssp.errors import ArgumentError, InputError
from ssp.io._files import file_problem
from ssp.io.folder import check_folder, is_bop_scene
from ssp.io.results import MODELS_JSON, ObjectIds
from ssp.io.rosbag import is_bag
from ssp.pipeline.bag import BagSource, bag_input_files
from ssp.pipeline.bop import BOP_FOLDERS, BopSource
from ssp.pipeline.folder import open_folder_source
from ssp.pipeline.sources import FrameSource

__all__ = [
    "DEFAULT_SCENE_ID",
    "INPUT_KINDS",
    "input_files",
    "input_kind",
    "open_source",
    "run_object_ids",
    "run_scene_id",
]

log = logging.getLogger(__name__)

INPUT_KINDS = ("folder", "bop", "bag")
#: The BOP ``scene_id`` of the rows of an input that names none (a folder of clouds, a bag).
DEFAULT_SCENE_ID = 1


def input_kind(path: Path) -> str:
    """The kind of input at ``path`` (one of :data:`INPUT_KINDS`). Never opens a file.

    Raises:
        InputError: ``path`` is neither a bag nor an existing folder.
    """
    if is_bag(path):
        return "bag"
    check_folder(path)
    return "bop" if is_bop_scene(path) else "folder"


def input_files(path: Path, kind: str) -> dict[str, Any]:
    """``{relative name: [size, mtime_ns]}`` (or the problem of an entry that is not a regular
    file) of the files a run of ``path`` reads: the input folder's own files, and for a BOP
    scene those of ``depth/``, ``instance/`` and ``mask_visib/``; a bag's files. Never opens
    a file."""
    if kind == "bag":
        return bag_input_files(path)
    out: dict[str, Any] = {}
    folders = [path] + ([path / d for d in BOP_FOLDERS] if kind == "bop" else [])
    for folder in folders:
        if not folder.is_dir():
            continue
        with os.scandir(folder) as it:
            entries = sorted(it, key=lambda e: e.name)
        for e in entries:
            problem = file_problem(e.path)
            if e.name.startswith(".") or problem == "is a folder, not a file":
                continue
            rel = os.path.relpath(e.path, path)
            if problem is None:
                st = e.stat()
                out[rel] = [st.st_size, st.st_mtime_ns]
            else:
                out[rel] = problem
    return out


def open_source(
    path: Path,
    kind: str,
    library: Mapping,
    cfg: SSPConfig,
    classes: Sequence[str] | None,
    mode: str,
    *,
    estimates: Any = None,
    masks: str = "auto",
    period: float | None = None,
    bag: Mapping[str, Any] | None = None,
) -> FrameSource:
    """The source of the input ``path`` of ``kind`` (:func:`input_kind`): ``mode`` one of
    :data:`ssp.pipeline.sources.HYPOTHESES_MODES`, ``classes`` the estimator's candidate
    classes; ``estimates``, ``masks``, ``period`` are a BOP scene's options
    (:class:`~ssp.pipeline.bop.BopSource`), ``bag`` a bag's (:class:`ssp.io.rosbag.BagOptions`
    as a dict).

    Raises:
        InputError: the input as a whole cannot be used.
    """
    if kind == "bag":
        return BagSource(path, library, cfg, classes, mode, bag)
    if kind == "bop":
        return BopSource(path, library, cfg, classes, mode, estimates=estimates, masks=masks,
                         period=period)  # fmt: skip
    return open_folder_source(path, library, cfg, classes, mode)


def source_scene_id(source: FrameSource) -> int | None:
    """The BOP ``scene_id`` the input names itself: a BOP scene's (its folder name when it is
    a number, else its ``sequence.json``'s); None for inputs that name none."""
    if not isinstance(source, BopSource):
        return None
    scene = source.scene
    if scene.path.name.isdigit() or "scene_id" in scene.meta:
        return int(scene.scene_id)
    return None


def run_scene_id(source: FrameSource, scene_id: int | None) -> int:
    """The ``scene_id`` of a run's CSV rows: ``scene_id`` when given, else the one the input
    names (:func:`source_scene_id`), else :data:`DEFAULT_SCENE_ID`.

    Raises:
        ArgumentError: ``scene_id`` is not an integer >= 0, or contradicts the BOP scene's own
            id (its rows would be scored against another scene's ground truth).
    """
    own = source_scene_id(source)
    if scene_id is None:
        if own is None:
            log.info("the input names no BOP scene_id: its rows get scene_id %d (give one with "
                     "--scene-id)", DEFAULT_SCENE_ID)  # fmt: skip
        return DEFAULT_SCENE_ID if own is None else own
    if isinstance(scene_id, bool) or not isinstance(scene_id, int) or scene_id < 0:
        raise ArgumentError(f"scene_id must be an integer >= 0, got {scene_id!r}")
    if own is not None and own != scene_id:
        raise ArgumentError(
            f"scene_id {scene_id} contradicts the BOP scene {getattr(source, 'path', '')} "
            f"(scene_id {own}): its rows would be scored against scene {scene_id}'s ground "
            "truth; leave --scene-id out for a BOP scene"
        )
    return int(scene_id)


def run_object_ids(
    path: Path,
    kind: str,
    source: FrameSource,
    library: Mapping,
    obj_ids: str | os.PathLike | ObjectIds | Mapping[str, int] | None = None,
) -> tuple[ObjectIds, str]:
    """The BOP ``obj_id`` of every class of ``library`` for a run of ``path`` (of ``kind``),
    and where they come from, in words. The first that applies:

    1. ``obj_ids``: an id table (:meth:`ObjectIds.from_file`: a BOP ``models.json``,
       ``models_info.json`` or ``models/`` folder, an earlier run's ``obj_ids.json``), an
       :class:`ObjectIds` or a ``{class: obj_id}`` mapping; it must give an id to every class
       of the library;
    2. the input's own: a BOP scene's (its dataset's ``models.json`` or ``models_info.json``),
       a folder's (or ROS 2 bag folder's) ``models.json``; classes of the library it misses
       get new ids after its largest (a warning names them);
    3. the library's names when each is a BOP model's (``obj_000005``: 5), as the models of a
       BOP ``models/`` folder (``--models DATASET/models``) are named;
    4. the 1-based positions of the sorted class names (a warning says the ids are ssp's).

    Raises:
        InputError: an ``obj_ids`` table that cannot be read, or that misses a class of the
            library (the message names it).
        ArgumentError: an ``obj_ids`` mapping with an id below 1 or one id for two classes.
    """
    classes = list(library)
    if isinstance(obj_ids, Mapping):
        try:
            obj_ids = ObjectIds(obj_ids)
        except ValueError as exc:
            raise ArgumentError(f"obj_ids: {exc}") from exc
    if obj_ids is not None:
        ids = obj_ids if isinstance(obj_ids, ObjectIds) else ObjectIds.from_file(obj_ids)
        where = "the ids given" if isinstance(obj_ids, ObjectIds) else str(obj_ids)
        missing = ids.missing(classes)
        if missing:
            raise InputError(
                f"{where}: no obj_id for the class{'es' if len(missing) > 1 else ''} "
                f"{', '.join(repr(c) for c in missing)} of the library: add "
                f"{'them' if len(missing) > 1 else 'it'} to the id table, or give only the "
                "models of the dataset with --models"
            )
        return ids, where
    own = _own_ids(path, kind, source, classes)
    if own is not None:
        return own
    ids = ObjectIds.from_bop_names(classes)
    if ids is not None:
        return ids, "the BOP model names (obj_XXXXXX) of the library"
    log.warning("%s: no id table (models.json) in the input and no --obj-ids: the obj_ids of the "
                "results are the positions of the sorted class names, which no dataset "
                "knows", path)  # fmt: skip
    return ObjectIds.from_classes(classes), "the sorted class names"


def _own_ids(
    path: Path, kind: str, source: FrameSource, classes: list[str]
) -> tuple[ObjectIds, str] | None:
    """The input's own ids (:func:`run_object_ids`, step 2), or None."""
    if isinstance(source, BopSource) and source.scene.classes:
        ids, where = source.object_ids(), f"the BOP dataset of {path}"
        known = set(source.scene.classes.values())
    elif (path / MODELS_JSON).is_file():
        ids, where = ObjectIds.for_input(path, classes), str(path / MODELS_JSON)
        known = set(ObjectIds.from_models_json(path / MODELS_JSON))
    else:
        return None
    added = sorted(set(classes) - known)
    if added:
        log.warning("%s has no obj_id for %s: given %s (no dataset knows them)", where,
                    ", ".join(added), ", ".join(str(ids[c]) for c in added))  # fmt: skip
    return ids, where
