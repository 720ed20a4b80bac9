"""Data-guiding forces (ssp.forces): kernel, wrench, caching, and a World integration test."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ssp.config import ForcesConfig, PhysicsConfig
from ssp.forces import DataForces, SegmentField, point_pair_forces
from ssp.library.model import ObjectInstance
from ssp.physics import World

G = 9.81
CUBE_EDGE = 0.0508  # the conftest cube
DT = ForcesConfig().max_distance
FRAC = ForcesConfig().gravity_fraction


def pose(x=0.0, y=0.0, z=0.0, yaw_deg=0.0) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = (x, y, z)
    return T


def self_field(model, T=None) -> SegmentField:
    """The model's own surface samples at pose ``T`` as its segment."""
    T = np.eye(4) if T is None else T
    return SegmentField(model.surface_points @ T[:3, :3].T + T[:3, 3], DT)


# ----------------------------------------------------------------------------- kernel
@pytest.mark.parametrize(
    ("r", "expected"),
    [(0.0, 0.0), (DT / 4, 0.75), (DT / 2, 1.0), (DT, 0.0), (1.5 * DT, 0.0), (10 * DT, 0.0)],
)
def test_kernel_magnitude_by_hand(r, expected):
    p_c = np.zeros((1, 3))
    p_d = np.array([[r, 0.0, 0.0]])
    f = point_pair_forces(p_c, p_d, DT)
    assert f.shape == (1, 3)
    # |f| = r (d_t - r) / (d_t^2 / 4): 0 at 0, 3/4 at d_t/4, 1 at d_t/2, 0 at d_t.
    assert np.linalg.norm(f) == pytest.approx(expected, abs=1e-12)
    if expected > 0:
        assert f[0, 0] > 0 and f[0, 1] == 0 and f[0, 2] == 0  # towards the data point


def test_kernel_direction_and_nonfinite_target():
    p_c = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    p_d = np.array([[0.0, -0.005, 0.0], [np.inf, 1.0, 1.0]])
    f = point_pair_forces(p_c, p_d, DT)
    assert f[0, 1] < 0 and f[0, 0] == 0 and f[0, 2] == 0
    np.testing.assert_array_equal(f[1], 0.0)


# ----------------------------------------------------------------------------- field
def test_segment_field_nearest_and_cutoff():
    pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    field = SegmentField(pts, DT)
    q = np.array([[0.003, 0.0, 0.0], [0.098, 0.001, 0.0], [0.05, 0.0, 0.0]])
    tgt, dist = field.nearest(q)
    np.testing.assert_allclose(tgt[0], pts[0])
    np.testing.assert_allclose(tgt[1], pts[1])
    assert dist[0] == pytest.approx(0.003)
    assert dist[2] == np.inf  # 5 cm > d_t: no match, target = the query point itself
    np.testing.assert_allclose(tgt[2], q[2])


def test_segment_field_empty():
    field = SegmentField(np.zeros((0, 3)), DT)
    tgt, dist = field.nearest(np.ones((4, 3)))
    assert len(field) == 0 and np.all(np.isinf(dist))
    np.testing.assert_array_equal(tgt, np.ones((4, 3)))


def test_segment_field_rejects_bad_input():
    with pytest.raises(ValueError):
        SegmentField(np.zeros((3, 2)))
    with pytest.raises(ValueError):
        SegmentField(np.array([[0.0, np.nan, 0.0]]))


# ----------------------------------------------------------------------------- wrench
@pytest.fixture(scope="module")
def cube(cube_model):
    assert np.allclose(cube_model.extents, CUBE_EDGE)
    return cube_model


def symmetric(model):
    """``model`` with its surface samples mirrored in x, y and z (an exactly symmetric cloud)."""
    p = model.surface_points - model.center_of_mass
    signs = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
    pts = (p[None] * signs[:, None]).reshape(-1, 3) + model.center_of_mass
    return dataclasses.replace(model, surface_points=pts, surface_normals=np.zeros_like(pts))


def test_translation_offset_gives_restoring_force(cube):
    cube = symmetric(cube)
    df = DataForces([cube], [self_field(cube)])
    F, tau = df.compute(pose(x=0.005)[None], G)
    fmax = FRAC * cube.mass * G
    assert F.shape == (1, 3) and tau.shape == (1, 3)
    assert F[0, 0] < -0.2 * fmax  # restoring, along -x
    assert np.linalg.norm(F[0]) <= fmax
    assert abs(F[0, 1]) < 0.1 * abs(F[0, 0]) and abs(F[0, 2]) < 0.1 * abs(F[0, 0])
    # Symmetric box and cloud: the torque vanishes.
    assert np.linalg.norm(tau[0]) < 1e-9 * abs(F[0, 0]) * CUBE_EDGE


