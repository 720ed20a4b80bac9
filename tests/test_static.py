"""Static objects across frames (ssp.static): which objects the search leaves where they were."""

from __future__ import annotations

import numpy as np

from ssp.config import SSPConfig
from ssp.geometry import make_pose
from ssp.library import ObjectLibrary
from ssp.parser import SceneParser
from ssp.scene import TransitionMode
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
