"""Loading and validating object meshes: metres, watertight, positive volume.

:func:`load_mesh` reads any format trimesh reads (scenes are concatenated into one mesh), as
is: no vertex is merged or dropped at reading (a NaN vertex is reported by validation, never
silently removed). Text formats in another encoding than UTF-8 (a Latin-1 comment in an OBJ)
are decoded by trimesh with charset-normalizer, a dependency for that reason.
:func:`validate_mesh` applies a unit scale (uniform or per axis), decimates meshes of more than
``LibraryConfig.max_mesh_faces`` faces, checks the size against the plausible range of
:class:`~ssp.config.LibraryConfig` (the usual mistake is a mesh in millimetres), repairs what can
be repaired (duplicate vertices, degenerate and duplicate faces, planar holes, inconsistent
winding, inside-out bodies) and raises a typed error naming the model and its file for the rest.
:func:`load_convex_parts` reads a file of convex parts (one per OBJ object/group).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import numpy as np
import trimesh

from ssp.config import LibraryConfig
from ssp.errors import GeometryError, ModelFileError, UnitsError

log = logging.getLogger(__name__)

#: Unit names accepted in models.yaml and their scale to metres.
UNIT_SCALES: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}

#: A hole is filled when its boundary loop lies within this fraction of the loop's size of
#: its best-fit plane (a cut-off handle end, a missing cap); other holes are errors.
PLANAR_HOLE_TOLERANCE = 0.05

_OPEN_SURFACE_WHY = (
    "volume, centre of mass, inertia and interior samples are undefined for an open surface"
)


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a mesh file (OBJ, PLY, STL, GLB, ...); multi-geometry files are concatenated.

    Raises:
        ModelFileError: the file is missing, unreadable, not a mesh, or has no triangles.
    """
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"mesh file not found: {path}")
    if not path.is_file():
        raise ModelFileError(f"mesh path is not a file: {path}")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise ModelFileError(f"cannot read mesh file {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise ModelFileError(
            f"{path} does not contain a triangle mesh (got {type(loaded).__name__})"
        )
    if len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise ModelFileError(f"{path} contains no triangles (empty or unreadable mesh file)")
    return loaded


def describe(name: str, source: str | Path | None = None) -> str:
    """``model 'name'`` or ``model 'name' (file)`` for messages."""
    return f"model {name!r}" + (f" ({source})" if source is not None else "")


def _boundary_loops(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """Vertex indices of each boundary loop (edges used by one face only)."""
    import networkx as nx

    counts = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
    edges = mesh.edges_unique[counts == 1]
    graph = nx.Graph()
    graph.add_edges_from(edges.tolist())
    return [np.array(sorted(c)) for c in nx.connected_components(graph)]


def _loop_flatness(points: np.ndarray) -> float:
    """Largest distance of ``points`` (n, 3) from their best-fit plane over their size."""
    centred = points - points.mean(axis=0)
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    size = float(np.ptp(centred @ vt[0])) if len(sv) else 0.0
    if size <= 0:
        return 0.0
    return float(np.abs(centred @ vt[-1]).max()) / size


def fill_planar_holes(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int, int] | None:
    """Close every hole of ``mesh`` if all of them are planar (:data:`PLANAR_HOLE_TOLERANCE`).

    The holes are filled by MeshFix (pymeshfix ``fill_small_boundaries``, no refinement),
    which triangulates holes of any number of edges (trimesh's own ``fill_holes`` only closes
    triangles and quads). Returns ``(mesh, holes, new_faces)``, or None when a hole is not
    planar, an edge is shared by more than two faces, or the result is still open.
    """
    from pymeshfix import PyTMesh

    counts = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
    if (counts > 2).any():
        return None
    loops = _boundary_loops(mesh)
    if not loops or any(
        _loop_flatness(mesh.vertices[loop]) > PLANAR_HOLE_TOLERANCE for loop in loops
    ):
        return None
    fixer = PyTMesh()
    fixer.set_quiet(True)
    fixer.load_array(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64),
        np.ascontiguousarray(mesh.faces, dtype=np.int32),
    )
    fixer.fill_small_boundaries(nbe=0, refine=False)
    vertices, faces = fixer.return_arrays()
    filled = trimesh.Trimesh(vertices, faces, process=False)
    if not filled.is_watertight:
        return None
    return filled, len(loops), len(filled.faces) - len(mesh.faces)


