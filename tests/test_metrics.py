"""``ssp.eval.metrics``: errors, matching, precision and induced noise on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.eval.metrics import (
    chordal_mean_rotation,
    hypothesis_errors,
    match_frame,
    pose_error,
    precision_deviations,
    summarize,
)
from ssp.library.symmetry import Symmetry
from ssp.scene import Hypothesis


def pose(x=0.0, y=0.0, z=0.0, rotvec_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


def cube_symmetry() -> Symmetry:
    R = Rotation.create_group("O").as_matrix()
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    return Symmetry(T)


SYMS = {"cube": cube_symmetry(), "tool": None}


def test_known_offsets_give_known_errors():
    gt = pose(0.1, 0.2, 0.03, (0, 0, 20))
    est = gt @ pose(0.0, 0.0, 0.0, (0, 0, 7))
    est[:3, 3] += [0.003, -0.004, 0.0]
    mm, deg = pose_error(gt, est)
    assert mm == pytest.approx(5.0)
    assert deg == pytest.approx(7.0)


def test_symmetric_cube_rotated_by_90_degrees_has_no_error():
    gt = pose(0.0, 0.0, 0.025, (0, 0, 15))
    est = gt @ pose(rotvec_deg=(90, 0, 0))
    assert pose_error(gt, est, SYMS["cube"]) == pytest.approx((0.0, 0.0), abs=1e-6)
    assert pose_error(gt, est, None)[1] == pytest.approx(90.0)
    # 90 deg plus 3 deg about another axis: 3 deg with the symmetry
    assert pose_error(gt, est @ pose(rotvec_deg=(0, 3, 0)), SYMS["cube"])[1] == pytest.approx(3.0)


def test_matching_counts_missed_and_false_positives_and_is_optimal():
    gt = {
        "c1": ("cube", pose(0.00, 0.0, 0.025)),
        "c2": ("cube", pose(0.06, 0.0, 0.025)),
        "t1": ("tool", pose(0.30, 0.0, 0.01)),
        "c3": ("cube", pose(0.50, 0.5, 0.025)),  # nothing near it: missed
    }
    estimates = [
        ("cube", pose(0.028, 0.0, 0.025)),  # nearest to c1, but the only estimate c2 can have
        ("cube", pose(-0.040, 0.0, 0.025)),  # c1's other option (greedy would miss c2)
        ("tool", pose(0.301, 0.0, 0.01)),
        ("cube", pose(-0.5, 0.0, 0.025)),  # far from everything: false positive
        ("tool", pose(0.0, 0.0, 0.025)),  # a tool where a cube is: class differs, false pos.
    ]
    fm = match_frame(gt, estimates, SYMS)
    by = fm.by_gt()
    assert set(by) == {"c1", "c2", "t1"}
    assert by["c1"].est_index == 1 and by["c1"].trans_mm == pytest.approx(40.0)
    assert by["c2"].est_index == 0 and by["c2"].trans_mm == pytest.approx(32.0)
    assert by["t1"].trans_mm == pytest.approx(1.0)
    assert [m.gt_id for m in fm.matches] == ["c1", "c2", "t1"]  # ground-truth order
    assert fm.missed == ["c3"]
    assert fm.false_positives == [3, 4]


def test_matching_gate():
    gt = {"c1": ("cube", pose(0.0, 0.0, 0.025))}
    far = [("cube", pose(0.051, 0.0, 0.025))]
    assert match_frame(gt, far, SYMS).missed == ["c1"]
    assert match_frame(gt, far, SYMS, gate=0.06).matches[0].trans_mm == pytest.approx(51.0)
    empty = match_frame(gt, [], SYMS)
    assert empty.missed == ["c1"] and not empty.matches


def test_matching_accepts_a_library_like_mapping():
    class Model:
        symmetry = cube_symmetry()

    gt = {"c1": ("cube", pose(0.0, 0.0, 0.025))}
    est = [("cube", pose(0.0, 0.0, 0.025, (0, 0, 90)))]
    assert match_frame(gt, est, {"cube": Model()}).matches[0].rot_deg == pytest.approx(0, abs=1e-6)


def test_precision_of_identical_estimates_is_zero():
    T = pose(0.1, 0.0, 0.02, (10, 20, 30))
    dt, dr = precision_deviations([T, T.copy(), T.copy()])
    assert np.allclose(dt, 0.0) and np.allclose(dr, 0.0, atol=1e-6)
    s = summarize(dt, dr)
    assert s["trans_mm_mean"] == pytest.approx(0.0) and s["rot_deg_std"] == pytest.approx(0.0)


def test_precision_of_alternating_estimates():
    base = pose(0.1, 0.0, 0.02)
    poses = [base @ pose(0.001 * s, 0, 0, (0, 0, 2 * s)) for s in (1, -1, 1, -1)]
    dt, dr = precision_deviations(poses)
    assert dt == pytest.approx([1.0] * 4)
    assert dr == pytest.approx([2.0] * 4, abs=1e-6)
    s = summarize(dt, dr)
    assert s["trans_mm_mean"] == pytest.approx(1.0) and s["trans_mm_std"] == pytest.approx(0.0)
    assert s["rot_deg_mean"] == pytest.approx(2.0, abs=1e-6)


def test_precision_snaps_symmetric_estimates_before_averaging():
    base = pose(0.0, 0.0, 0.025)
    # the same cube orientation reported as +-1 deg about z, every other one in a 90-deg
    # equivalent parametrisation: without snapping, the mean would be meaningless
    poses = [
        base @ pose(rotvec_deg=(0, 0, 1)),
        base @ pose(rotvec_deg=(0, 0, -1)) @ pose(rotvec_deg=(90, 0, 0)),
        base @ pose(rotvec_deg=(0, 0, 1)) @ pose(rotvec_deg=(0, 0, 180)),
        base @ pose(rotvec_deg=(0, 0, -1)),
    ]
    _, dr = precision_deviations(poses, SYMS["cube"])
    assert dr == pytest.approx([1.0] * 4, abs=1e-6)


def test_precision_needs_two_estimates():
    assert precision_deviations([pose()]) == ([], [])


def test_chordal_mean_of_symmetric_rotations_about_an_axis():
    Rs = [Rotation.from_rotvec([0, 0, np.radians(a)]).as_matrix() for a in (-5, 5, 10, -10)]
    assert np.allclose(chordal_mean_rotation(Rs), np.eye(3), atol=1e-9)


def test_hypothesis_errors_use_the_nearest_object_and_count_outliers():
    gt = {"a": ("cube", pose(0, 0, 0.025)), "b": ("cube", pose(0.1, 0, 0.025))}
    hyps = [
        Hypothesis("cube", pose(0.003, 0, 0.025)),
        Hypothesis("cube", pose(0.1, 0.004, 0.025, (0, 0, 92))),
        Hypothesis("cube", pose(0.3, 0, 0.025)),  # outlier
        Hypothesis("tool", pose(0, 0, 0.025)),  # no tool in the frame: outlier
    ]
    errs, outliers = hypothesis_errors(gt, hyps, SYMS)
    assert outliers == 2
    assert errs[0] == pytest.approx((3.0, 0.0), abs=1e-6)
    assert errs[1] == pytest.approx((4.0, 2.0), abs=1e-6)


def test_summarize_empty_is_none():
    assert summarize([], []) == {
        "trans_mm_mean": None,
        "trans_mm_std": None,
        "rot_deg_mean": None,
        "rot_deg_std": None,
    }


def test_hypothesis_errors_follow_recorded_sources():
    gt = {"a": ("cube", pose(0, 0, 0.025)), "b": ("cube", pose(0.03, 0, 0.025))}
    hyps = [
        Hypothesis("cube", pose(0.02, 0, 0.025)),  # nearer b, but drawn from a
        Hypothesis("cube", pose(0.2, 0, 0.025)),  # far from its source: still counted
        Hypothesis("cube", pose(0.0, 0, 0.025)),  # of no object
    ]
    errs, outliers = hypothesis_errors(gt, hyps, SYMS, sources=["a", "b", None])
    assert outliers == 1
    assert np.allclose(errs, [(20.0, 0.0), (170.0, 0.0)], atol=1e-6)
    with pytest.raises(ValueError, match="sources"):
        hypothesis_errors(gt, hyps, SYMS, sources=["a"])


def test_errors_and_matching_are_measured_at_the_centre_of_mass():
    """A mesh whose origin lies 95 mm from its centre: a 10 deg turn about the centre moves
    the origin by 16.5 mm, but the object's centre not at all; matching uses the centre."""

    class OffCentre:
        symmetry = Symmetry()
        center_of_mass = np.array([0.095, 0.0, 0.0])

    lib = {"tool": OffCentre()}
    c = OffCentre.center_of_mass
    R = Rotation.from_rotvec([0.0, 0.0, np.radians(10.0)]).as_matrix()
    T_gt = np.eye(4)
    T_est = np.eye(4)
    T_est[:3, :3] = R
    T_est[:3, 3] = c - R @ c  # turned about the centre
    fm = match_frame({"a": ("tool", T_gt)}, [("tool", T_est)], lib, gate=0.01)
    assert len(fm.matches) == 1
    assert fm.matches[0].trans_mm == pytest.approx(0.0, abs=1e-9)
    assert fm.matches[0].rot_deg == pytest.approx(10.0)
    # with bare symmetries (no centre) the origin is the centre: 16.5 mm, beyond a 1 cm gate
    assert match_frame({"a": ("tool", T_gt)}, [("tool", T_est)], {"tool": Symmetry()}, 0.01).missed
