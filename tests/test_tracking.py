"""Id switches (CLEAR MOT) and the stream conditions behind failures."""

from __future__ import annotations

import numpy as np

from ssp.eval.failures import false_object_cause, object_conditions
from ssp.eval.tracking import IdSwitches
from ssp.scene import Hypothesis


def _T(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_id_switches_count_swaps_losses_and_static_ones():
    gt = {"a": ("cube", _T(0.0)), "b": ("cube", _T(0.1))}
    ids = IdSwitches()
    ids.update(0, gt, {"a": "cube_0", "b": "cube_1"})
    ids.update(1, gt, {"a": "cube_0", "b": "cube_1"})
    assert ids.switches == 0
    ids.update(2, gt, {"a": "cube_1", "b": "cube_0"})  # a swap: two switches, both static
    assert (ids.switches, ids.static_switches) == (2, 2)
    ids.update(3, gt, {"a": None})  # lost: no switch, and the memory stays
    moved = {"a": ("cube", _T(0.05)), "b": gt["b"]}
    ids.update(4, moved, {"a": "cube_7"})  # found again under a new id after moving
    assert (ids.switches, ids.static_switches) == (3, 2)
    assert ids.events[-1] == {"frame": 4, "object": "a", "from": "cube_1", "to": "cube_7",
                              "static": False}  # fmt: skip


def test_object_conditions_and_false_object_causes():
    gt = {"a": ("cube", _T(0.0)), "b": ("cube", _T(0.2)), "c": ("block", _T(0.4))}
    visib = {"a": 1.0, "b": 0.05, "c": 0.9}
    hyps = [Hypothesis("cube", _T(0.0), 0.9), Hypothesis("block", _T(0.41), 0.8),
            Hypothesis("cube", _T(0.6), 0.5)]  # fmt: skip
    sources = ["a", "c", None]
    kinds = ["nominal", "flip", "false_positive"]
    cond = object_conditions(gt, visib, hyps, sources, kinds)
    assert cond == {"a": "nominal", "b": "hidden", "c": "top1_flip"}
    assert object_conditions(gt, visib, hyps[:1], sources[:1], kinds[:1])["c"] == "dropout"
    distractors = {"d": ("distractor_can", _T(0.8))}
    cause = lambda x, cls="cube": false_object_cause(  # noqa: E731
        _T(x), cls, gt, distractors, hyps, kinds
    )
    assert cause(0.61) == "false_positive"
    assert cause(0.79) == "distractor"
    assert cause(0.39, "cube") == "class_confusion"
    assert cause(0.01) == "duplicate"
    assert cause(1.5) == "elsewhere"


def test_never_detected_objects_are_told_from_dropouts():
    from ssp.eval.failures import DetectionHistory

    gt = {"a": ("cube", _T(0.0)), "b": ("cube", _T(0.2))}
    h = DetectionHistory()
    assert h.update(gt, {"a"}) == {"a"}  # b appeared in a dropout
    assert h.update(gt, set()) == {"a"}  # a is in a dropout now, b still never seen
    assert object_conditions(gt, {"a": 1.0, "b": 1.0}, [], [], [], {"a"}) == {
        "a": "dropout", "b": "never_detected",
    }  # fmt: skip
    moved = {"a": ("cube", _T(0.05)), "b": gt["b"]}
    assert h.update(moved, set()) == set()  # a moved while undetected: never seen there
    assert h.update(moved, {"b"}) == {"b"}


def test_flips_count_turns_of_objects_that_did_not_move():
    from ssp.eval.tracking import Flips
    from ssp.library import ObjectLibrary

    lib = ObjectLibrary.builtin()
    T = np.eye(4)
    turned = np.eye(4)
    turned[:3, :3] = [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]  # half a turn
    gt = {"a": ("mallet", T), "c": ("cube", T)}
    f = Flips()
    f.update(gt, {"a": T, "c": T}, lib)
    f.update(gt, {"a": turned, "c": turned}, lib)  # the cube's half turn is a symmetry
    assert (f.flips, f.from_right) == (1, 1)
    f.update(gt, {"a": T}, lib)  # back: a flip from a wrong orientation
    assert (f.flips, f.from_right) == (2, 1)
    moved = {"a": ("mallet", turned)}
    f.update(moved, {"a": turned}, lib)  # the object turned: not a flip
    assert f.flips == 2
