"""Unchanged segments keep their hypotheses (ssp.perception.reuse, issue 34).

A static object seen again from the same camera is not estimated again: its segment keeps the
hypotheses of the frame they were estimated on. A moved object, a moved camera, another
segmentation or the setting off estimate again; the memory is state, and round-trips.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ssp.config import SSPConfig
from ssp.errors import SSPError
from ssp.geometry import make_pose
from ssp.perception.estimator import HypothesisEstimator, SegmentResult
from ssp.perception.pipeline import Perception
from ssp.perception.reuse import (
    SAME_CENTROID,
    SAME_POINTS,
    SAME_SPREAD,
    SegmentMemory,
    SegmentShape,
    confident,
)
from ssp.scene import Hypothesis
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at

CAMERA = look_at([-0.45, -0.55, 0.6], [0.0, 0.0, 0.03])


def _cloud(rng, n=2000):
    return rng.normal(0.0, 0.02, (n, 3)) + [0.1, 0.0, 0.05]


def test_a_shape_is_the_same_within_the_noise_of_a_static_segment_only():
    rng = np.random.default_rng(0)
    p = _cloud(rng)
    a = SegmentShape.of(p, CAMERA)
    assert a.same(SegmentShape.of(p + rng.normal(0.0, 0.0003, p.shape), CAMERA))
    moved = SegmentShape.of(p + [1.5 * SAME_CENTROID, 0.0, 0.0], CAMERA)
    assert not a.same(moved)
    fewer = SegmentShape.of(p[: int(len(p) * (1 - 2 * SAME_POINTS))], CAMERA)
    assert not a.same(fewer)
    c = p.mean(axis=0)
    spread = SegmentShape.of(c + (p - c) * (1 + 2 * SAME_SPREAD), CAMERA)  # turned or grown
    assert not a.same(spread)
    cam = CAMERA.copy()
    cam[:3, 3] += [0.002, 0.0, 0.0]
    assert not a.same(SegmentShape.of(p, cam))
    assert not a.same(SegmentShape.of(p, None)) and not SegmentShape.of(p, None).same(a)


def test_the_memory_recalls_a_segment_by_label_classes_and_shape_and_round_trips():
    rng = np.random.default_rng(1)
    p = _cloud(rng)
    shape = SegmentShape.of(p, CAMERA)
    T = make_pose(np.eye(3), [0.1, 0.0, 0.05])
    result = SegmentResult(
        [[Hypothesis("cube", T, 0.9)]], 0.04, 120, "", coverage=[0.95], rival=[0.6]
    )
    bars = (0.7, 0.85, 0.05)
    assert confident(result, *bars)
    assert not confident(replace(result, coverage=[0.8]), *bars)  # 20 % unexplained
    assert not confident(replace(result, rival=[0.88]), *bars)  # another orientation as good
    low = SegmentResult([[Hypothesis("cube", T, 0.6)]], coverage=[0.95], rival=[0.0])
    assert not confident(low, *bars)
    assert not confident(SegmentResult(stopped="no pose explained it"), *bars)
    m = SegmentMemory()
    m.remember(4, ("cube",), shape, result)
    m.end_frame()
    got = m.recall(4, ("cube",), shape)
    assert got is not None and got.reused and got.seconds == 0.0
    assert got.objects == result.objects and not result.reused
    assert m.recall(5, ("cube",), shape) is None  # another segment
    m.end_frame()  # kept for the next frame: recalled
    assert m.recall(4, ("cube", "mallet"), shape) is None  # other classes asked
    m.begin_frame()
    back = SegmentMemory()
    back.restore(m.state())
    assert back.state() == m.state()
    again = back.recall(4, ("cube",), shape)
    assert again is not None and np.array_equal(again.objects[0][0].T_world_obj, T)
    with pytest.raises(SSPError, match="segment memory"):
        SegmentMemory().restore([{"label": 4}])
    back.forget()
    assert back.state() == [] and back.recall(4, ("cube",), shape) is None


@pytest.fixture
def counted(monkeypatch):
    calls = []
    real = HypothesisEstimator.estimate

    def estimate(self, points, *args, **kwargs):
        calls.append(len(points))
        return real(self, points, *args, **kwargs)

    monkeypatch.setattr(HypothesisEstimator, "estimate", estimate)
    return calls


def _perceive(perception, lib, T, seed, camera=CAMERA, kind="instance"):
    f = synthetic_frame(lib, {"cube_0": ("cube", T)}, T_world_cam=camera, rng=seed, k=1)
    if kind == "cluster":  # no masks: the cloud above the table is clustered
        return perception.from_points(f.points, frame="world", T_world_cam=camera, labels=None)
    return perception.from_points(
        f.points, frame="world", T_world_cam=camera, labels=f.labels, label_kind="instance"
    )


def test_an_unchanged_segment_keeps_its_hypotheses_and_a_changed_one_is_estimated(lib, counted):
    cube = lib["cube"]
    T = make_pose(np.eye(3), [0.02, 0.01, -float(cube.mesh.bounds[0][2])])
    perception = Perception(lib, SSPConfig(), classes=["cube"])
    first = _perceive(perception, lib, T, seed=0)
    assert len(counted) == 1 and first.frame.hypotheses
    again = _perceive(perception, lib, T, seed=1)  # the same view, other sensor noise
    assert len(counted) == 1
    (seg,) = again.segments.values()
    assert seg.reused and again.timings.get("unchanged segments", 0.0) > 0.0
    assert [h.T_world_obj.tolist() for h in again.frame.hypotheses] == [
        h.T_world_obj.tolist() for h in first.frame.hypotheses
    ]
    moved = T.copy()
    moved[0, 3] += 0.006
    _perceive(perception, lib, moved, seed=2)
    assert len(counted) == 2
    _perceive(perception, lib, moved, seed=3)
    assert len(counted) == 2
    other = look_at([-0.40, -0.58, 0.6], [0.0, 0.0, 0.03])
    _perceive(perception, lib, moved, seed=4, camera=other)
    assert len(counted) == 3
    _perceive(perception, lib, moved, seed=5, camera=other, kind="cluster")
    _perceive(perception, lib, moved, seed=6, camera=other, kind="cluster")
    assert len(counted) == 5  # a cluster is no object's: estimated every frame
    _perceive(perception, lib, moved, seed=7, camera=other)
    assert len(counted) == 6  # ... and the memory was forgotten
    cfg = SSPConfig()
    cfg.perception.reuse_unchanged = False
    off = Perception(lib, cfg, classes=["cube"])
    _perceive(off, lib, T, seed=0)
    _perceive(off, lib, T, seed=1)
    assert len(counted) == 8
