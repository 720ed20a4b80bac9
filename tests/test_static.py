"""Static objects across frames (ssp.static): which objects the search leaves where they were."""

from __future__ import annotations

import numpy as np

from ssp.config import SSPConfig
from ssp.geometry import make_pose
from ssp.library import ObjectLibrary
from ssp.parser import SceneParser
from ssp.scene import Frame, Hypothesis, TransitionMode
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at
from ssp.static import settled_objects

LIB = ObjectLibrary.builtin()
CUBE = LIB["cube"]
CAM = look_at([-0.45, -0.55, 0.6], [0.0, 0.0, 0.03])


def on_table(x: float, y: float = 0.0) -> np.ndarray:
    return make_pose(np.eye(3), [x, y, -float(CUBE.mesh.bounds[0, 2])])


def test_only_unchanged_objects_far_from_every_change_are_settled():
    models = {k: CUBE for k in "abcd"}
    poses = {
        "a": [on_table(0.0)],
        "b": [on_table(0.2)],
        "c": [on_table(0.05)],  # 9 mm beside the moving object's box (cubes 5 cm)
        "d": [on_table(0.11), on_table(0.12)],  # moving: two candidates
    }
    assert settled_objects({"a", "b", "c"}, poses, models, reach=0.02) == {"a", "b"}
    assert settled_objects({"a", "b", "c"}, poses, models, reach=0.005) == {"a", "b", "c"}
    assert settled_objects(set(), poses, models, reach=0.02) == set()
    assert settled_objects(set("abcd"), poses, models, reach=0.02) == set("abcd")


def _frames(gt_seq, seed=3):
    rng = np.random.default_rng(seed)
    return [
        synthetic_frame(LIB, gt, T_world_cam=CAM, rng=rng, k=5, stamp=float(t))
        for t, gt in enumerate(gt_seq)
    ]


def test_a_change_tests_only_the_objects_near_it():
    far = {"a": ("cube", on_table(-0.12)), "b": ("cube", on_table(0.0, 0.12))}
    gt0 = {**far, "c": ("cube", on_table(0.1))}
    gt1 = {**far, "c": ("cube", on_table(0.12))}  # c slides 2 cm
    frames = _frames([gt0, gt1])
    parser = SceneParser(LIB)
    parser.update(frames[0])
    est = parser.update(frames[1])
    assert not est.unchanged
    by_id = {o.id: o for o in est.objects}
    settled = [o for o in est.objects if o.source == "previous (settled)"]
    assert len(settled) == 2 and len(est.objects) == 3
    moved = next(o for o in est.objects if o not in settled)
    assert moved.mode == TransitionMode.PERTURBED
    assert abs(moved.T_world_obj[0, 3] - 0.12) < 0.003
    assert all(o.mode == TransitionMode.STATIC for o in settled)
    # testing every object again gives the same scene within a fraction of a millimetre
    cfg = SSPConfig()
    cfg.search.skip_settled = False
    cfg.search.retest_static = True
    full = SceneParser(LIB, cfg)
    full.update(frames[0])
    ref = full.update(frames[1])
    assert ref.hypotheses_tested > est.hypotheses_tested
    for o in ref.objects:
        assert np.linalg.norm(o.T_world_obj[:3, 3] - by_id[o.id].T_world_obj[:3, 3]) < 5e-4


def test_a_settled_object_that_the_settle_moves_is_searched_after_all():
    from ssp.static import settle_moved

    T = on_table(0.0)
    sunk = T.copy()
    sunk[2, 3] -= 0.002  # 2 mm: what held it up is gone
    turned = T @ make_pose(
        np.array([[1.0, 0.0, 0.0], [0.0, 0.999, -0.0447], [0.0, 0.0447, 0.999]])
    )  # about 2.6 deg about x
    crept = T.copy()
    crept[0, 3] += 0.0002
    objects = {"sunk": (T, sunk, CUBE), "turned": (T, turned, CUBE), "crept": (T, crept, CUBE)}
    assert settle_moved(objects) == {"sunk", "turned"}


# ------------------------------------------------------------------ what counts as unchanged
BLOCK = LIB["block"]