def _units_hint(extent: float, scale: float, config: LibraryConfig) -> str:
    """Most likely units mistake for a largest extent (m, after ``scale``) out of range."""

    def plausible(x: float) -> bool:
        return config.min_extent <= x <= config.max_extent

    raw = extent / scale  # extent in the file's own units
    if extent > config.max_extent:
        for unit in ("mm", "cm"):
            if plausible(raw * UNIT_SCALES[unit]):
                name = {"mm": "millimetres", "cm": "centimetres"}[unit]
                return (
                    f"the mesh looks like it is in {name}; declare `units: {unit}` "
                    f"(scale {UNIT_SCALES[unit]:g}) in models.yaml"
                )
        return (
            "check the mesh units (`units:` in models.yaml) or raise library.max_extent "
            f"({config.max_extent:g} m)"
        )
    if scale != 1.0 and plausible(raw):
        return (
            f"the mesh already looks like it is in metres, but a scale of {scale:g} was "
            "applied; remove the `units:` entry (or set `units: m`) in models.yaml"
        )
    return (
        "check the mesh units (`units:` in models.yaml) or lower library.min_extent "
        f"({config.min_extent:g} m)"
    )


def _signed_volumes(mesh: trimesh.Trimesh, groups: list[np.ndarray]) -> np.ndarray:
    """Signed volume (m^3) enclosed by each face group (divergence theorem)."""
    tri = mesh.triangles
    per_face = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    return np.array([per_face[g].sum() for g in groups])


def _fix_orientation(mesh: trimesh.Trimesh) -> None:
    """Make every body's normals consistent and outward, in place.

    Bodies (connected face groups) with negative enclosed volume are inverted, except those
    lying inside another body (cavities, whose inward normals are correct).
    """
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
    groups = trimesh.graph.connected_components(
        mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1
    )
    groups = [np.asarray(g, dtype=np.int64) for g in groups]
    if len(groups) <= 1:
        with np.errstate(all="ignore"):
            if mesh.volume < 0:
                mesh.invert()
        return
    vols = _signed_volumes(mesh, groups)
    if np.all(vols >= 0):
        return
    faces = mesh.faces.copy()
    changed = False
    for i, g in enumerate(groups):
        if vols[i] >= 0:
            continue
        probe = mesh.vertices[faces[g[0], 0]][None]
        inside_other = False
        for j, h in enumerate(groups):
            if j == i or vols[j] <= 0:
                continue
            body = trimesh.Trimesh(mesh.vertices, faces[h], process=False)
            if body.contains(probe)[0]:
                inside_other = True
                break
        if not inside_other:
            faces[g] = faces[g][:, ::-1]
            changed = True
    if changed:
        mesh.faces = faces


def _open_edges_description(mesh: trimesh.Trimesh) -> str:
    """Why a mesh is not watertight: counts of boundary and non-manifold edges."""
    counts = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
    boundary = int((counts == 1).sum())
    nonmanifold = int((counts > 2).sum())
    parts = []
    if boundary:
        parts.append(f"{boundary} boundary edges (holes)")
    if nonmanifold:
        parts.append(f"{nonmanifold} edges shared by more than two faces")
    if not parts:
        parts.append("edges with inconsistent orientation")
    return ", ".join(parts)


def scale_vector(scale: float | Sequence[float] | np.ndarray, who: str = "model") -> np.ndarray:
    """``scale`` (a number or 3 per-axis factors) as a positive, finite (3,) array."""
    try:
        v = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise GeometryError(
            f"{who}: scale must be a number or 3 numbers (x, y, z), got {scale!r}"
        ) from None
    if not (np.all(np.isfinite(v)) and np.all(v > 0)):
        raise GeometryError(f"{who}: scale must be positive and finite, got {scale!r}")
    return v


