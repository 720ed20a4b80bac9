"""The realistic protocol: estimator stream, mask defects, distractors, dynamic events."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from ssp.eval.metrics import pose_error
from ssp.library.model import ObjectInstance
from ssp.physics.world import World
from ssp.probability import pose_change
from ssp.sim.distractors import distractor_models
from ssp.sim.events import run_event
from ssp.sim.generate import ISOLATED_REGION, default_camera_pose, generate_sequence
from ssp.sim.masks import add_mask_defects
from ssp.sim.realistic import (
    RealisticNoise,
    RealisticStream,
    SceneRealism,
    alignment,
    confusable_classes,
    misorientations,
    near_symmetries,
)
from ssp.sim.render import Camera

EDGE = 0.0508


def _pose(x, y, z=EDGE / 2):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def _draws(lib, noise, gt, frames, seed=0, visib=None, **kw):
    stream = RealisticStream(lib, noise, seed, classes=sorted({c for c, _ in gt.values()}))
    visib = visib or {k: 1.0 for k in gt}
    return [stream.draw(i, gt, visib, **kw) for i in range(frames)]


GT = {"a": ("cube", _pose(0.0, 0.0)), "b": ("block", _pose(0.1, 0.0, 0.0127))}


def test_stream_is_deterministic_and_objects_draw_independently(lib):
    noise = RealisticNoise()
    one = _draws(lib, noise, GT, 6, seed=4)
    two = _draws(lib, noise, GT, 6, seed=4)
    for fa, fb in zip(one, two, strict=True):
        assert [(h.kind, h.source) for h in fa] == [(h.kind, h.source) for h in fb]
        assert all(
            np.array_equal(a.hypothesis.T_world_obj, b.hypothesis.T_world_obj)
            for a, b in zip(fa, fb, strict=True)
        )
    # the cube's hypotheses do not depend on whether the block is in the scene
    alone = _draws(lib, noise.replace(false_positive_rate=0.0), {"a": GT["a"]}, 6, seed=4)
    both = _draws(lib, noise.replace(false_positive_rate=0.0), GT, 6, seed=4)
    for fa, fb in zip(alone, both, strict=True):
        pa = sorted(h.hypothesis.score for h in fa)
        pb = sorted(h.hypothesis.score for h in fb if h.source == "a")
        assert pa == pb


def test_rates_of_gross_outliers_dropouts_and_false_positives(lib):
    noise = RealisticNoise(confusion_rate=0.0, flip_rate=0.0, distractor_rate=0.0)
    frames = _draws(lib, noise, GT, 400, seed=1)
    kinds = Counter(h.kind for f in frames for h in f)
    per_object = kinds["nominal"] + kinds["gross"]
    assert kinds["gross"] / per_object == pytest.approx(noise.gross_rate, abs=0.03)
    # dropouts: runs of frames without any hypothesis of an object
    present = np.array([[any(h.source == o for h in f) for f in frames] for o in GT])
    missed = 1.0 - present.mean()
    expect = noise.dropout_start * noise.dropout_frames  # about, for small rates
    assert 0.5 * expect < missed < 1.5 * expect
    runs = [
        len(r) for row in present for r in "".join("x" if p else "." for p in row).split("x") if r
    ]
    assert np.mean(runs) == pytest.approx(noise.dropout_frames, rel=0.35)
    fps = [h for f in frames for h in f if h.kind == "false_positive"]
    assert fps and all(h.source is None and h.hypothesis.segment is None for h in fps)
    # gross outliers are 2-10 cm or 30-180 deg off
    for f in frames[:50]:
        for h in f:
            if h.kind == "gross":
                mm, deg = pose_error(
                    GT[h.source][1], h.hypothesis.T_world_obj, lib[GT[h.source][0]].symmetry,
                    lib[GT[h.source][0]].center_of_mass,
                )  # fmt: skip
                assert deg > 25.0 or mm > 15.0


def test_bias_persists_while_static_and_is_redrawn_when_the_object_moves(lib):
    noise = RealisticNoise(
        bias_share=1.0, bias_rho=1.0, gross_rate=0.0, flip_rate=0.0, confusion_rate=0.0,
        dropout_start=0.0, false_positive_rate=0.0, k=1, sigma_t=0.002,
    )  # fmt: skip
    gt = {"a": ("block", _pose(0.0, 0.0, 0.0127))}
    stream = RealisticStream(lib, noise, 3, classes=["block"])
    errs = []
    for i in range(4):
        (h,) = stream.draw(i, gt, {"a": 1.0})
        errs.append(h.hypothesis.T_world_obj[:3, 3] - gt["a"][1][:3, 3])
    assert all(np.allclose(errs[0], e) for e in errs[1:])  # same error every frame
    moved = {"a": ("block", _pose(0.05, 0.0, 0.0127))}
    (h,) = stream.draw(4, moved, {"a": 1.0})
    e = h.hypothesis.T_world_obj[:3, 3] - moved["a"][1][:3, 3]
    assert not np.allclose(e, errs[0])


def test_segments_are_tagged_and_distractors_get_library_hypotheses(lib):
    noise = RealisticNoise(distractor_rate=1.0, mode_persistence=1.0, false_positive_rate=0.0)
    can = distractor_models()["distractor_can"]
    T_can = _pose(0.2, 0.0, 0.06)
    frames = _draws(
        lib, noise, GT, 3, segments={"a": 0, "b": 1, "d": 2}, distractors={"d": (can, T_can)}
    )
    for f in frames:
        for h in f:
            if h.kind == "distractor":
                assert h.hypothesis.segment == 2 and h.source is None
                assert h.hypothesis.class_name in ("cube", "block")
            elif h.source is not None:
                assert h.hypothesis.segment == {"a": 0, "b": 1}[h.source]
    assert any(h.kind == "distractor" for f in frames for h in f)


def test_misorientations_near_symmetries_and_confusions(lib):
    assert misorientations(lib["cube"], 0.004) == []  # every box turn of a cube is a symmetry
    turns = misorientations(lib["block"], 0.004)  # no near-symmetry: box turns
    assert turns and all(pose_change(np.eye(4), S, lib["block"].symmetry)[1] > 0.1 for S in turns)
    # the hexagonal handle's quarter turns (its 60-degree turns are declared symmetries)
    flips = near_symmetries(lib["screwdriver"], 0.004)
    angles = sorted(round(math.degrees(pose_change(np.eye(4), S)[1])) for S in flips)
    assert 90 in angles and 60 not in angles
    assert confusable_classes({n: lib[n] for n in ("cube", "block")}, 0.2) == {
        "cube": "block", "block": "cube",
    }  # fmt: skip
    T = alignment(lib["cube"], lib["block"])  # centres of mass coincide
    c = T[:3, :3] @ lib["block"].center_of_mass + T[:3, 3]
    assert np.allclose(c, lib["cube"].center_of_mass)


def test_noise_settings_are_checked():
    with pytest.raises(ValueError, match="gross_rate"):
        RealisticNoise(gross_rate=1.5)
    with pytest.raises(ValueError, match="k must"):
        RealisticNoise(k=0)
    with pytest.raises(ValueError, match="distractors"):
        SceneRealism(distractors=9)


def test_mask_defects_bleed_and_fly_only_at_the_border():
    depth = np.full((60, 60), 1.0)
    depth[20:40, 20:40] = 0.8
    inst = np.full((60, 60), -1)
    inst[20:40, 20:40] = 0
    d2, i2, counts = add_mask_defects(
        depth, inst, np.random.default_rng(0), fraction=(0.03, 0.03), bleed_share=0.5
    )
    changed = (i2 == 0) & (inst != 0)
    assert counts[0] == changed.sum() == round(0.03 * 400)
    ring = np.zeros_like(changed)
    ring[18:42, 18:42] = True
    ring[20:40, 20:40] = False
    assert not (changed & ~ring).any()  # within 2 px of the segment
    vals = d2[changed]
    assert ((vals > 0.8) & (vals <= 1.0)).all()  # bled (1.0) or flying (in between)
    assert (vals < 1.0).any() and (vals == 1.0).any()
    assert np.array_equal(d2[inst == 0], depth[inst == 0])  # the object itself is untouched


@pytest.fixture()
def tower_world(lib):
    cube = lib["cube"]
    w = World([ObjectInstance(i, cube) for i in ("c0", "c1", "c2")], table=True)
    w.set_poses(
        {"c0": _pose(0.0, 0.0), "c1": _pose(0.0, 0.0, 1.5 * EDGE + 1e-4), "c2": _pose(0.15, 0.1)}
    )
    w.settle()
    return w


def test_events_move_knock_and_stack(lib, tower_world):
    w = tower_world
    cam, T_wc = Camera.default(), default_camera_pose()
    start = w.save_state()
    before = w.poses()
    rng = np.random.default_rng(0)
    ev = run_event("move", w, w.ids, rng, T_wc=T_wc, camera=cam, region=ISOLATED_REGION)
    assert ev is not None and ev.target in ("c1", "c2")  # c0 carries c1: never picked
    others = [o for o in w.ids if o != ev.target]
    assert all(np.allclose(w.get_pose(o)[:3, 3], before[o][:3, 3], atol=0.002) for o in others)
    assert np.linalg.norm(w.get_pose(ev.target)[:2, 3] - before[ev.target][:2, 3]) > 0.01
    w.restore_state(start)
    ev = run_event("knock", w, w.ids, rng, T_wc=T_wc, camera=cam, region=ISOLATED_REGION)
    assert ev is not None and ev.target == "c1" and "c1" in ev.moved
    w.restore_state(start)
    ev = run_event(
        "stack", w, w.ids, rng, T_wc=T_wc, camera=cam, region=ISOLATED_REGION, prefer=["c2"]
    )
    assert ev is not None and ev.target == "c2"
    assert w.get_pose("c2")[2, 3] == pytest.approx(2.5 * EDGE, abs=0.003)  # on top of c1
    with pytest.raises(ValueError, match="unknown event"):
        run_event("fly", w, w.ids, rng, T_wc=T_wc, camera=cam, region=ISOLATED_REGION)


def test_realistic_sequence_has_distractors_events_kinds_and_is_deterministic(lib):
    kw = dict(
        stages=2, frames_per_stage=1, stride=4, hypotheses=RealisticNoise(), realism=SceneRealism()
    )
    seq = generate_sequence("structure", 7, lib, **kw)
    assert [e["kind"] for e in seq.info["events"]] + [
        e["kind"] for e in seq.info["events_skipped"]
    ] == ["move", "knock", "stack"]
    assert len(seq.frames) == 2 + len(seq.info["events"])
    f = seq.frames[-1]
    assert len(f.distractors) == 2 and not set(f.distractors) & set(f.gt)
    assert f.instance.max() >= len(f.gt)  # distractors are labelled after the ground truth
    kinds = seq.info["hypothesis_kinds"]
    assert len(kinds) == len(seq.frames) and all(
        len(k) == len(fr.hypotheses) for k, fr in zip(kinds, seq.frames, strict=True)
    )
    again = generate_sequence("structure", 7, lib, **kw)
    for a, b in zip(seq.frames, again.frames, strict=True):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.instance, b.instance)
        assert [h.score for h in a.hypotheses] == [h.score for h in b.hypotheses]
