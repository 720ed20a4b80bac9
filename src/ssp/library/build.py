"""Build an :class:`~ssp.library.model.ObjectModel` from a mesh and its physical properties."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ssp.config import LibraryConfig
from ssp.errors import ModelError
from ssp.library.decomposition import (
    Status,
    centred_vertices,
    clean_parts,
    decompose,
    default_cache_dir,
    find_entry,
    hull_iou,
    write_entry,
)
from ssp.library.mesh import describe, load_mesh, scale_vector, validate_mesh
from ssp.library.model import DecompositionInfo, ObjectModel
from ssp.library.sampling import interior_samples, surface_samples
from ssp.library.symmetry import (
    DETECT_ORDERS,
    DETECT_QUERY_POINTS,
    DETECT_REFERENCE_POINTS,
    AxisSymmetry,
    Symmetry,
    SymmetryDetection,
    close_group,
    detect_symmetries,
)

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


def _given_parts(
    name: str,
    solid: trimesh.Trimesh,
    convex_parts: Sequence[trimesh.Trimesh],
    factors: np.ndarray,
    method: str,
    config: LibraryConfig,
) -> tuple[tuple[trimesh.Trimesh, ...], DecompositionInfo]:
    """The supplied convex parts, scaled and re-hulled, with their measured IoU."""
    scaled = []
    for p in convex_parts:
        p = p.copy() if isinstance(p, trimesh.Trimesh) else trimesh.Trimesh(*p, process=False)
        if not np.all(factors == 1.0):
            p.apply_transform(np.diag([*factors, 1.0]))
        scaled.append(p)
    parts = clean_parts(scaled, float(solid.volume))
    if not parts:
        raise ModelError(f"model {name!r}: none of the given convex parts has a volume")
    if len(parts) < len(scaled):
        log.warning("model %r: dropped %d degenerate convex parts", name, len(scaled) - len(parts))
    n_iou = config.decomposition.iou_samples
    if method == "exact":  # built-in primitives: their union is the mesh by construction
        n_iou = min(n_iou, EXACT_PARTS_IOU_SAMPLES)
    iou = hull_iou(solid, parts, n_iou, config.decomposition.seed)
    return parts, DecompositionInfo(method, len(parts), iou)


def _plausibility(name: str, source, extents: np.ndarray, mass: float, config) -> None:
    """Log a model too large or too heavy for a hand-held object (a forgotten scale)."""
    largest = float(extents.max())
    if largest > config.max_hand_extent or mass > config.max_hand_mass:
        log.warning(
            "%s: %.3g m long and %.4g kg, implausible for a hand-held object (limits %g m, "
            "%g kg); if the mesh is meant to be scaled, set `scale:` (or `units:`) for it in "
            "models.yaml",
            describe(name, source),
            largest,
            mass,
            config.max_hand_extent,
            config.max_hand_mass,
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
    scale: float | Sequence[float] = 1.0,
    cache_dir: Path | None = None,
    parts_method: str = "given",
    status: Status | None = None,
    detect_symmetry: float | None = None,
    use_detected_symmetry: bool = False,
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
            when given CoACD is skipped (method ``parts_method``), each part is re-hulled and
            their IoU against the mesh is measured.
        source: mesh file, for provenance and messages.
        scale: factor to metres (mm: 0.001), or three per-axis factors.
        cache_dir: hull cache folder (default :func:`default_cache_dir`).
        parts_method: ``"given"`` (user-supplied parts) or ``"exact"`` (the built-in models'
            primitives).
        status: called with one-line status texts while the model is built (progress).
        detect_symmetry: MSSD tolerance (m) of the approximate symmetry detection
            (:func:`ssp.library.symmetry.detect_symmetries`, cached); None: no detection.
        use_detected_symmetry: the model's symmetry is the group generated by ``symmetry``
            and the detected one (otherwise the detection is only reported).

    Raises:
        ModelError (or its subclasses GeometryError, UnitsError, ModelFileError).
    """
    if isinstance(mesh, (str, Path)):
        source = Path(mesh) if source is None else source
        mesh = load_mesh(mesh)
    who = describe(name, source)
    factors = scale_vector(scale, who)
    if status is not None:
        status(f"{name}: validating")
    solid = validate_mesh(mesh, name, config, scale=factors, source=source)
    mass, friction = _mass_and_friction(name, source, solid, mass, density, friction, config)
    return _model_of_solid(
        name,
        solid,
        source,
        factors,
        mass,
        friction,
        config,
        symmetry=symmetry,
        convex_parts=convex_parts,
        cache_dir=cache_dir,
        parts_method=parts_method,
        status=status,
        detect_symmetry=detect_symmetry,
        use_detected_symmetry=use_detected_symmetry,
    )


