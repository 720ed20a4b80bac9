"""What the data says under an object the physics says would fall (ssp.holders): whether
something undetected could hold it up. Rendered depth (no noise) with instance labels, seen
from above as a wrist camera sees a table."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.config import SSPConfig
from ssp.geometry import make_pose
from ssp.holders import REMEMBERED, nothing_holds, reaches_below, seen_under, under_column
from ssp.library.library import ObjectLibrary
from ssp.sim.distractors import distractor_models
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at
from ssp.visibility import CameraView

LIB = ObjectLibrary.builtin()
CFG = SSPConfig()
CUBE = LIB["cube"]
MODELS = {"cube": CUBE, "can": distractor_models()["distractor_can"]}
HALF = float(CUBE.extents[2]) / 2
LIMIT = CFG.verification.fallback_below


def _seen(gt: dict, elevation_deg: float) -> tuple[CameraView, dict]:
    """The view of ``gt`` from 0.9 m at ``elevation_deg`` and each object's points."""
    e = np.radians(elevation_deg)
    cam = look_at([-0.9 * np.cos(e), -0.2 * np.cos(e), 0.9 * np.sin(e)], [0.0, 0.0, 0.05])
    f = synthetic_frame(MODELS, gt, T_world_cam=cam, rng=0, k=0, noise=False, stride=1)
    view = CameraView(f.points, cam, labels=f.labels, depth_tolerance=0.005)
    return view, {oid: f.points[f.labels == k] for k, oid in enumerate(gt)}


@pytest.mark.parametrize("elevation", [45.0, 65.0])
def test_a_cube_fitted_to_a_cans_top_has_nothing_under_it_but_the_can(elevation):
    """The wrist tower's ghosts (development seeds 15 and 16): a cube proposed on a can, slid
    onto its top, explains the can's segment; the rays under the cube meet the can's side: the
    same instance, not a holder. The parser's segment of the cube holds only the can's points
    near the cube, where the share below it says nothing."""
    view, pts = _seen({"can": ("can", make_pose(t=[0.0, 0.0, 0.06]))}, elevation)
    T_top = make_pose(t=[0.0, 0.0, 0.12 - HALF])
    rays, unheld = seen_under(CUBE, T_top, view, 0)
    assert rays >= 10 and unheld / rays > 0.9, (rays, unheld)
    near = pts["can"][pts["can"][:, 2] > 0.12 - 2 * HALF - 0.012]  # its top and upper side
    assert reaches_below(CUBE, T_top, near) <= LIMIT
    why = nothing_holds(CUBE, T_top, near, view, 0, LIMIT)
    assert why is not None and why.startswith("the camera sees its own segment under it"), why
    assert nothing_holds(CUBE, T_top, near, view, None, LIMIT) is None  # no mask, no ruling


def test_seen_from_above_the_ruling_of_an_earlier_frame_stands():
    """Straight from above nothing under the cube is seen (its own top hides the column): the
    ruling of the frame before, at the same spot, stands; farther than ``near`` it does not;
    carried on, it is not nested."""
    view, pts = _seen({"can": ("can", make_pose(t=[0.0, 0.0, 0.06]))}, 89.0)
    T_top = make_pose(t=[0.0, 0.0, 0.12 - HALF])
    assert seen_under(CUBE, T_top, view, 0)[0] < 10
    seg = pts["can"]
    assert nothing_holds(CUBE, T_top, seg, view, 0, LIMIT) is None
    fallen = make_pose(t=[0.01, 0.0, HALF + 0.01])  # where the search let it fall
    ruled = [(fallen, "the camera sees its own segment under it: ...")]
    why = nothing_holds(CUBE, T_top, seg, view, 0, LIMIT, ruled, 0.05)
    assert why == f"{REMEMBERED} (the camera sees its own segment under it: ...)"
    assert nothing_holds(CUBE, T_top, seg, view, 0, LIMIT, [(fallen, why)], 0.05) == why
    far = [(make_pose(t=[0.1, 0.0, 0.095]), ruled[0][1])]
    assert nothing_holds(CUBE, T_top, seg, view, 0, LIMIT, far, 0.05) is None


def test_a_cube_on_an_undetected_cube_may_be_held():
    """The case strong data keeps: the cube below has its own instance (another label)."""
    lower, upper = make_pose(t=[0.0, 0.0, HALF]), make_pose(t=[0.0, 0.0, 3 * HALF])
    view, pts = _seen({"up": ("cube", upper), "low": ("cube", lower)}, 50.0)
    rays, unheld = seen_under(CUBE, upper, view, 0)
    assert rays >= 10 and unheld < 0.1 * rays, (rays, unheld)
    assert nothing_holds(CUBE, upper, pts["up"], view, 0, LIMIT) is None


def test_a_floating_cube_may_be_held_from_above():
    """Free space under a cube rules nothing out: a gripper holds it from above
    (test_parser_verdicts: the search does not move an object off strong data)."""
    T = make_pose(t=[0.0, 0.0, 0.08])
    view, pts = _seen({"c": ("cube", T)}, 50.0)
    rays, unheld = seen_under(CUBE, T, view, 0)
    assert rays >= 10 and unheld == 0
    assert nothing_holds(CUBE, T, pts["c"], view, 0, LIMIT) is None
    # on the table there is no column to look at
    assert not len(under_column(CUBE, make_pose(t=[0.0, 0.0, HALF]))[0])


def test_the_ruling_is_kept_in_the_parsers_state():
    """A resumed run remembers why nothing held a rejected object (``Rejected.unheld``); a state
    written before it has none."""
    from ssp.estimate import Rejected
    from ssp.parser import SceneParser

    parser = SceneParser(LIB)
    T = make_pose(t=[0.0, 0.0, 0.095])
    parser._rejected = [Rejected("cube_3", "cube", T, "would fall ...", unheld="ruled")]
    state = parser.state()
    assert state["rejected"][0]["unheld"] == "ruled"
    again = SceneParser.from_state(LIB, state)
    assert again._rejected[0].unheld == "ruled" and np.allclose(again._rejected[0].T_world_obj, T)
    del state["rejected"][0]["unheld"]
    assert SceneParser.from_state(LIB, state)._rejected[0].unheld is None
