"""Scene tests of SceneParser.update (issue 3): small generated scenes, each check able to fail.

Frames are rendered depth with sensor noise (ssp.sim) from a camera about 0.9 m away; the
simplest tests use a cloud of the models' upward and sideways surface samples instead.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import ssp.parser as parser_module
from ssp.config import SSPConfig
from ssp.frame_context import Stage
from ssp.geometry import make_pose, transform_points
from ssp.library import ObjectInstance, ObjectLibrary
from ssp.motion import RESIDUAL_CAP
from ssp.parser import SceneEstimate, SceneParser, parse_sequence
from ssp.physics import World
from ssp.probability import pose_change
from ssp.scene import Frame, FrameError, Hypothesis, TransitionMode
from ssp.scoring import SceneScorer
from ssp.segments import surface_residual
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at
from ssp.verification import evidence
from ssp.visibility import CameraView

LIB = ObjectLibrary.builtin()
CUBE = LIB["cube"]
BLOCK = LIB["block"]
E = float(CUBE.extents[2])
CAMERA = look_at([-0.45, -0.55, 0.6], [0.0, 0.0, 0.03])  # about 0.9 m away, from a corner


def on_table(model, x=0.0, y=0.0, z_extra=0.0, yaw_deg=0.0, level=0):
    """Pose of ``model`` resting flat at (x, y), ``level`` cubes up."""
    zmin = float(model.mesh.bounds[0, 2])
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return make_pose(R, [x, y, -zmin + level * E + z_extra])


def cloud(gt, hidden=(), table=True):
    """(points, labels) of the scene ``gt`` (id -> (class, pose)); ``hidden`` ids give no points."""
    pts, labels = [], []
    for k, (oid, (cls, T)) in enumerate(gt.items()):
        if oid in hidden:
            continue
        m = LIB[cls]
        p = transform_points(T, m.surface_points)
        n = m.surface_normals @ T[:3, :3].T
        keep = (n[:, 2] > -0.5) & (p[:, 2] > 0.001)
        pts.append(p[keep])
        labels.append(np.full(int(keep.sum()), k))
    if table:
        g = np.arange(-0.15, 0.15, 0.004)
        xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
        free = np.ones(len(xy), bool)
        for oid, (cls, T) in gt.items():
            if oid in hidden and oid.startswith("keep-footprint"):
                continue
            lo, hi = LIB[cls].mesh.bounds
            if T[2, 3] + lo[2] > 0.01:  # not on the table
                continue
            local = (xy - T[:2, 3]) @ T[:2, :2]
            free &= ~np.all((local > lo[:2] - 0.002) & (local < hi[:2] + 0.002), axis=1)
        pts.append(np.column_stack([xy[free], np.zeros(free.sum())]))
        labels.append(np.full(int(free.sum()), -1))
    return np.concatenate(pts), np.concatenate(labels)


def noisy(T, rng, st=0.005, sr_deg=5.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = Rotation.from_rotvec(np.radians(sr_deg) * abs(rng.normal()) * axis).as_matrix()
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] += rng.normal(size=3) * st / np.sqrt(3)
    return out


def frame(gt, rng, k=5, stamp=0.0, detect=None, hidden=(), ids=False, st=0.005, sr_deg=5.0):
    """A rendered frame (depth with sensor noise, ssp.sim) of ``gt`` with ``k`` noisy hypotheses
    per detected object; the points of ``hidden`` objects are dropped (sensor dropout)."""
    f = synthetic_frame(
        LIB,
        gt,
        T_world_cam=CAMERA,
        rng=rng,
        k=k,
        stamp=stamp,
        sigma_t=st,
        sigma_r_deg=sr_deg,
        detect=detect,
        give_ids=ids,
        stride=2,
    )
    if hidden:
        drop = np.isin(f.labels, [i for i, oid in enumerate(gt) if oid in hidden])
        f.points, f.labels = f.points[~drop], f.labels[~drop]
    return f


def errors(est: SceneEstimate, gt):
    """(mm, deg) error of each gt object against the nearest estimated object of its class."""
    out = {}
    for oid, (cls, T) in gt.items():
        cands = [o for o in est.objects if o.class_name == cls]
        o = min(cands, key=lambda o: np.linalg.norm(o.T_world_obj[:3, 3] - T[:3, 3]))
        dt, dth = pose_change(T, o.T_world_obj, LIB[cls].symmetry)
        out[oid] = (dt * 1000, np.degrees(dth))
    return out


def max_penetration(est: SceneEstimate) -> float:
    w = World([ObjectInstance(o.id, LIB[o.class_name]) for o in est.objects])
    w.set_poses(est.poses())
    d = np.asarray(w.contacts().depth)
    return float(d.max()) if len(d) else 0.0


def tower(n=3):
    return {f"t{i}": ("cube", on_table(CUBE, level=i)) for i in range(n)}


# ------------------------------------------------------------------------------ physics


def test_block_hypothesised_above_the_table_settles_onto_it():
    gt = {"b": ("block", on_table(BLOCK, yaw_deg=20))}
    pts, labels = cloud(gt)
    T_up = on_table(BLOCK, yaw_deg=20, z_extra=0.01)
    est = SceneParser(LIB).update(Frame(0.0, pts, [Hypothesis("block", T_up)], labels=labels))
    (o,) = est.objects
    assert abs(o.T_world_obj[2, 3] - gt["b"][1][2, 3]) < 0.001
    assert o.mode == TransitionMode.ADDED
    assert o.terms.stability > np.log(0.9)
    assert [(e.supporter, e.supported) for e in est.support] == [("table", o.id)]


def test_interpenetrating_hypotheses_are_pushed_apart():
    gt = {"a": ("cube", on_table(CUBE, x=-E / 2)), "b": ("cube", on_table(CUBE, x=E / 2))}
    pts, labels = cloud(gt)
    hyps = [
        Hypothesis("cube", on_table(CUBE, x=-E / 2 + 0.004)),
        Hypothesis("cube", on_table(CUBE, x=E / 2 - 0.004)),
    ]
    est = SceneParser(LIB).update(Frame(0.0, pts, hyps, labels=labels))
    assert len(est) == 2
    assert max_penetration(est) < 0.0005
    assert all(mm < 1.5 for mm, _ in errors(est, gt).values())
    assert all(o.terms.collision > np.log(0.9) for o in est.objects)


def test_unsimulated_terms_rank_first_guesses_by_data_and_previous_pose():
    """log P_D + log P_T without simulation: a pose on the segment beats one 1 cm off it, and
    a turn from the previous pose costs its transition term."""
    from ssp.probability import log_transition_from_poses

    cfg = SSPConfig()
    world = World([ObjectInstance("b", BLOCK)], config=cfg.physics)
    T = on_table(BLOCK)
    seg = transform_points(T, np.asarray(BLOCK.surface_points))
    scorer = SceneScorer(world, cfg, {"b": seg}, {"b": None})
    assert scorer.unsimulated(0, T) > scorer.unsimulated(0, on_table(BLOCK, x=0.01)) + 1
    T_prev = on_table(BLOCK, yaw_deg=30.0)
    moved = SceneScorer(world, cfg, {"b": seg}, {"b": T_prev})
    expected = log_transition_from_poses(T_prev, T, cfg.transition, BLOCK.symmetry)
    assert expected < -1
    assert moved.unsimulated(0, T) == pytest.approx(scorer.unsimulated(0, T) + expected)


def test_scorer_prefers_a_supported_pose_to_a_hovering_one():
    cfg = SSPConfig()
    world = World([ObjectInstance("c", CUBE)], config=cfg.physics)
    scorer = SceneScorer(world, cfg, {}, {"c": None})
    world.set_pose("c", on_table(CUBE))
    resting = scorer.evaluate(world)
    world.set_pose("c", on_table(CUBE, z_extra=0.01))
    hovering = scorer.evaluate(world)
    assert resting.object_terms(0).stability > np.log(0.9)
    assert hovering.object_terms(0).stability < np.log(0.01)
    assert resting.total > hovering.total + 3


def test_hovering_hypothesis_loses_to_a_supported_one():
    """Pure selection (no simulation windows): the supported hypothesis must win."""
    cfg = SSPConfig.from_dict(
        {
            "search": {
                k: 0.0
                for k in (
                    "settle_with_forces",
                    "settle_without_forces",
                    "initial_settle",
                    "final_settle",
                )
            }
        }
    )
    gt = {"c": ("cube", on_table(CUBE))}
    pts, labels = cloud(gt)
    for first in ("hover", "rest"):  # whichever comes first (higher detector score)
        hyps = [
            Hypothesis("cube", on_table(CUBE, z_extra=0.008), 0.9 if first == "hover" else 0.5),
            Hypothesis("cube", on_table(CUBE), 0.9 if first == "rest" else 0.5),
        ]
        est = SceneParser(LIB, cfg).update(Frame(0.0, pts, hyps, labels=labels))
        assert abs(est.objects[0].T_world_obj[2, 3] - E / 2) < 1e-6, first


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_three_block_tower_within_2mm_2deg(seed):
    rng = np.random.default_rng(seed)
    gt = tower(3)
    est = SceneParser(LIB).update(frame(gt, rng, k=5))
    assert len(est) == 3
    for oid, (mm, deg) in errors(est, gt).items():
        assert mm < 2.0 and deg < 2.0, (oid, mm, deg)
    edges = {(e.supporter, e.supported) for e in est.support}
    by_z = sorted(est.objects, key=lambda o: o.T_world_obj[2, 3])
    assert edges == {("table", by_z[0].id), (by_z[0].id, by_z[1].id), (by_z[1].id, by_z[2].id)}
    assert max_penetration(est) < 0.0005


# ------------------------------------------------------------------------------ temporal


def test_block_carrying_another_is_support_retained_when_undetected():
    rng = np.random.default_rng(3)
    h_block = float(BLOCK.extents[2])
    gt = {"low": ("block", on_table(BLOCK)), "top": ("cube", on_table(CUBE, z_extra=h_block))}
    parser = SceneParser(LIB)
    est0 = parser.update(frame(gt, rng, ids=True))
    # the lower block's detections and points vanish (dropout); the cube still sits on it
    est1 = parser.update(frame(gt, rng, stamp=1.0, detect={"top"}, hidden={"low"}, ids=True))
    assert "low" in est1 and "top" in est1
    assert est1["low"].mode == TransitionMode.SUPPORT_RETAINED
    assert est1["top"].mode == TransitionMode.STATIC
    dt, _ = pose_change(est0["low"].T_world_obj, est1["low"].T_world_obj)
    assert dt < 0.002
    assert ("low", "top") in {(e.supporter, e.supported) for e in est1.support}


def test_block_removed_with_its_volume_seen_empty_is_removed():
    rng = np.random.default_rng(4)
    gt = {"a": ("block", on_table(BLOCK, x=-0.06)), "b": ("cube", on_table(CUBE, x=0.06))}
    parser = SceneParser(LIB)
    parser.update(frame(gt, rng, ids=True))
    gt1 = {"b": gt["b"]}  # "a" taken away: the table is seen where it stood
    est = parser.update(frame(gt1, rng, stamp=1.0, ids=True))
    assert est.ids == ("b",)
    assert [o.id for o in est.removed] == ["a"]
    assert est.removed[0].mode == TransitionMode.REMOVED
    assert "a" not in parser.objects


def test_unseen_undetected_object_without_load_is_removed_without_camera():
    rng = np.random.default_rng(5)
    gt = {"a": ("cube", on_table(CUBE, x=-0.06)), "b": ("cube", on_table(CUBE, x=0.06))}
    parser = SceneParser(LIB)
    parser.update(frame(gt, rng, ids=True))
    f = frame(gt, rng, stamp=1.0, detect={"b"}, hidden={"a"}, ids=True)
    f.T_world_cam = None
    est = parser.update(f)
    assert est.ids == ("b",) and [o.id for o in est.removed] == ["a"]


def test_undetected_but_visible_object_stays():
    rng = np.random.default_rng(6)
    gt = {"a": ("cube", on_table(CUBE, x=-0.06)), "b": ("cube", on_table(CUBE, x=0.06))}
    parser = SceneParser(LIB)
    est0 = parser.update(frame(gt, rng, ids=True))
    est1 = parser.update(frame(gt, rng, stamp=1.0, detect={"b"}, ids=True))  # "a" still in view
    assert est1["a"].mode == TransitionMode.STATIC
    dt, _ = pose_change(est0["a"].T_world_obj, est1["a"].T_world_obj)
    assert dt < 0.001


def test_static_scene_takes_the_unchanged_shortcut_and_keeps_ids():
    rng = np.random.default_rng(7)
    gt = tower(2)
    parser = SceneParser(LIB)
    est0 = parser.update(frame(gt, rng))
    est1 = parser.update(frame(gt, rng, stamp=1.0))
    assert est1.unchanged and est1.hypotheses_tested == 0
    assert set(est1.ids) == set(est0.ids)
    assert all(o.mode == TransitionMode.STATIC for o in est1.objects)


def test_moved_object_is_perturbed():
    rng = np.random.default_rng(8)
    gt = {"a": ("cube", on_table(CUBE, x=-0.05)), "b": ("cube", on_table(CUBE, x=0.06))}
    parser = SceneParser(LIB)
    est0 = parser.update(frame(gt, rng))
    gt1 = {"a": ("cube", on_table(CUBE, x=-0.03)), "b": gt["b"]}  # slid 2 cm
    est1 = parser.update(frame(gt1, rng, stamp=1.0))
    assert not est1.unchanged
    assert set(est1.ids) == set(est0.ids)  # same ids: associated, not re-added
    moved = min(est1.objects, key=lambda o: abs(o.T_world_obj[0, 3] + 0.03))
    assert moved.mode == TransitionMode.PERTURBED
    assert errors(est1, gt1)["a"][0] < 2.0


def _remembered_off(x_wrong: float):
    """A parser state after one frame of cubes a (at x = -0.05) and b, with a's pose moved to
    ``x_wrong`` (m); the next frame of the same scene; a's state entry; a's evidence at the
    wrong pose in that frame."""
    rng = np.random.default_rng(8)
    gt = {"a": ("cube", on_table(CUBE, x=-0.05)), "b": ("cube", on_table(CUBE, x=0.06))}
    parser = SceneParser(LIB)
    parser.update(frame(gt, rng))
    f1 = frame(gt, rng, stamp=1.0)
    wrong = on_table(CUBE, x=x_wrong)
    cfg = SSPConfig()
    view = CameraView(f1.points, CAMERA, labels=f1.labels,
                      depth_tolerance=cfg.temporal.depth_tolerance)  # fmt: skip
    there = evidence(CUBE, wrong, f1.points[f1.labels == 0], view, cfg, own_label=0)
    cap = RESIDUAL_CAP * cfg.data.inlier_radius
    there = SimpleNamespace(
        fit=there.fit, residual=surface_residual(f1.points[f1.labels == 0], CUBE, wrong, cap)
    )
    state = parser.state()
    (a,) = [o for o in state["objects"] if abs(o["T_world_obj"][0][3] + 0.05) < 0.005]
    assert 0 < a["seen_residual"] < 0.0015 and a["seen_fit"] > 0.9  # right, in frame 0
    a["T_world_obj"] = wrong.tolist()
    return state, f1, a, there


def test_a_corrected_estimate_of_an_object_that_did_not_move_is_static():
    # the parser remembers cube a 10 mm off where it stands; the frame shows it where it is,
    # and its estimate goes there: motion in the world only if the data left the old place
    state, f1, a, there = _remembered_off(-0.04)
    seen_where_it_is = np.asarray(a["seen_points"])
    seen_where_it_was = seen_where_it_is + [0.01, 0.0, 0.0]  # had it stood at -0.04
    modes = {}
    # the data there as it was; or (then) explained as well as at the right pose, and the
    # points seen of it then where it is (a view that could not see the error) or 10 mm off
    for case, seen, points in (
        ("as it was", (there.fit, there.residual), seen_where_it_was),
        ("seen where it is", (a["seen_fit"], a["seen_residual"]), seen_where_it_is),
        ("seen where it was", (a["seen_fit"], a["seen_residual"]), seen_where_it_was),
    ):
        a["seen_fit"], a["seen_residual"] = seen
        a["seen_points"] = points.tolist()
        est = SceneParser.from_state(LIB, state).update(f1)
        (o,) = [o for o in est.objects if o.id == a["id"]]
        assert abs(o.T_world_obj[0, 3] + 0.05) < 0.003  # where it is
        modes[case] = o
    assert modes["as it was"].mode == TransitionMode.STATIC, modes["as it was"].reason
    assert "static in the world, its estimate corrected by 10 mm" in modes["as it was"].reason
    o = modes["seen where it is"]
    assert o.mode == TransitionMode.STATIC, o.reason
    assert "explains the points seen of it before as well" in o.reason
    assert modes["seen where it was"].mode == TransitionMode.PERTURBED
    assert "static in the world" not in modes["seen where it was"].reason


@pytest.mark.parametrize("b_moved_in", ["no", "stays", "leaves"])
def test_an_object_static_in_the_world_keeps_its_pose_over_a_worse_estimate(
    monkeypatch, b_moved_in
):
    # issue 32's drift: a block at rest, its data where it stands as it was, and the frame's
    # search lands on a pose 6 mm / 15 deg off that explains less of its visible surface (made
    # here by a stage that moves its result there): the output keeps where it stood, unless
    # the cube's estimate now lies where the block stood (kept, the block would be inside it);
    # a cube the frame removes does not count (it is still in the frame's world)
    rng = np.random.default_rng(3)
    right = on_table(BLOCK, x=-0.05, yaw_deg=10)
    wrong = on_table(BLOCK, x=-0.044, y=0.003, yaw_deg=25)
    gt = {"a": ("block", right), "b": ("cube", on_table(CUBE, x=0.07))}
    parser = SceneParser(LIB)
    for k in range(3):  # at rest: static in the frames before
        parser.update(frame(gt, rng, stamp=float(k)))

    def drift(ctx):
        ids = ctx.scene_score.ids
        (i,) = [i for i, oid in enumerate(ids) if ctx.models[oid] is BLOCK]
        oid = ids[i]
        ctx.scene_score.poses[i] = wrong
        ctx.sim.world.set_pose(oid, wrong)
        ctx.evidence[oid] = evidence(
            BLOCK, wrong, ctx.segment_trees.tree(oid), ctx.view, ctx.config,
            own_label=ctx.owner.get(oid),
        )  # fmt: skip
        if b_moved_in != "no":
            (j,) = [j for j, other in enumerate(ids) if ctx.models[other] is CUBE]
            ctx.sim.world.set_pose(ids[j], on_table(CUBE, x=-0.08))
            if b_moved_in == "leaves":
                ctx.gone.add(ids[j])

    stages = list(parser_module.STAGES)
    at = [s.name for s in stages].index("static fusion")
    monkeypatch.setattr(
        parser_module, "STAGES", (*stages[:at], Stage("drift", drift), *stages[at:])
    )
    gt1 = {"a": gt["a"], "b": ("cube", on_table(CUBE, x=0.09))}  # b moves: no shortcut
    est = parser.update(frame(gt1, rng, stamp=3.0))
    (o,) = [o for o in est.objects if o.class_name == "block"]
    if b_moved_in == "stays":
        assert np.allclose(o.T_world_obj, wrong, atol=1e-9), o.reason
        assert "kept where it was" not in o.reason
        return
    # kept, it is still at rest: the next frame keeps it again
    (then,) = [
        x for x in parser.update(frame(gt1, rng, stamp=4.0)).objects if x.class_name == "block"
    ]
    for kept in (o, then):
        dt, dr = pose_change(right, kept.T_world_obj, BLOCK.symmetry)
        assert dt < 0.001 and np.degrees(dr) < 1.0, kept.reason
        assert kept.mode == TransitionMode.STATIC
        assert "kept where it was" in kept.reason


@pytest.mark.parametrize("cls", ["cube", "block"])
def test_an_object_turned_or_slid_a_little_is_perturbed(cls):
    # turned 10 deg in place, most of its surface stays within the inlier radius of where it
    # was; slid 10 mm along its long side, its top and sides stay in their planes: the data
    # there changed all the same, and the mode says so
    model = LIB[cls]
    for after in (on_table(model, x=-0.05, yaw_deg=10), on_table(model, x=-0.04)):
        rng = np.random.default_rng(8)
        gt = {"a": (cls, on_table(model, x=-0.05)), "b": ("cube", on_table(CUBE, x=0.08))}
        parser = SceneParser(LIB)
        parser.update(frame(gt, rng))
        gt1 = {"a": (cls, after), "b": gt["b"]}
        est = parser.update(frame(gt1, rng, stamp=1.0))
        o = min(est.objects, key=lambda o: np.linalg.norm(o.T_world_obj[:2, 3] - after[:2, 3]))
        assert errors(est, gt1)["a"][1] < 2.0
        assert o.mode == TransitionMode.PERTURBED, o.reason


def _outputs(gt_frames, config):
    """Cube a's output position (m) in each frame of ``gt_frames`` (one parser)."""
    rng = np.random.default_rng(3)
    parser = SceneParser(LIB, config)
    out = []
    for t, gt in enumerate(gt_frames):
        est = parser.update(frame(gt, rng, stamp=float(t)))
        T = gt["a"][1]
        o = min(est.objects, key=lambda o: np.linalg.norm(o.T_world_obj[:3, 3] - T[:3, 3]))
        out.append(o.T_world_obj[:3, 3].copy())
    return np.array(out)


