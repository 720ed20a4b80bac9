"""Overlap-volume estimate of the collision term (Eq. 8): ssp.overlap."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.library.model import DecompositionInfo, ObjectModel
from ssp.overlap import HullSet, overlap_fraction_table, overlap_fractions, same_volume

EDGE = 0.05  # m


def grid(size_xyz, n_xyz, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Cell-centred grid of n_x * n_y * n_z points filling a box of ``size_xyz`` at ``offset``."""
    axes = [
        (np.arange(n) + 0.5) / n * s - s / 2 + o
        for s, n, o in zip(size_xyz, n_xyz, offset, strict=True)
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


@pytest.fixture(scope="module")
def cube(make_box) -> ObjectModel:
    """5 cm cube with a 20^3 interior grid."""
    m = make_box("cube5", (EDGE,) * 3)
    return dataclasses.replace(m, interior_points=grid((EDGE,) * 3, (20, 20, 20)))


@pytest.fixture(scope="module")
def flat_cube(make_box) -> ObjectModel:
    """5 cm cube with a fine grid in x and y, coarse in z (for rotations about z)."""
    m = make_box("cube5xy", (EDGE,) * 3)
    return dataclasses.replace(m, interior_points=grid((EDGE,) * 3, (40, 40, 2)))


def at(x=0.0, y=0.0, z=0.0, R=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = (x, y, z)
    return T


HIGH = 0.5  # m, well above the table


def l_shape_model() -> ObjectModel:
    """An L in the xy plane made of two convex boxes; the notch is around (0.04, 0.04)."""
    arm_x = trimesh.creation.box(bounds=[[0.0, 0.0, 0.0], [0.06, 0.02, 0.02]])
    arm_y = trimesh.creation.box(bounds=[[0.0, 0.0, 0.0], [0.02, 0.06, 0.02]])
    mesh = trimesh.util.concatenate([arm_x, arm_y])  # only the parts and points are used here
    pts = np.concatenate(
        [
            grid((0.06, 0.02, 0.02), (12, 4, 4), (0.03, 0.01, 0.01)),
            grid((0.02, 0.04, 0.02), (4, 8, 4), (0.01, 0.04, 0.01)),
        ]
    )
    return ObjectModel(
        name="L",
        mesh=mesh,
        convex_parts=(arm_x, arm_y),
        mass=0.1,
        friction=1.0,
        center_of_mass=np.zeros(3),
        inertia=np.eye(3) * 1e-5,
        surface_points=np.zeros((0, 3)),
        surface_normals=np.zeros((0, 3)),
        interior_points=pts,
        decomposition=DecompositionInfo("exact", 2, 1.0),
    )


# --- HullSet ---------------------------------------------------------------------------------


def test_hullset_box_planes_and_cache(cube, make_box):
    hs = HullSet.of(cube)
    assert HullSet.of(cube) is hs
    assert HullSet.of(make_box("other", (EDGE,) * 3)) is not hs
    assert hs.n_parts == 1
    assert hs.planes[0].shape == (6, 4)  # coplanar triangles merged
    np.testing.assert_allclose(hs.radius, EDGE * np.sqrt(3) / 2)
    np.testing.assert_allclose(hs.centre, 0.0, atol=1e-12)


def test_hullset_contains_box_and_tol(cube):
    hs = HullSet.of(cube)
    h = EDGE / 2
    pts = np.array([[0, 0, 0], [h - 1e-4, 0, 0], [h + 1e-4, 0, 0], [0, 0, -h - 1e-4], [1, 1, 1]])
    np.testing.assert_array_equal(hs.contains(pts), [True, True, False, False, False])
    np.testing.assert_array_equal(hs.contains(pts, tol=2e-4), [True, True, True, True, False])
    np.testing.assert_array_equal(hs.contains(pts[:2], tol=-2e-4), [True, False])
    assert hs.contains(np.zeros((0, 3))).shape == (0,)


def _contains_by_planes(hs: HullSet, p: np.ndarray, tol: float) -> np.ndarray:
    """The definition: inside a part when within the model's and the part's bounding spheres
    grown by ``max(tol, 0)`` and ``n . p + b <= tol`` for every plane of it (numpy, part by
    part)."""
    grow = max(tol, 0.0)
    inside = np.zeros(len(p), dtype=bool)
    model_sphere = ((p - hs.centre) ** 2).sum(axis=1) <= (hs.radius + grow) ** 2
    for eq, c, r in zip(hs.planes, hs.part_centres, hs.part_radii, strict=True):
        near = ((p - c) ** 2).sum(axis=1) <= (r + grow) ** 2
        inside |= near & (eq[:, :3] @ p.T + eq[:, 3:4] <= tol).all(axis=0)
    return inside & model_sphere


@pytest.mark.parametrize("name", ["drill", "clamp", "wrench", "node", "block"])
def test_compiled_contains_is_every_plane_of_a_part(name, lib):
    """The compiled test (spheres first, then each part's planes) against the definition, on
    built-in models of many convex parts, points around them, margins either way."""
    hs = HullSet.of(lib[name])
    assert hs.n_parts >= 1
    rng = np.random.default_rng(7)
    around = hs.centre + rng.uniform(-1.1, 1.1, (4000, 3)) * hs.radius
    parts = hs.part_centres[rng.integers(0, hs.n_parts, 4000)]
    near = parts + rng.normal(0.0, 1.0, (4000, 3)) * hs.part_radii.min()  # thin parts too
    p = np.concatenate([around, near])
    for tol in (0.0, 0.003, -0.002):
        want = _contains_by_planes(hs, p, tol)
        assert 0 < want.sum() < len(p)
        np.testing.assert_array_equal(hs.contains(p, tol), want)


def test_l_shape_notch_not_contained():
    hs = HullSet.of(l_shape_model())
    assert hs.n_parts == 2
    # (0.035, 0.035) is inside the convex hull of the whole L but in its notch
    notch = [[0.035, 0.035, 0.01], [0.05, 0.05, 0.01]]
    arms = [[0.05, 0.01, 0.01], [0.01, 0.05, 0.01], [0.01, 0.01, 0.01], [0.059, 0.019, 0.019]]
    assert not hs.contains(notch).any()
    assert hs.contains(arms).all()


def test_cube_in_l_notch_does_not_overlap(make_box):
    L = l_shape_model()
    small = make_box("small", (0.015,) * 3)  # fits in the notch [0.02, 0.06]^2
    f = overlap_fractions([L, small], [at(z=HIGH), at(0.04, 0.04, HIGH + 0.01)])
    np.testing.assert_array_equal(f, [0.0, 0.0])
    # moved onto the corner of the L it overlaps fully
    f = overlap_fractions([L, small], [at(z=HIGH), at(0.01, 0.01, HIGH + 0.01)])
    assert f[1] == 1.0 and f[0] > 0.0


# --- pairs of objects ------------------------------------------------------------------------


def test_identical_cubes_same_pose(cube):
    f = overlap_fractions([cube, cube], [at(z=HIGH), at(z=HIGH)])
    np.testing.assert_allclose(f, [1.0, 1.0])


def test_random_interior_points_same_pose(cube_model):
    # the conftest model (100 random interior points), as built models are used
    f = overlap_fractions([cube_model, cube_model], [at(z=HIGH)] * 2)
    np.testing.assert_allclose(f, [1.0, 1.0])


def test_half_edge_offset(cube):
    f = overlap_fractions([cube, cube], [at(z=HIGH), at(EDGE / 2, 0, HIGH)])
    np.testing.assert_allclose(f, [0.5, 0.5], atol=0.03)


@pytest.mark.parametrize("frac", [0.1, 0.3, 0.75])
def test_offset_along_y_gives_overlap_fraction(cube, frac):
    f = overlap_fractions([cube, cube], [at(z=HIGH), at(0, (1 - frac) * EDGE, HIGH)])
    np.testing.assert_allclose(f, [frac, frac], atol=0.03)


def test_separated_cubes(cube):
    f = overlap_fractions([cube, cube], [at(z=HIGH), at(EDGE + 1e-3, 0, HIGH)])
    np.testing.assert_array_equal(f, [0.0, 0.0])
    # touching faces (solver resting penetration ~0.02 mm) do not count either
    f = overlap_fractions([cube, cube], [at(z=HIGH), at(0, 0, HIGH + EDGE - 2e-5)])
    np.testing.assert_array_equal(f, [0.0, 0.0])


def test_points_inside_several_others_count_once(cube):
    f = overlap_fractions([cube, cube, cube], [at(z=HIGH)] * 3)
    np.testing.assert_allclose(f, [1.0, 1.0, 1.0])


def test_small_cube_inside_big_cube(cube, make_box):
    big = make_box("big", (0.2,) * 3)
    f = overlap_fractions([big, cube], [at(z=HIGH), at(0.03, -0.02, HIGH + 0.01)])
    assert f[1] == 1.0
    assert 0.0 < f[0] < 0.2  # the big cube's random points: ~1.6 % of its volume


def test_rotated_45_about_z_octagon(flat_cube):
    # a square and the same square turned 45 degrees about its centre intersect in a regular
    # octagon of inradius a/2: area 8 (a/2)^2 tan(pi/8) = 2 (sqrt 2 - 1) a^2
    R = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    f = overlap_fractions([flat_cube, flat_cube], [at(0.1, 0.2, HIGH), at(0.1, 0.2, HIGH, R)])
    expected = 2 * (np.sqrt(2) - 1)
    np.testing.assert_allclose(f, [expected, expected], atol=0.02)


def test_rotated_both_same_relative_pose(cube):
    # rotating the whole scene does not change the fractions
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    base = [at(z=HIGH), at(EDGE / 2, 0, HIGH)]
    W = at(0.3, -0.1, 0.4, R)
    f0 = overlap_fractions([cube, cube], base, table=False)
    f1 = overlap_fractions([cube, cube], [W @ T for T in base], table=False)
    np.testing.assert_allclose(f1, f0, atol=1e-12)
    np.testing.assert_allclose(f1, [0.5, 0.5], atol=0.03)


def test_pairs_restrict_tests(cube):
    poses = [at(z=HIGH), at(EDGE / 2, 0, HIGH), at(-EDGE / 2, 0, HIGH)]
    full = overlap_fractions([cube] * 3, poses)
    np.testing.assert_allclose(full, [1.0, 0.5, 0.5], atol=0.03)
    only01 = overlap_fractions([cube] * 3, poses, pairs=[(0, 1)])
    np.testing.assert_allclose(only01, [0.5, 0.5, 0.0], atol=0.03)
    # unordered: (1, 0) is the same pair; self pairs are ignored
    np.testing.assert_array_equal(
        overlap_fractions([cube] * 3, poses, pairs=[(1, 0), (2, 2)]), only01
    )
    np.testing.assert_array_equal(overlap_fractions([cube] * 3, poses, pairs=[]), [0, 0, 0])
    with pytest.raises(IndexError):
        overlap_fractions([cube] * 3, poses, pairs=[(0, 3)])


def test_broad_phase_skips_far_objects(cube, monkeypatch):
    calls = []
    orig = HullSet.contains

    def counting(self, points_local, tol=0.0):
        calls.append(len(points_local))
        return orig(self, points_local, tol)

    monkeypatch.setattr(HullSet, "contains", counting)
    poses = [at(z=HIGH), at(EDGE / 2, 0, HIGH), at(1.0, 1.0, HIGH), at(-1.0, 0, HIGH)]
    f = overlap_fractions([cube] * 4, poses)
    np.testing.assert_allclose(f, [0.5, 0.5, 0.0, 0.0], atol=0.03)
    assert len(calls) == 2  # only 0 -> 1 and 1 -> 0
    calls.clear()
    overlap_fractions([cube] * 4, poses, pairs=[(0, 2), (2, 3)])
    assert calls == []  # explicit pairs far apart are skipped too


# --- table -----------------------------------------------------------------------------------


def test_cube_sunk_into_table(cube):
    T = at(z=EDGE / 2 - 0.01)  # 1 cm of the 5 cm cube below z = 0
    assert overlap_fraction_table(cube, T) == pytest.approx(0.2, abs=0.03)
    np.testing.assert_allclose(overlap_fractions([cube], [T]), [0.2], atol=0.03)
    np.testing.assert_array_equal(overlap_fractions([cube], [T], table=False), [0.0])


def test_cube_resting_on_table(cube):
    T = at(z=EDGE / 2 + 1e-5)
    assert overlap_fraction_table(cube, T) == 0.0
    np.testing.assert_array_equal(
        overlap_fractions([cube, cube], [T, at(0.2, 0, EDGE / 2)]), [0, 0]
    )


def test_rotated_cube_edge_down_into_table(make_box):
    # cube turned 45 degrees about x: its yz cross-section is a diamond; sinking its lowest edge
    # s below the table puts a triangle of area s^2 under it, i.e. a fraction s^2 / a^2
    m = make_box("c", (EDGE,) * 3)
    m = dataclasses.replace(m, interior_points=grid((EDGE,) * 3, (2, 40, 40)))
    R = Rotation.from_euler("x", 45, degrees=True).as_matrix()
    s = 0.02
    T = at(0.3, 0.1, EDGE / np.sqrt(2) - s, R)
    assert overlap_fraction_table(m, T) == pytest.approx(s**2 / EDGE**2, abs=0.02)
    T = at(0, 0, 0.0, R)  # centre on the table plane: half below
    assert overlap_fraction_table(m, T) == pytest.approx(0.5, abs=0.03)


def test_table_and_other_object_count_once(cube):
    # cube 0 is half in the table and fully inside cube 1 -> 1, not 1.5
    T = at(z=0.0)
    f = overlap_fractions([cube, cube], [T, T])
    np.testing.assert_allclose(f, [1.0, 1.0])


# --- edge cases ------------------------------------------------------------------------------


def test_no_interior_points_and_no_objects(cube):
    empty = dataclasses.replace(cube, name="empty", interior_points=np.zeros((0, 3)))
    f = overlap_fractions([empty, cube], [at(z=HIGH), at(z=HIGH)])
    np.testing.assert_array_equal(f, [0.0, 1.0])
    assert overlap_fraction_table(empty, at(z=-1.0)) == 0.0
    assert overlap_fractions([], np.zeros((0, 4, 4))).shape == (0,)


def test_bad_pose_shape(cube):
    with pytest.raises(ValueError):
        overlap_fractions([cube, cube], [at()])
    with pytest.raises(ValueError):
        overlap_fractions([cube], [np.full((4, 4), np.nan)])


def test_same_volume(cube):
    T = np.eye(4)
    assert same_volume(cube, T, T, 0.3)
    half = T.copy()
    half[0, 3] = EDGE / 2  # half the volume shared
    assert same_volume(cube, T, half, 0.3) and not same_volume(cube, T, half, 0.7)
    far = T.copy()
    far[0, 3] = 2 * EDGE
    assert not same_volume(cube, T, far, 0.0)
