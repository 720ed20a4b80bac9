"""Shared fixtures: simple box models built directly (no library, no decomposition)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ssp.library.model import DecompositionInfo, ObjectModel

CUBE_EDGE = 0.0508  # 2-inch cube, m
WOOD_DENSITY = 700.0  # kg/m^3


def box_model(
    name: str,
    size_xyz=(0.05, 0.05, 0.05),
    mass: float = 0.1,
    friction: float = 1.0,
    offset=(0.0, 0.0, 0.0),
) -> ObjectModel:
    """A solid box ``size_xyz`` (m) of ``mass`` (kg), centred at ``offset`` in its model frame.

    Its only convex part is the box itself; the inertia is the exact box inertia about the centre
    of mass. ``offset`` moves the geometry (and the centre of mass) away from the model origin.
    """
    a, b, c = (float(s) for s in size_xyz)
    mesh = trimesh.creation.box(extents=(a, b, c))
    mesh.apply_translation(offset)
    inertia = np.diag([b * b + c * c, a * a + c * c, a * a + b * b]) * mass / 12.0
    rng = np.random.default_rng(0)
    pts, faces = trimesh.sample.sample_surface(mesh, 200, seed=0)
    interior = (rng.random((100, 3)) - 0.5) * np.array([a, b, c]) + np.asarray(offset)
    return ObjectModel(
        name=name,
        mesh=mesh,
        convex_parts=(mesh,),
        mass=float(mass),
        friction=float(friction),
        center_of_mass=np.asarray(offset, dtype=float),
        inertia=inertia,
        surface_points=np.asarray(pts, dtype=float),
        surface_normals=np.asarray(mesh.face_normals[faces], dtype=float),
        interior_points=interior,
        decomposition=DecompositionInfo("exact", 1, 1.0),
    )


@pytest.fixture(scope="session")
def cube_model() -> ObjectModel:
    """The 50.8 mm (2 inch) wooden cube, ~700 kg/m^3 (about 92 g)."""
    return box_model("cube2in", (CUBE_EDGE,) * 3, WOOD_DENSITY * CUBE_EDGE**3)


@pytest.fixture(scope="session")
def make_box():
    """The :func:`box_model` factory."""
    return box_model


@pytest.fixture(scope="session")
def lib():
    """The built-in library (``ObjectLibrary.builtin()``), built once per test run; modules
    that need other models define their own ``lib``."""
    from ssp.library import ObjectLibrary

    return ObjectLibrary.builtin()
