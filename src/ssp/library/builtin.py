"""Built-in object models generated from convex primitives (no outside data, no licence issues).

Every built-in model is the union of a few convex primitives (boxes, polygonal prisms and
frusta, ellipsoids made of latitude rings). The primitives are at the same time the model's
exact convex decomposition for the physics engine, so no CoACD run is needed, and the watertight
``mesh`` is their boolean union (manifold3d).

Models (all in metres, model frame at the centre of the axis-aligned bounding box, z up in the
canonical resting pose where there is one):

* ``cube``, ``block``: the 2-inch cube and the 2x1x1-inch block of the block-stacking scenes.
* ``link``, ``node``: CoSTAR-style construction pieces; a 5-inch square beam with enlarged end
  blocks, and a 2-inch cube with a square socket recessed into every face.
* tools (:data:`TOOL_NAMES`): ``mallet``, ``ball_pein_hammer``, ``claw_hammer``, ``drill``,
  ``sander``, ``screwdriver``, ``wrench``, ``clamp``; non-convex, 10-35 cm.

Symmetries are exact for the meshes as built: round parts are polygonal prisms, so a model has
at most discrete rotational symmetries and never a continuous one. A tool has a symmetry only
if the whole shape has it (mirror symmetries are not rigid motions and do not count), with one
declared exception: the screwdriver's six 60-degree turns about its hexagonal handle, which
move its surface by at most 1.9 mm (MSSD; :attr:`BuiltinSpec.symmetry_tolerance` 2 mm; see
docs/models.md, "Approximate symmetries", for the measurement and the decision).

Densities are single effective values per model (e.g. a steel head on a wooden handle gives a
value in between), chosen so that the masses are plausible.

:func:`builtin_specs` builds every model once per process (cached); it returns fresh copies,
so callers may modify the meshes they get.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ssp.errors import GeometryError, UnknownObjectError
from ssp.library.symmetry import Symmetry

INCH = 0.0254
"""One inch in metres."""

BLOCK_NAMES: tuple[str, ...] = ("cube", "block", "link", "node")
"""The block-world models (convex or nearly so, axis-aligned symmetric shapes)."""

TOOL_NAMES: tuple[str, ...] = (
    "mallet",
    "ball_pein_hammer",
    "claw_hammer",
    "drill",
    "sander",
    "screwdriver",
    "wrench",
    "clamp",
)
"""The tool-like, non-convex models."""

VIEW_AMBIGUOUS_NAMES: tuple[str, ...] = ("mug", "tin")
"""Models whose orientation a view often cannot decide (a mug's handle hidden behind its
body; a nearly square tin, whose quarter turns nearly fit): not in the default library,
written by ``export_builtin(..., view_ambiguous=True)`` for the protocols that measure it
(docs/benchmarks.md, "View-ambiguous objects")."""

MAX_FACES = 5000
"""Upper bound on the face count of a built-in mesh (kept modest for collision and rendering)."""


@dataclass(frozen=True)
class BuiltinSpec:
    """One built-in model.

    Attributes:
        name: model (class) name.
        mesh: watertight boolean union of ``parts``, metres, model frame.
        parts: the convex primitives (each convex and watertight), model frame; their union is
            exactly ``mesh`` and they are the model's convex decomposition. Parts may overlap:
            take mass and inertia from ``mesh``, not from a density on every part.
        symmetry: exact discrete rotational symmetries (BOP convention, metres).
        density: kg/m^3 (one effective value for the whole model).
        friction: sliding friction coefficient.
        description: one line of text.
        symmetry_tolerance: largest surface distance (MSSD, m) a declared symmetry may move
            the surface by; 0 for exact symmetries (all but the screwdriver's).
    """

    name: str
    mesh: trimesh.Trimesh
    parts: tuple[trimesh.Trimesh, ...]
    symmetry: Symmetry
    density: float
    friction: float
    description: str
    symmetry_tolerance: float = 0.0

    @property
    def mass(self) -> float:
        """kg, ``density * mesh.volume``."""
        return float(self.density * self.mesh.volume)

    def copy(self) -> BuiltinSpec:
        """A deep copy (meshes and symmetry arrays are not shared)."""
        return dataclasses.replace(
            self,
            mesh=self.mesh.copy(),
            parts=tuple(p.copy() for p in self.parts),
            symmetry=Symmetry(self.symmetry.discrete.copy(), self.symmetry.continuous),
        )


# --------------------------------------------------------------------------------------------
# primitives


_AXES = {"x": 0, "y": 1, "z": 2}
# (u, v) basis of the cross-section plane for a primitive along each axis (right-handed: u x v
# is the axis). The polygon vertex k sits at angle phase + 2 pi k / n from u towards v.
_BASIS = {0: (1, 2), 1: (2, 0), 2: (0, 1)}


def _convex(points: np.ndarray) -> trimesh.Trimesh:
    """Convex hull of ``points`` as a processed, watertight mesh with outward normals."""
    hull = trimesh.convex.convex_hull(np.asarray(points, dtype=float))
    if not hull.is_watertight or hull.volume <= 0:
        raise GeometryError("degenerate convex primitive")
    return hull


def _apply(points: np.ndarray, transform: np.ndarray | None) -> np.ndarray:
    if transform is None:
        return points
    return points @ transform[:3, :3].T + transform[:3, 3]


def _box(
    extents: Sequence[float] | np.ndarray,
    center: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    transform: np.ndarray | None = None,
) -> trimesh.Trimesh:
    """Box of ``extents`` centred at ``center``, then moved by ``transform`` (4x4)."""
    half = np.asarray(extents, dtype=float) / 2.0
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return _convex(_apply(corners * half + np.asarray(center, dtype=float), transform))


def _frustum(
    axis: str,
    start: float,
    stop: float,
    radius: float | tuple[float, float],
    radius_end: float | tuple[float, float] | None = None,
    center: Sequence[float] = (0.0, 0.0),
    sections: int = 24,
    phase: float = 0.0,
    transform: np.ndarray | None = None,
) -> trimesh.Trimesh:
    """Polygonal prism / frustum along a coordinate ``axis`` from ``start`` to ``stop``.

    ``radius`` (or ``(ru, rv)`` semi-axes for an elliptical section) at ``start`` and
    ``radius_end`` at ``stop`` (same as ``radius`` if None). ``center``: the (u, v) position of
    the axis in the cross-section basis of :data:`_BASIS` (x: (y, z), y: (z, x), z: (x, y)).
    The polygon is exact: vertex k at angle ``phase + 2 pi k / sections`` from u towards v.
    """
    a = _AXES[axis]
    u, v = _BASIS[a]
    r0 = np.broadcast_to(np.asarray(radius, dtype=float), (2,))
    r1 = r0 if radius_end is None else np.broadcast_to(np.asarray(radius_end, dtype=float), (2,))
    ang = phase + 2.0 * np.pi * np.arange(sections) / sections
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    pts = []
    for t, r in ((start, r0), (stop, r1)):
        p = np.zeros((sections, 3))
        p[:, u] = center[0] + r[0] * ring[:, 0]
        p[:, v] = center[1] + r[1] * ring[:, 1]
        p[:, a] = t
        pts.append(p)
    return _convex(_apply(np.concatenate(pts), transform))


def _ellipsoid(
    center: Sequence[float],
    radii: float | Sequence[float],
    axis: str = "z",
    rings: int = 8,
    sections: int = 24,
    phase: float = 0.0,
) -> trimesh.Trimesh:
    """Polyhedral ellipsoid: ``rings`` latitude rings of ``sections`` vertices plus two poles.

    ``radii`` are the semi-axes along x, y, z; the rings are perpendicular to ``axis`` so the
    solid has the exact ``sections``-fold symmetry about it (and the 2-fold ones across it).
    """
    a = _AXES[axis]
    u, v = _BASIS[a]
    rad = np.broadcast_to(np.asarray(radii, dtype=float), (3,))
    lat = np.pi * (np.arange(1, rings + 1) / (rings + 1) - 0.5)  # open interval (-pi/2, pi/2)
    lon = phase + 2.0 * np.pi * np.arange(sections) / sections
    pts = [np.eye(3)[a], -np.eye(3)[a]]
    for phi in lat:
        p = np.zeros((sections, 3))
        p[:, u] = np.cos(phi) * np.cos(lon)
        p[:, v] = np.cos(phi) * np.sin(lon)
        p[:, a] = np.sin(phi)
        pts.append(p)
    unit = np.vstack(pts)
    return _convex(unit * rad + np.asarray(center, dtype=float))


def _posed_box(
    extents: Sequence[float], center: Sequence[float] | np.ndarray, axis: str, degrees: float
) -> trimesh.Trimesh:
    """Box of ``extents`` rotated by ``degrees`` about the coordinate ``axis`` (through its own
    centre) and centred at ``center``."""
    T = _rotation(axis, degrees)
    T[:3, 3] = np.asarray(center, dtype=float)
    return _box(extents, transform=T)


def _rotation(
    axis: str, degrees: float, about: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0)
) -> np.ndarray:
    """4x4 rotation by ``degrees`` about the coordinate ``axis`` through the point ``about``."""
    return trimesh.transformations.rotation_matrix(
        np.radians(degrees), np.eye(3)[_AXES[axis]], point=np.asarray(about, dtype=float)
    )


def _exact_rotation(axis: str, quarter_turns: int) -> np.ndarray:
    """4x4 rotation by ``quarter_turns`` * 90 degrees about a coordinate axis, exact entries."""
    a = _AXES[axis]
    u, v = _BASIS[a]
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns % 4]
    T = np.eye(4)
    T[u, u], T[u, v], T[v, u], T[v, v] = c, -s, s, c
    return T


def _box_group(extents: Sequence[float]) -> np.ndarray:
    """Proper rotations among the 48 signed axis permutations that map a centred box of
    ``extents`` onto itself, ``(S, 4, 4)``, identity first (24 for a cube, 8 for a square bar)."""
    e = np.asarray(extents, dtype=float)
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0 and np.allclose(np.abs(R) @ e, e, rtol=1e-9, atol=1e-12):
                T = np.eye(4)
                T[:3, :3] = R
                out.append(T)
    out.sort(key=lambda T: not np.array_equal(T, np.eye(4)))  # identity first
    return np.stack(out)


# --------------------------------------------------------------------------------------------
# assembly


def _finish(
    name: str,
    parts: Iterable[trimesh.Trimesh],
    symmetries: Sequence[np.ndarray] | np.ndarray = (),
    *,
    density: float,
    friction: float,
    description: str,
    symmetry_tolerance: float = 0.0,
) -> BuiltinSpec:
    """Centre the parts on their bounding box, union them, and check the result.

    ``symmetries`` are 4x4 transforms in the construction frame (before centring); they are
    conjugated into the model frame.
    """
    parts = list(parts)
    lo = np.min([p.bounds[0] for p in parts], axis=0)
    hi = np.max([p.bounds[1] for p in parts], axis=0)
    shift = np.eye(4)
    shift[:3, 3] = -(lo + hi) / 2.0
    moved = []
    for p in parts:
        q = p.copy()
        q.apply_transform(shift)
        moved.append(q)
    mesh = moved[0].copy() if len(moved) == 1 else trimesh.boolean.union(moved, engine="manifold")
    # manifold3d returns coincident copies of some vertices (and zero-area triangles between
    # them where parts meet in degenerate ways): merge the copies and drop those triangles
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if not mesh.is_watertight or not mesh.is_winding_consistent or mesh.volume <= 0:
        raise GeometryError(f"built-in model {name!r}: union is not a watertight solid")
    if mesh.body_count != 1:
        raise GeometryError(f"built-in model {name!r}: union has {mesh.body_count} bodies")
    if len(mesh.faces) > MAX_FACES:
        raise GeometryError(f"built-in model {name!r}: {len(mesh.faces)} faces > {MAX_FACES}")
    inv = np.linalg.inv(shift)
    sym = [shift @ np.asarray(T, dtype=float) @ inv for T in symmetries]
    discrete = np.stack([np.eye(4), *sym]) if sym else np.eye(4)[None]
    return BuiltinSpec(
        name=name,
        mesh=mesh,
        parts=tuple(moved),
        symmetry=Symmetry(discrete),
        density=float(density),
        friction=float(friction),
        description=description,
        symmetry_tolerance=float(symmetry_tolerance),
    )


# --------------------------------------------------------------------------------------------
# block-world models


def _cube() -> BuiltinSpec:
    e = (2 * INCH,) * 3
    return _finish(
        "cube",
        [_box(e)],
        _box_group(e)[1:],
        density=700.0,
        friction=0.9,
        description="2-inch (50.8 mm) wooden cube",
    )


def _block() -> BuiltinSpec:
    e = (2 * INCH, INCH, INCH)
    return _finish(
        "block",
        [_box(e)],
        _box_group(e)[1:],
        density=700.0,
        friction=0.9,
        description="2x1x1-inch (50.8 x 25.4 x 25.4 mm) wooden block, long axis x",
    )


def _link() -> BuiltinSpec:
    length, end, bar = 5 * INCH, INCH, 0.75 * INCH
    half = length / 2
    parts = [
        # the beam ends half-way into the end blocks: overlap, no coplanar faces
        _box((length - end, bar, bar)),
        _box((end, end, end), center=(half - end / 2, 0, 0)),
        _box((end, end, end), center=(-(half - end / 2), 0, 0)),
    ]
    return _finish(
        "link",
        parts,
        _box_group((length, end, end))[1:],
        density=900.0,
        friction=0.8,
        description="CoSTAR-style link: 5-inch beam, 3/4-inch square, with 1-inch end blocks",
    )


def _node() -> BuiltinSpec:
    """2-inch cube with a 1-inch square socket, 1/4 inch deep, in the centre of every face.

    Exact decomposition: the core cube inside the socket floors, plus the 12 edge columns
    (points with two coordinates beyond the socket half-width), which are solid everywhere.
    """
    h, a, depth = INCH, INCH / 2, INCH / 4
    c = h - depth
    parts = [_box((2 * c,) * 3)]
    for axis in range(3):
        j, k = (axis + 1) % 3, (axis + 2) % 3
        for sj in (1, -1):
            for sk in (1, -1):
                ext = np.zeros(3)
                ctr = np.zeros(3)
                ext[axis], ext[j], ext[k] = 2 * h, h - a, h - a
                ctr[j], ctr[k] = sj * (h + a) / 2, sk * (h + a) / 2
                parts.append(_box(ext, ctr))
    return _finish(
        "node",
        parts,
        _box_group((2 * h,) * 3)[1:],
        density=900.0,
        friction=0.8,
        description="CoSTAR-style node: 2-inch cube with a 1-inch square socket, 1/4 inch "
        "deep, recessed in each face",
    )


# --------------------------------------------------------------------------------------------
# tools (construction frames: handle along +x, lying on the table, z up, unless stated)


def _mallet() -> BuiltinSpec:
    """Wooden mallet: 24-gon head along y, round handle along x through the head centre."""
    n = 24
    parts = [
        # head: flat facets on top and bottom (phase pi/n), symmetric under z -> -z
        _frustum("y", -0.06, 0.06, 0.0325, sections=n, phase=np.pi / n),
        _frustum("y", -0.064, -0.06, 0.0295, 0.0325, sections=n, phase=np.pi / n),
        _frustum("y", 0.06, 0.064, 0.0325, 0.0295, sections=n, phase=np.pi / n),
        _frustum("x", 0.0, 0.29, 0.0125, sections=n),
        _frustum("x", 0.29, 0.30, 0.0125, 0.0105, sections=n),
    ]
    # the half turn about the handle axis maps head (even n, reflection-symmetric) and handle
    return _finish(
        "mallet",
        parts,
        [_exact_rotation("x", 2)],
        density=700.0,
        friction=0.7,
        description="wooden mallet, 65 mm x 128 mm head, 30 cm overall",
    )


def _ball_pein_hammer() -> BuiltinSpec:
    """Ball-pein hammer: steel head along y (face at -y, ball at +y), oval wooden handle."""
    n = 24
    parts = [
        _frustum("y", -0.062, -0.056, 0.0135, 0.0155, sections=n, phase=np.pi / n),  # face
        _frustum("y", -0.056, 0.012, 0.0155, sections=n, phase=np.pi / n),  # body
        _frustum("y", 0.010, 0.036, 0.013, 0.0085, sections=n, phase=np.pi / n),  # neck
        _ellipsoid((0.0, 0.046, 0.0), 0.0135, axis="y", rings=8, sections=n),  # ball
        _frustum("x", 0.0, 0.30, (0.0155, 0.0115), (0.0125, 0.0105), sections=n),  # handle
        _frustum("x", 0.30, 0.325, (0.0125, 0.0105), (0.0145, 0.0115), sections=n),  # grip end
    ]
    return _finish(
        "ball_pein_hammer",
        parts,
        density=2400.0,
        friction=0.6,
        description="ball-pein hammer, steel head on an oval wooden handle (effective "
        "density), 33 cm",
    )


def _claw_hammer() -> BuiltinSpec:
    """Claw hammer: round face at -y, eye block, claw curving towards the handle (+x)."""
    n = 24
    parts = [
        _frustum("y", -0.068, -0.062, 0.0125, 0.0145, sections=n, phase=np.pi / n),  # face
        _frustum("y", -0.062, -0.012, 0.0145, sections=n, phase=np.pi / n),  # poll
        _box((0.036, 0.036, 0.024), center=(0.0, 0.0, 0.0)),  # eye block
    ]
    # claw: a root box along +y tilted 12 degrees towards +x, then two prongs (a 3 mm slot
    # between them in z) tilted 40 degrees
    root_len, prong_len = 0.030, 0.032
    start = np.array([0.0, 0.012, 0.0])
    d1 = np.array([np.sin(np.radians(12)), np.cos(np.radians(12)), 0.0])
    parts.append(_posed_box((0.016, root_len, 0.022), start + d1 * root_len / 2, "z", -12))
    s2 = start + d1 * (root_len - 0.006)
    d2 = np.array([np.sin(np.radians(40)), np.cos(np.radians(40)), 0.0])
    c2 = s2 + d2 * prong_len / 2
    for zc in (0.0065, -0.0065):
        parts.append(_posed_box((0.010, prong_len, 0.0095), c2 + (0, 0, zc), "z", -40))
    parts += [
        _frustum("x", 0.0, 0.30, (0.0150, 0.0110), (0.0125, 0.0100), sections=n),  # handle
        _frustum("x", 0.30, 0.325, (0.0125, 0.0100), (0.0145, 0.0110), sections=n),
    ]
    return _finish(
        "claw_hammer",
        parts,
        density=2300.0,
        friction=0.6,
        description="claw hammer, steel head with a split claw on a wooden handle "
        "(effective density), 33 cm",
    )


def _drill() -> BuiltinSpec:
    """Cordless pistol-grip drill standing on its battery pack (z up, chuck towards +x)."""
    n = 24
    tilt = 15.0  # grip leans back (top towards -x)
    grip_c = np.array([-0.005, 0.0, 0.100])
    grip_T = _rotation("y", -tilt, about=grip_c)
    axis_dir = grip_T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    front_dir = grip_T[:3, :3] @ np.array([1.0, 0.0, 0.0])
    trigger_c = grip_c + 0.030 * axis_dir + 0.021 * front_dir
    zc = 0.185  # motor axis height
    parts = [
        _box((0.105, 0.078, 0.045), center=(0.0, 0.0, 0.0225)),  # battery pack
        _posed_box((0.038, 0.050, 0.135), grip_c, "y", -tilt),  # grip
        _posed_box((0.014, 0.012, 0.026), trigger_c, "y", -tilt),  # trigger
        _frustum("x", -0.070, 0.090, 0.032, center=(0.0, zc), sections=n),  # motor body
        _frustum("x", -0.085, -0.070, 0.025, 0.032, center=(0.0, zc), sections=n),  # end cap
        _frustum("x", 0.090, 0.112, 0.028, 0.026, center=(0.0, zc), sections=n),  # clutch
        _frustum("x", 0.112, 0.160, 0.0195, 0.0150, center=(0.0, zc), sections=n),  # chuck
    ]
    return _finish(
        "drill",
        parts,
        density=1300.0,
        friction=0.8,
        description="cordless pistol-grip drill standing on its battery pack, 24 cm long",
    )


def _sander() -> BuiltinSpec:
    """Palm sander: square pad and base plate, round waist, domed knob (z up, 4-fold)."""
    n = 24
    parts = [
        _box((0.114, 0.114, 0.012), center=(0.0, 0.0, 0.006)),  # pad with paper
        _box((0.104, 0.104, 0.014), center=(0.0, 0.0, 0.017)),  # base plate
        _frustum("z", 0.020, 0.080, 0.040, 0.034, sections=n),  # motor housing (waist)
        _ellipsoid(
            (0.0, 0.0, 0.095), (0.047, 0.047, 0.030), axis="z", rings=7, sections=n, phase=np.pi / n
        ),  # palm knob, vertices between the housing's
    ]
    # quarter turns about the vertical axis: square plates and 24-gons are all 4-fold
    sym = [_exact_rotation("z", k) for k in (1, 2, 3)]
    return _finish(
        "sander",
        parts,
        sym,
        density=1600.0,
        friction=0.9,
        description="quarter-sheet palm sander, 114 mm square pad, domed palm knob",
    )


def _screwdriver() -> BuiltinSpec:
    """Flat-blade screwdriver lying on a flat of its hexagonal handle (axis x)."""
    parts = [
        # hexagon with vertices on +-y: flats on top and bottom (z)
        _frustum("x", -0.006, 0.0, 0.0125, 0.016, sections=6),
        _frustum("x", 0.0, 0.100, 0.016, sections=6),
        _frustum("x", 0.098, 0.114, 0.0105, 0.0055, sections=16),  # ferrule
        _frustum("x", 0.110, 0.212, 0.003, sections=16),  # shaft
        _convex(
            np.array(
                [
                    [x, sy * 0.003, sz * h]
                    for x, h in ((0.208, 0.003), (0.226, 0.0006))
                    for sy in (1, -1)
                    for sz in (1, -1)
                ]
            )
        ),  # flat tip
    ]
    # The half turn about the handle axis is exact. The other 60-degree turns map the hexagonal
    # handle onto itself and move the 6 mm blade, ferrule and shaft by at most 1.9 mm (MSSD,
    # measured by ssp.library.symmetry.detect_symmetries): not observable in depth data, and
    # each keeps the handle resting on a flat. Declared (docs/models.md, "Approximate
    # symmetries").
    return _finish(
        "screwdriver",
        parts,
        [_exact_rotation("x", 2)] + [_rotation("x", 60.0 * k) for k in (1, 2, 4, 5)],
        density=1500.0,
        friction=0.7,
        description="flat-blade screwdriver with a hexagonal handle, 23 cm",
        symmetry_tolerance=0.002,
    )


def _wrench_head(opening: float, anchor: np.ndarray, angle: float, thick: float) -> list:
    """Open-end wrench head: palm with a round back and two jaws around a slot of width
    ``opening`` facing direction ``angle`` (degrees, in the xy plane); the round back is
    centred at ``anchor``."""
    t = 0.55 * opening + 0.002
    width = opening + 2 * t
    palm = 0.55 * width
    jaw = 0.9 * opening
    # local frame: u along the slot (out of the head), v across it, origin at the slot bottom
    T = (
        trimesh.transformations.translation_matrix(anchor)
        @ _rotation("z", angle)
        @ trimesh.transformations.translation_matrix((palm, 0.0, 0.0))
    )
    parts = [
        _box((palm, width, thick), center=(-palm / 2, 0, 0), transform=T),
        _frustum("z", -thick / 2, thick / 2, width / 2, center=(-palm, 0.0), transform=T),
    ]
    for s in (1, -1):
        parts.append(
            _box(
                (jaw + 0.002, t, thick),
                center=(jaw / 2 - 0.001, s * (opening + t) / 2, 0),
                transform=T,
            )
        )
    return parts


def _wrench() -> BuiltinSpec:
    """Double open-end wrench, 13 mm and 17 mm, jaws at 15 degrees, lying flat (z up)."""
    thick = 0.006
    parts = [_box((0.150, 0.014, 0.005))]
    parts += _wrench_head(0.013, np.array([0.075, 0.0, 0.0]), 15.0, thick)
    parts += _wrench_head(0.017, np.array([-0.075, 0.0, 0.0]), 195.0, thick)
    return _finish(
        "wrench",
        parts,
        density=7850.0,
        friction=0.5,
        description="double open-end steel wrench, 13/17 mm, 15-degree heads, lying flat",
    )


def _clamp() -> BuiltinSpec:
    """C-clamp lying flat: frame in the xy plane, screw along y with a T-bar (z up)."""
    th = 0.016  # frame thickness (z); every other part stays within it, so it lies flat
    parts = [
        _box((0.020, 0.140, th), center=(-0.050, 0.0, 0.0)),  # spine
        _box((0.066, 0.020, th), center=(-0.023, 0.060, 0.0)),  # upper arm
        _box((0.066, 0.020, th), center=(-0.023, -0.060, 0.0)),  # lower arm
        _box((0.026, 0.028, th), center=(0.0, 0.061, 0.0)),  # threaded boss
        _box((0.024, 0.010, th), center=(0.0, -0.047, 0.0)),  # anvil
        _frustum("y", -0.016, 0.094, 0.005, center=(0.0, 0.0), sections=16),  # screw
        _frustum("y", -0.022, -0.014, 0.0075, center=(0.0, 0.0), sections=16),  # swivel pad
        _frustum("x", -0.035, 0.035, 0.004, center=(0.092, 0.0), sections=16),  # T-bar
    ]
    return _finish(
        "clamp",
        parts,
        density=7200.0,
        friction=0.5,
        description="100 mm cast-iron C-clamp with a T-bar screw, lying flat",
    )


def _mug() -> BuiltinSpec:
    """Mug standing on its base (z up): a 32-gon body 80 mm across and 95 mm tall, open at the
    top (5 mm wall, 8 mm floor), and a square-section handle at +x (a C of three bars, 12 mm
    wide). Seen from the side opposite its handle it is a cylinder: any yaw explains that view.
    The cavity, which a camera above the rim sees, tells its top from its bottom (a solid mug's
    handle, nearly centred in height, would leave that to a few millimetres).

    Convex parts: the floor, one wall piece per side of the 32-gon (an annular sector), the
    handle's bars."""
    n = 32
    r, h = 0.040, 0.095
    wall, floor = 0.005, 0.008
    w = 0.012  # the handle's section
    reach = 0.030  # how far the handle stands off the body
    # polygon corners at phase + 2 pi k / n, as _frustum's (the inner ring's edges parallel)
    ang = np.pi / n + 2.0 * np.pi * np.arange(n + 1) / n
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    walls = []
    for k in range(n):
        xy = np.concatenate([ring[k : k + 2] * r, ring[k : k + 2] * (r - wall)])
        walls.append(_convex(np.concatenate([np.c_[xy, np.zeros(4)], np.c_[xy, np.full(4, h)]])))
    parts = [
        _frustum("z", 0.0, floor, r, sections=n, phase=np.pi / n),
        *walls,
        _box((reach + 0.006, w, w), center=(r + reach / 2 - 0.003, 0.0, 0.078)),  # top bar
        _box((reach + 0.006, w, w), center=(r + reach / 2 - 0.003, 0.0, 0.022)),  # bottom bar
        _box((w, w, 0.056 + w), center=(r + reach - w / 2, 0.0, 0.050)),  # grip
    ]
    return _finish(
        "mug",
        parts,
        density=2000.0,  # stoneware
        friction=0.8,
        description="mug, 80 mm body 95 mm tall, open top, with a side handle",
    )


def _tin() -> BuiltinSpec:
    """A tea tin lying flat (z up): a box 66 x 60 x 45 mm, nearly square in plan. Its exact
    symmetries are the box's four half-turns; a quarter turn about z moves each side by 3 mm,
    less than the data term's inlier radius (3.7 mm): what tells the two apart is the fit of
    the whole outline (ICP), not the visible surface explained."""
    e = (0.066, 0.060, 0.045)
    return _finish(
        "tin",
        [_box(e)],
        _box_group(e)[1:],
        density=450.0,  # a tin half full of tea: 80 g
        friction=0.4,
        description="tea tin, 66 x 60 x 45 mm box, nearly square in plan",
    )


_VIEW_AMBIGUOUS_BUILDERS: tuple[Callable[[], BuiltinSpec], ...] = (_mug, _tin)


_BUILDERS: tuple[Callable[[], BuiltinSpec], ...] = (
    _cube,
    _block,
    _link,
    _node,
    _mallet,
    _ball_pein_hammer,
    _claw_hammer,
    _drill,
    _sander,
    _screwdriver,
    _wrench,
    _clamp,
)


def _build_all() -> tuple[BuiltinSpec, ...]:
    """Build every model from scratch (uncached)."""
    return tuple(build() for build in _BUILDERS)


@functools.lru_cache(maxsize=1)
def _cached() -> tuple[BuiltinSpec, ...]:
    return _build_all()


def builtin_specs() -> list[BuiltinSpec]:
    """All built-in models, in a fixed order (blocks first, then tools).

    Built once per process; every call returns fresh deep copies.
    """
    return [s.copy() for s in _cached()]


def builtin_names() -> list[str]:
    """Names of the built-in models, in the order of :func:`builtin_specs`."""
    return [s.name for s in _cached()]


def builtin_spec(name: str) -> BuiltinSpec:
    """The built-in model ``name`` (a copy); :class:`UnknownObjectError` if there is none."""
    return _lookup(name).copy()


@functools.lru_cache(maxsize=1)
def _cached_view_ambiguous() -> tuple[BuiltinSpec, ...]:
    return tuple(build() for build in _VIEW_AMBIGUOUS_BUILDERS)


def view_ambiguous_specs() -> list[BuiltinSpec]:
    """The view-ambiguous models (:data:`VIEW_AMBIGUOUS_NAMES`), fresh copies."""
    return [s.copy() for s in _cached_view_ambiguous()]


def _lookup(name: str) -> BuiltinSpec:
    """The cached (shared, not to be modified) spec ``name`` (a default model, or a
    view-ambiguous one)."""
    for s in _cached() + (_cached_view_ambiguous() if name in VIEW_AMBIGUOUS_NAMES else ()):
        if s.name == name:
            return s
    raise UnknownObjectError(
        f"unknown built-in model {name!r}; available: "
        f"{', '.join([*builtin_names(), *VIEW_AMBIGUOUS_NAMES])}"
    )


# --------------------------------------------------------------------------------------------
# export


def _fmt(x: float) -> str:
    return f"{float(x):.10g}"


def _write_obj(
    path: Path, meshes: Sequence[trimesh.Trimesh], names: Sequence[str] | None, header: str
) -> None:
    """Plain OBJ: vertices and triangles; one ``o`` object per mesh if ``names`` is given."""
    lines = [f"# {header}"]
    base = 1
    for i, m in enumerate(meshes):
        if names is not None:
            lines.append(f"o {names[i]}")
        lines += [f"v {_fmt(a)} {_fmt(b)} {_fmt(c)}" for a, b, c in m.vertices]
        lines += [f"f {a + base} {b + base} {c + base}" for a, b, c in m.faces]
        base += len(m.vertices)
    path.write_text("\n".join(lines) + "\n")


def _clean(x: float) -> float:
    """Round away float noise (exact symmetries are signed permutations)."""
    y = round(float(x), 12)
    return 0.0 if y == 0 else y


def export_builtin(
    folder: Path | str, names: Iterable[str] | None = None, *, view_ambiguous: bool = False
) -> list[Path]:
    """Write the built-in models to ``folder`` (created if needed); with ``view_ambiguous``
    (and no ``names``), the view-ambiguous ones (:data:`VIEW_AMBIGUOUS_NAMES`) too.

    For every model: ``NAME.obj`` (the mesh) and ``NAME.parts.obj`` (one ``o part_i`` object
    per convex part), plus one ``models.yaml`` describing them all (units m, density,
    friction, convex parts, BOP-style symmetries). Existing files are overwritten. ``names``
    restricts the export to some models. Returns the written paths, ``models.yaml`` last.

    The parts file reads back into one mesh per part with
    ``trimesh.load(path, split_objects=True, group_material=False, force="scene")``.
    """
    import yaml

    if names is None:
        specs = _cached() + (_cached_view_ambiguous() if view_ambiguous else ())
    else:
        specs = tuple(_lookup(n) for n in names)  # an unknown name raises before any write
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    objects: dict = {}
    for s in specs:
        mesh_path = folder / f"{s.name}.obj"
        parts_path = folder / f"{s.name}.parts.obj"
        _write_obj(mesh_path, [s.mesh], None, f"ssp built-in model {s.name} (metres)")
        _write_obj(
            parts_path,
            s.parts,
            [f"part_{i}" for i in range(len(s.parts))],
            f"ssp built-in model {s.name}: {len(s.parts)} convex parts (metres)",
        )
        written += [mesh_path, parts_path]
        entry: dict = {
            "mesh": mesh_path.name,
            "density": s.density,
            "friction": s.friction,
            "convex_parts": parts_path.name,
        }
        bop = s.symmetry.to_bop()
        if "symmetries_discrete" in bop:
            entry["symmetries_discrete"] = [
                [_clean(x) for x in T] for T in bop["symmetries_discrete"]
            ]
        if "symmetries_continuous" in bop:
            entry["symmetries_continuous"] = [
                {"axis": [_clean(x) for x in c["axis"]], "offset": [_clean(x) for x in c["offset"]]}
                for c in bop["symmetries_continuous"]
            ]
        objects[s.name] = entry
    yaml_path = folder / "models.yaml"
    yaml_path.write_text(
        "# ssp built-in models (generated by ssp.library.builtin.export_builtin)\n"
        + yaml.safe_dump(
            {"units": "m", "objects": objects}, sort_keys=False, default_flow_style=None, width=100
        )
    )
    written.append(yaml_path)
    return written