def test_a_static_objects_output_averages_its_estimates_and_a_small_push_is_followed():
    still = {"a": ("cube", on_table(CUBE, x=-0.05)), "b": ("cube", on_table(CUBE, x=0.06))}
    fused = _outputs([still] * 6, SSPConfig())
    raw = _outputs([still] * 6, SSPConfig(temporal={"static_fusion_frames": 1}))
    spread = lambda p: np.linalg.norm(p[1:] - p[1:].mean(0), axis=1).max()  # noqa: E731
    assert spread(fused) < spread(raw)
    # pushed 5 mm (within the static thresholds): the data where it was changed, so its
    # output goes where the data put it, not a mean with where it was
    pushed = {"a": ("cube", on_table(CUBE, x=-0.045)), "b": still["b"]}
    out = _outputs([still] * 4 + [pushed] * 2, SSPConfig())
    assert abs(out[4, 0] + 0.045) < 0.0015, out[:, 0]


def test_a_correction_the_data_prefer_is_not_averaged_with_the_wrong_pose():
    # the parser remembers cube a 5 mm off (within the static thresholds) and at rest there
    # for three frames; the frame shows it where it is: its estimate goes there, not to a
    # mean with the wrong pose (the data fit the new estimate better)
    state, f1, a, there = _remembered_off(-0.045)
    a.update(seen_fit=there.fit, seen_residual=there.residual, still=3)
    est = SceneParser.from_state(LIB, state).update(f1)
    (o,) = [o for o in est.objects if o.id == a["id"]]
    assert o.mode == TransitionMode.STATIC
    assert abs(o.T_world_obj[0, 3] + 0.05) < 0.0015, o.T_world_obj[0, 3]  # mean: -0.0488