def test_translation_offset_random_samples_small_torque(cube):
    # The fixture's 200 random samples are not symmetric: small torque, lever arm < 10 % of
    # half an edge.
    F, tau = DataForces([cube], [self_field(cube)]).compute(pose(x=0.005)[None], G)
    assert F[0, 0] < 0
    assert np.linalg.norm(tau[0]) < 0.1 * abs(F[0, 0]) * CUBE_EDGE / 2


def test_force_bounded_by_f_m_g(cube):
    rng = np.random.default_rng(1)
    df = DataForces([cube], [self_field(cube)])
    fmax = FRAC * cube.mass * G
    for _ in range(20):
        off = rng.normal(scale=0.008, size=3)
        F, _ = df.compute(pose(*off, yaw_deg=rng.normal(scale=10))[None], G)
        assert np.linalg.norm(F[0]) <= fmax * (1 + 1e-12)


def test_rotation_offset_gives_restoring_torque(cube):
    # The cube's COM is at the model origin, so this is a pure rotation about the COM.
    df = DataForces([cube], [self_field(cube)])
    _, tau_pos = df.compute(pose(yaw_deg=5.0)[None], G)
    _, tau_neg = df.compute(pose(yaw_deg=-5.0)[None], G)
    assert tau_pos[0, 2] < 0 < tau_neg[0, 2]
    assert abs(tau_pos[0, 0]) < 0.2 * abs(tau_pos[0, 2])
    assert abs(tau_pos[0, 1]) < 0.2 * abs(tau_pos[0, 2])


def test_offset_com_torque_about_com(make_box):
    # Geometry and COM moved away from the model origin: a pure translation must still give
    # about zero torque (the lever arm is taken from the COM, not the origin).
    m = symmetric(make_box("off", (0.04, 0.04, 0.04), 0.1, offset=(0.03, -0.02, 0.01)))
    df = DataForces([m], [self_field(m)])
    F, tau = df.compute(pose(y=0.004)[None], G)
    assert F[0, 1] < 0
    assert np.linalg.norm(tau[0]) < 1e-9 * abs(F[0, 1]) * 0.02


def test_force_scales_linearly_with_mass(make_box):
    light = make_box("light", (0.05,) * 3, 0.1)
    heavy = make_box("heavy", (0.05,) * 3, 0.3)
    df = DataForces([light, heavy], [self_field(light), self_field(heavy)])
    F, tau = df.compute(np.stack([pose(x=0.006, yaw_deg=3)] * 2), G)
    np.testing.assert_allclose(F[1], 3.0 * F[0], rtol=1e-12)
    np.testing.assert_allclose(tau[1], 3.0 * tau[0], rtol=1e-12)
    # and with g and f
    F2, _ = DataForces(
        [light], [self_field(light)], config=ForcesConfig(gravity_fraction=FRAC / 2)
    ).compute(pose(x=0.006, yaw_deg=3)[None], 2 * G)
    np.testing.assert_allclose(F2[0], F[0], rtol=1e-12)


def test_masses_override(cube):
    df = DataForces([cube], [self_field(cube)], masses=[2 * cube.mass])
    ref = DataForces([cube], [self_field(cube)])
    T = pose(x=0.004)[None]
    np.testing.assert_allclose(df.compute(T, G)[0], 2 * ref.compute(T, G)[0], rtol=1e-12)


def test_empty_segment_and_none_give_zero(cube):
    df = DataForces([cube, cube, cube], [SegmentField(np.zeros((0, 3))), None, self_field(cube)])
    F, tau = df.compute(np.stack([pose(x=0.005)] * 3), G)
    np.testing.assert_array_equal(F[:2], 0.0)
    np.testing.assert_array_equal(tau[:2], 0.0)
    assert F[2, 0] < 0


def test_far_segment_gives_zero(cube):
    df = DataForces([cube], [self_field(cube, pose(x=0.5))])
    F, tau = df.compute(pose()[None], G)
    np.testing.assert_array_equal(F, 0.0)
    np.testing.assert_array_equal(tau, 0.0)


def test_at_true_pose_zero_force(cube):
    df = DataForces([cube], [self_field(cube, pose(0.1, 0.2, 0.3, 40))])
    F, tau = df.compute(pose(0.1, 0.2, 0.3, 40)[None], G)
    assert np.abs(F).max() < 1e-12 and np.abs(tau).max() < 1e-12