def _model_of_solid(
    name: str,
    solid: trimesh.Trimesh,
    source: Path | None,
    factors: np.ndarray,
    mass: float,
    friction: float,
    config: LibraryConfig,
    *,
    symmetry: Symmetry | None,
    convex_parts: Sequence[trimesh.Trimesh] | None,
    cache_dir: Path | None,
    parts_method: str,
    status: Status | None,
    detect_symmetry: float | None,
    use_detected_symmetry: bool,
) -> ObjectModel:
    """:func:`build_model` of the validated mesh ``solid`` (metres; ``factors``: the scale it
    was given) of ``mass`` and ``friction``: the mass properties, samples, convex parts and
    symmetries."""
    center_of_mass, inertia = _mass_properties(solid, mass)

    if status is not None:
        status(f"{name}: sampling")
    points, normals = surface_samples(
        solid, config.surface_spacing, config.max_surface_points, config.sample_seed, name=name
    )
    interior = interior_samples(solid, config.interior_spacing, config.max_interior_points)

    if convex_parts is not None:
        parts, decomposition = _given_parts(
            name, solid, convex_parts, factors, parts_method, config
        )
    else:
        parts, decomposition = decompose(
            solid,
            config.decomposition,
            cache_dir or default_cache_dir(config),
            status=None if status is None else (lambda text: status(f"{name}: {text}")),
        )
    decomposition = _check_iou(name, source, decomposition, config)

    symmetry = symmetry if symmetry is not None else Symmetry()
    detected = None
    if detect_symmetry is not None:
        if status is not None:
            status(f"{name}: detecting symmetries")
        detected = cached_symmetry_detection(
            solid,
            center_of_mass,
            inertia,
            float(detect_symmetry),
            cache_dir or default_cache_dir(config),
        )
        if use_detected_symmetry and len(detected.group) > 1:
            both = close_group([*symmetry.discrete[1:], *detected.group[1:]], f"model {name!r}")
            symmetry = Symmetry(both, symmetry.continuous)
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
        detected_symmetry=detected,
    )


def _mass_and_friction(
    name: str,
    source: Path | None,
    solid: trimesh.Trimesh,
    mass: float | None,
    density: float | None,
    friction: float | None,
    config: LibraryConfig,
) -> tuple[float, float]:
    """:func:`build_model`'s checked ``(mass, friction)`` of the validated mesh ``solid``
    (the defaults of ``config`` for the ones not given)."""
    who = describe(name, source)
    volume = float(solid.volume)
    if mass is not None and density is not None:
        raise ModelError(f"{who}: give mass or density, not both")
    if mass is not None:
        mass = _positive(name, "mass", mass)
    else:
        rho = config.default_density if density is None else _positive(name, "density", density)
        mass = rho * volume
    friction = config.default_friction if friction is None else friction
    friction = _positive(name, "friction", friction, allow_zero=True)
    _plausibility(name, source, np.asarray(solid.extents), mass, config)
    return mass, friction