def test_symmetric_cube_never_flips_between_frames():
    rng = np.random.default_rng(9)
    sym = CUBE.symmetry.discrete
    gt = {"c": ("cube", on_table(CUBE, yaw_deg=10))}
    parser = SceneParser(LIB)
    prev = None
    for t in range(4):
        f = frame(gt, rng, k=3, stamp=float(t))
        for h in f.hypotheses:  # the detector reports an arbitrary symmetric equivalent
            h.T_world_obj = h.T_world_obj @ sym[rng.integers(len(sym))]
        est = parser.update(f)
        R = est.objects[0].T_world_obj[:3, :3]
        if prev is not None:
            angle = np.degrees(Rotation.from_matrix(prev.T @ R).magnitude())
            assert angle < 3.0, (t, angle)
        prev = R


# ------------------------------------------------------------------------------ API


def _poses(est):
    return {o.id: o.T_world_obj for o in est.objects}


def test_same_input_twice_gives_identical_output():
    rng = np.random.default_rng(10)
    frames = [frame(tower(3), rng, stamp=float(t)) for t in range(2)]
    outs = []
    for _ in range(2):
        parser = SceneParser(LIB)
        outs.append([_poses(parser.update(f)) for f in frames])
    for a, b in zip(*outs, strict=True):
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])


