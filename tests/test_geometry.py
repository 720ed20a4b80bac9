"""SE(3) helpers and pose validation."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ssp.errors import InvalidPoseError
from ssp.geometry import (
    in_box,
    invert,
    make_pose,
    pose_from_xyz_quat,
    quat_xyzw,
    rotation_angle,
    squared_distances,
    transform_points,
    validate_pose,
)

quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3
)
vecs = st.lists(st.floats(-10, 10), min_size=3, max_size=3)


@settings(max_examples=50, deadline=None)
@given(quats, vecs)
def test_invert_is_inverse(q, t):
    T = pose_from_xyz_quat(np.array(t), np.array(q))
    assert np.allclose(T @ invert(T), np.eye(4), atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(quats, vecs)
def test_quaternion_round_trip_xyzw(q, t):
    T = pose_from_xyz_quat(np.array(t), np.array(q))
    T2 = pose_from_xyz_quat(T[:3, 3], quat_xyzw(T))
    assert np.allclose(T, T2, atol=1e-9)
    assert quat_xyzw(T)[3] >= 0


def test_quaternion_order_is_xyzw():
    # 90 deg about z: (x, y, z, w) = (0, 0, sin 45, cos 45)
    T = pose_from_xyz_quat([0, 0, 0], [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0])


def test_rotation_angle_and_transform_points():
    R = Rotation.from_rotvec([0, 0.3, 0]).as_matrix()
    assert rotation_angle(R) == pytest.approx(0.3)
    T = make_pose(R, [1, 2, 3])
    p = np.array([[0.0, 0, 0], [1, 0, 0]])
    assert np.allclose(transform_points(T, p)[0], [1, 2, 3])


@pytest.mark.parametrize(
    "T",
    [
        np.full((4, 4), np.nan),
        np.eye(3),
        np.diag([1.0, 1.0, 2.0, 1.0]),
        np.diag([1.0, 1.0, -1.0, 1.0]),  # reflection
        np.array([[1.0, 0, 0, np.inf], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]),
        "not a pose",
    ],
)
def test_validate_pose_rejects(T):
    with pytest.raises(InvalidPoseError):
        validate_pose(T)


def test_validate_pose_reorthonormalises_small_error():
    R = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    T = make_pose(np.round(R, 7), [0, 0, 1])
    out = validate_pose(T)
    assert np.allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-12)


def test_in_box_is_the_row_wise_test_bounds_included():
    rng = np.random.default_rng(2)
    points = np.round(rng.uniform(-1, 1, (4000, 3)), 1)  # many on the bounds
    lo, hi = np.array([-0.5, -0.2, 0.0]), np.array([0.3, 0.5, 0.4])
    want = np.all((points >= lo) & (points <= hi), axis=1)
    assert want.any() and not want.all()
    assert np.array_equal(in_box(points, lo, hi), want)
    assert not in_box(points[:0], lo, hi).size


def test_squared_distances_are_the_row_wise_sums_bit_for_bit():
    rng = np.random.default_rng(3)
    for scale in (1e-3, 1.0, 1e3):
        points, centre = rng.normal(0, scale, (20000, 3)), rng.normal(0, scale, 3)
        d2 = squared_distances(points, centre)
        assert np.array_equal(d2, ((points - centre) ** 2).sum(axis=1))
        assert np.array_equal(np.sqrt(d2), np.linalg.norm(points - centre, axis=1))
