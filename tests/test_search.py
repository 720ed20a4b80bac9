"""The layered search's choice of the objects a test leaves out (ssp.search)."""

from __future__ import annotations

from ssp.geometry import make_pose
from ssp.library import ObjectInstance
from ssp.physics import World
from ssp.search import _out_of_reach


def test_objects_out_of_reach_are_left_out_unless_they_hold_up_the_others(lib):
    """Testing the top of a three-cube tower: the bottom cube is far from it but carries the
    middle one, so it stays; a cube farther along the table carries nothing and is left out."""
    cube = lib["cube"]
    e = float(cube.extents[2])
    poses = {f"t{k}": make_pose(t=[0.0, 0.0, e / 2 + k * e]) for k in range(3)}
    poses["far"] = make_pose(t=[0.3, 0.0, e / 2])
    world = World([ObjectInstance(oid, cube) for oid in poses])
    world.set_poses(poses)
    i = world.ids.index("t2")
    parents = {world.ids.index("t1"): [world.ids.index("t0")], i: [world.ids.index("t1")]}
    far = _out_of_reach(world, i, [poses["t2"]], [], 0.02, parents)
    assert [world.ids[k] for k in far] == ["far"]
    far = _out_of_reach(world, i, [poses["t2"]], [], 0.02, {})
    assert sorted(world.ids[k] for k in far) == ["far", "t0"]


def test_a_window_without_forces_ends_early_only_when_the_scene_is_at_rest(lib):
    """search.rest_check_every: a cube resting on the table stops after one chunk of steps;
    one in mid-air falls for the whole window; 0 (the default) always steps the window."""
    from ssp.config import SSPConfig
    from ssp.forces import SegmentField
    from ssp.search import Simulator
    from ssp.timing import StageTimer

    cube = lib["cube"]
    e = float(cube.extents[2])
    cfg = SSPConfig()
    cfg.search.rest_check_every = 4
    for z, steps in ((e / 2, 4), (e / 2 + 0.01, 20)):
        world = World([ObjectInstance("c", cube)])
        world.set_pose("c", make_pose(t=[0.0, 0.0, z]))
        world.step(40)  # settle the contacts of the resting cube
        sim = Simulator.for_world(world, [SegmentField(cube.surface_points)], cfg, StageTimer())
        if z > e / 2:
            world.set_pose("c", make_pose(t=[0.0, 0.0, z]))
        sim.settle(0.1, with_forces=False)
        assert sim.steps == steps
    cfg.search.rest_check_every = 0
    sim = Simulator.for_world(world, [None], cfg, StageTimer())
    sim.settle(0.1, with_forces=False)
    assert sim.steps == 20