def validate_mesh(
    mesh: trimesh.Trimesh,
    name: str,
    config: LibraryConfig,
    scale: float | Sequence[float] | np.ndarray = 1.0,
    source: str | Path | None = None,
) -> trimesh.Trimesh:
    """Return a cleaned, repaired copy of ``mesh`` scaled by ``scale`` (to metres).

    ``scale`` is one factor or three per-axis factors (URDF-style non-uniform scale), applied
    before the units check. The copy has no visuals, merged vertices, no degenerate or
    duplicate faces, outward normals and positive volume; a mesh of more than
    ``config.max_mesh_faces`` faces is decimated to that many (logged). ``name`` and
    ``source`` (the mesh file) are used in messages.

    Raises:
        GeometryError: NaN/inf vertices, fewer than 4 faces, flat or degenerate geometry, zero
            volume, or an open surface that could not be repaired.
        UnitsError: the largest extent after ``scale`` is outside
            ``[config.min_extent, config.max_extent]``.
    """
    who = describe(name, source)
    if not isinstance(mesh, trimesh.Trimesh):
        raise GeometryError(f"{who}: expected a trimesh.Trimesh, got {type(mesh)}")
    factors = scale_vector(scale, who)
    vertices, faces = _checked_arrays(mesh, who)
    m = trimesh.Trimesh(vertices * factors, faces, process=False)
    if len(m.faces) > config.max_mesh_faces:
        m = _decimated(m, who, config)
    m.remove_unreferenced_vertices()
    extents = _checked_extents(m, who, factors, config)
    m, repaired = _cleaned(m, who)
    if len(m.faces) < 4:
        raise GeometryError(f"{who}: fewer than 4 faces are left after cleaning")
    if not m.is_watertight:
        raise GeometryError(
            f"{who}: the mesh is not watertight after repair "
            f"({_open_edges_description(m)}; only holes whose edges lie in a plane are "
            f"filled); {_OPEN_SURFACE_WHY}. Close the mesh in a mesh editor (e.g. fill holes / "
            "make manifold) and try again"
        )
    volume = _oriented_volume(m, repaired)
    if repaired:
        log.info("%s: repaired mesh: %s", who, "; ".join(repaired))
    if not np.isfinite(volume) or volume <= 1e-9 * float(np.prod(extents)):
        raise GeometryError(
            f"{who}: the mesh encloses no volume ({volume:.3g} m^3 for extents "
            f"{np.round(extents, 4)} m); it may be a flat sheet or self-cancelling surfaces"
        )
    return m


