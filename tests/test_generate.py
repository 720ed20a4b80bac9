"""Synthetic sequence generator (ssp.sim.generate) and hypothesis noise (ssp.sim.hypotheses)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.library import ObjectLibrary
from ssp.library.builtin import BLOCK_NAMES
from ssp.library.model import ObjectInstance
from ssp.physics import World
from ssp.probability import pose_change
from ssp.sim.frames import visible_fractions
from ssp.sim.generate import calibrate_noise, generate_sequence
from ssp.sim.hypotheses import CHI3_MEAN, HypothesisNoise, draw_hypotheses, induced_errors

SMALL = dict(stride=8, frames_per_stage=2)


@pytest.fixture(scope="module")
def isolated(lib):
    return generate_sequence("isolated", 3, lib, stages=2, objects_per_stage=3, **SMALL)


@pytest.fixture(scope="module")
def structure(lib):
    return generate_sequence("structure", 1, lib, stages=3, n_objects=9, **SMALL)


def _same(a, b):
    assert len(a) == len(b)
    for fa, fb in zip(a.frames, b.frames, strict=True):
        assert list(fa.gt) == list(fb.gt)
        for iid in fa.gt:
            assert fa.gt[iid][0] == fb.gt[iid][0]
            np.testing.assert_array_equal(fa.gt[iid][1], fb.gt[iid][1])
        np.testing.assert_array_equal(fa.depth, fb.depth)
        np.testing.assert_array_equal(fa.instance, fb.instance)
        assert fa.visib_fract == fb.visib_fract
        assert [h.score for h in fa.hypotheses] == [h.score for h in fb.hypotheses]
        for ha, hb in zip(fa.hypotheses, fb.hypotheses, strict=True):
            np.testing.assert_array_equal(ha.T_world_obj, hb.T_world_obj)


def test_deterministic(lib, isolated, structure):
    _same(isolated, generate_sequence("isolated", 3, lib, stages=2, objects_per_stage=3, **SMALL))
    _same(structure, generate_sequence("structure", 1, lib, stages=3, n_objects=9, **SMALL))
    other = generate_sequence("isolated", 4, lib, stages=1, objects_per_stage=3, **SMALL)
    assert not np.array_equal(other.frames[0].depth, isolated.frames[0].depth)


def _drift(lib, gt, seconds=0.5):
    """Re-simulate the ground truth (dynamics, from rest): largest displacement, m."""
    world = World([ObjectInstance(i, lib[c]) for i, (c, _) in gt.items()])
    world.set_poses({i: T for i, (_, T) in gt.items()})
    world.step(round(seconds / world.timestep), quasi_static=False)
    return max(pose_change(T, world.get_pose(i))[0] for i, (_, T) in gt.items()), world


def test_isolated_scene(lib, isolated):
    seq = isolated
    assert seq.experiment == "isolated" and seq.seed == 3
    assert len(seq) == 4 and seq.camera.shape == (60, 80)
    assert [len(f.gt) for f in seq.frames] == [3, 3, 6, 6]
    assert all(c not in BLOCK_NAMES for f in seq.frames for c, _ in f.gt.values())
    gt = seq.frames[-1].gt
    drift, world = _drift(lib, gt)
    assert drift < 1e-3
    contacts = world.contacts()
    assert not (contacts.obj_b >= 0).any()  # no object touches another
    # every object is on the table and inside the image
    for cls, T in gt.values():
        z = lib[cls].hull_vertices @ T[2, :3] + T[2, 3]
        assert abs(z.min()) < 1e-3
    f = seq.frames[-1]
    assert set(np.unique(f.instance[f.instance >= 0])) == set(range(len(gt)))


def test_structure_support_and_occlusion(lib, structure):
    seq = structure
    assert {c for f in seq.frames for c, _ in f.gt.values()} <= {"cube", "block"}
    counts = seq.info["stage_objects"]
    assert counts == [3, 6, 9]
    gt = seq.frames[-1].gt
    drift, _ = _drift(lib, gt)
    assert drift < 1e-3
    lowest = [float((lib[c].hull_vertices @ T[2, :3] + T[2, 3]).min()) for c, T in gt.values()]
    assert max(lowest) > 0.02  # some object stands on others
    assert min(seq.frames[-1].visib_fract.values()) < 0.5  # and some is occluded


def test_static_groups(isolated):
    seq = isolated
    groups = [f.static_group for f in seq.frames]
    assert groups == [0, 0, 1, 1]
    a, b = seq.frames[0], seq.frames[1]
    assert list(a.gt) == list(b.gt)
    for iid in a.gt:
        np.testing.assert_array_equal(a.gt[iid][1], b.gt[iid][1])
    assert a.visib_fract == b.visib_fract
    np.testing.assert_array_equal(a.instance, b.instance)
    assert not np.array_equal(a.depth, b.depth)  # fresh sensor noise every frame
    assert a.depth.dtype == np.float32 and a.instance.dtype == np.int16
    assert [f.stamp for f in seq.frames] == [0.0, 1.0, 2.0, 3.0]
    # objects already placed stay where physics left them (up to re-settling)
    for iid, (_, T) in a.gt.items():
        assert pose_change(T, seq.frames[2].gt[iid][1])[0] < 1e-3
    # the sequence's cloud and labels
    fr = seq.frame(0)
    assert fr.points.shape[0] == fr.labels.shape[0] > 0
    assert all(h.instance_id is None for h in fr.hypotheses)


def test_visib_fract_matches_full_renders(lib, structure):
    f = structure.frames[-1]
    ref = visible_fractions(lib, f.gt, T_world_cam=structure.T_world_cam, stride=8)
    for iid, v in f.visib_fract.items():
        assert v == pytest.approx(ref[iid], abs=1e-9)


# ------------------------------------------------------------------ hypotheses
def _cube_gt(lib, cls="cube"):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 0.3).as_matrix()
    T[:3, 3] = [0.1, -0.05, float(lib[cls].extents[2]) / 2]
    return {"a": (cls, T)}


def _draws(lib, gt, v, noise, n, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        hyps, src = draw_hypotheses(gt, {"a": v}, lib, noise, rng)
        out.append(hyps)
    return out


def test_hypotheses_zero_mean(lib):
    noise = HypothesisNoise(sigma_t=0.004, sigma_r_deg=4.0, k=5)
    gt = _cube_gt(lib, "claw_hammer")  # asymmetric: no flips
    T = gt["a"][1]
    hyps = [h for hs in _draws(lib, gt, 1.0, noise, 400) for h in hs]
    assert len(hyps) == 2000
    dt = np.array([h.T_world_obj[:3, 3] - T[:3, 3] for h in hyps])
    rv = Rotation.from_matrix(
        np.array([h.T_world_obj[:3, :3] @ T[:3, :3].T for h in hyps])
    ).as_rotvec()
    se = noise.sigma_t / np.sqrt(len(hyps))
    assert np.all(np.abs(dt.mean(axis=0)) < 4 * se)
    assert np.all(np.abs(rv.mean(axis=0)) < 4 * np.radians(noise.sigma_r_deg) / np.sqrt(len(hyps)))
    assert dt.std(axis=0) == pytest.approx([noise.sigma_t] * 3, rel=0.1)
    mean_err = np.linalg.norm(dt, axis=1).mean()
    assert mean_err == pytest.approx(CHI3_MEAN * noise.sigma_t, rel=0.05)


def test_noise_grows_as_visibility_drops(lib):
    noise = HypothesisNoise(sigma_t=0.003, sigma_r_deg=3.0, growth=2.0)
    gt = _cube_gt(lib)
    means = {}
    for v in (1.0, 0.5, 0.2):
        frames = _draws(lib, gt, v, noise, 300, seed=1)
        sym = lib["cube"].symmetry
        err = [pose_change(gt["a"][1], h.T_world_obj, sym) for hs in frames for h in hs]
        means[v] = np.mean([e[0] for e in err]), np.mean([e[1] for e in err])
    assert means[1.0][0] < means[0.5][0] < means[0.2][0]
    assert means[1.0][1] < means[0.5][1] < means[0.2][1]
    assert means[0.2][0] / means[1.0][0] == pytest.approx(noise.sigma_scale(0.2), rel=0.1)


def test_missed_detections_only_when_hardly_visible(lib):
    noise = HypothesisNoise()
    gt = _cube_gt(lib)
    for v in (1.0, 0.5, noise.miss_below):
        assert all(len(hs) == noise.k for hs in _draws(lib, gt, v, noise, 100))
    assert all(len(hs) == 0 for hs in _draws(lib, gt, 0.0, noise, 50))
    low = [len(hs) for hs in _draws(lib, gt, 0.05, noise, 400)]
    assert set(low) == {0, noise.k}
    assert np.mean([n == 0 for n in low]) == pytest.approx(noise.miss_prob, abs=0.08)


def test_symmetric_flips_for_cubes(lib):
    noise = HypothesisNoise(sigma_t=0.002, sigma_r_deg=2.0)
    gt = _cube_gt(lib)
    T = gt["a"][1]
    sym = lib["cube"].symmetry
    hyps = [h for hs in _draws(lib, gt, 1.0, noise, 60) for h in hs]
    raw = np.array([pose_change(T, h.T_world_obj)[1] for h in hyps])
    symm = np.array([pose_change(T, h.T_world_obj, sym)[1] for h in hyps])
    assert np.degrees(symm).max() < 20.0
    assert (np.degrees(raw) > 60).mean() > 0.8  # 23 of 24 equivalents are far from identity
    assert len({tuple(np.round(h.T_world_obj[:3, :3], 1).ravel()) for h in hyps}) > 10
    # no flips without the option, nor for an asymmetric model
    plain = _draws(lib, gt, 1.0, noise.replace(flip_symmetric=False), 20)
    assert max(pose_change(T, h.T_world_obj)[1] for hs in plain for h in hs) < np.radians(20)


def test_scores_rank_but_do_not_reveal_the_best(lib, structure):
    noise = HypothesisNoise.structure()
    frames, sources = [], []
    for rep in range(4):
        for f in structure.frames:
            rng = np.random.default_rng([rep, f.index])
            hyps, src = draw_hypotheses(f.gt, f.visib_fract, lib, noise, rng)
            assert [h.score for h in hyps] == sorted((h.score for h in hyps), reverse=True)
            frames.append(f.__class__(f.index, 0.0, f.gt, f.depth, f.instance, f.visib_fract, hyps))
            sources.append(src)
    e = induced_errors(frames, lib, sources)
    top = e["rank"] == 0
    p_best = e["is_best"][top].mean()
    assert 0.3 < p_best < 0.8
    assert e["translation_mm"][top].mean() < e["translation_mm"].mean()
    # without recorded sources, nearest-object matching finds the same errors
    e2 = induced_errors(frames[:3], lib)
    e3 = induced_errors(frames[:3], lib, sources[:3])
    np.testing.assert_allclose(e2["translation_mm"], e3["translation_mm"])


def test_sequence_records_hypothesis_sources(lib, structure):
    src = structure.info["hypothesis_sources"]
    assert [len(s) for s in src] == [len(f.hypotheses) for f in structure.frames]
    e = induced_errors(structure, lib)
    assert len(e["translation_mm"]) == sum(len(f.hypotheses) for f in structure.frames)
    assert 0 < e["translation_mm"].mean() < 20


def test_presets_and_validation():
    iso, st = HypothesisNoise.isolated(), HypothesisNoise.structure()
    assert iso.k == st.k == 5
    assert CHI3_MEAN * iso.sigma_t * 1000 == pytest.approx(3.05, rel=0.05)  # nearly all visible
    assert st.sigma_t > iso.sigma_t
    with pytest.raises(ValueError):
        HypothesisNoise(miss_prob=1.5)
    with pytest.raises(ValueError):
        HypothesisNoise.for_experiment("towers")


def test_calibrate_noise_tiny(lib):
    r = calibrate_noise(
        "structure", lib, seeds=[0], stages=2, frames_per_stage=1, stride=8, n_objects=4
    )
    assert r["n_sequences"] == 1 and r["n_hypotheses"] > 0
    assert r["sigma_t"] > 0 and r["sigma_r_deg"] > 0
    t_mean, _ = r["measured"]["translation_mm"]
    r_mean, _ = r["measured"]["rotation_deg"]
    assert t_mean == pytest.approx(5.19, rel=0.35)
    assert r_mean == pytest.approx(5.7, rel=0.35)


def test_bad_arguments(lib):
    with pytest.raises(ValueError):
        generate_sequence("pile", 0, lib)
    with pytest.raises(ValueError):
        generate_sequence("isolated", -1, lib)
    tools_only = ObjectLibrary([lib["mallet"]])
    with pytest.raises(ValueError, match="cube"):
        generate_sequence("structure", 0, tools_only, stages=1, **SMALL)