def test_state_round_trip_resumes_identically():
    rng = np.random.default_rng(11)
    gt = {"a": ("cube", on_table(CUBE, x=-0.05)), "b": ("block", on_table(BLOCK, x=0.06))}
    f0, f1 = frame(gt, rng), frame(gt, rng, stamp=1.0, sr_deg=8.0, st=0.01)
    p1 = SceneParser(LIB)
    p1.update(f0)
    state = json.loads(json.dumps(p1.state()))
    p2 = SceneParser.from_state(LIB, state)
    assert p2.state() == p1.state()
    a, b = p1.update(f1), p2.update(f1)
    assert _poses(a).keys() == _poses(b).keys()
    for k in _poses(a):
        np.testing.assert_array_equal(_poses(a)[k], _poses(b)[k])


def test_bad_frame_is_rejected_and_the_state_is_untouched():
    rng = np.random.default_rng(12)
    gt = tower(2)
    parser = SceneParser(LIB)
    parser.update(frame(gt, rng))
    before = parser.state()
    bad = frame(gt, rng, stamp=1.0)
    bad.hypotheses[0] = Hypothesis("no_such_class", np.eye(4))
    with pytest.raises(FrameError, match="unknown object class"):
        parser.update(bad)
    empty = Frame(2.0, np.full((5, 3), np.nan), [])
    with pytest.raises(FrameError, match="empty cloud"):
        parser.update(empty)
    assert parser.state() == before
    results = list(parse_sequence(parser, [bad, frame(gt, rng, stamp=3.0)]))
    assert isinstance(results[0][1], FrameError)
    assert isinstance(results[1][1], SceneEstimate) and len(results[1][1]) == 2


