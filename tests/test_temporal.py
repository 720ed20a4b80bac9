"""Association, transition modes and symmetry snapping (ssp.temporal)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.config import TemporalConfig
from ssp.errors import DuplicateObjectError, SSPError
from ssp.geometry import make_pose, rotation_angle
from ssp.library.symmetry import ContinuousSymmetry, Symmetry
from ssp.scene import Hypothesis, TransitionMode
from ssp.temporal import (
    associate,
    classify,
    default_id_factory,
    same_volume_test,
    snap_symmetric,
)

CUBE_SYM = Symmetry(np.stack([make_pose(R) for R in Rotation.create_group("O").as_matrix()]))
CYL_SYM = Symmetry(continuous=(ContinuousSymmetry(np.array([0.0, 0.0, 1.0])),))
SYMS = {"cube": CUBE_SYM}


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def pose(x=0.0, y=0.0, z=0.0254, R=None) -> np.ndarray:
    return make_pose(R, [x, y, z])


def ids_by_x(groups) -> dict[float, str]:
    return {round(float(hs[0].T_world_obj[0, 3]), 4): k for k, hs in groups.items()}


# --------------------------------------------------------------------------------- associate


def test_given_ids_are_kept():
    hs = [Hypothesis("cube", pose(0.0), 1.0, "mine"), Hypothesis("cube", pose(0.301), 0.5)]
    out = associate(hs, {"mine": ("cube", pose(0.3)), "cube_0": ("cube", pose(0.6))}, SYMS)
    # "mine" keeps its id though it moved 30 cm; the previous "mine" is claimed by it, so the
    # hypothesis right at its old place is a new object (cube_0 is taken: cube_1).
    assert ids_by_x(out) == {0.0: "mine", 0.301: "cube_1"}
    assert all(h.instance_id == k for k, v in out.items() for h in v)


def test_unlabelled_hypothesis_near_given_id_joins_it():
    hs = [Hypothesis("cube", pose(0.0), 0.9, "a"), Hypothesis("cube", pose(0.004), 0.95)]
    out = associate(hs, {}, SYMS)
    assert list(out) == ["a"] and len(out["a"]) == 2
    assert out["a"][0].score == 0.95  # best first


@pytest.mark.parametrize("swap", [False, True])
def test_two_cubes_match_previous_ids_whatever_the_order(swap):
    prev = {"left": ("cube", pose(-0.1)), "right": ("cube", pose(0.1))}
    hs = [Hypothesis("cube", pose(-0.098), 0.7), Hypothesis("cube", pose(0.103, R=rot("z", 90)))]
    if swap:
        hs = hs[::-1]
    out = associate(hs, prev, SYMS)
    assert ids_by_x(out) == {-0.098: "left", 0.103: "right"}


def test_new_object_gets_new_id():
    prev = {"cube_0": ("cube", pose(0.0)), "cube_1": ("cube", pose(0.2))}
    hs = [
        Hypothesis("cube", pose(0.0)),
        Hypothesis("cube", pose(0.2)),
        Hypothesis("cube", pose(0.4)),
    ]
    out = associate(hs, prev, SYMS)
    assert ids_by_x(out) == {0.0: "cube_0", 0.2: "cube_1", 0.4: "cube_2"}


def test_other_class_never_matches():
    out = associate([Hypothesis("block", pose(0.0))], {"cube_0": ("cube", pose(0.0))}, SYMS)
    assert list(out) == ["block_0"]


def test_custom_new_id_and_collision():
    hs = [Hypothesis("cube", pose(0.0))]
    assert list(associate(hs, {}, SYMS, new_id=lambda c: f"{c}-new")) == ["cube-new"]
    with pytest.raises(DuplicateObjectError, match="in use"):
        associate(hs, {"x": ("cube", pose(0.5))}, SYMS, new_id=lambda c: "x")


def test_default_id_factory_skips_taken():
    f = default_id_factory(["cube_0", "cube_2"])
    assert [f("cube"), f("cube"), f("ball")] == ["cube_1", "cube_3", "ball_0"]


def test_five_noisy_hypotheses_form_one_cluster():
    rng = np.random.default_rng(1)
    hs = []
    for i in range(5):
        noise = rng.normal(0, 0.005, 3)
        R = Rotation.from_rotvec(rng.normal(0, math.radians(3), 3)).as_matrix()
        hs.append(Hypothesis("cube", pose(*(np.array([0.2, 0.1, 0.0254]) + noise), R=R), i / 5))
    far = Hypothesis("cube", pose(-0.2), 0.1)
    out = associate([*hs, far], {"c": ("cube", pose(0.2, 0.1))}, SYMS)
    assert list(out) == ["c", "cube_0"]
    assert len(out["c"]) == 5 and [h.score for h in out["c"]] == [0.8, 0.6, 0.4, 0.2, 0.0]


def test_alternative_orientations_are_one_object_and_toppled_keeps_id():
    # Asymmetric object: the same place, orientations 90 deg apart, is one object.
    hs = [Hypothesis("tool", pose(0.0, R=rot("x", 90)), 0.9), Hypothesis("tool", pose(0.0), 0.8)]
    out = associate(hs, {"t": ("tool", pose(0.003))}, {})
    assert list(out) == ["t"] and len(out["t"]) == 2
    out = associate(hs[:1], {"t": ("tool", pose(0.003))}, {})
    assert list(out) == ["t"]  # toppled in place: rotation does not gate


def test_hungarian_beats_greedy():
    # Greedy (best score first, nearest previous) gives c1 -> A and leaves c2 unmatched
    # (c2 is 8 cm from B); the optimal assignment is c1 -> B, c2 -> A, both within the gate.
    prev = {"A": ("cube", pose(0.0)), "B": ("cube", pose(0.045))}
    c1 = Hypothesis("cube", pose(0.02), 0.9)
    c2 = Hypothesis("cube", pose(-0.035), 0.5)
    out = associate([c1, c2], prev, SYMS)
    assert ids_by_x(out) == {0.02: "B", -0.035: "A"}


def test_rotation_breaks_ties_symmetry_aware():
    # Two previous objects equally far; the one with the matching orientation wins. For a cube
    # a 90 deg turn about z is no rotation at all.
    prev = {"P": ("tool", pose(-0.01)), "Q": ("tool", pose(0.01, R=rot("z", 30)))}
    out = associate([Hypothesis("tool", pose(0.0, R=rot("z", 30)))], prev, {})
    assert list(out) == ["Q"]
    prev = {"P": ("cube", pose(-0.01, R=rot("z", 30))), "Q": ("cube", pose(0.01, R=rot("z", 90)))}
    out = associate([Hypothesis("cube", pose(0.0))], prev, SYMS)
    assert list(out) == ["Q"]


def test_association_is_deterministic():
    rng = np.random.default_rng(5)
    prev = {f"p{i}": ("cube", pose(0.1 * i)) for i in range(6)}
    hs = [Hypothesis("cube", pose(0.1 * i + rng.normal(0, 0.01)), 0.5) for i in range(8)]
    a = associate(hs, prev, SYMS)
    b = associate(hs, dict(reversed(list(prev.items()))), SYMS)
    assert list(a) == list(b)
    for k in a:
        assert [h.T_world_obj.tobytes() for h in a[k]] == [h.T_world_obj.tobytes() for h in b[k]]


# ---------------------------------------------------------------------------------- classify

CFG = TemporalConfig()


@pytest.mark.parametrize(
    ("dx_mm", "deg", "mode"),
    [
        (0.0, 0.0, TransitionMode.STATIC),
        (7.4, 0.0, TransitionMode.STATIC),
        (7.5, 0.0, TransitionMode.PERTURBED),  # not strictly below
        (7.6, 0.0, TransitionMode.PERTURBED),
        (0.0, 4.9, TransitionMode.STATIC),
        (0.0, 5.1, TransitionMode.PERTURBED),
        (7.4, 4.9, TransitionMode.STATIC),
        (30.0, 0.0, TransitionMode.PERTURBED),
    ],
)
def test_classify_static_perturbed_edges(dx_mm, deg, mode):
    prev = pose(0.0)  # dt is then exactly dx: 7.5 mm sits on the threshold
    cur = pose(dx_mm / 1000, R=rot("y", deg))
    assert classify(prev, cur, None, CFG) is mode


def test_classify_symmetric_turn_is_static():
    assert classify(pose(), pose(R=rot("z", 90)), CUBE_SYM, CFG) is TransitionMode.STATIC
    assert classify(pose(), pose(R=rot("z", 90)), None, CFG) is TransitionMode.PERTURBED


def test_classify_added_removed_retained():
    assert classify(None, pose(), None, CFG) is TransitionMode.ADDED
    assert classify(pose(), None, None, CFG) is TransitionMode.REMOVED
    assert classify(pose(), None, None, CFG, retained=True) is TransitionMode.SUPPORT_RETAINED
    assert classify(pose(), pose(), None, CFG, retained=True) is TransitionMode.SUPPORT_RETAINED
    with pytest.raises(SSPError):
        classify(None, None, None, CFG)
    with pytest.raises(SSPError):
        classify(None, pose(), None, CFG, retained=True)


def _angle_between(T1, T2) -> float:
    return math.degrees(float(rotation_angle(T1[:3, :3].T @ T2[:3, :3])))


def _is_equivalent(T_cur, T_snap, sym: Symmetry) -> bool:
    S = np.linalg.inv(T_cur) @ T_snap
    return any(np.allclose(S, D, atol=1e-9) for D in sym.discrete)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_snap_cube_90_plus_3(axis):
    prev = pose(0.1, R=rot("z", 17))
    cur = pose(0.102, R=rot("z", 17) @ rot(axis, 93))
    assert _angle_between(prev, cur) == pytest.approx(93)
    snapped = snap_symmetric(prev, cur, CUBE_SYM)
    assert _angle_between(prev, snapped) == pytest.approx(3.0, abs=1e-6)
    assert _is_equivalent(cur, snapped, CUBE_SYM)
    np.testing.assert_allclose(snapped[:3, 3], cur[:3, 3])  # no offsets: same translation


def test_snap_already_closest_unchanged():
    prev = pose(R=rot("x", 10))
    cur = pose(0.001, R=rot("x", 12))
    for sym in (CUBE_SYM, CYL_SYM, None, Symmetry()):
        out = snap_symmetric(prev, cur, sym)
        np.testing.assert_allclose(out, cur, atol=1e-12)
        assert out is not cur


def test_snap_continuous_axis_exact():
    prev = pose(R=rot("x", 5))
    cur = pose(R=rot("x", 5) @ rot("z", 140) @ rot("x", 2))
    snapped = snap_symmetric(prev, cur, CYL_SYM)
    assert _angle_between(prev, snapped) == pytest.approx(2.0, abs=1e-6)
    # exact: no sampled equivalent is closer
    sampled = [cur @ S for S in CYL_SYM.transforms(np.radians(0.5))]
    assert _angle_between(prev, snapped) <= min(_angle_between(prev, T) for T in sampled) + 1e-9
    # same physical pose: the axis (model z) maps to the same world direction
    np.testing.assert_allclose(snapped[:3, 2], cur[:3, 2], atol=1e-12)


def test_snap_continuous_with_offset_keeps_the_axis_line():
    sym = Symmetry(continuous=(ContinuousSymmetry(np.array([0, 0, 1.0]), np.array([0.02, 0, 0])),))
    prev = pose()
    cur = pose(R=rot("z", 60))
    snapped = snap_symmetric(prev, cur, sym)
    assert _angle_between(prev, snapped) == pytest.approx(0.0, abs=1e-6)
    p = np.array([0.02, 0.0, 0.05, 1.0])  # a point on the axis is fixed
    np.testing.assert_allclose(snapped @ p, cur @ p, atol=1e-12)


def test_snap_sphere_takes_previous_rotation():
    sym = Symmetry(
        continuous=(
            ContinuousSymmetry(np.array([0, 0, 1.0])),
            ContinuousSymmetry(np.array([1.0, 0, 0])),
        )
    )
    prev = pose(R=rot("y", 30))
    cur = pose(0.01, R=rot("x", 70))
    snapped = snap_symmetric(prev, cur, sym)
    np.testing.assert_allclose(snapped[:3, :3], prev[:3, :3], atol=1e-12)
    np.testing.assert_allclose(snapped[:3, 3], cur[:3, 3], atol=1e-12)


def test_snap_sequence_never_flips():
    # A cube jittering about 45 deg would flip between 44 and -46 deg without snapping.
    T = pose(R=rot("z", 44))
    for k, deg in enumerate([46, 44.5, 45.5, 47, 43]):
        cur = pose(R=rot("z", deg - 90 * (k % 2)))  # the estimator alternates equivalents
        T = snap_symmetric(T, cur, CUBE_SYM)
        assert _angle_between(pose(R=rot("z", deg)), T) == pytest.approx(0.0, abs=1e-6)


def test_hypotheses_sharing_a_volume_are_one_object():
    from ssp.library import ObjectLibrary

    lib = ObjectLibrary.builtin()
    block = lib["block"]
    assert block.extents[0] > 1.9 * block.extents[1]  # long along x
    z = -float(block.mesh.bounds[0, 2])
    a = Hypothesis("block", make_pose(t=[0.0, 0.0, z]), 0.9)
    b = Hypothesis("block", make_pose(t=[0.022, 0.0, z]), 0.8)  # 22 mm along its length
    far = Hypothesis("block", make_pose(t=[0.0, 0.03, z]), 0.7)  # beside it: no shared volume
    sym = {"block": block.symmetry}
    gate = {"block": 0.02}
    assert len(associate([a, b, far], {}, sym, max_distance=gate)) == 3
    same = same_volume_test(lib, TemporalConfig().merge_overlap)
    merged = associate([a, b, far], {}, sym, max_distance=gate, same_volume=same)
    assert len(merged) == 2
    groups = sorted(merged.values(), key=len)
    assert [h.score for h in groups[1]] == [0.9, 0.8] and [h.score for h in groups[0]] == [0.7]


def test_hypotheses_of_different_instance_segments_are_never_one_object(lib):
    """A half-hidden block's hypothesis can reach into the block on top of it: from different
    instance segments, the two are kept apart (clustering and same-volume merging alike);
    without segments, or from one segment, they are grouped as before."""
    block = lib["block"]
    z = -float(block.mesh.bounds[0, 2])
    sym = {"block": block.symmetry}
    gate = {"block": 0.02}
    same = same_volume_test(lib, TemporalConfig().merge_overlap)
    near = (make_pose(t=[0.0, 0.0, z]), make_pose(t=[0.004, 0.0, z]))  # clustered by distance
    apart = (make_pose(t=[0.0, 0.0, z]), make_pose(t=[0.022, 0.0, z]))  # merged by volume
    for T_a, T_b in (near, apart):
        for seg_a, seg_b, groups in ((None, None, 1), (3, 3, 1), (3, None, 1), (3, 4, 2)):
            hs = [Hypothesis("block", T_a, 0.9, segment=seg_a)]
            hs.append(Hypothesis("block", T_b, 0.8, segment=seg_b))
            out = associate(hs, {}, sym, max_distance=gate, same_volume=same)
            assert len(out) == groups, (T_b[0, 3], seg_a, seg_b)
    # the previous object keeps its id through the segment whose hypothesis is nearest it
    prev = {"block_0": ("block", make_pose(t=[0.0, 0.0, z]))}
    hs = [
        Hypothesis("block", make_pose(t=[0.005, 0.0, z]), 0.9, segment=7),  # the block on top
        Hypothesis("block", make_pose(t=[0.0, 0.001, z]), 0.4, segment=2),  # the hidden one
    ]
    out = associate(hs, prev, sym, max_distance=gate, same_volume=same)
    assert {k: [h.segment for h in v] for k, v in out.items()} == {"block_0": [2], "block_1": [7]}
