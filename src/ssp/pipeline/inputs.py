"""Which :class:`~ssp.pipeline.sources.FrameSource` reads an input path, and the files it is
read from (recorded in ``run.json`` to check a resume).

Kinds: ``bag`` (a ROS 1 bag, an MCAP file or a ROS 2 bag folder: :mod:`ssp.pipeline.bag`),
``bop`` (a BOP scene folder: :mod:`ssp.pipeline.bop`), ``folder`` (a folder of PLY/PCD
clouds: :mod:`ssp.pipeline.folder`). A new input format adds its source module and its
branch in each function here.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ssp.config import SSPConfig
from ssp.io._files import file_problem
from ssp.io.folder import check_folder, is_bop_scene
from ssp.io.rosbag import is_bag
from ssp.pipeline.bag import BagSource, bag_input_files
from ssp.pipeline.bop import BOP_FOLDERS, BopSource
from ssp.pipeline.folder import open_folder_source
from ssp.pipeline.sources import FrameSource

__all__ = ["INPUT_KINDS", "input_files", "input_kind", "open_source"]

INPUT_KINDS = ("folder", "bop", "bag")


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
