"""Candidates evaluated in parallel (ssp.lanes, ``search.threads``): the same results."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.config import SSPConfig
from ssp.errors import WorldMismatchError
from ssp.eval.bench_parser import _slide, stacks
from ssp.library import ObjectInstance, ObjectLibrary
from ssp.parser import SceneParser
from ssp.physics import World
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at

LIB = ObjectLibrary.builtin()


def test_a_replica_restores_the_states_of_its_world_bit_for_bit():
    cube = LIB["cube"]
    T = np.eye(4)
    T[2, 3] = 0.04  # 1.5 cm above the table: it falls
    world = World([ObjectInstance("a", cube)])
    twin = world.replica()
    world.set_pose("a", T)
    start = world.save_state()
    world.step(30, quasi_static=False)
    twin.restore_state(start)
    twin.step(30, quasi_static=False)
    np.testing.assert_array_equal(world.pose_array(), twin.pose_array())
    other = World([ObjectInstance("a", cube)])
    with pytest.raises(WorldMismatchError):
        other.restore_state(start)


def _run(threads: int, frames) -> list:
    cfg = SSPConfig()
    cfg.search.threads = threads
    parser = SceneParser(LIB, cfg)
    return [parser.update(f) for f in frames]


def test_two_threads_give_the_same_scenes_as_one():
    rng = np.random.default_rng(5)
    gt = stacks(LIB, 5, seed=2)
    cam = look_at([-0.5, -0.6, 0.65], [0.0, 0.0, 0.03])
    frames = [
        synthetic_frame(LIB, g, T_world_cam=cam, rng=rng, k=3, stamp=float(t))
        for t, g in enumerate([gt, _slide(gt, 0.015), _slide(gt, 0.015)])
    ]
    one, two = _run(1, frames), _run(2, frames)
    assert one[2].unchanged  # the third frame: the shortcut (ICP polish, evidence in lanes)
    for a, b in zip(one, two, strict=True):
        assert a.hypotheses_tested == b.hypotheses_tested
        assert a.segments == b.segments and a.warnings == b.warnings
        assert [o.id for o in a.objects] == [o.id for o in b.objects]
        for oa, ob in zip(a.objects, b.objects, strict=True):
            np.testing.assert_array_equal(oa.T_world_obj, ob.T_world_obj)
            assert oa.source == ob.source and oa.terms == ob.terms
            assert oa.evidence == ob.evidence and oa.reason == ob.reason
