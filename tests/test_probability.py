"""Probability terms (ssp.probability) against hand-computed values, DESIGN section 4 defaults."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ssp.config import (
    CollisionConfig,
    DataConfig,
    StabilityConfig,
    SupportConfig,
    TransitionConfig,
)
from ssp.geometry import make_pose, rotation_angle
from ssp.library.symmetry import ContinuousSymmetry, Symmetry
from ssp.probability import (
    ObjectTerms,
    collision_severity,
    data_fit_fraction,
    log_collision,
    log_data,
    log_logistic,
    log_stability,
    log_support,
    log_transition,
    log_transition_from_poses,
    pose_change,
)

G = 9.81
# The paper's / reference code's constants (DESIGN section 4), set explicitly so that these
# hand-computed values do not depend on the calibrated defaults.
STAB = StabilityConfig(steepness=40.0, midpoint=0.1)  # a_t = a_R = 1
COLL = CollisionConfig(steepness=2000.0, midpoint=0.002)
SUPP = SupportConfig(steepness=0.5, offset=0.5)
DATA = DataConfig(steepness=10.0, midpoint=0.36, c_max=0.5, inlier_radius=0.0037)
TRANS = TransitionConfig()  # sigma_t 0.01 m, sigma_r 18 deg


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def test_transition_defaults_are_the_reference_constants():
    assert TRANS.sigma_translation == 0.01
    assert TRANS.sigma_rotation == pytest.approx(math.radians(18))


# ---------------------------------------------------------------- log_logistic


def test_log_logistic_values():
    assert log_logistic(0.0) == pytest.approx(math.log(0.5))
    assert log_logistic(4.0) == pytest.approx(math.log(1 / (1 + math.exp(-4))))
    assert log_logistic(-4.0) == pytest.approx(math.log(1 / (1 + math.exp(4))))


def test_log_logistic_huge_arguments():
    out = log_logistic(np.array([-1e6, -1e3, 1e3, 1e6]))
    assert np.all(np.isfinite(out))
    assert out[0] == pytest.approx(-1e6, rel=1e-12)
    assert out[1] == pytest.approx(-1e3, rel=1e-12)
    assert out[2] == 0.0 and out[3] == 0.0


# ---------------------------------------------------------------- stability (Eq. 7)


def test_stability_at_rest():
    out = log_stability(np.zeros((2, 3)), np.zeros((2, 3)), np.array([100.0, 5.0]), G, STAB)
    expected = 2 * math.log(1 / (1 + math.exp(-4)))  # 2 log L(40 * 0.1)
    assert out.shape == (2,)
    np.testing.assert_allclose(out, [expected, expected], rtol=1e-12)


def test_stability_hand_values():
    # beta_t = 0.2: L(-40 (0.2 - 0.1)) = L(-4); rotation at rest: L(4)
    lin = np.array([[0.0, 0.0, -0.2 * G], [0.0, 0.0, 0.0], [0.0, 0.1 * G, 0.0]])
    # second object: |alpha| / alpha_max = 30 / 100 = 0.3 -> L(-40 * 0.2) = L(-8)
    # third object: beta_t = 0.1 exactly -> L(0) = 0.5; beta_R = 0.05 -> L(2)
    ang = np.array([[0.0, 0.0, 0.0], [0.0, 30.0, 0.0], [0.0, 0.0, 5.0]])
    out = log_stability(lin, ang, np.array([100.0, 100.0, 100.0]), G, STAB)
    l4, lm4 = math.log(1 / (1 + math.exp(-4))), math.log(1 / (1 + math.exp(4)))
    lm8 = math.log(1 / (1 + math.exp(8)))
    l2 = math.log(1 / (1 + math.exp(-2)))
    np.testing.assert_allclose(out, [lm4 + l4, l4 + lm8, math.log(0.5) + l2], rtol=1e-12)


def test_stability_weights_used():
    cfg = StabilityConfig(steepness=40.0, midpoint=0.1, translation_weight=2.0, rotation_weight=0.0)
    out = log_stability([[0.1 * G, 0, 0]], [[1e6, 0, 0]], 1.0, G, cfg)
    # 2 * 0.1 - 0.1 = 0.1 -> L(-4); rotation weight 0 -> L(4)
    assert out[0] == pytest.approx(
        math.log(1 / (1 + math.exp(4))) + math.log(1 / (1 + math.exp(-4)))
    )


def test_stability_decreasing_in_acceleration():
    mags = np.linspace(0.0, 3 * G, 50)
    lin = np.stack([mags, np.zeros_like(mags), np.zeros_like(mags)], axis=1)
    out_t = log_stability(lin, np.zeros_like(lin), 50.0, G, STAB)
    out_r = log_stability(np.zeros_like(lin), lin, 50.0, G, STAB)
    assert np.all(np.diff(out_t) < 0) and np.all(np.diff(out_r) < 0)


def test_stability_huge_acceleration_is_finite():
    out = log_stability([[1e6, 0, 0]], [[0, 1e6, 0]], 1.0, G, STAB)
    assert np.all(np.isfinite(out))
    # -40 * (1e6 - 0.1) - 40 * (1e6/9.81 - 0.1), to within rounding
    assert out[0] == pytest.approx(-40 * (1e6 - 0.1) - 40 * (1e6 / G - 0.1), rel=1e-9)


def test_stability_rejects_bad_alpha_max():
    with pytest.raises(ValueError):
        log_stability(np.zeros((1, 3)), np.zeros((1, 3)), 0.0, G, STAB)


# ---------------------------------------------------------------- collision (Eq. 8)


def test_collision_severity_hand_values():
    e = collision_severity([0.004, -0.003, 0.01], [0.5, 0.9, 1.5], [0.1, 0.1, 0.05])
    # 0.004/0.1*0.5 = 0.02; negative depth -> 0; fraction clipped to 1: 0.01/0.05 = 0.2
    np.testing.assert_allclose(e, [0.02, 0.0, 0.2], rtol=1e-12)


def test_collision_hand_values():
    out = log_collision([0.0, 0.002, 0.02], COLL)
    expected = [
        math.log(1 / (1 + math.exp(-4))),  # L(-2000 (0 - 0.002)) = L(4)
        math.log(0.5),  # at the midpoint
        -math.log1p(math.exp(36)),  # L(-2000 * 0.018) = L(-36)
    ]
    np.testing.assert_allclose(out, expected, rtol=1e-12)


def test_collision_decreasing_in_depth_and_overlap():
    depths = np.linspace(0.0, 0.02, 40)
    by_depth = log_collision(collision_severity(depths, 0.5, 0.05), COLL)
    fracs = np.linspace(0.0, 1.0, 40)
    by_frac = log_collision(collision_severity(0.005, fracs, 0.05), COLL)
    assert np.all(np.diff(by_depth) < 0) and np.all(np.diff(by_frac) < 0)


def test_collision_huge_severity_is_finite():
    out = log_collision(1e6, COLL)
    assert np.isfinite(out[0]) and out[0] == pytest.approx(-2000 * (1e6 - 0.002))


# ---------------------------------------------------------------- support (Eq. 9)


def test_support_hand_values():
    out = log_support([0.0, 1.0, 2.0, -1.0], SUPP)
    expected = [
        math.log(1 / (1 + math.exp(-0.5))),  # supports nothing: L(0.5) = 0.622
        math.log(1 / (1 + math.exp(-1.0))),  # L(1.0) = 0.731
        math.log(1 / (1 + math.exp(-1.5))),  # L(1.5) = 0.818
        math.log(0.5),
    ]
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    assert math.exp(out[0]) == pytest.approx(0.622, abs=1e-3)


def test_support_increasing():
    out = log_support(np.linspace(0, 5, 30), SUPP)
    assert np.all(np.diff(out) > 0)


# ---------------------------------------------------------------- data (Eq. 10)


def test_data_hand_values():
    out = log_data([0.0, 0.18, 0.3, 0.5], DATA)
    expected = [
        math.log(1 / (1 + math.exp(3.6))),  # L(10 (0 - 0.36)) = 0.027
        math.log(0.5),  # 0.18 / 0.5 = 0.36: midpoint
        math.log(1 / (1 + math.exp(-2.4))),  # L(10 (0.6 - 0.36)) = 0.917
        math.log(1 / (1 + math.exp(-6.4))),  # L(10 (1 - 0.36)) = 0.998
    ]
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    np.testing.assert_allclose(np.exp(out), [0.027, 0.5, 0.917, 0.998], atol=1e-3)


def test_data_increasing_then_capped_at_c_max():
    c = np.linspace(0, 1, 41)
    out = log_data(c, DATA)
    below = c <= DATA.c_max
    assert np.all(np.diff(out[below]) > 0)
    np.testing.assert_array_equal(out[~below], log_data(DATA.c_max, DATA)[0])


def test_data_fit_fraction_exact_half():
    r = DATA.inlier_radius
    segment = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    near = np.array([[0.5 * r, 0, 0], [1.0, 0.9 * r, 0], [0, 0, -0.99 * r]])
    far = np.array([[1.5 * r, 0, 0], [1.0, 0, 1.1 * r], [0.5, 0, 0]])
    pts = np.concatenate([near, far])
    assert data_fit_fraction(pts, segment, r) == 0.5
    assert data_fit_fraction(pts, cKDTree(segment), r) == 0.5  # prebuilt tree
    # 1 of 4 within radius
    assert data_fit_fraction(np.concatenate([near[:1], far]), segment, r) == 0.25


def test_data_fit_fraction_boundary_counts_as_within():
    assert data_fit_fraction(np.array([[0.25, 0, 0]]), np.zeros((1, 3)), 0.25) == 1.0


def test_data_fit_fraction_empty():
    pts = np.zeros((5, 3))
    assert data_fit_fraction(pts, np.zeros((0, 3)), 0.01) == 0.0
    assert data_fit_fraction(pts, cKDTree(np.zeros((0, 3))), 0.01) == 0.0
    assert data_fit_fraction(np.zeros((0, 3)), np.zeros((3, 3)), 0.01) == 0.0


# ---------------------------------------------------------------- transition (Eq. 4)


def test_transition_hand_values():
    s_r = math.radians(18)
    assert log_transition(0.0, 0.0, TRANS) == 0.0
    assert log_transition(0.01, 0.0, TRANS) == pytest.approx(-0.5)  # one sigma_t
    assert log_transition(0.0, s_r, TRANS) == pytest.approx(-0.5)  # one sigma_r
    assert log_transition(0.02, s_r, TRANS) == pytest.approx(-2.0 - 0.5)
    out = log_transition(np.array([0.0, 0.005]), np.array([math.radians(5), 0.0]), TRANS)
    np.testing.assert_allclose(out, [-((5 / 18) ** 2) / 2, -0.125], rtol=1e-12)


def test_transition_decreasing_down_to_its_floor():
    d = np.linspace(0, 0.1, 20)
    for out in (log_transition(d, 0.0, TRANS), log_transition(0.0, d * 20, TRANS)):
        above = out > TRANS.floor
        assert np.all(np.diff(out[above]) < 0)  # strictly decreasing above the floor
        assert np.all(out >= TRANS.floor) and out[-1] == TRANS.floor
    # a half turn costs the floor, not -(pi / sigma_r)^2 / 2 = -50: the data can overturn it
    assert log_transition(0.0, math.pi, TRANS) == pytest.approx(-8.0)
    gauss = TRANS.model_copy(update={"floor": -1e9})
    assert log_transition(0.0, math.pi, gauss) == pytest.approx(-50.0)


def test_transition_new_object_is_zero():
    T = make_pose(rot("x", 70), [1.0, 2.0, 3.0])
    assert log_transition_from_poses(None, T, TRANS) == 0.0
    assert log_transition_from_poses(None, T, TRANS, Symmetry()) == 0.0


def test_transition_from_poses():
    T0 = make_pose(rot("z", 10), [0.1, 0.2, 0.3])
    T1 = make_pose(rot("z", 10 + 18), [0.1, 0.21, 0.3])
    assert log_transition_from_poses(T0, T1, TRANS) == pytest.approx(-1.0)


def test_pose_change_asymmetric():
    T0 = make_pose(rot("y", 30), [0.0, 0.0, 0.0])
    T1 = make_pose(rot("y", 30) @ rot("x", 40), [0.03, 0.04, 0.0])
    dt, dth = pose_change(T0, T1, None)
    assert dt == pytest.approx(0.05)
    assert dth == pytest.approx(math.radians(40))
    # no symmetry object given == identity-only symmetry
    assert pose_change(T0, T1, Symmetry())[1] == pytest.approx(math.radians(40))


def test_pose_change_small_angle_is_accurate():
    T1 = make_pose(Rotation.from_rotvec([1e-7, 0, 0]).as_matrix())
    assert pose_change(np.eye(4), T1)[1] == pytest.approx(1e-7, rel=1e-6)


def cube_symmetry() -> Symmetry:
    mats = Rotation.create_group("O").as_matrix()  # the 24 rotations of a cube
    d = np.tile(np.eye(4), (24, 1, 1))
    d[:, :3, :3] = mats
    return Symmetry(d)


def test_pose_change_cube_symmetry():
    sym = cube_symmetry()
    assert len(sym.discrete) == 24
    T0 = make_pose(rot("z", 15), [0.2, 0.0, 0.1])
    for axis in "xyz":
        T1 = T0 @ make_pose(rot(axis, 90))
        dt, dth = pose_change(T0, T1, sym)
        assert dt == pytest.approx(0.0, abs=1e-12)
        assert dth == pytest.approx(0.0, abs=1e-7)
        assert pose_change(T0, T1, None)[1] == pytest.approx(math.pi / 2)  # not without it
    # 100 deg about z is 10 deg from a symmetric equivalent
    assert pose_change(T0, T0 @ make_pose(rot("z", 100)), sym)[1] == pytest.approx(math.radians(10))
    # cube equivalents are 90 deg apart, so no change exceeds the cube's covering radius
    rng = np.random.default_rng(0)
    for R in Rotation.random(50, random_state=rng).as_matrix():
        assert pose_change(T0, T0 @ make_pose(R), sym)[1] <= math.radians(62.8 + 0.1)


def test_pose_change_continuous_axis_exact():
    sym = Symmetry(continuous=(ContinuousSymmetry(np.array([0.0, 0.0, 2.0])),))  # cylinder
    T0 = make_pose(rot("x", 20))
    # spin about the model z axis: equivalent
    assert pose_change(T0, T0 @ make_pose(rot("z", 77)), sym)[1] == pytest.approx(0, abs=1e-9)
    # tilt 25 deg about x plus any spin: 25 deg
    T1 = T0 @ make_pose(rot("x", 25) @ rot("z", 130))
    assert pose_change(T0, T1, sym)[1] == pytest.approx(math.radians(25))
    # agrees with (and is no worse than) dense sampling of the symmetry (0.5 deg steps)
    Rs = sym.transforms(math.radians(0.5))[:, :3, :3]
    rng = np.random.default_rng(1)
    for R in Rotation.random(20, random_state=rng).as_matrix():
        T1 = T0 @ make_pose(R)
        exact = pose_change(T0, T1, sym)[1]
        sampled = rotation_angle(T0[:3, :3].T @ T1[:3, :3] @ Rs).min()
        assert exact <= sampled + 1e-7
        assert exact == pytest.approx(sampled, abs=math.radians(0.3))


def test_pose_change_sphere_is_zero():
    sym = Symmetry(
        continuous=(
            ContinuousSymmetry(np.array([0.0, 0.0, 1.0])),
            ContinuousSymmetry(np.array([1.0, 0.0, 0.0])),
        )
    )
    T1 = make_pose(rot("y", 123), [0.0, 0.01, 0.0])
    assert pose_change(np.eye(4), T1, sym) == pytest.approx((0.01, 0.0))


# ---------------------------------------------------------------- container


def test_object_terms():
    t = ObjectTerms(stability=-0.1, collision=-0.2, support=-0.3, data=-0.4, transition=0.0)
    assert t.total == pytest.approx(-1.0)
    d = t.as_dict()
    assert d == {
        "stability": -0.1,
        "collision": -0.2,
        "support": -0.3,
        "data": -0.4,
        "transition": 0.0,
    }
    assert ObjectTerms(**d) == t
    with pytest.raises(AttributeError):
        t.data = 0.0  # frozen