def _other(T: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``T`` turned 90 deg about the vertical and moved by ``(dx, dy)`` (m): another
    orientation of a block."""
    U = T.copy()
    U[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
    U[0, 3] += dx
    U[1, 3] += dy
    return U


def _estimator_frame(gt, rng, stamp, *, ranked=True, extra=()):
    """A rendered frame of ``gt`` whose hypotheses are an estimator's: per object (its instance
    segment) the best pose first, 1 mm off, then three other orientations 4 cm away (what a
    partial view allows too); ``ranked``: their scores say which is best (else all
    1). ``extra``: further hypotheses."""
    f = synthetic_frame(LIB, gt, T_world_cam=CAM, rng=rng, k=1, stamp=stamp, sigma_t=0.001,
                        sigma_r_deg=0.5)  # fmt: skip
    hyps = []
    for label, (oid, (cls, _)) in enumerate(gt.items()):
        best = next(h for h in f.hypotheses if h.class_name == cls and _near(h, gt[oid][1]))
        others = [_other(best.T_world_obj, *d) for d in ((0.04, 0), (0, 0.04), (0.04, 0.04))]
        scores = (1.0, 0.6, 0.5, 0.4) if ranked else (1.0,) * 4
        poses = [best.T_world_obj, *others]
        hyps += [Hypothesis(cls, T, s, segment=label) for T, s in zip(poses, scores, strict=True)]
    f.hypotheses = [*hyps, *extra]
    return f


def _near(h, T, tol=0.01):
    return float(np.linalg.norm(h.T_world_obj[:3, 3] - T[:3, 3])) < tol


def test_an_estimators_best_pose_where_the_object_was_is_no_change():
    """A static scene seen again: an estimator's best pose of each object where it was, beside
    the other orientations it also proposes (whose median is anywhere), is no change (the frame
    takes the unchanged shortcut); unranked, the same poses are not (noisy copies of one pose
    would agree in the median); an object moved 15 mm whose best pose says so is a change."""
    lying = -float(BLOCK.mesh.bounds[0, 2])
    gt = {
        "a": ("block", make_pose(t=[-0.08, 0, lying])),
        "b": ("block", make_pose(t=[0.08, 0, lying])),
    }
    for ranked, unchanged in ((True, True), (False, False)):
        rng = np.random.default_rng(5)
        parser = SceneParser(LIB)
        parser.update(_estimator_frame(gt, rng, 0.0, ranked=ranked))
        est = parser.update(_estimator_frame(gt, rng, 1.0, ranked=ranked))
        assert est.unchanged is unchanged
        assert all(o.mode == TransitionMode.STATIC for o in est.objects)
    moved = {**gt, "a": ("block", make_pose(t=[-0.065, 0, lying]))}
    est = parser.update(_estimator_frame(moved, rng, 2.0))
    assert not est.unchanged
    a = min(est.objects, key=lambda o: o.T_world_obj[0, 3])
    assert a.mode == TransitionMode.PERTURBED and abs(a.T_world_obj[0, 3] + 0.065) < 0.003


def _block_on(T_cube: np.ndarray, rng) -> np.ndarray:
    """A block's pose on the upper front quarter of a cube at ``T_cube``: its visible faces
    lie on the cube's, a few millimetres off at random (an estimator's pose of a thing it
    does not know)."""
    T = T_cube.copy()
    T[1, 3] -= 0.0127
    T[2, 3] += 0.0127
    T[:2, 3] += rng.uniform(-0.004, 0.004, 2)
    return T


def test_a_thing_rejected_frame_after_frame_is_no_change():
    """A cube that an estimator takes for a block (the block explains only part of the
    cube's segment: rejected) is rejected again in the next frames without a search: the
    frame is unchanged, the rejection says it is repeated, and a parser resumed from the
    state does the same. When a block really lies there, it is found."""
    from ssp.static import REPEATED

    known = {"a": ("block", make_pose(t=[-0.08, 0, -float(BLOCK.mesh.bounds[0, 2])]))}
    thing = ("cube", on_table(0.08))
    gt = {**known, "d": thing}  # "d": rendered, never proposed as what it is
    rng = np.random.default_rng(7)

    def frame(stamp, scene=gt, T_block=None):
        T = _block_on(thing[1], rng) if T_block is None else T_block
        block = Hypothesis("block", T, 0.7, segment=1)
        f = _estimator_frame(known, rng, stamp)  # hypotheses of "a" (segment 0)
        g = synthetic_frame(LIB, scene, T_world_cam=CAM, rng=rng, k=1, stamp=stamp)
        return Frame(stamp, g.points, [*f.hypotheses, block], labels=g.labels,
                     T_world_cam=g.T_world_cam)  # fmt: skip

    parser = SceneParser(LIB)
    est0 = parser.update(frame(0.0))
    assert [o.class_name for o in est0.objects] == ["block"] and not est0.unchanged
    assert [r.class_name for r in est0.rejected] == ["block"]
    assert not est0.rejected[0].reason.endswith(REPEATED)
    state = parser.state()
    assert [r["class"] for r in state["rejected"]] == ["block"]
    f1 = frame(1.0)
    for p in (parser, SceneParser.from_state(LIB, state)):
        est1 = p.update(f1)
        assert est1.unchanged, est1.rejected
        assert [o.class_name for o in est1.objects] == ["block"]
        assert [r.class_name for r in est1.rejected] == ["block"]
        assert est1.rejected[0].reason.endswith(REPEATED)
    # without the memory the same frame is searched
    fresh = dict(state, rejected=[])
    assert not SceneParser.from_state(LIB, fresh).update(f1).unchanged
    # a block where the estimator says: found
    T_real = _block_on(thing[1], rng)
    T_real[2, 3] = -float(BLOCK.mesh.bounds[0, 2])  # on the table
    est2 = parser.update(frame(2.0, {**known, "d": ("block", T_real)}, T_real))
    assert not est2.unchanged
    assert sorted(o.class_name for o in est2.objects) == ["block", "block"]