def _mass_properties(solid: trimesh.Trimesh, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """``(centre of mass (3,), inertia (3, 3) about it)`` of ``solid`` of ``mass`` kg."""
    props = solid.mass_properties  # unit density
    center_of_mass = np.asarray(props["center_mass"], dtype=np.float64)
    inertia = np.asarray(props["inertia"], dtype=np.float64) * (mass / float(props["mass"]))
    inertia = (inertia + inertia.T) / 2
    return center_of_mass, inertia


def _check_iou(
    name: str, source, info: DecompositionInfo, config: LibraryConfig
) -> DecompositionInfo:
    """``info`` with a warning (also logged) when its IoU is below ``min_iou``."""
    threshold = config.decomposition.min_iou
    if info.iou >= threshold:
        return info
    text = (
        f"the {info.n_parts} convex part(s) ({info.method}) match the mesh at volume IoU "
        f"{info.iou:.3f} < {threshold:g} (decomposition.min_iou): the physics collides with "
        "a different shape; give the model finer `decomposition:` settings in models.yaml "
        "(e.g. a smaller threshold, mode: coacd) or better convex_parts"
    )
    log.warning("%s: %s", describe(name, source), text)
    return replace(info, warnings=(*info.warnings, text))


#: Bump when the symmetry detection or its cache layout changes.
SYMMETRY_CACHE_VERSION = 2


def _translate(T: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``T`` expressed in a frame moved by ``offset``: ``Tr(offset) T Tr(-offset)``."""
    A = np.eye(4)
    A[:3, 3] = offset
    B = np.eye(4)
    B[:3, 3] = -offset
    return A @ T @ B


def cached_symmetry_detection(
    mesh: trimesh.Trimesh,
    center_of_mass: np.ndarray,
    inertia: np.ndarray,
    tolerance: float,
    cache_dir: Path,
) -> SymmetryDetection:
    """:func:`~ssp.library.symmetry.detect_symmetries` of ``mesh``, cached in ``cache_dir``
    like the convex parts (content-keyed: a re-export or a re-centred copy hits the cache)."""
    import hashlib
    import json

    centre, centred, tol = centred_vertices(mesh)
    h = hashlib.sha256()
    with np.errstate(all="ignore"):
        key = [
            f"ssp-symmetry-v{SYMMETRY_CACHE_VERSION}",
            len(mesh.vertices),
            len(mesh.faces),
            f"{float(mesh.volume):.4g}",
            f"{float(mesh.area):.4g}",
            f"{tolerance:.6g}",
            list(DETECT_ORDERS),
            DETECT_QUERY_POINTS,
            DETECT_REFERENCE_POINTS,
        ]
    h.update(json.dumps(key).encode())
    bucket = Path(cache_dir) / f"sym-{h.hexdigest()}"
    entry = find_entry(bucket, centred, tol)
    if entry is not None:
        _, meta, arrays = entry
        try:
            group = np.stack([_translate(T, centre) for T in arrays["group"]])
            axes = tuple(
                AxisSymmetry(
                    np.asarray(a["axis"], dtype=float),
                    a["label"],
                    tuple(a["orders"]),
                    int(a["order"]),
                    float(a["mssd"]),
                    bool(a["near_continuous"]),
                    tuple(float(x) for x in a.get("order_mssd", ())),
                )
                for a in meta["axes"]
            )
            return SymmetryDetection(group, axes, float(meta["tolerance"]), float(meta["floor"]))
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("ignoring unreadable symmetry cache entry %s: %s", bucket, exc)
    result = detect_symmetries(mesh, center_of_mass, inertia, tolerance)
    meta = {
        "tolerance": result.tolerance,
        "floor": result.floor,
        "axes": [
            {
                "axis": a.axis.tolist(),
                "label": a.label,
                "orders": list(a.orders),
                "order": a.order,
                "mssd": a.mssd,
                "near_continuous": a.near_continuous,
                "order_mssd": list(a.order_mssd),
            }
            for a in result.axes
        ],
    }
    group = np.stack([_translate(T, -centre) for T in result.group])
    write_entry(bucket, centred, meta, group=group)
    return result