def test_frames_out_of_time_order_are_rejected():
    rng = np.random.default_rng(13)
    parser = SceneParser(LIB)
    parser.update(frame(tower(1), rng, stamp=5.0))
    with pytest.raises(FrameError, match="earlier"):
        parser.update(frame(tower(1), rng, stamp=4.0))


def test_estimate_reports_terms_timings_and_json():
    rng = np.random.default_rng(14)
    est = SceneParser(LIB).update(frame(tower(2), rng))
    for stage in (
        "association",
        "segments",
        "world",
        "forces",
        "stepping",
        "contacts",
        "scoring",
        "total",
    ):
        assert est.timings[stage] >= 0.0, stage
    assert est.timings["total"] >= est.timings["stepping"]
    d = json.loads(json.dumps(est.to_dict()))
    assert len(d["objects"]) == 2 and d["objects"][0]["terms"].keys() == {
        "stability",
        "collision",
        "support",
        "data",
        "transition",
    }
    assert est.log_prob == pytest.approx(sum(o.log_prob for o in est.objects))
    assert est.hypotheses_tested >= 2 * 5


def test_from_state_rejects_bad_states():
    from ssp.errors import SSPError, UnknownObjectError

    with pytest.raises(SSPError, match="not an ssp scene state"):
        SceneParser.from_state(LIB, {"format": "x"})
    good = SceneParser(LIB).state()
    good["objects"] = [{"id": "z", "class": "nope", "T_world_obj": np.eye(4).tolist()}]
    with pytest.raises(UnknownObjectError):
        SceneParser.from_state(LIB, good)


