"""Issue 15 on the scene parser: verification, undetected objects, moved objects, reasons.

Each test is a failure class measured on real captures (issue 15, items 3-7 and the tower's
ghost), rebuilt on rendered frames; each fails on the parser before these changes.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ssp.geometry import make_pose
from ssp.library.build import build_model
from ssp.library.library import ObjectLibrary
from ssp.parser import SceneParser
from ssp.probability import pose_change
from ssp.scene import Hypothesis, TransitionMode
from ssp.sim.frames import synthetic_frame
from test_parser import CAMERA, CUBE, LIB, E, frame, on_table


def test_a_missed_detection_keeps_a_cube_in_full_view():
    """Item 5: the still-visible test scores the visible surface (a cube in full view scored
    0.37-0.55 over its whole surface against 0.5, and was removed and re-added)."""
    rng = np.random.default_rng(1)
    gt = {"a": ("cube", on_table(CUBE, 0.02, 0.0, yaw_deg=30))}
    parser = SceneParser(LIB)
    parser.update(frame(gt, rng))
    est = parser.update(frame(gt, rng, stamp=1.0, detect=set()))  # no hypothesis this frame
    assert est.ids == ("cube_0",) and not est.removed
    assert est["cube_0"].mode == TransitionMode.STATIC
    assert "still visible" in est["cube_0"].reason
    est = parser.update(frame(gt, rng, stamp=2.0))
    assert est.ids == ("cube_0",)  # the same id when it is detected again


def test_a_hidden_undetected_bottom_cube_holds_up_the_one_on_it():
    """Item 6: the support test reads the contact forces: without the bottom cube the top one
    would fall at g (a 0.1 s quasi-static settle let it fall 4.9 mm, under the 7.5 mm
    threshold, so the bottom cube was removed and the top one left in mid-air)."""
    rng = np.random.default_rng(2)
    gt = {"b": ("cube", on_table(CUBE)), "t": ("cube", on_table(CUBE, level=1))}
    parser = SceneParser(LIB)
    est0 = parser.update(frame(gt, rng, ids=True))
    assert set(est0.ids) == {"b", "t"}
    # the bottom cube gives no points (sensor dropout) and no hypothesis: no data either way
    est = parser.update(frame(gt, rng, stamp=1.0, detect={"t"}, hidden={"b"}, ids=True))
    assert "b" in est and est["b"].mode == TransitionMode.SUPPORT_RETAINED
    assert "holds up t" in est["b"].reason
    assert abs(est["t"].T_world_obj[2, 3] - 1.5 * E) < 0.003  # not left in mid-air


def test_false_objects_far_away_or_floating_are_rejected_with_reasons():
    """Item 3: a hypothesis 5 m above the table or 30 m away was added with fit 0."""
    rng = np.random.default_rng(3)
    gt = {"a": ("cube", on_table(CUBE))}
    f = frame(gt, rng)
    f.hypotheses += [
        Hypothesis("cube", make_pose(t=[0.0, 0.0, 5.0]), 0.9),
        Hypothesis("cube", make_pose(t=[30.0, 0.0, 0.0254]), 0.9),
        Hypothesis("block", make_pose(t=[0.1, 0.05, 0.3]), 0.95),  # floating in view
    ]
    est = SceneParser(LIB).update(f)
    assert [o.class_name for o in est.objects] == ["cube"]
    assert len(est.rejected) == 3
    reasons = " ".join(r.reason for r in est.rejected)
    assert "not in the camera's view" in reasons and "seen empty" in reasons
    assert all(r.evidence for r in est.rejected)


def test_every_segment_gets_a_verdict():
    rng = np.random.default_rng(4)
    gt = {"a": ("cube", on_table(CUBE)), "b": ("block", on_table(LIB["block"], 0.1, 0.0))}
    f = frame(gt, rng, detect={"a"})  # the block's segment gets no hypothesis
    est = SceneParser(LIB).update(f)
    assert est.segments == {
        0: f"object {est.ids[0]}",
        1: "no object: no hypothesis was given for it",
    }
    assert est.to_dict()["segments"]["1"].startswith("no object")


def test_a_picked_and_placed_cube_keeps_its_id_and_leaves_no_ghost():
    """The tower's ghost: a cube picked and put down 24 cm away stayed at its old place (its
    volume plainly empty in the depth) beside its new estimate."""
    rng = np.random.default_rng(5)
    before = {"a": ("cube", on_table(CUBE, -0.12, 0.0)), "c": ("cube", on_table(CUBE, 0.05, 0.1))}
    after = {"a": ("cube", on_table(CUBE, 0.12, 0.0)), "c": before["c"]}
    parser = SceneParser(LIB)
    est0 = parser.update(frame(before, rng))
    old = min(est0.objects, key=lambda o: o.T_world_obj[0, 3]).id  # the cube at x = -0.12
    est = parser.update(frame(after, rng, stamp=1.0))
    assert len(est.objects) == 2 and not est.removed  # no ghost, nothing lost
    moved = est[old]
    assert abs(moved.T_world_obj[0, 3] - 0.12) < 0.005
    assert moved.mode == TransitionMode.PERTURBED and "re-identified" in moved.reason


def test_association_and_gates_are_measured_at_the_centre_of_mass():
    """Item 7: association and its gates measured distances between model origins; a mesh
    whose origin lies 95 mm from its body, turned 30 degrees in place, moved its origin by
    49 mm, beyond the gate: a new object every time it turned."""
    import trimesh

    from ssp.config import SSPConfig

    mesh = trimesh.creation.box([0.06, 0.04, 0.03])
    mesh.apply_translation([0.095, 0.0, 0.015])  # the model origin far outside the body
    off = build_model("offbox", mesh, config=SSPConfig().library, density=600.0,
                      convex_parts=[mesh])  # fmt: skip
    lib = ObjectLibrary([off, CUBE])
    c = off.center_of_mass
    a = np.radians(30.0)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    turned = np.eye(4)
    turned[:3, :3] = R
    turned[:3, 3] = c - R @ c  # turned about the body's centre
    parser = SceneParser(lib)
    ids = []
    for i, T in enumerate((np.eye(4), turned)):
        f = synthetic_frame(lib, {"o": ("offbox", T)}, T_world_cam=CAMERA, stamp=float(i),
                            rng=np.random.default_rng(6 + i), k=3, stride=2)  # fmt: skip
        est = parser.update(f)
        assert len(est.objects) == 1, [o.id for o in est.objects]
        ids.append(est.objects[0].id)
        dt, dth = pose_change(T, est.objects[0].T_world_obj, None, c)
        assert dt < 0.004 and np.degrees(dth) < 4.0
    assert ids[0] == ids[1] and not est.removed
    assert "re-identified" not in est.objects[0].reason  # associated, not found again


def test_an_object_that_would_fall_is_reported():
    """Item 4: a physically impossible output is no longer returned silently. The data shows a
    cube 3 cm above the table and the windows that would let it drop are off: the parser
    keeps it where its strong data puts it, and says that it would fall."""
    rng = np.random.default_rng(7)
    resting = SceneParser(LIB).update(frame({"a": ("cube", on_table(CUBE))}, rng))
    assert not resting.warnings  # a cube resting on the table: nothing to say
    cfg = SceneParser(LIB).config.model_copy(deep=True)
    cfg.forces.final_icp = False
    cfg.search.settle_without_forces = 0.0
    cfg.search.final_settle = 0.0
    high = {"a": ("cube", on_table(CUBE, z_extra=0.03))}
    est = SceneParser(LIB, cfg).update(frame(high, rng))
    assert len(est.objects) == 1 and est.objects[0].terms.stability < -5.0
    assert any("would fall" in w for w in est.warnings), est.warnings


def test_the_search_does_not_move_an_object_off_strong_data():
    """Item 4, no worse than the evidence: a cube held 3 cm above the table by something not
    in the scene (a gripper) is where its data says, not on the table where physics alone
    would put it; the estimate says what happened."""
    rng = np.random.default_rng(8)
    held = {"a": ("cube", on_table(CUBE, z_extra=0.03))}
    est = SceneParser(LIB).update(frame(held, rng))
    (obj,) = est.objects
    assert abs(obj.T_world_obj[2, 3] - held["a"][1][2, 3]) < 0.003
    assert any("off its data" in w for w in est.warnings), est.warnings


def test_a_known_object_the_depth_contradicts_hands_its_id_to_the_new_one_beside_it():
    """A static object's id switched when the estimator's hypotheses of it (wrong, kept by
    association) held the known object in empty space while its true place got a new id."""
    rng = np.random.default_rng(9)
    A = on_table(CUBE, 0.0, 0.0)
    B = on_table(CUBE, 0.07, 0.0)  # where it really is in the second frame: beyond the gate
    parser = SceneParser(LIB)
    (old,) = parser.update(frame({"a": ("cube", A)}, rng)).ids
    f = frame({"a": ("cube", B)}, rng, stamp=1.0)
    wrong = on_table(CUBE, 0.008, 0.0)  # hypotheses that keep the known cube near A
    f.hypotheses = [Hypothesis("cube", wrong, 0.95), *f.hypotheses]
    est = parser.update(f)
    near_b = [o for o in est.objects if np.linalg.norm(o.T_world_obj[:2, 3] - B[:2, 3]) < 0.01]
    assert len(near_b) == 1 and near_b[0].id == old, [(o.id, o.reason) for o in est.objects]
    assert all(np.linalg.norm(o.T_world_obj[:2, 3] - A[:2, 3]) > 0.02 for o in est.objects)


def test_a_concave_object_in_full_view_explains_what_the_camera_can_see():
    """Item 5 for concave models: the node's socket walls behind its rim, and a clamp's inner
    jaw, are hidden by the object itself; the fit counts only what the camera could see (the
    node at its true pose scored 0.73, so a pose a few mm off fell below the 0.5 of
    ``temporal.visible_fit`` and a missed detection removed a clamp in full view)."""
    from ssp.config import SSPConfig
    from ssp.verification import evidence
    from ssp.visibility import CameraView

    cfg = SSPConfig()
    node = LIB["node"]
    gt = {"n": ("node", on_table(node))}
    f = frame(gt, np.random.default_rng(5), ids=True)
    view = CameraView(f.points, f.T_world_cam, labels=f.labels, depth_tolerance=0.005)
    own = int(np.bincount(f.labels[f.labels >= 0]).argmax())
    ev = evidence(node, gt["n"][1], f.points[f.labels == own], view, cfg, own_label=own)
    assert ev.fit >= 0.85


def test_a_false_object_seen_through_is_rejected_though_something_rests_on_it():
    """A cube hypothesis on an undetected block under a cube (a false positive on an object the
    estimator does not know) holds the top cube up in the simulation; the camera sees through
    31 % of its volume. It was kept ("unverified ... but holds up t") for as long as the top
    cube stayed: one false object in 24 frames on the realistic stream, seed 1002."""
    T_top = on_table(CUBE)
    T_top[2, 3] += float(LIB["block"].extents[2])
    gt = {"b": ("block", on_table(LIB["block"], yaw_deg=90)), "t": ("cube", T_top)}
    f = frame(gt, np.random.default_rng(4), ids=True, detect={"t"})
    f.hypotheses += [Hypothesis("cube", on_table(CUBE), 0.9, instance_id="b")]
    est = SceneParser(LIB).update(f)
    assert est.ids == ("t",)
    (rej,) = est.rejected
    assert rej.id == "b" and "seen empty" in rej.reason and "rests on it, t" in rej.reason


def test_an_object_the_robot_moved_keeps_its_id_where_it_was_put():
    """Frame.moved: the robot that picked a cube from where the camera cannot see (behind a
    tower: the ghost of the tower's seed 2000, trial 2) says where it put it; the parser takes
    that as the cube's previous pose (one cube, its id, ``perturbed``), and one that left the
    scene is removed with the reason. An unknown id is a FrameError that leaves the state."""
    from ssp.scene import FrameError

    rng = np.random.default_rng(6)
    parser = SceneParser(LIB)
    parser.update(frame({"a": ("cube", on_table(CUBE, 0.1, 0.1))}, rng))
    T_b = on_table(CUBE, -0.1, -0.05, yaw_deg=20)
    f = frame({"a": ("cube", T_b)}, rng, stamp=1.0)
    bad = replace(f, moved={"cube_9": T_b})
    with pytest.raises(FrameError, match="cube_9"):
        parser.update(bad)
    f.moved = {"cube_0": T_b}
    est = parser.update(f)
    assert est.ids == ("cube_0",) and not est.removed
    assert est["cube_0"].mode == TransitionMode.PERTURBED and "Frame.moved" in est["cube_0"].reason
    assert pose_change(est["cube_0"].T_world_obj, T_b, CUBE.symmetry)[0] < 0.005
    f = frame({"a": ("cube", T_b)}, rng, stamp=2.0, detect=set(), hidden={"a"})
    f.moved = {"cube_0": None}  # in the gripper
    est = parser.update(f)
    assert est.ids == () and [r.id for r in est.removed] == ["cube_0"]
    assert "left the scene" in est.removed[0].reason


def test_a_cluster_of_touching_objects_is_not_judged_as_one_instance():
    """Without instance masks, touching objects are one cluster: each object accounts for a
    part of it only. Judged as instance segments (``explained`` < 85 %), both were rejected;
    as a cluster, both are kept and the cluster's verdict names them both."""
    rng = np.random.default_rng(11)
    gt = {"a": ("cube", on_table(CUBE)), "b": ("cube", on_table(CUBE, 2 * E + 0.0005, 0.0))}
    f = frame(gt, rng)
    cluster = np.where(f.labels >= 0, 0, f.labels)  # the two cubes' points are one label
    as_instance = SceneParser(LIB).update(replace(f, labels=cluster))
    assert len(as_instance.objects) < 2  # the failure: judged against the whole cluster
    est = SceneParser(LIB).update(replace(f, labels=cluster, label_kind="cluster"))
    assert len(est.objects) == 2 and not est.rejected
    assert est.segments == {0: "objects " + ", ".join(sorted(est.ids))}
    for o in est.objects:
        T = min(
            (T for _, T in gt.values()),
            key=lambda T: np.linalg.norm(T[:3, 3] - o.T_world_obj[:3, 3]),
        )
        assert np.linalg.norm(o.T_world_obj[:3, 3] - T[:3, 3]) < 0.003


def test_label_kind_is_checked():
    from ssp.scene import Frame, FrameError

    f = Frame(0.0, np.zeros((5, 3)) + [0, 0, 0.01], label_kind="instances")
    with pytest.raises(FrameError, match="label_kind"):
        f.validate(LIB)


def test_an_object_kept_at_its_hypothesis_is_not_put_into_another(monkeypatch):
    """Step 8 keeps a new object whose searched pose fails at a hypothesis that passes; two
    such objects (a duplicate in a cluster of touching boxes, real captures) were both put at
    one place, 1262 deep in each other. Without its own instance segment the second is now
    judged where the search put it; with one, it stays, with the doubt in its reason."""
    import ssp.verification as verification_mod
    from ssp.verification import Verdict

    rng = np.random.default_rng(12)
    gt = {"a": ("cube", on_table(CUBE)), "b": ("cube", on_table(CUBE, 3 * E, 0.0))}
    f = frame(gt, rng, ids=True)
    real = verification_mod.verify_final

    def at_a(model, T_final, hypotheses, *args, **kw):
        v = real(model, T_final, hypotheses, *args, **kw)
        return Verdict(True, "kept at its hypothesis", v.evidence, gt["a"][1].copy(),
                       Verdict(False, "its search failed", v.evidence))  # fmt: skip

    monkeypatch.setattr(verification_mod, "verify_final", at_a)
    clusters = replace(f, labels=np.where(f.labels >= 0, 0, f.labels), label_kind="cluster")
    est = SceneParser(LIB).update(clusters)
    kept = [o for o in est.objects if np.allclose(o.T_world_obj, gt["a"][1])]
    assert len(kept) == 1  # one of them at the shared hypothesis, not both
    others = [o for o in est.objects if o is not kept[0]] + list(est.rejected)
    assert len(others) == 1
    (other,) = others
    assert "inside another object" in other.reason and "its search failed" in other.reason
    # each with its own instance segment: both stay, the second with the doubt said
    est = SceneParser(LIB).update(f)
    assert len(est.objects) == 2 and not est.rejected
    doubt = [o for o in est.objects if "inside another object" in o.reason]
    assert len(doubt) == 1 and doubt[0].terms.collision < -1.0
    assert any("inside another object" in w for w in est.warnings)


def test_the_output_terms_leave_out_the_rejected_objects():
    """A false cube 1 cm beside a true one is rejected (seen empty); the true cube, kept at
    its hypothesis, reported a collision term of -1860 and a support fraction of 12.9 from the
    rejected cube, which was still in the scored scene."""
    rng = np.random.default_rng(3)
    gt = {"a": ("cube", on_table(CUBE))}
    f = frame(gt, rng, ids=True)
    T = on_table(CUBE).copy()
    T[0, 3] += 0.01
    f.hypotheses += [Hypothesis("cube", T, 0.95, instance_id="x")]
    est = SceneParser(LIB).update(f)
    assert est.ids == ("a",) and [r.id for r in est.rejected] == ["x"]
    assert est["a"].terms.collision > -1.0
    (edge,) = est.support
    assert edge.supported == "a" and edge.fraction < 1.5
