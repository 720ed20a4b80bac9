"""Build an :class:`~ssp.library.model.ObjectModel` from a mesh and its physical properties."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ssp.config import LibraryConfig
from ssp.errors import ModelError
from ssp.library.decomposition import clean_parts, decompose, default_cache_dir, hull_iou
from ssp.library.mesh import load_mesh, validate_mesh
from ssp.library.model import DecompositionInfo, ObjectModel
from ssp.library.sampling import interior_samples, surface_samples
from ssp.library.symmetry import Symmetry

log = logging.getLogger(__name__)

#: Monte Carlo points of the IoU check of given (exact) convex parts.
EXACT_PARTS_IOU_SAMPLES = 20_000


def _positive(name: str, what: str, value: float, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ModelError(f"model {name!r}: {what} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        sign = "non-negative" if allow_zero else "positive"
        raise ModelError(f"model {name!r}: {what} must be {sign} and finite, got {value!r}")
    return v


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.flags.writeable = False
    return a


def _check_symmetry(name: str, symmetry: Symmetry, points: np.ndarray, spacing: float) -> None:
    """Warn when a discrete symmetry does not map the surface samples onto themselves."""
    if len(symmetry.discrete) <= 1 or len(points) == 0:
        return
    tree = cKDTree(points)
    for i, T in enumerate(symmetry.discrete[1:], start=1):
        moved = points @ T[:3, :3].T + T[:3, 3]
        d, _ = tree.query(moved)
        if np.median(d) > 2 * spacing:
            log.warning(
                "model %r: discrete symmetry %d moves the surface by %.1f mm (median); "
                "check it (translations are in the file's units)",
                name,
                i,
                1000 * float(np.median(d)),
            )


def build_model(
    name: str,
    mesh: trimesh.Trimesh | str | Path,
    *,
    config: LibraryConfig,
    mass: float | None = None,
    density: float | None = None,
    friction: float | None = None,
    symmetry: Symmetry | None = None,
    convex_parts: Sequence[trimesh.Trimesh] | None = None,
    source: Path | None = None,
    scale: float = 1.0,
    cache_dir: Path | None = None,
) -> ObjectModel:
    """Validate ``mesh`` and compute everything an :class:`ObjectModel` holds.

    Args:
        name: class name.
        mesh: triangle mesh (or a mesh file path) in units that ``scale`` turns into metres.
        config: library settings (extents check, defaults, samples, decomposition).
        mass: kg; or ``density`` kg/m^3 (not both); neither: ``config.default_density``.
        friction: sliding friction coefficient (default ``config.default_friction``).
        symmetry: model-frame symmetries in metres (default: none).
        convex_parts: the model's own convex parts, same units as ``mesh`` (``scale`` applies);
            when given CoACD is skipped (method ``"exact"``), each part is re-hulled.
        source: mesh file, for provenance.
        scale: factor to metres (mm: 0.001).
        cache_dir: hull cache folder (default :func:`default_cache_dir`).

    Raises:
        ModelError (or its subclasses GeometryError, UnitsError, ModelFileError).
    """
    if isinstance(mesh, (str, Path)):
        source = Path(mesh) if source is None else source
        mesh = load_mesh(mesh)
    solid = validate_mesh(mesh, name, config, scale=scale)
    volume = float(solid.volume)

    if mass is not None and density is not None:
        raise ModelError(f"model {name!r}: give mass or density, not both")
    if mass is not None:
        mass = _positive(name, "mass", mass)
    else:
        rho = config.default_density if density is None else _positive(name, "density", density)
        mass = rho * volume
    friction = config.default_friction if friction is None else friction
    friction = _positive(name, "friction", friction, allow_zero=True)

    props = solid.mass_properties  # unit density
    center_of_mass = np.asarray(props["center_mass"], dtype=np.float64)
    inertia = np.asarray(props["inertia"], dtype=np.float64) * (mass / float(props["mass"]))
    inertia = (inertia + inertia.T) / 2

    points, normals = surface_samples(
        solid, config.surface_spacing, config.max_surface_points, config.sample_seed
    )
    interior = interior_samples(solid, config.interior_spacing, config.max_interior_points)

    if convex_parts is not None:
        scaled = []
        for p in convex_parts:
            p = p.copy() if isinstance(p, trimesh.Trimesh) else trimesh.Trimesh(*p, process=False)
            if scale != 1.0:
                p.apply_scale(scale)
            scaled.append(p)
        parts = clean_parts(scaled, volume)
        if not parts:
            raise ModelError(f"model {name!r}: none of the given convex parts has a volume")
        if len(parts) < len(scaled):
            log.warning(
                "model %r: dropped %d degenerate convex parts", name, len(scaled) - len(parts)
            )
        n_iou = min(config.decomposition.iou_samples, EXACT_PARTS_IOU_SAMPLES)
        iou = hull_iou(solid, parts, n_iou, config.decomposition.seed)
        decomposition = DecompositionInfo("exact", len(parts), iou)
    else:
        parts, decomposition = decompose(
            solid, config.decomposition, cache_dir or default_cache_dir(config)
        )

    symmetry = symmetry if symmetry is not None else Symmetry()
    _check_symmetry(name, symmetry, points, config.surface_spacing)

    return ObjectModel(
        name=name,
        mesh=solid,
        convex_parts=tuple(parts),
        mass=float(mass),
        friction=float(friction),
        center_of_mass=_readonly(center_of_mass),
        inertia=_readonly(inertia),
        surface_points=_readonly(points),
        surface_normals=_readonly(normals),
        interior_points=_readonly(interior),
        symmetry=symmetry,
        decomposition=decomposition,
        source=Path(source) if source is not None else None,
    )
