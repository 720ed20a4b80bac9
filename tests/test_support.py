"""Support graph (ssp.support, paper Alg. 2) from settled MuJoCo scenes."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.library.model import ObjectInstance
from ssp.physics import Contacts, World
from ssp.support import GROUND, build_support_graph

G = 9.81
E = 0.0508  # edge of the conftest cube


def pose(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def settled(instances, poses, steps=100, disabled=()):
    world = World(instances)
    world.set_poses(poses)
    for oid in disabled:
        world.set_enabled(oid, False)
    world.step(steps)  # quasi-static: contact forces at rest
    return world


def graph(world, **kw):
    return build_support_graph(world.contacts(), world.masses, world.config.gravity, **kw)


@pytest.fixture(scope="module")
def tower(cube_model):
    inst = [ObjectInstance(f"c{i}", cube_model) for i in range(3)]
    return settled(inst, {f"c{i}": pose(z=E / 2 + i * E) for i in range(3)})


def test_tower(tower):
    g = graph(tower)
    assert g.ids == ("c0", "c1", "c2")
    assert g.edges() == [(GROUND, 0), (0, 1), (1, 2)]
    assert g.layers() == [[0], [1], [2]]
    assert g.unsupported() == []
    np.testing.assert_allclose(g.edge_fraction, 1.0, rtol=0.05)
    # Raw vertical forces carry everything above: 3, 2, 1 cube weights.
    np.testing.assert_allclose(g.edge_vertical / (tower.masses[0] * G), [3, 2, 1], rtol=0.05)
    assert np.all(g.edge_force >= g.edge_vertical * (1 - 1e-9))
    assert g.supported_by(0) == [GROUND] and g.supported_by(2) == [1]
    assert g.children(GROUND) == [0] and g.children(0) == [1] and g.children(2) == []
    assert g.support_sum(0) == pytest.approx(1.0, rel=0.05)
    assert g.support_sum(2) == 0.0
    np.testing.assert_allclose(g.support_sums(), [1, 1, 0], atol=0.05)
    assert g.supported_fraction(1) == pytest.approx(1.0, rel=0.05)
    assert g.fraction(0, 1) == pytest.approx(1.0, rel=0.05) and g.fraction(1, 0) == 0.0
    assert g.penetration.shape == (3,) and np.all(g.penetration >= 0)
    assert np.all(g.penetration < 1e-4)  # stiff contacts: well under 0.1 mm
    assert "3 objects" in repr(g)


def test_side_by_side_both_on_table(cube_model):
    inst = [ObjectInstance("a", cube_model), ObjectInstance("b", cube_model)]
    # Touching faces (the lateral contact carries no vertical load: no edge between them).
    w = settled(inst, {"a": pose(x=-E / 2, z=E / 2), "b": pose(x=E / 2, z=E / 2)})
    g = graph(w)
    assert g.edges() == [(GROUND, 0), (GROUND, 1)]
    assert g.layers() == [[0, 1]]
    np.testing.assert_allclose(g.edge_fraction, 1.0, rtol=0.05)
    np.testing.assert_allclose(g.support_sums(), 0.0)


def test_bridge_supported_by_both(cube_model, make_box):
    plank = make_box("plank", (0.12, 0.05, 0.02), 0.05)
    inst = [
        ObjectInstance("left", cube_model),
        ObjectInstance("right", cube_model),
        ObjectInstance("plank", plank),
    ]
    poses = {"left": pose(x=-0.04, z=E / 2), "right": pose(x=0.04, z=E / 2)}
    poses["plank"] = pose(z=E + 0.01)
    g = graph(settled(inst, poses))
    assert sorted(g.supported_by(2)) == [0, 1]
    assert g.layers() == [[0, 1], [2]]
    assert g.fraction(0, 2) == pytest.approx(0.5, abs=0.05)
    assert g.fraction(1, 2) == pytest.approx(0.5, abs=0.05)
    assert g.supported_fraction(2) == pytest.approx(1.0, rel=0.05)
    # Each cube carries half the plank; the table carries each cube's own weight fully.
    assert g.support_sum(0) == pytest.approx(0.5, abs=0.05)
    assert g.fraction(GROUND, 0) == pytest.approx(1.0, rel=0.05)


def test_floating_object_is_unsupported_last(cube_model):
    inst = [ObjectInstance("ground", cube_model), ObjectInstance("air", cube_model)]
    # Settle with the floater disabled (it keeps its pose), then enable it: no contacts.
    w = settled(inst, {"ground": pose(z=E / 2), "air": pose(x=0.3, z=0.3)}, disabled=["air"])
    w.set_enabled("air", True)
    g = graph(w)
    assert g.edges() == [(GROUND, 0)]
    assert g.layers() == [[0], [1]]  # last group: no support path
    assert g.unsupported() == [1]
    assert g.supported_by(1) == [] and g.supported_fraction(1) == 0.0
    assert g.penetration[1] == 0.0


def test_falling_stack_is_unsupported(cube_model):
    # Two stacked cubes in free fall (quasi-static steps): they touch but carry no load, so
    # there is no edge and both land in the final, unsupported group.
    inst = [ObjectInstance("air", cube_model), ObjectInstance("top", cube_model)]
    w = World(inst)
    w.set_poses({"air": pose(z=0.2), "top": pose(z=0.2 + E)})
    w.step(20)  # both fall together
    g = graph(w)
    assert g.layers() == [[0, 1]] and g.unsupported() == [0, 1]


def test_deterministic(tower):
    a, b = graph(tower), graph(tower)
    for name in ("supporter", "supported", "edge_force", "edge_vertical", "edge_fraction"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.layers() == b.layers()


def test_min_force_drops_light_edges(tower):
    g = graph(tower, min_force=1.5 * tower.masses[0] * G)  # keep only >= 1.5 cube weights
    assert g.edges() == [(GROUND, 0), (0, 1)]
    assert g.layers() == [[0], [1], [2]]  # c2 has no support path now: last group


def test_empty_and_validation():
    c = Contacts.empty(("a", "b"))
    g = build_support_graph(c, [0.1, 0.2], G)
    assert len(g) == 0 and g.layers() == [[0, 1]] and g.unsupported() == [0, 1]
    np.testing.assert_array_equal(g.support_sums(), [0.0, 0.0])
    empty = build_support_graph(Contacts.empty(()), np.zeros(0), G)
    assert empty.layers() == [] and empty.unsupported() == []
    with pytest.raises(ValueError):
        build_support_graph(c, [0.1], G)
    with pytest.raises(ValueError):
        build_support_graph(c, [0.1, 0.2], 0.0)


def test_direction_from_synthetic_contacts():
    # Normal from a (index 0) to b (index 1) pointing down: b is below and supports a.
    ids = ("a", "b")
    c = Contacts(
        ids,
        np.array([0, 0, 1]),
        np.array([1, 1, -1]),
        np.zeros((3, 3)),
        np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]),
        np.array([1e-5, 3e-5, 2e-5]),
        np.array([0.5, 0.5, 2.0]),
    )
    g = build_support_graph(c, [0.1, 0.1], 10.0)
    assert g.edges() == [(GROUND, 1), (1, 0)]
    assert g.fraction(1, 0) == pytest.approx(1.0)  # 1 N on a 0.1 kg object at g = 10
    assert g.fraction(GROUND, 1) == pytest.approx(1.0)  # 2 N up minus 1 N passed to a
    assert g.edge_vertical.tolist() == pytest.approx([2.0, 1.0])
    np.testing.assert_allclose(g.penetration, [3e-5, 3e-5])
