"""ssp.physics.World: stability at rest, accelerations, contacts, state, validation."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.config import PhysicsConfig
from ssp.errors import InvalidPoseError, PhysicsError, SSPError, UnknownObjectError
from ssp.geometry import make_pose, rotation_angle
from ssp.library.model import ObjectInstance
from ssp.physics import Contacts, DuplicateObjectError, World, WorldMismatchError, WorldState

G = 9.81
H = 0.0508  # edge of the conftest cube (2 inch)


def rot(axis, angle_deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(
        np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(angle_deg)
    ).as_matrix()


def cube_world(model, n, **kw) -> World:
    return World([ObjectInstance(f"c{i}", model) for i in range(n)], **kw)


def tower(model, n, z0=0.0) -> World:
    """n cubes stacked in exact face contact on the table."""
    w = cube_world(model, n)
    for i in range(n):
        w.set_pose(f"c{i}", make_pose(t=[0.0, 0.0, z0 + H / 2 + i * H]))
    return w


# --------------------------------------------------------------------------- construction
def test_build_ids_and_models(cube_model, make_box):
    box = make_box("box", (0.1, 0.05, 0.02), 0.3)
    w = World(
        [ObjectInstance("a", cube_model), ObjectInstance("b", box), ObjectInstance("c", cube_model)]
    )
    assert w.ids == ("a", "b", "c") and len(w) == 3 and "b" in w
    assert cube_model.extents == pytest.approx([H, H, H])
    assert w.model_of("b") is box and w.model_of("c") is cube_model
    assert w.total_mass == pytest.approx(2 * cube_model.mass + 0.3)
    assert w.model.nmesh == 2  # one mesh asset per model class, shared by instances
    # explicit inertial from the model, not from the hull
    assert w.model.body_mass[2] == pytest.approx(0.3)
    assert np.sort(w.model.body_inertia[2]) == pytest.approx(np.sort(np.diag(box.inertia)))
    assert w.timestep == PhysicsConfig().timestep


def test_full_inertia_and_com_are_used(make_box):
    box = make_box("off", (0.08, 0.04, 0.02), 0.2, offset=(0.03, -0.01, 0.005))
    R = rot([1, 2, 3], 40)
    inertia = R @ box.inertia @ R.T  # non-diagonal tensor
    from dataclasses import replace

    model = replace(box, inertia=inertia)
    w = World([ObjectInstance("o", model)])
    m = w.model
    assert m.body_ipos[1] == pytest.approx([0.03, -0.01, 0.005])
    from scipy.spatial.transform import Rotation

    Rb = Rotation.from_quat(np.roll(m.body_iquat[1], -1)).as_matrix()
    assert Rb @ np.diag(m.body_inertia[1]) @ Rb.T == pytest.approx(inertia, abs=1e-12)


def test_duplicate_ids_rejected(cube_model):
    with pytest.raises(DuplicateObjectError, match="'x'"):
        World([ObjectInstance("x", cube_model), ObjectInstance("x", cube_model)])
    assert issubclass(DuplicateObjectError, SSPError)


def test_empty_world_table_only():
    w = World([])
    assert w.ids == ()
    w.step(3)
    w.step(3, quasi_static=False)
    lin, ang = w.acceleration_from_rest()
    assert lin.shape == (0, 3) and ang.shape == (0, 3)
    assert len(w.contacts()) == 0
    w.apply_wrenches(np.zeros((0, 3)), np.zeros((0, 3)))
    w.restore_state(w.save_state())
    assert w.poses() == {}


def test_worlds_are_independent(cube_model):
    a, b = cube_world(cube_model, 1), cube_world(cube_model, 1)
    a.set_pose("c0", make_pose(t=[0, 0, 0.5]))
    b.set_pose("c0", make_pose(t=[0, 0, H / 2]))
    a.step(10)
    assert b.get_pose("c0")[2, 3] == H / 2


# --------------------------------------------------------------------------- poses
def test_pose_round_trip(cube_model):
    w = cube_world(cube_model, 3)
    T = make_pose(rot([0.3, -1, 0.2], 123), [0.1, -0.2, 0.3])
    w.set_pose("c1", T)
    assert w.get_pose("c1") == pytest.approx(T, abs=1e-14)
    w.set_poses({"c0": make_pose(t=[1, 2, 3]), "c2": T})
    P = w.poses()
    assert list(P) == ["c0", "c1", "c2"]
    assert P["c0"][:3, 3] == pytest.approx([1, 2, 3])
    assert P["c2"] == pytest.approx(T, abs=1e-14)
    assert w.pose_array().shape == (3, 4, 4)


def test_set_pose_zeroes_velocity(cube_model):
    w = cube_world(cube_model, 1)
    w.set_pose("c0", make_pose(t=[0, 0, 0.5]))
    w.step(20, quasi_static=False)
    assert np.abs(w.velocities()[0]).max() > 0.5
    w.set_pose("c0", make_pose(t=[0, 0, 0.5]))
    lin, ang = w.velocities()
    assert not lin.any() and not ang.any()


@pytest.mark.parametrize(
    "bad",
    [
        np.full((4, 4), np.nan),
        make_pose(t=[np.inf, 0, 0]),
        make_pose(R=np.diag([1.0, 1.0, 1.1])),  # not orthonormal
        make_pose(R=np.diag([1.0, 1.0, -1.0])),  # reflection
        np.eye(3),  # wrong shape
        "pose",
    ],
    ids=["nan", "inf", "scaled", "reflection", "shape", "string"],
)
def test_invalid_pose_rejected(cube_model, bad):
    w = cube_world(cube_model, 2)
    before = w.pose_array()
    with pytest.raises(InvalidPoseError):
        w.set_pose("c0", bad)
    with pytest.raises(InvalidPoseError):
        w.set_poses({"c1": make_pose(t=[0, 0, 1]), "c0": bad})
    assert np.array_equal(w.pose_array(), before)  # nothing written


def test_unknown_id(cube_model):
    w = cube_world(cube_model, 2)
    calls = [
        lambda: w.set_pose("nope", np.eye(4)),
        lambda: w.get_pose("nope"),
        lambda: w.apply_wrench("nope", [0, 0, 0], [0, 0, 0]),
        lambda: w.set_enabled("nope", False),
        lambda: w.is_enabled("nope"),
        lambda: w.model_of("nope"),
        lambda: w.set_poses({"nope": np.eye(4)}),
    ]
    for call in calls:
        with pytest.raises(UnknownObjectError) as exc:
            call()
        msg = str(exc.value)
        assert "'nope'" in msg and "'c0'" in msg and "'c1'" in msg


def test_wrench_validation(cube_model):
    w = cube_world(cube_model, 2)
    with pytest.raises(ValueError):
        w.apply_wrench("c0", [0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        w.apply_wrench("c0", [0, 0, np.nan], [0, 0, 0])
    with pytest.raises(ValueError):
        w.apply_wrenches(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError):
        w.apply_wrenches(np.full((2, 3), np.inf), np.zeros((2, 3)))
    w.apply_wrenches(np.arange(6.0).reshape(2, 3), -np.arange(6.0).reshape(2, 3))
    f, t = w.wrenches()
    assert f[1] == pytest.approx([3, 4, 5]) and t[0] == pytest.approx([0, -1, -2])
    w.clear_wrenches()
    assert not np.any(w.wrenches()[0])


# --------------------------------------------------------------------------- rest stability
@pytest.mark.parametrize("quasi_static", [False, True], ids=["dynamic", "quasi-static"])
def test_ten_cube_tower_stands_still(cube_model, quasi_static):
    """50.8 mm cubes at 700 kg/m^3 in exact face contact: 2 s without moving."""
    w = tower(cube_model, 10)
    P0 = w.pose_array()
    steps = round(2.0 / w.timestep)
    worst = 0.0
    for _ in range(steps // 25):
        w.step(25, quasi_static=quasi_static)
        worst = max(worst, np.abs(w.pose_array()[:, :3, 3] - P0[:, :3, 3]).max())
    P1 = w.pose_array()
    assert worst < 1e-4  # every cube, every 25 steps, x y z: < 0.1 mm
    angles = rotation_angle(np.swapaxes(P1[:, :3, :3], 1, 2) @ P0[:, :3, :3])
    assert np.degrees(angles).max() < 0.1
    assert w.time == pytest.approx(2.0)


# --------------------------------------------------------------------------- accelerations
def test_free_cube_accelerates_at_g(cube_model):
    w = cube_world(cube_model, 1)
    w.set_pose("c0", make_pose(t=[0, 0, H / 2 + 0.01]))
    lin, ang = w.acceleration_from_rest()
    assert lin[0] == pytest.approx([0, 0, -G], rel=0.01, abs=0.01 * G)
    assert np.abs(ang).max() < 1e-6


def test_acceleration_is_of_the_centre_of_mass_in_world_frame(make_box):
    """Off-centre, rotated body: pure torque gives alpha = I_w^-1 tau and no COM acceleration."""
    box = make_box("off", (0.08, 0.04, 0.02), 0.2, offset=(0.03, -0.01, 0.005))
    w = World([ObjectInstance("o", box)], table=False)
    R = rot([1, 1, 0], 30)
    w.set_pose("o", make_pose(R, [0.0, 0.0, 0.5]))
    lin, ang = w.acceleration_from_rest()
    assert lin[0] == pytest.approx([0, 0, -G], abs=1e-9)
    assert ang[0] == pytest.approx([0, 0, 0], abs=1e-9)
    tau = np.array([0.001, -0.002, 0.0005])
    w.apply_wrench("o", [0.0, 0.0, box.mass * G], tau)
    lin, ang = w.acceleration_from_rest()
    I_world = R @ box.inertia @ R.T
    assert ang[0] == pytest.approx(np.linalg.solve(I_world, tau), rel=1e-6)
    assert lin[0] == pytest.approx([0, 0, 0], abs=1e-9)


def test_wrench_cancelling_weight_holds_a_floating_cube(cube_model):
    w = cube_world(cube_model, 1)
    T = make_pose(rot([0, 1, 0], 20), [0, 0, 0.2])
    w.set_pose("c0", T)
    w.apply_wrench("c0", [0, 0, cube_model.mass * G], [0, 0, 0])
    lin, ang = w.acceleration_from_rest()
    assert np.abs(lin).max() < 1e-9 and np.abs(ang).max() < 1e-9
    w.step(50, quasi_static=False)
    assert w.get_pose("c0") == pytest.approx(T, abs=1e-9)


def test_resting_cube_has_no_acceleration(cube_model):
    w = tower(cube_model, 2)
    w.step(40)
    lin, ang = w.acceleration_from_rest()
    assert np.abs(lin).max() < 0.01 * G and np.abs(ang).max() < 0.1


def test_acceleration_from_rest_does_not_change_the_state(cube_model):
    w = tower(cube_model, 3)
    w.set_pose("c2", make_pose(rot([1, 0, 0], 10), [0.01, 0, 0.2]))
    w.step(5, quasi_static=False)
    before = w.save_state()
    w.acceleration_from_rest()
    assert np.array_equal(w.save_state().state, before.state)


def test_quasi_static_step_moves_g_dt2_per_step(cube_model):
    """From rest each quasi-static step moves a free object by a dt^2 (semi-implicit Euler:
    v = a dt, x += v dt), so a free fall advances g dt^2 per step, linearly in the step count."""
    w = cube_world(cube_model, 1)
    z0 = H / 2 + 0.01
    w.set_pose("c0", make_pose(t=[0, 0, z0]))
    dt = w.timestep
    w.step(1)
    assert z0 - w.get_pose("c0")[2, 3] == pytest.approx(G * dt**2, rel=1e-9)
    w.step(4)
    assert z0 - w.get_pose("c0")[2, 3] == pytest.approx(5 * G * dt**2, rel=1e-9)
    # dynamic steps accelerate instead: sum_{k=1..5} k g dt^2
    w.set_pose("c0", make_pose(t=[0, 0, z0]))
    w.step(5, quasi_static=False)
    assert z0 - w.get_pose("c0")[2, 3] == pytest.approx(15 * G * dt**2, rel=1e-9)


# --------------------------------------------------------------------------- contacts
@pytest.mark.parametrize("cone", ["elliptic", "pyramidal"])
def test_resting_cube_normal_forces_sum_to_weight(cube_model, cone):
    w = cube_world(cube_model, 1, config=PhysicsConfig(cone=cone))
    w.set_pose("c0", make_pose(t=[0.0, 0.0, H / 2]))
    w.step(100, quasi_static=False)
    c = w.contacts()
    assert len(c) >= 3
    assert np.all(c.obj_a == 0) and np.all(c.obj_b == -1)
    assert c.normal_force.sum() == pytest.approx(cube_model.mass * G, rel=0.02)
    assert np.abs(c.depth).max() < 1e-4


def test_two_cube_stack_forces(cube_model):
    w = tower(cube_model, 2)
    w.step(100, quasi_static=False)
    c = w.contacts()
    weight = cube_model.mass * G
    table = c.involving(Contacts.TABLE)
    interface = c.between(0, 1)
    assert len(table) + len(interface) == len(c)
    assert table.normal_force.sum() == pytest.approx(2 * weight, rel=0.02)
    assert interface.normal_force.sum() == pytest.approx(weight, rel=0.02)
    # a -> b: from the bottom cube up into the top one
    assert np.all(interface.obj_a == 0) and np.all(interface.obj_b == 1)
    assert interface.normal[:, 2] == pytest.approx(np.ones(len(interface)), abs=1e-6)


def test_table_contacts_are_obj_b_with_normal_into_the_table(cube_model):
    w = cube_world(cube_model, 2)
    w.set_pose("c0", make_pose(rot([1, 1, 0], 30), [0, 0, 0.02]))  # a corner into the table
    w.set_pose("c1", make_pose(t=[0.2, 0, H / 2 - 0.001]))
    c = w.contacts()
    assert len(c) >= 2 and set(c.obj_a.tolist()) == {0, 1}
    assert np.all(c.obj_b == -1)
    assert c.normal == pytest.approx(np.tile([0, 0, -1.0], (len(c), 1)), abs=1e-9)
    assert np.linalg.norm(c.normal, axis=1) == pytest.approx(np.ones(len(c)))
    recs = c.records()
    assert recs[0].b is None and recs[0].a in ("c0", "c1")
    assert [r.depth for r in c] == pytest.approx(c.depth.tolist())
    with pytest.raises(ValueError):
        c.depth[0] = 1.0  # read-only snapshot


@pytest.mark.parametrize("into", ["table", "cube"])
def test_five_mm_interpenetration_depth(cube_model, into):
    w = cube_world(cube_model, 2)
    w.set_pose("c0", make_pose(t=[0, 0, H / 2]))
    if into == "table":
        w.set_pose("c1", make_pose(t=[0.3, 0, H / 2 - 0.005]))
        pair = w.contacts().between(1, -1)
    else:
        w.set_pose("c1", make_pose(t=[0.01, 0.005, 1.5 * H - 0.005]))
        pair = w.contacts().between(0, 1)
    assert len(pair) > 0
    assert pair.max_depth == pytest.approx(0.005, abs=3e-4)
    assert w.time == 0.0  # read before any step


def test_contacts_do_not_change_the_state(cube_model):
    w = tower(cube_model, 3)
    w.step(3, quasi_static=False)
    before = w.save_state()
    c1 = w.contacts()
    c2 = w.contacts()
    assert np.array_equal(c1.normal_force, c2.normal_force)
    assert np.array_equal(w.save_state().state, before.state)


def test_contact_margin_setting(cube_model):
    w = cube_world(cube_model, 1, config=PhysicsConfig(contact_margin=0.001))
    w.set_pose("c0", make_pose(t=[0, 0, H / 2 + 0.0005]))
    c = w.contacts()
    assert len(c) > 0 and c.depth == pytest.approx(np.full(len(c), -0.0005), abs=1e-6)
    assert w.data.contact.includemargin == pytest.approx(np.full(len(c), 0.001))
    w0 = cube_world(cube_model, 1, config=PhysicsConfig(contact_margin=0.0))
    w0.set_pose("c0", make_pose(t=[0, 0, H / 2 + 0.0005]))
    assert len(w0.contacts()) == 0


# --------------------------------------------------------------------------- enable / disable
def test_disabled_object_neither_moves_nor_collides(cube_model):
    w = cube_world(cube_model, 2)
    T0 = make_pose(rot([0, 0, 1], 15), [0, 0, 0.2])
    w.set_pose("c0", T0)  # floating, would fall
    w.set_pose("c1", make_pose(t=[0, 0, 0.3]))  # above c0
    w.set_enabled("c0", False)
    T0 = w.get_pose("c0")  # as stored (quaternion round trip)
    assert not w.is_enabled("c0") and w.is_enabled("c1")
    w.apply_wrench("c0", [1, 2, 3], [0.1, 0, 0])  # no effect while disabled
    w.step(80, quasi_static=False)
    assert np.array_equal(w.get_pose("c0"), T0)
    assert not np.any(w.velocities()[0][0])
    # c1 fell through c0 onto the table
    assert w.get_pose("c1")[2, 3] == pytest.approx(H / 2, abs=2e-4)
    c = w.contacts()
    assert np.all((c.obj_a != 0) & (c.obj_b != 0))
    lin, ang = w.acceleration_from_rest()
    assert not lin[0].any() and not ang[0].any()
    # enabling restores collisions: c0 placed into c1 now reports a contact
    w.clear_wrenches()
    w.set_pose("c0", make_pose(t=[0, 0, 1.5 * H - 0.001]))
    assert len(w.contacts().between(0, 1)) == 0
    w.set_enabled("c0", True)
    assert len(w.contacts().between(0, 1)) > 0


def test_disabled_object_quasi_static_is_exact(cube_model):
    w = cube_world(cube_model, 2)
    T0 = make_pose(t=[0.3, 0, 0.1])
    w.set_pose("c0", T0)
    w.set_pose("c1", make_pose(t=[0, 0, H / 2]))
    w.set_enabled("c0", False)
    T0 = w.get_pose("c0")
    w.step(30)
    assert np.array_equal(w.get_pose("c0"), T0)


def _sleep_script(w: World) -> list[np.ndarray]:
    """Poses after each stage of a sequence of enable/disable changes, steps and a restore."""
    out = []
    for i in range(3):  # a 3-cube stack, two cubes leaning on it, one floating
        w.set_pose(f"c{i}", make_pose(rot([0, 0, 1], 5 * i), [0, 0, H / 2 + i * (H + 0.001)]))
    w.set_pose("c3", make_pose(rot([0, 1, 0], 12), [0.052, 0, H / 2 + 0.004]))
    w.set_pose("c4", make_pose(rot([1, 0, 0], 9), [0, 0.053, H / 2 + 0.003]))
    w.set_pose("c5", make_pose(t=[0.3, 0, 0.2]))
    w.set_enabled("c3", False)
    w.set_enabled("c5", False)
    w.step(25)
    out.append(w.pose_array())
    s = w.save_state()
    w.set_enabled("c4", False)
    w.step(10, quasi_static=False)
    out.append(w.pose_array())
    w.set_enabled("c3", True)  # woken: it now leans on the stack and moves
    w.step(15)
    out.append(w.pose_array())
    w.set_enabled("c3", False)
    w.set_enabled("c4", True)
    w.contacts()
    w.acceleration_from_rest()
    w.step(12)
    out.append(w.pose_array())
    for i in range(6):
        w.set_enabled(f"c{i}", True)
    w.step(10)
    out.append(w.pose_array())
    w.restore_state(s)
    w.step(20)
    out.append(w.pose_array())
    return out


def test_disabled_objects_sleep_and_the_rest_moves_as_when_they_are_held(cube_model):
    held = _sleep_script(cube_world(cube_model, 6, config=PhysicsConfig(sleep_disabled=False)))
    w = cube_world(cube_model, 6)
    slept = _sleep_script(w)
    for a, b in zip(held, slept, strict=True):
        assert np.array_equal(a, b)
    assert not np.array_equal(held[1][3], held[2][3])  # c3 moved once enabled again
    # after the restore c3 and c5 are disabled: MuJoCo skips them
    assert list(w.data.tree_asleep[[3, 5]]) == [3, 5]
    assert np.all(w.data.tree_asleep[[0, 1, 2, 4]] < 0) and w.data.nv_awake == 24
    for i in range(6):
        w.set_enabled(f"c{i}", True)
    w.step(1)
    assert w.data.nv_awake == 36 and np.all(w.data.tree_asleep < 0)


def test_enabling_a_sleeping_object_restores_its_contacts_and_motion(cube_model):
    w = cube_world(cube_model, 2)
    w.set_pose("c1", make_pose(t=[0, 0, H / 2]))
    w.set_pose("c0", make_pose(t=[0.2, 0, 0.1]))
    w.set_enabled("c0", False)
    w.step(5)
    assert w.data.tree_asleep[0] == 0  # asleep
    w.set_pose("c0", make_pose(t=[0, 0, 1.5 * H - 0.001]))  # into c1, while asleep
    assert len(w.contacts().between(0, 1)) == 0
    w.set_enabled("c0", True)
    assert len(w.contacts().between(0, 1)) > 0
    z = w.get_pose("c0")[2, 3]
    w.step(20)
    assert w.get_pose("c0")[2, 3] > z  # pushed out of c1


# --------------------------------------------------------------------------- state
def _busy_world(model) -> World:
    w = cube_world(model, 5)
    for i in range(4):
        w.set_pose(
            f"c{i}",
            make_pose(rot([1, i, 0.5], 7 * i), [0.01 * i, 0.005 * i, H / 2 + i * (H + 0.002)]),
        )
    w.set_pose("c4", make_pose(t=[0.2, 0, 0.1]))
    return w


@pytest.mark.parametrize("quasi_static", [False, True], ids=["dynamic", "quasi-static"])
def test_save_restore_is_bit_identical(cube_model, quasi_static):
    w = _busy_world(cube_model)
    w.step(20, quasi_static=False)  # moving, with contacts and warm start
    w.apply_wrench("c1", [0.05, 0, 0.2], [0, 0.001, 0])
    w.set_enabled("c4", False)
    s = w.save_state()
    w.step(40, quasi_static=quasi_static)
    P1 = w.pose_array()
    # change everything the state covers, then restore
    w.clear_wrenches()
    w.set_enabled("c4", True)
    w.set_pose("c0", make_pose(t=[1, 1, 1]))
    w.step(7, quasi_static=not quasi_static)
    w.restore_state(s)
    assert not w.is_enabled("c4")
    assert w.wrenches()[0][1] == pytest.approx([0.05, 0, 0.2])
    w.contacts()  # queries in between must not perturb the replay
    w.acceleration_from_rest()
    w.step(40, quasi_static=quasi_static)
    assert np.array_equal(w.pose_array(), P1)


def test_world_state_is_immutable_and_tied_to_its_world(cube_model):
    w1, w2 = cube_world(cube_model, 1), cube_world(cube_model, 1)
    s = w1.save_state()
    assert isinstance(s, WorldState) and s.time == 0.0
    w1.step(3)
    assert w1.save_state().time == pytest.approx(3 * w1.timestep)
    with pytest.raises(ValueError):
        s.state[0] = 1.0
    with pytest.raises(WorldMismatchError):
        w2.restore_state(s)
    with pytest.raises(TypeError):
        w1.restore_state("state")


def test_independent_worlds_are_deterministic(cube_model, make_box):
    def run():
        plank = make_box("plank", (0.2, 0.04, 0.02), 0.15, friction=0.6)
        w = World(
            [ObjectInstance("p", plank)] + [ObjectInstance(f"c{i}", cube_model) for i in range(3)]
        )
        w.set_pose("p", make_pose(rot([0, 1, 0], 10), [0, 0, 0.06]))
        for i in range(3):
            w.set_pose(
                f"c{i}", make_pose(rot([1, 0, 1], 20 * i), [0.05 * (i - 1), 0.0, 0.12 + 0.06 * i])
            )
        w.step(60, quasi_static=False)
        w.step(20)
        return w.pose_array(), w.contacts().normal_force

    (P1, f1), (P2, f2) = run(), run()
    assert np.array_equal(P1, P2) and np.array_equal(f1, f2)


# --------------------------------------------------------------------------- failures
def test_divergence_raises_physics_error_and_state_is_restorable(cube_model, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the warning to ./MUJOCO_LOG.TXT
    w = cube_world(cube_model, 1)
    w.set_pose("c0", make_pose(t=[0, 0, 0.2]))
    s = w.save_state()
    w.apply_wrench("c0", [1e30, 0, 0], [0, 0, 0])
    with pytest.raises(PhysicsError, match="diverged"):
        w.step(3)
    w.restore_state(s)
    w.step(3)
    assert w.get_pose("c0")[2, 3] == pytest.approx(0.2 - 3 * G * w.timestep**2)


def test_step_count_validation(cube_model):
    w = cube_world(cube_model, 1)
    with pytest.raises(ValueError):
        w.step(-1)
    w.step(0)
    assert w.time == 0.0


def test_unusable_model_is_reported(make_box):
    from dataclasses import replace

    bad = replace(make_box("b"), mass=0.0)
    with pytest.raises(PhysicsError, match="mass"):
        World([ObjectInstance("b", bad)])


def test_collision_geometry_follows_the_model_frame(make_box):
    """Geometry away from the model origin, rotated: it must land on the table where the pose
    puts it (MuJoCo re-centres meshes internally; the body frame must stay the model frame)."""
    box = make_box("off", (0.08, 0.04, 0.02), 0.2, offset=(0.03, -0.01, 0.005))
    w = World([ObjectInstance("o", box)])
    T = make_pose(rot([0, 0, 1], 35), [0.1, 0.2, 0.0])
    low = (box.mesh.vertices @ T[:3, :3].T + T[:3, 3])[:, 2].min()
    T[2, 3] += 0.001 - low  # lowest face 1 mm above the table
    w.set_pose("o", T)
    w.step(100, quasi_static=False)
    P = w.get_pose("o")
    verts = box.mesh.vertices @ P[:3, :3].T + P[:3, 3]
    assert verts[:, 2].min() == pytest.approx(0.0, abs=5e-5)
    assert P[:2, 3] == pytest.approx(T[:2, 3], abs=1e-6)
    c = w.contacts()
    footprint = verts[verts[:, 2] < 1e-3, :2]
    assert np.all(c.position[:, :2] >= footprint.min(0) - 1e-6)
    assert np.all(c.position[:, :2] <= footprint.max(0) + 1e-6)


# --------------------------------------------------------------------------- many-part models
@pytest.fixture(scope="module")
def grid_model():
    """A 50 x 50 x 40 mm box as 100 touching 10 mm convex parts (a many-part model)."""
    import trimesh

    from ssp.config import LibraryConfig
    from ssp.library import build_model

    parts = [
        trimesh.creation.box(
            (0.0102,) * 3,
            trimesh.transformations.translation_matrix(
                ((i - 2) * 0.01, (j - 2) * 0.01, (k - 1.5) * 0.01)
            ),
        )
        for i in range(5)
        for j in range(5)
        for k in range(4)
    ]
    mesh = trimesh.creation.box((0.0502, 0.0502, 0.0402))
    return build_model("grid", mesh, config=LibraryConfig(), convex_parts=parts)


def test_many_part_world_builds_and_overlaps_without_mujoco_warnings(
    grid_model, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    w = World([ObjectInstance(f"g{i}", grid_model) for i in range(3)])
    # the identity-pose forward at construction computed no contacts (3 x 100 parts overlap)
    assert all(int(x.number) == 0 for x in w.data.warning)
    # two of them pushed fully into each other and into the table: still within the arena
    w.set_pose("g0", make_pose(t=[0, 0, 0.01]))
    w.set_pose("g1", make_pose(t=[0, 0, 0.01]))
    w.set_pose("g2", make_pose(t=[0.2, 0, 0.0201]))
    c = w.contacts()
    assert len(c.between(0, 1)) > 5000
    w.acceleration_from_rest()
    w.step(2)
    assert all(int(x.number) == 0 for x in w.data.warning)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_contact_overflow_raises_physics_error_and_logs_not_to_a_file(
    grid_model, tmp_path, monkeypatch, caplog
):
    import ssp.physics.world as world_module

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(world_module, "_logged_warnings", set())  # each text is logged once
    w = World([ObjectInstance(f"g{i}", grid_model) for i in range(4)])
    w.set_poses({f"g{i}": make_pose(t=[0, 0, 0.01]) for i in range(4)})  # 4 deep overlaps
    with caplog.at_level("WARNING", logger="ssp.physics.mujoco"):
        with pytest.raises(PhysicsError, match="buffer full"):
            w.contacts()
        with pytest.raises(PhysicsError, match="buffer full"):
            w.acceleration_from_rest()
    assert any("MuJoCo" in r.message for r in caplog.records)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def _model_arrays(m) -> dict[str, np.ndarray]:
    out = {}
    for name in dir(m):
        if name.startswith("_"):
            continue
        try:
            value = getattr(m, name)
        except Exception:  # noqa: BLE001 (an attribute the bindings cannot read here)
            continue
        if isinstance(value, np.ndarray):
            out[name] = value
    return out


def test_a_scene_compiled_before_is_copied_not_compiled_again(cube_model, make_box):
    """The same models in the same order give the same MjModel whatever the ids: the copy of
    the earlier compile equals a fresh compile array for array, and changing it leaves the
    kept one alone."""
    from ssp.physics import mjcf

    block = make_box("block", (0.1, 0.05, 0.05), mass=0.2)
    cfg = PhysicsConfig()
    first = [ObjectInstance("a", cube_model), ObjectInstance("b", block)]
    renamed = [ObjectInstance("x", cube_model), ObjectInstance("y", block)]
    m1 = mjcf.compiled_mjmodel(first, table=True, config=cfg)
    m2 = mjcf.compiled_mjmodel(renamed, table=True, config=cfg)
    fresh = mjcf.build_mjmodel(renamed, table=True, config=cfg)
    a2, af = _model_arrays(m2), _model_arrays(fresh)
    assert a2.keys() == af.keys() and len(a2) > 50
    for name, value in af.items():
        assert np.array_equal(a2[name], value), name
    m2.geom_contype[:] = 0  # what World does to disable an object: the kept compile unchanged
    m3 = mjcf.compiled_mjmodel(first, table=True, config=cfg)
    assert np.array_equal(m3.geom_contype, m1.geom_contype) and m3.geom_contype.any()
    # another order, another table or other settings are other scenes
    swapped = mjcf.compiled_mjmodel(first[::-1], table=True, config=cfg)
    assert not np.array_equal(swapped.body_mass, m1.body_mass)
    assert mjcf.compiled_mjmodel(first, table=False, config=cfg).ngeom < m1.ngeom
    slow = mjcf.compiled_mjmodel(first, table=True, config=PhysicsConfig(timestep=0.004))
    assert slow.opt.timestep == 0.004 != m1.opt.timestep


def test_a_world_from_the_kept_compile_steps_as_a_fresh_one(cube_model):
    """Two worlds of the same scene (the second from the kept compile) step bit for bit alike."""
    poses = [make_pose(t=[0.0, 0.0, 0.03]), make_pose(t=[0.0, 0.0, 0.08])]
    runs = []
    for ids in (("a", "b"), ("c", "d")):
        w = World([ObjectInstance(i, cube_model) for i in ids])
        for i, T in zip(ids, poses, strict=True):
            w.set_pose(i, T)
        for _ in range(50):
            w.step()
        runs.append(w.pose_array())
    assert np.array_equal(runs[0], runs[1])
