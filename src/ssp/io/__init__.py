"""File input and output of ``ssp run``: point clouds (PLY, PCD), pose hypotheses JSON, input
folders, result files (per-frame JSON, BOP19 CSV, object ids, TUM trajectories), and pose
estimators' outputs (:mod:`ssp.io.estimators`). Formats: docs/formats.md."""

from __future__ import annotations

from ssp.io._files import to_jsonable, write_json
from ssp.io.clouds import CLOUD_SUFFIXES, LABEL_FIELDS, Cloud, read_cloud, write_cloud
from ssp.io.estimators import EstimatorHypotheses, read_estimates
from ssp.io.folder import (
    FolderInput,
    FrameFile,
    RawFrame,
    SceneSpec,
    is_bop_scene,
    natural_key,
    open_folder,
    read_scene_json,
)
from ssp.io.hypotheses import (
    HypothesisFile,
    matrix_to_quat_xyzw,
    read_hypotheses,
    to_world,
    write_hypotheses,
)
from ssp.io.results import BopCsvWriter, ObjectIds, bop_csv_name, frame_record, read_bop_csv
from ssp.io.tum import TumWriter, write_tum

__all__ = [
    "CLOUD_SUFFIXES",
    "LABEL_FIELDS",
    "BopCsvWriter",
    "Cloud",
    "EstimatorHypotheses",
    "FolderInput",
    "FrameFile",
    "HypothesisFile",
    "ObjectIds",
    "RawFrame",
    "SceneSpec",
    "TumWriter",
    "bop_csv_name",
    "frame_record",
    "is_bop_scene",
    "matrix_to_quat_xyzw",
    "natural_key",
    "open_folder",
    "read_bop_csv",
    "read_cloud",
    "read_estimates",
    "read_hypotheses",
    "read_scene_json",
    "to_jsonable",
    "to_world",
    "write_cloud",
    "write_hypotheses",
    "write_json",
    "write_tum",
]