def test_object_hidden_behind_a_new_tower_is_kept_as_ephemeral():
    rng = np.random.default_rng(15)
    a = {"a": ("cube", on_table(CUBE, x=0.06, y=0.07))}
    tower3 = {f"t{i}": ("cube", on_table(CUBE, x=0.009, y=0.008, level=i)) for i in range(3)}
    parser = SceneParser(LIB)
    est0 = parser.update(frame(a, rng, ids=True))
    gt1 = {**a, **tower3}  # a tower now stands between the camera and "a"
    est1 = parser.update(frame(gt1, rng, stamp=1.0, detect=set(tower3), ids=True))
    assert "a" in est1, [o.id for o in est1.removed]
    assert est1["a"].ephemeral and est1["a"].mode == TransitionMode.STATIC
    dt, _ = pose_change(est0["a"].T_world_obj, est1["a"].T_world_obj)
    assert dt < 0.002
    assert parser.state()["objects"][0]["ephemeral"] is True
    # the tower is taken away and "a" is seen again: no longer ephemeral
    est2 = parser.update(frame(a, rng, stamp=2.0, ids=True))
    assert not est2["a"].ephemeral and [o.id for o in est2.removed] == ["t0", "t1", "t2"]


@pytest.mark.parametrize("explained", [0.9, 1.0])
def test_wrong_class_hypotheses_on_an_undetected_objects_segment_are_a_duplicate(explained):
    """Only a block is proposed from the segment of a known cube that has not moved: the cube,
    where it was, explains the segment, so no block is added and the cube keeps its data.
    With the test disabled (1.0) the block is added beside the cube."""
    rng = np.random.default_rng(16)
    gt = {"a": ("cube", on_table(CUBE, x=-0.06)), "b": ("cube", on_table(CUBE, x=0.06))}
    cfg = SSPConfig(temporal={"explained_fraction": explained})
    parser = SceneParser(LIB, cfg)
    est0 = parser.update(frame(gt, rng))
    f = frame(gt, rng, stamp=1.0, detect={"b"})
    T_wrong = on_table(BLOCK, x=-0.07, yaw_deg=40)
    f.hypotheses = [*f.hypotheses, Hypothesis("block", T_wrong, 0.6, segment=0)]
    est1 = parser.update(f)
    cube_a = min(est0.objects, key=lambda o: o.T_world_obj[0, 3]).id
    if explained < 1:
        assert sorted(o.class_name for o in est1.objects) == ["cube", "cube"]
        assert est1[cube_a].mode == TransitionMode.STATIC and est1[cube_a].fit > 0.5
        dt, _ = pose_change(est0[cube_a].T_world_obj, est1[cube_a].T_world_obj)
        assert dt < 0.001
    else:
        assert "block" in [o.class_name for o in est1.objects]


