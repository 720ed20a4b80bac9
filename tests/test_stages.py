"""SceneParser.update as a list of named stages (ssp.parser.STAGES over one FrameContext):
the list, the stages run by hand, and single stages on a context built for them."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.frame_context import FrameContext, Known
from ssp.geometry import make_pose
from ssp.library import ObjectLibrary
from ssp.parser import STAGES, SceneParser, run_stages
from ssp.retention import Triage, TriageState, triage_undetected
from ssp.scene import Hypothesis
from ssp.search import CandidateSource
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at
from ssp.temporal import Association, associate_frame

LIB = ObjectLibrary.builtin()
CUBE = LIB["cube"]
E = float(CUBE.extents[2])
CAMERA = look_at([-0.45, -0.55, 0.6], [0.0, 0.0, 0.03])


def on_table(x=0.0, y=0.0, level=0, yaw_deg=0.0):
    R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return make_pose(R, [x, y, E / 2 + level * E])


def scene_frame(gt, seed=0, stamp=0.0):
    return synthetic_frame(
        LIB, gt, T_world_cam=CAMERA, rng=np.random.default_rng(seed), k=3, stamp=stamp, stride=2
    )


def context(parser: SceneParser, frame) -> FrameContext:
    """The context the parser would build for ``frame``."""
    return parser.frame_context(frame.validate(LIB))


def test_the_stages_are_named_in_order_and_live_in_their_concepts_modules():
    names = [s.name for s in STAGES]
    assert names[:6] == [
        "depth correction",
        "association",
        "segments",
        "verification of the new",
        "triage of the undetected",
        "world",
    ]
    assert names[-1] == "outcome" and len(set(names)) == len(names)
    modules = {s.name: s.run.__module__ for s in STAGES}
    assert modules["depth correction"] == "ssp.correction"
    assert modules["association"] == "ssp.temporal"
    assert modules["search"] == "ssp.search"
    assert modules["support-retained"] == "ssp.retention"
    assert modules["polish"] == "ssp.polish"
    assert modules["outcome"] == "ssp.outcome"
    assert not any(m == "ssp.parser" for m in modules.values())
    # the search and the unchanged shortcut exclude each other
    when = {s.name: s.when for s in STAGES}
    assert when["search"] is not None and when["unchanged shortcut"] is not None


def test_running_the_stages_by_hand_gives_what_update_gives():
    gt = {"a": ("cube", on_table(-0.06)), "b": ("cube", on_table(0.06, yaw_deg=20))}
    frame = scene_frame(gt)
    by_update = SceneParser(LIB).update(frame)
    by_hand = SceneParser(LIB)
    ctx = context(by_hand, frame)
    run_stages(ctx, STAGES)
    assert ctx.estimate is not None
    assert [o.id for o in ctx.estimate.objects] == [o.id for o in by_update.objects]
    for a, b in zip(ctx.estimate.objects, by_update.objects, strict=True):
        assert np.array_equal(a.T_world_obj, b.T_world_obj)
        assert a.source == b.source and a.reason == b.reason
    assert set(ctx.next_known) == {o.id for o in by_update.objects}


def test_each_stage_fills_its_fields_and_the_shortcut_replaces_the_search():
    gt = {"a": ("cube", on_table())}
    parser = SceneParser(LIB)
    parser.update(scene_frame(gt, seed=1))
    ctx = context(parser, scene_frame(gt, seed=1, stamp=1.0))
    ran = []
    for stage in STAGES:
        if stage.when is None or stage.when(ctx):
            stage.run(ctx)
            ran.append(stage.name)
        if stage.name == "association":
            assert list(ctx.groups) == ["cube_0"] and set(ctx.first) == {"cube_0"}
        if stage.name == "segments":
            assert len(ctx.segments["cube_0"]) > 50 and ctx.view is not None
        if stage.name == "world":
            assert list(ctx.sim.world.ids) == ["cube_0"] and ctx.sim.with_data == {"cube_0"}
    # the same cube with the same data: nothing changed, so no search
    assert ctx.unchanged and "unchanged shortcut" in ran and "search" not in ran
    assert ctx.chosen == {"cube_0": CandidateSource.UNCHANGED}
    assert ctx.estimate is not None and ctx.estimate.unchanged


def test_triage_on_its_own_removes_a_replaced_object_and_keeps_a_claimed_one():
    parser = SceneParser(LIB)
    ctx = context(parser, scene_frame({"n": ("cube", on_table(0.1))}))
    # two remembered cubes: one where the frame's cube now is, one whose segment was claimed
    ctx.known = {"old": Known("cube", on_table(0.1)), "seen": Known("cube", on_table(-0.1))}
    T_new = on_table(0.1)
    ctx.association = Association({"cube_9": []}, {}, {"seen": 3}, {}, {})
    ctx.groups = {"cube_9": [Hypothesis("cube", T_new)]}
    ctx.models = {oid: CUBE for oid in ("old", "seen", "cube_9")}
    ctx.prev_pose = {oid: k.T_world_obj for oid, k in ctx.known.items()}
    ctx.first = {"cube_9": T_new}
    ctx.segments = {"old": np.zeros((0, 3)), "seen": np.zeros((0, 3)), "cube_9": np.zeros((0, 3))}
    triage_undetected(ctx)
    assert ctx.missing == ["old", "seen"]
    assert ctx.verdicts["old"].state == TriageState.REPLACED
    assert ctx.verdicts["seen"] == Triage(
        TriageState.VISIBLE, "undetected; its segment's points lie on it"
    )
    assert ctx.removed == {"old"}


def test_association_on_its_own_counts_ids_on_from_the_parsers_counters():
    parser = SceneParser(LIB)
    ctx = context(parser, scene_frame({"a": ("cube", on_table())}))
    ctx.counters = {"cube": 7}
    associate_frame(ctx)
    assert list(ctx.groups) == ["cube_7"]
    assert ctx.assoc.counters == {"cube": 8}
    assert ctx.classes == {"cube_7": "cube"} and ctx.models["cube_7"] is CUBE
