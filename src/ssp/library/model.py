"""``ObjectModel``: everything ssp knows about one rigid object class, in its model frame.

All arrays are float64 in metres (model frame) unless stated. A model is immutable once built;
build one with :func:`ssp.library.build.build_model` (from a mesh) or take it from an
:class:`~ssp.library.library.ObjectLibrary`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ssp.library.symmetry import Symmetry, SymmetryDetection


@dataclass(frozen=True)
class DecompositionInfo:
    """How the convex parts were obtained.

    ``method``: ``"exact"`` (a built-in model's own convex primitives), ``"given"`` (parts
    supplied with the model, ``convex_parts`` in models.yaml), ``"convex"`` (the mesh is convex
    within tolerance: its hull), ``"shells"`` (the mesh's own convex shells), ``"coacd"``,
    ``"coacd-coarse"`` (the fallback run) or ``"convex-hull"`` (last resort, or asked for).
    ``iou``: volume IoU of the union of the parts against the mesh (Monte Carlo).
    ``seconds``: decomposition time (0 when cached). ``note``: how the parts were obtained
    (fallback reasons, merges). ``warnings``: problems worth a look (an IoU below
    ``DecompositionConfig.min_iou``), also logged.
    """

    method: str
    n_parts: int
    iou: float
    seconds: float = 0.0
    cached: bool = False
    note: str = ""
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """One object class: geometry, mass properties, friction, samples and symmetries.

    Attributes:
        name: class name (unique in a library).
        mesh: watertight triangle mesh, metres, model frame.
        convex_parts: convex hulls (model frame) whose union approximates ``mesh``; the
            physics engine collides with these.
        mass: kg. friction: sliding friction coefficient.
        center_of_mass: (3,) m, model frame, of the solid ``mesh`` at uniform density.
        inertia: (3, 3) kg m^2 about the centre of mass, model-frame axes.
        surface_points, surface_normals: (M, 3) even samples on ``mesh`` (~``surface_spacing``).
        interior_points: (K, 3) points inside ``mesh`` on a grid, for overlap-volume estimates.
        symmetry: discrete and continuous symmetries (BOP convention).
        decomposition: provenance and quality of ``convex_parts``.
        source: mesh file the model came from (None for generated models).
        detected_symmetry: approximate symmetries found at build time (when asked for:
            ``symmetry: {detect: ...}`` in models.yaml or ``ssp models prepare``), else None.
    """

    name: str
    mesh: trimesh.Trimesh
    convex_parts: tuple[trimesh.Trimesh, ...]
    mass: float
    friction: float
    center_of_mass: np.ndarray
    inertia: np.ndarray
    surface_points: np.ndarray
    surface_normals: np.ndarray
    interior_points: np.ndarray
    symmetry: Symmetry = field(default_factory=Symmetry)
    decomposition: DecompositionInfo = field(
        default_factory=lambda: DecompositionInfo("exact", 0, 1.0)
    )
    source: Path | None = None
    detected_symmetry: SymmetryDetection | None = None

    @property
    def volume(self) -> float:
        """Solid volume, m^3."""
        return float(self.mesh.volume)

    @property
    def density(self) -> float:
        """kg/m^3."""
        return self.mass / self.volume

    @property
    def extents(self) -> np.ndarray:
        """Axis-aligned bounding box size (3,), m."""
        return np.asarray(self.mesh.extents, dtype=float)

    @cached_property
    def hull_vertices(self) -> np.ndarray:
        """(V, 3) vertices of the convex hull of the mesh."""
        return np.asarray(self.mesh.convex_hull.vertices, dtype=float)

    @cached_property
    def surface_tree(self) -> cKDTree:
        """KD-tree of :attr:`surface_points` (model frame), built once: a query of world
        points moved into the model frame replaces a tree built per pose."""
        return cKDTree(np.asarray(self.surface_points, dtype=float))

    @cached_property
    def convexity_excess(self) -> float:
        """Largest height (m) of the object above the tangent plane of one of its surface
        samples: ``max_i max_v n_i . (v - p_i)`` over the samples ``p_i, n_i`` and the hull
        vertices ``v``; 0 (to rounding) for a convex mesh. No sample can be hidden behind the
        object's own surface when this is below the depth tolerance of
        :meth:`ssp.visibility.CameraView.classify`'s self-occlusion test."""
        p = np.asarray(self.surface_points, dtype=float)
        n = np.asarray(self.surface_normals, dtype=float)
        v = self.hull_vertices
        if not len(p) or not len(v):
            return 0.0
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        excess = 0.0
        for a in range(0, len(p), 4096):  # (chunk, V) at a time
            nc, pc = n[a : a + 4096], p[a : a + 4096]
            excess = max(excess, float(((nc @ v.T).max(axis=1) - (nc * pc).sum(1)).max()))
        return excess

    @cached_property
    def diameter(self) -> float:
        """Largest distance between two points of the object (eps_d of the paper's Eq. 10), m."""
        from scipy.spatial.distance import pdist

        v = self.hull_vertices
        return float(pdist(v).max()) if len(v) > 1 else 0.0

    @cached_property
    def d_max(self) -> float:
        """Largest distance from the centre of mass to the object's surface (pivot arm; d_max of
        the paper's Eq. 8), m."""
        return float(np.linalg.norm(self.hull_vertices - self.center_of_mass, axis=1).max())

    def max_angular_acceleration(self, gravity: float) -> float:
        """alpha_max = m g d_max / I_pivot, rad/s^2: the paper's beta_R_max of Eq. 8 (which
        it prints inverted, I / (g d_max m); DESIGN section 4), the scale of beta_R in the
        stability term (Eq. 9).

        The angular acceleration gravity gives the object when it pivots about its farthest
        point with the lever arm horizontal; I_pivot is the smallest principal moment about the
        centre of mass moved to the pivot (parallel-axis theorem), so this is an upper bound.
        """
        i_min = float(np.linalg.eigvalsh(self.inertia)[0])
        return self.mass * gravity * self.d_max / (i_min + self.mass * self.d_max**2)

    def summary(self) -> dict:
        """Plain-type summary (for `ssp models show` and reports)."""
        return {
            "name": self.name,
            "source": str(self.source) if self.source else "built-in",
            "extents_mm": [round(float(x) * 1000, 2) for x in self.extents],
            "volume_cm3": round(self.volume * 1e6, 3),
            "mass_kg": round(self.mass, 5),
            "density_kg_m3": round(self.density, 1),
            "friction": self.friction,
            "center_of_mass_mm": [round(float(x) * 1000, 3) for x in self.center_of_mass],
            "principal_inertia_kg_m2": [
                float(f"{x:.4g}") for x in np.linalg.eigvalsh(self.inertia)
            ],
            "diameter_mm": round(self.diameter * 1000, 2),
            "surface_points": int(len(self.surface_points)),
            "interior_points": int(len(self.interior_points)),
            "convex_parts": int(len(self.convex_parts)),
            "decomposition": self.decomposition.method,
            "hull_iou": round(self.decomposition.iou, 4),
            "decomposition_warnings": list(self.decomposition.warnings),
            "discrete_symmetries": int(len(self.symmetry.discrete)),
            "continuous_symmetries": int(len(self.symmetry.continuous)),
            "detected_symmetries": (
                None if self.detected_symmetry is None else self.detected_symmetry.to_dict()
            ),
        }


class ObjectInstance(NamedTuple):
    """One object in a scene: a unique ``id`` and its class ``model``."""

    id: str
    model: ObjectModel
