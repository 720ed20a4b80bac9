"""Object models: meshes, mass properties, samples, convex parts, symmetries, libraries."""

from ssp.library.build import build_model
from ssp.library.library import ObjectLibrary, prepare_folder
from ssp.library.model import DecompositionInfo, ObjectInstance, ObjectModel
from ssp.library.symmetry import ContinuousSymmetry, Symmetry

__all__ = [
    "ContinuousSymmetry",
    "DecompositionInfo",
    "ObjectInstance",
    "ObjectLibrary",
    "ObjectModel",
    "Symmetry",
    "build_model",
    "prepare_folder",
]