def test_first_guess_is_the_previous_pose_when_any_hypothesis_agrees(lib):
    """A static object whose best hypothesis is wrong (its hidden part fits a standing pose)
    starts where it was when another hypothesis agrees; an object that moved starts at its best
    hypothesis; a new object too."""
    from ssp.config import TemporalConfig
    from ssp.first_guess import first_guess

    cfg = TemporalConfig()
    sym = lib["block"].symmetry
    T_prev = make_pose(t=[0.1, 0.0, 0.0125])
    standing = make_pose(Rotation.from_euler("y", 90, degrees=True).as_matrix(), [0.1, 0.0, 0.03])
    near = make_pose(Rotation.from_euler("z", 3, degrees=True).as_matrix(), [0.102, 0.0, 0.0125])
    moved = make_pose(t=[0.15, 0.0, 0.0125])
    hyps = [Hypothesis("block", standing, 0.9), Hypothesis("block", near, 0.4)]
    assert first_guess(hyps, T_prev, sym, cfg) is T_prev
    assert first_guess(hyps[:1], T_prev, sym, cfg) is standing
    assert first_guess([Hypothesis("block", moved, 0.9)], T_prev, sym, cfg) is moved
    assert first_guess(hyps, None, sym, cfg) is standing


def test_best_first_guess_weighs_the_previous_pose_with_the_hypotheses():
    from ssp.first_guess import best_first_guess

    T_prev, a, b = (make_pose(t=[x, 0.0, 0.0125]) for x in (0.0, 0.03, 0.06))
    hyps = [Hypothesis("block", a, 0.9), Hypothesis("block", b, 0.4)]
    by_x = {0.0: -1.0, 0.03: -3.0, 0.06: -2.0}

    def score(T):
        return by_x[round(float(T[0, 3]), 2)]

    assert best_first_guess(hyps, T_prev, score) is T_prev  # no hypothesis near it: still tested
    assert best_first_guess(hyps, None, score) is b
    assert best_first_guess(hyps, T_prev, lambda T: 0.0) is T_prev  # ties: the previous pose
    assert best_first_guess(hyps, None, lambda T: 0.0) is a
