"""``ssp.eval.baselines`` on tiny rendered sequences (2-4 frames, one or two objects)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.config import SSPConfig
from ssp.eval.baselines import (
    METHODS,
    BestFit,
    Estimator,
    ICPRefine,
    RaySlide,
    SSPMethod,
    TemporalFilter,
    icp_refine,
    make_method,
)
from ssp.eval.metrics import match_frame, pose_error, precision_deviations
from ssp.library import ObjectLibrary
from ssp.library.symmetry import Symmetry
from ssp.scene import Hypothesis
from ssp.sim.frames import render_scene
from ssp.sim.render import add_depth_noise, look_at
from ssp.sim.sequence import SimFrame, SimSequence

EDGE = 0.0508
T_WORLD_CAM = look_at([0.3, -0.35, 0.45], [0.0, 0.0, 0.02])


def pose(x=0.0, y=0.0, z=EDGE / 2, yaw_deg=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


def moved(T, dt=(0.0, 0.0, 0.0), rotvec_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    out = np.array(T, dtype=float)
    out[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix() @ out[:3, :3]
    out[:3, 3] += dt
    return out


@pytest.fixture(scope="module")
def lib(make_box) -> ObjectLibrary:
    """A symmetric 2-inch cube (24 rotations) and an asymmetric-enough bar, dense samples."""

    def dense(model, symmetry=None):
        pts, faces = trimesh.sample.sample_surface_even(model.mesh, 1500, seed=0)
        return dataclasses.replace(
            model,
            surface_points=np.asarray(pts, dtype=float),
            surface_normals=np.asarray(model.mesh.face_normals[faces], dtype=float),
            symmetry=symmetry or Symmetry(),
        )

    R = Rotation.create_group("O").as_matrix()
    S = np.tile(np.eye(4), (len(R), 1, 1))
    S[:, :3, :3] = R
    cube = dense(make_box("cube", (EDGE,) * 3, 0.09), Symmetry(S))
    bar = dense(make_box("bar", (0.1, 0.03, 0.02), 0.05))
    return ObjectLibrary([cube, bar])


def sequence(lib, gts, hyps, groups=None, seed=0) -> SimSequence:
    """Frames rendered (stride 2, depth noise) from per-frame ground truth and hypotheses."""
    rng = np.random.default_rng(seed)
    frames = []
    for i, (gt, h) in enumerate(zip(gts, hyps, strict=True)):
        r = render_scene(lib, gt, T_world_cam=T_WORLD_CAM, stride=2)
        frames.append(
            SimFrame(
                index=i,
                stamp=float(i),
                gt=gt,
                depth=add_depth_noise(r.depth, rng).astype(np.float32),
                instance=r.instance.astype(np.int16),
                visib_fract={k: 1.0 for k in gt},
                hypotheses=h,
                static_group=0 if groups is None else groups[i],
            )
        )
    return SimSequence("isolated", seed, r.camera, T_WORLD_CAM, frames, tuple(lib.names))


def errors(lib, gt, dets) -> dict[str, tuple[float, float]]:
    fm = match_frame(gt, dets, lib)
    assert not fm.missed and not fm.false_positives
    return {m.gt_id: (m.trans_mm, m.rot_deg) for m in fm.matches}


def test_registry_builds_every_method(lib):
    for name in METHODS:
        m = make_method(name, lib, SSPConfig())
        assert m.name == name
        m.reset()
    with pytest.raises(ValueError, match="unknown method"):
        make_method("nope", lib)


def test_estimator_picks_the_top_score_of_each_object(lib):
    gt = {"a": ("cube", pose(0.0, 0.0)), "b": ("bar", pose(0.12, 0.05, 0.01, 30))}
    Ta, Tb = gt["a"][1], gt["b"][1]
    hyps = [
        Hypothesis("cube", moved(Ta, (0.004, 0, 0)), score=0.5),
        Hypothesis("bar", moved(Tb, (0, 0.002, 0)), score=0.9),
        Hypothesis("cube", moved(Ta, (0.002, 0, 0)), score=1.0),
        Hypothesis("bar", moved(Tb, (0, -0.003, 0)), score=0.2),
    ]
    seq = sequence(lib, [gt], [hyps])
    dets = Estimator(lib).update(seq.frame(0))
    assert sorted(d.class_name for d in dets) == ["bar", "cube"]
    err = errors(lib, gt, dets)
    assert err["a"][0] == pytest.approx(2.0, abs=1e-6)
    assert err["b"][0] == pytest.approx(2.0, abs=1e-6)


def test_estimator_reports_alternatives_sharing_a_volume_once(lib):
    """The bar's two hypotheses lie 2.5 cm apart (beyond the association gate), turned by 90
    degrees, but share most of their volume: alternatives of one object, one detection."""
    gt = {"b": ("bar", pose(0.0, 0.0, 0.01, 0))}
    Tb = gt["b"][1]
    alt = moved(Tb, (0.0, 0.025, 0.0), (0, 0, 90))
    hyps = [Hypothesis("bar", Tb, score=0.9), Hypothesis("bar", alt, score=0.8)]
    seq = sequence(lib, [gt], [hyps])
    dets = Estimator(lib).update(seq.frame(0))
    assert len(dets) == 1
    assert errors(lib, gt, dets)["b"][0] == pytest.approx(0.0, abs=1e-9)
    # without the merge they are two objects
    cfg = SSPConfig.model_validate({"temporal": {"merge_overlap": 1.0}})
    assert len(Estimator(lib, cfg).update(seq.frame(0))) == 2


def test_bestfit_prefers_the_pose_that_fits_the_data(lib):
    gt = {"a": ("cube", pose(0.0, 0.0, yaw_deg=20))}
    T = gt["a"][1]
    hyps = [
        Hypothesis("cube", moved(T, (0.01, 0, 0)), score=1.0),  # top score, 1 cm off
        Hypothesis("cube", T.copy(), score=0.5),  # right
    ]
    seq = sequence(lib, [gt], [hyps])
    f = seq.frame(0)
    assert errors(lib, gt, Estimator(lib).update(f))["a"][0] == pytest.approx(10.0)
    assert errors(lib, gt, BestFit(lib).update(f))["a"][0] == pytest.approx(0.0, abs=1e-6)


def test_icp_reduces_a_3mm_error(lib):
    # the bar's end face is in view (edge-on, its long axis would be left to the damping)
    gt = {"a": ("cube", pose(0.0, 0.0, yaw_deg=20)), "b": ("bar", pose(0.12, 0.05, 0.01, -30))}
    hyps = [
        Hypothesis(c, moved(T, (0.002, -0.002, 0.001), (1.0, 1.5, 2.0))) for c, T in gt.values()
    ]
    seq = sequence(lib, [gt], [hyps])
    f = seq.frame(0)
    before = errors(lib, gt, Estimator(lib).update(f))
    after = errors(lib, gt, ICPRefine(lib).update(f))
    for k in gt:
        assert before[k][0] == pytest.approx(3.0, abs=1e-6)
        assert after[k][0] < 1.0, after
        assert after[k][1] < before[k][1]


def test_ray_slide_moves_a_depth_error_along_the_ray(lib):
    """An RGB estimator's error, 25 mm too far along the viewing ray: the user's simplest fix
    slides the pose back (within a few mm) without touching the rotation or the lateral
    position."""
    gt = {"a": ("cube", pose(0.0, 0.0, yaw_deg=20)), "b": ("bar", pose(0.12, 0.05, 0.01, -30))}
    cam = T_WORLD_CAM[:3, 3]
    hyps = []
    for c, T in gt.values():
        ray = (T[:3, 3] - cam) / np.linalg.norm(T[:3, 3] - cam)
        hyps.append(Hypothesis(c, moved(T, 0.025 * ray)))
    f = sequence(lib, [gt], [hyps]).frame(0)
    before = errors(lib, gt, Estimator(lib).update(f))
    after = errors(lib, gt, RaySlide(lib).update(f))
    for k in gt:
        assert before[k][0] == pytest.approx(25.0, abs=1e-6)
        assert after[k][0] < 5.0, after
        assert after[k][1] == pytest.approx(before[k][1], abs=1e-6)


def test_icp_without_data_keeps_the_pose(lib):
    T = pose()
    out = icp_refine(lib["cube"], T, np.zeros((0, 3)))
    assert np.allclose(out, T)


def test_temporal_filter_reduces_jitter_on_a_static_scene(lib):
    gt = {"a": ("cube", pose(0.0, 0.0, yaw_deg=20))}
    T = gt["a"][1]
    jitter = [((0.002, 0, 0), (0, 0, 2)), ((-0.002, 0, 0), (0, 0, -2))] * 2
    hyps = [[Hypothesis("cube", moved(T, d, r))] for d, r in jitter]
    seq = sequence(lib, [gt] * 4, hyps)
    raw, smooth = Estimator(lib), TemporalFilter(lib)
    raw_poses, smooth_poses = [], []
    for i in range(len(seq)):
        f = seq.frame(i)
        raw_poses.append(raw.update(f)[0].T_world_obj)
        (det,) = smooth.update(f)
        smooth_poses.append(det.T_world_obj)
    sym = lib["cube"].symmetry
    raw_t, raw_r = precision_deviations(raw_poses, sym)
    sm_t, sm_r = precision_deviations(smooth_poses, sym)
    assert np.mean(raw_t) == pytest.approx(2.0)
    assert np.mean(sm_t) < 0.6 * np.mean(raw_t)
    assert np.mean(sm_r) < 0.6 * np.mean(raw_r)
    # after a full window of alternating poses, the output is the ground truth
    assert pose_error(T, smooth_poses[-1], sym)[0] == pytest.approx(0.0, abs=1e-6)


def test_temporal_filter_restarts_a_track_that_jumps(lib):
    T0 = pose(0.0, 0.0)
    T1 = pose(0.015, 0.0)  # moved 1.5 cm: same track (within the association gate) ...
    f = TemporalFilter(lib, jump_translation=0.01)  # ... but a jump for this filter
    gts = [{"a": ("cube", T0)}, {"a": ("cube", T0)}, {"a": ("cube", T1)}]
    hyps = [[Hypothesis("cube", g["a"][1].copy())] for g in gts]
    seq = sequence(lib, gts, hyps)
    outs = [f.update(seq.frame(i))[0].T_world_obj for i in range(3)]
    assert np.allclose(outs[2], T1)  # no lag after the jump
    f.reset()
    assert f.update(seq.frame(0))[0].T_world_obj == pytest.approx(T0)


def test_temporal_filter_drops_objects_that_vanish(lib):
    T = pose()
    seq = sequence(lib, [{"a": ("cube", T)}] * 2, [[Hypothesis("cube", T)], []])
    f = TemporalFilter(lib)
    assert len(f.update(seq.frame(0))) == 1
    assert f.update(seq.frame(1)) == []


def test_ssp_method_wraps_the_parser(lib):
    gt = {"a": ("cube", pose(0.0, 0.0, yaw_deg=20))}
    hyps = [Hypothesis("cube", moved(gt["a"][1], (0.002, 0, 0.002)))]
    seq = sequence(lib, [gt], [hyps])
    m = SSPMethod(lib)
    dets = m.update(seq.frame(0))
    assert errors(lib, gt, dets)["a"][0] < 3.0
    assert m.last_estimate is not None and len(m.last_estimate.objects) == 1


def test_icp_filter_rejects_an_outlier_and_follows_a_confirmed_move(lib):
    from ssp.eval.baselines import ICPFilter

    T0 = pose(0.0, 0.0, yaw_deg=20)
    T1 = pose(0.03, 0.0, yaw_deg=20)  # moved 3 cm: beyond the 2 cm gate
    outlier = moved(T0, (0.0, 0.0, 0.0), (0, 0, 45))  # a gross turn of the best hypothesis
    gts = [{"a": ("cube", T0)}] * 3 + [{"a": ("cube", T1)}] * 4
    hyps = [
        [Hypothesis("cube", T0)],
        [Hypothesis("cube", T0)],
        [Hypothesis("cube", outlier, 0.9)],  # the only hypothesis: an outlier, rejected
        *[[Hypothesis("cube", T1)]] * 4,
    ]
    seq = sequence(lib, gts, hyps)
    f = ICPFilter(lib, window=3, confirm=3)
    outs = [f.update(seq.frame(i)) for i in range(len(seq))]
    sym = lib["cube"].symmetry
    assert pose_error(T0, outs[2][0].T_world_obj, sym)[1] < 2.0  # the outlier did not pass
    assert all(o[0].id == outs[0][0].id for o in outs)  # one track throughout
    assert pose_error(T0, outs[4][0].T_world_obj, sym)[0] < 2.0  # two outliers: still there
    assert pose_error(T1, outs[6][0].T_world_obj, sym)[0] < 2.0  # third: it moved


def test_icp_filter_coasts_through_a_missed_detection(lib):
    from ssp.eval.baselines import ICPFilter

    T = pose(0.0, 0.0)
    seq = sequence(lib, [{"a": ("cube", T)}] * 3, [[Hypothesis("cube", T, 0.8)], [], []])
    f = ICPFilter(lib, max_missed=1)
    (first,) = f.update(seq.frame(0))
    (coast,) = f.update(seq.frame(1))
    assert coast.id == first.id and coast.score == pytest.approx(0.4)
    assert f.update(seq.frame(2)) == []


def test_ssp_single_frame_has_no_memory(lib):
    from ssp.eval.baselines import SSPSingleFrame

    T = pose(0.0, 0.0)
    seq = sequence(lib, [{"a": ("cube", T)}] * 2, [[Hypothesis("cube", T)], []])
    m = SSPSingleFrame(lib)
    (det,) = m.update(seq.frame(0))
    assert det.id is None
    assert m.update(seq.frame(1)) == []  # the full parser would keep the unseen cube
    full = SSPMethod(lib)
    full.update(seq.frame(0))
    assert len(full.update(seq.frame(1))) == 1


def test_groups_are_one_object_per_instance_segment(lib):
    T = pose(0.0, 0.0)
    far = moved(T, (0.06, 0.0, 0.0))  # a gross outlier 6 cm away, from the same mask
    hyps = [
        Hypothesis("cube", T, 0.9, segment=0),
        Hypothesis("cube", far, 0.8, segment=0),
        Hypothesis("bar", T, 0.5, segment=0),  # a class confusion on the same mask
    ]
    seq = sequence(lib, [{"a": ("cube", T)}], [hyps])
    (det,) = Estimator(lib).update(seq.frame(0))
    assert det.class_name == "cube" and np.allclose(det.T_world_obj, T)