def _checked_arrays(mesh: trimesh.Trimesh, who: str) -> tuple[np.ndarray, np.ndarray]:
    """``mesh``'s (V, 3) float64 vertices and (F, 3) int64 faces, checked: finite vertices, at
    least 4 faces, every face index a vertex."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise GeometryError(f"{who}: mesh arrays have the wrong shape")
    if not np.all(np.isfinite(vertices)):
        bad = int((~np.isfinite(vertices)).any(axis=1).sum())
        raise GeometryError(
            f"{who}: {bad} of {len(vertices)} vertices have NaN or infinite coordinates; "
            "fix or remove them in the mesh file (ssp does not drop vertices or fill the "
            "holes they would leave)"
        )
    if len(faces) < 4:
        raise GeometryError(f"{who}: only {len(faces)} faces; a closed surface needs at least 4")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise GeometryError(f"{who}: faces reference vertices that do not exist")
    return vertices, faces


def _decimated(m: trimesh.Trimesh, who: str, config: LibraryConfig) -> trimesh.Trimesh:
    """``m`` (merged in place) decimated to ``config.max_mesh_faces`` faces (logged);
    GeometryError when that changes its volume by more than 1 %."""
    n_faces = len(m.faces)
    m.merge_vertices()
    with np.errstate(all="ignore"):
        volume_before = abs(float(m.volume))
    m = m.simplify_quadric_decimation(face_count=int(config.max_mesh_faces))
    with np.errstate(all="ignore"):
        change = abs(abs(float(m.volume)) / volume_before - 1.0) if volume_before else 0.0
    if change > 0.01:
        raise GeometryError(
            f"{who}: {n_faces} faces (more than library.max_mesh_faces "
            f"{config.max_mesh_faces}), and decimating it changed its volume by "
            f"{100 * change:.1f} %; decimate the mesh in a mesh editor, or raise "
            "library.max_mesh_faces"
        )
    log.warning(
        "%s: %d faces decimated to %d (library.max_mesh_faces) to bound memory and time",
        who,
        n_faces,
        len(m.faces),
    )
    return m


def _checked_extents(
    m: trimesh.Trimesh, who: str, factors: np.ndarray, config: LibraryConfig
) -> np.ndarray:
    """``m``'s (3,) extents, m: GeometryError when flat, UnitsError when the largest is outside
    ``[config.min_extent, config.max_extent]`` (``factors``: the scale applied, for the hint)."""
    extents = np.asarray(m.extents, dtype=float)
    largest = float(extents.max())
    if largest <= 0 or float(extents.min()) <= 1e-6 * largest:
        raise GeometryError(
            f"{who}: the mesh is flat or degenerate (extents {np.round(extents, 6)} m); "
            "a solid object needs thickness in all three directions"
        )
    if largest > config.max_extent or largest < config.min_extent:
        limit = "above" if largest > config.max_extent else "below"
        bound = config.max_extent if largest > config.max_extent else config.min_extent
        raise UnitsError(
            f"{who}: largest extent {largest:.4g} m is {limit} the plausible "
            f"{bound:g} m: {_units_hint(largest, float(np.prod(factors)) ** (1 / 3), config)}"
        )
    return extents


def _cleaned(m: trimesh.Trimesh, who: str) -> tuple[trimesh.Trimesh, list[str]]:
    """``m`` cleaned in place by operations that never open a closed surface (merged
    vertices, no repeated-vertex or duplicate faces), then, when open, without zero-area faces
    and with its planar holes filled (a new mesh); and what was repaired."""
    m.merge_vertices(merge_tex=True, merge_norm=True)
    f = m.faces
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if repeated.any():
        m.update_faces(~repeated)
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    repaired: list[str] = []
    if not m.is_watertight:
        n_before = len(m.faces)
        m.update_faces(m.nondegenerate_faces())
        m.remove_unreferenced_vertices()
        if len(m.faces) < n_before:
            repaired.append(f"removed {n_before - len(m.faces)} zero-area faces")
        if not m.is_watertight and len(m.faces) >= 4:
            filled = fill_planar_holes(m)
            if filled is not None:
                m, holes, new_faces = filled
                log.warning(
                    "%s: filled %d planar hole(s) with %d faces (the mesh was open)",
                    who,
                    holes,
                    new_faces,
                )
                repaired.append(f"filled {holes} planar holes with {new_faces} faces")
    return m, repaired


def _oriented_volume(m: trimesh.Trimesh, repaired: list[str]) -> float:
    """Orient ``m``'s faces outward in place (:func:`_fix_orientation`) and return its volume,
    m^3; what was fixed is appended to ``repaired``."""
    was_consistent = m.is_winding_consistent
    with np.errstate(all="ignore"):
        volume_before = float(m.volume)
    _fix_orientation(m)
    if not was_consistent:
        repaired.append("fixed inconsistent face winding")
    with np.errstate(all="ignore"):
        volume = float(m.volume)
    if was_consistent and volume_before < 0 < volume:
        repaired.append("inverted inside-out mesh")
    return volume


def load_convex_parts(path: str | Path) -> list[trimesh.Trimesh]:
    """Read convex parts: one per OBJ object/group, else one per geometry or connected piece.

    Returns the parts as read (file units; not yet hulled or validated).

    Raises:
        ModelFileError: the file is missing, unreadable or has no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"convex parts file not found: {path}")
    parts: list[trimesh.Trimesh] = []
    try:
        if path.suffix.lower() == ".obj":
            # one geometry per OBJ object/group (trimesh's OBJ loader does the splitting)
            scene = cast(  # force="scene": always a Scene
                trimesh.Scene,
                trimesh.load(
                    path, split_objects=True, group_material=False, force="scene", process=False
                ),
            )
            parts = [g for g in scene.geometry.values() if isinstance(g, trimesh.Trimesh)]
        if len(parts) <= 1:
            loaded = trimesh.load(path)
            if isinstance(loaded, trimesh.Scene):
                geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
            else:
                geoms = [loaded] if isinstance(loaded, trimesh.Trimesh) else []
            parts = []
            for g in geoms:
                parts.extend(g.split(only_watertight=False) if len(geoms) == 1 else [g])
    except (ValueError, IndexError, OSError) as exc:
        raise ModelFileError(f"cannot read convex parts file {path}: {exc}") from exc
    except Exception as exc:  # trimesh raises many types for bad files
        raise ModelFileError(
            f"cannot read convex parts file {path}: {type(exc).__name__}: {exc}"
        ) from exc
    parts = [p for p in parts if len(p.faces) > 0]
    if not parts:
        raise ModelFileError(f"convex parts file {path} contains no triangles")
    return parts