def test_deterministic(cube):
    T = np.stack([pose(0.004, -0.002, 0.001, 4), pose(-0.003, 0, 0, -7)])
    runs = []
    for _ in range(2):
        df = DataForces([cube, cube], [self_field(cube)] * 2, max_points=120, seed=3)
        runs.append(df.compute(T, G))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert DataForces([cube], [None], max_points=120).counts.tolist() == [120]


def test_max_points_subsample_close_to_full(cube):
    T = pose(x=0.005)[None]
    full = DataForces([cube], [self_field(cube)]).compute(T, G)[0]
    sub = DataForces([cube], [self_field(cube)], max_points=150).compute(T, G)[0]
    assert np.linalg.norm(sub - full) < 0.2 * np.linalg.norm(full)


class _CountingField(SegmentField):
    calls = 0
    sizes: list[int] = []

    def _nearest(self, points):
        type(self).calls += 1
        type(self).sizes.append(len(points))
        return super()._nearest(points)


def test_refresh_cadence_reuses_targets(cube):
    _CountingField.calls = 0
    field = _CountingField(cube.surface_points, DT)
    df = DataForces([cube], [field], refresh_every=3)
    every = DataForces([cube], [self_field(cube)])
    Ts = [pose(x=0.006 - 0.0005 * k) for k in range(7)]
    out = [df.compute(T[None], G)[0] for T in Ts]
    assert _CountingField.calls == 3  # calls 0, 3, 6
    # Refresh calls equal the always-refresh result; the cached ones stay close to it.
    for k, T in enumerate(Ts):
        ref = every.compute(T[None], G)[0]
        if k % 3 == 0:
            np.testing.assert_allclose(out[k], ref, rtol=1e-12, atol=1e-15)
        else:
            # Stale targets act like springs to fixed scene points: same direction, and
            # here within 40 % (200 sparse samples, ~9 mm apart, make the refreshed pairs jump).
            assert out[k][0, 0] < 0
            assert np.linalg.norm(out[k] - ref) < 0.4 * np.linalg.norm(ref)
    df.reset()
    df.compute(Ts[1][None], G)
    assert _CountingField.calls == 4


def test_rejects_bad_arguments(cube):
    with pytest.raises(ValueError):
        DataForces([cube], [])
    with pytest.raises(ValueError):
        DataForces([cube], [None], refresh_every=0)
    with pytest.raises(ValueError):
        DataForces([cube], [None]).compute(np.eye(4), G)


def test_no_objects():
    F, tau = DataForces([], []).compute(np.zeros((0, 4, 4)), G)
    assert F.shape == (0, 3) and tau.shape == (0, 3)


# ----------------------------------------------------------------------------- integration
def test_world_integration_pulls_cube_to_segment(cube_model, make_box):
    """A cube 8 mm to the side of its segment slides back under the data force.

    Low friction (0.05, table and cube): with the default friction 1 a force of at most
    f m g = 0.5 m g can never slide an object resting on the table. The remaining error is where
    the (vanishing) data force equals the friction limit, about 0.5 mm here.
    """
    mu = 0.05
    cube = make_box("slick", (CUBE_EDGE,) * 3, cube_model.mass, friction=mu)
    world = World([ObjectInstance("c", cube)], config=PhysicsConfig(table_friction=mu))
    true = pose(z=CUBE_EDGE / 2)
    df = DataForces([cube], [self_field(cube, true)], refresh_every=1)
    world.set_pose("c", pose(x=0.008, z=CUBE_EDGE / 2))
    g = world.config.gravity
    for _ in range(400):
        F, tau = df.compute(world.pose_array(), g)
        world.apply_wrenches(F, tau)
        world.step(1)
    T = world.get_pose("c")
    assert np.linalg.norm(T[:3, 3] - true[:3, 3]) < 0.001
    assert abs(T[2, 3] - CUBE_EDGE / 2) < 1e-4  # gravity + table keep z
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 1.0


def test_matches_at_a_seen_pose_are_reused_and_the_same(cube):
    """After reset(), an object back at a pose it was matched at is not queried again (the
    objects a search test does not move), and the wrench is the one a fresh query gives."""
    _CountingField.calls = 0
    field = _CountingField(cube.surface_points, DT)
    df = DataForces([cube], [field])
    T = pose(x=0.004, yaw_deg=3)[None]
    first = df.compute(T, G)
    df.compute(pose(x=0.002)[None], G)
    df.reset()
    again = df.compute(T, G)
    assert _CountingField.calls == 2
    fresh = DataForces([cube], [self_field(cube)]).compute(T, G)
    for a, b, c in zip(first, again, fresh, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


# ----------------------------------------------------------------------------- compiled kernel
def test_pairwise_sum_is_numpys_bit_for_bit():
    """The kernel's sums are numpy's (pairwise blocks of 128, eight accumulators), including
    the +0.0 of a sum of negative zeros."""
    from ssp.jit import pairwise_sum

    rng = np.random.default_rng(3)
    for n in [*range(0, 300), 511, 512, 1000, 1031, 4097, 10_000]:
        a = rng.normal(size=n) * 10.0 ** rng.uniform(-9, 3, size=n)
        assert np.float64(pairwise_sum(a, n)).tobytes() == a.sum().tobytes(), n
        z = -np.zeros(n)
        assert np.float64(pairwise_sum(z, n)).tobytes() == z.sum().tobytes(), n


def _numpy_wrenches(df: DataForces, T: np.ndarray, enabled: np.ndarray, g: float):
    """The wrenches of ``df``'s cached targets at poses ``T``, as numpy expressions (the code
    the compiled kernel replaced)."""
    forces, torques = np.zeros((df.n, 3)), np.zeros((df.n, 3))
    idx = np.flatnonzero(enabled)
    r, cog = df._world_samples(T, idx)
    dt = df.max_distance
    diff = df._targets[idx] - r - cog[:, :, None]
    dist = np.sqrt((diff * diff).sum(axis=1))
    scale = df.gravity_fraction * float(g) * df.masses[idx] / np.maximum(df.counts[idx], 1)
    w = np.maximum(dt - dist, 0.0) * df._matched[idx] * (scale / (dt * dt / 4.0))[:, None]
    f = diff * w[:, None, :]
    forces[idx] = f.sum(axis=2)
    rx, ry, rz = r[:, 0], r[:, 1], r[:, 2]
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    torques[idx] = np.stack(
        [
            (ry * fz - rz * fy).sum(axis=1),
            (rz * fx - rx * fz).sum(axis=1),
            (rx * fy - ry * fx).sum(axis=1),
        ],
        axis=1,
    )
    return forces, torques


@pytest.mark.parametrize("camera", [None, (0.4, -0.3, 0.5)], ids=["no camera", "camera"])
def test_compiled_wrenches_equal_the_numpy_formula_bit_for_bit(cube_model, make_box, camera):
    """Objects with different sample counts (padded), disabled ones, one without a segment,
    segments offset so that part of the samples is beyond d_t, between and on refreshes."""
    rng = np.random.default_rng(5)
    box = make_box("box", (0.03, 0.05, 0.02), mass=0.2)
    box = dataclasses.replace(  # fewer samples than the cube: its rows are padded
        box, surface_points=box.surface_points[:137], surface_normals=box.surface_normals[:137]
    )
    models = [cube_model, box, cube_model]
    T0 = np.array([pose(0.0, 0.0, 0.03), pose(0.1, 0.0, 0.02, 30), pose(-0.1, 0.05, 0.03, 10)])
    fields = [
        SegmentField(
            m.surface_points[::2] @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.004, (1, 3)), DT
        )
        for m, T in zip(models, T0, strict=True)
    ]
    fields[2] = None
    df = DataForces(models, fields, refresh_every=2, seed=1, camera_position=camera)
    if camera is None:  # and one object pulled toward a whole pose
        df.set_pose_target(1, pose(0.105, 0.0, 0.02, 28))
    assert len(set(df.counts.tolist())) > 1  # padded
    for step in range(8):
        T = T0.copy()
        T[:, :3, 3] += rng.normal(0, 0.006, (3, 3))
        enabled = np.array([True, step % 3 != 1, True])
        got = df.compute(T, G, enabled)
        want = _numpy_wrenches(df, T, enabled, G)
        assert np.abs(got[0]).max() > 0
        for a, b in zip(got, want, strict=True):
            assert a.tobytes() == b.tobytes()


def test_only_the_samples_facing_the_camera_are_queried(cube_model):
    """The samples facing away do not pull: leaving them out of the query changes nothing."""
    T = pose(0.003, -0.002, 0.03, 4)[None]
    cam = np.array([0.3, -0.4, 0.6])
    field = self_field(cube_model, pose(0.0, 0.0, 0.03))
    _CountingField.calls = 0
    counting = _CountingField(field.points, DT)
    df = DataForces([cube_model], [counting], camera_position=cam)
    got = df.compute(T, G)
    everything = DataForces([cube_model], [field], camera_position=cam)
    everything._match = lambda k, pts, facing, j: everything.fields[k]._nearest(pts)
    want = everything.compute(T, G)
    for a, b in zip(got, want, strict=True):
        assert a.tobytes() == b.tobytes()
    assert 0 < _CountingField.sizes[-1] < len(cube_model.surface_points)
