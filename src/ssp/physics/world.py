"""``World``: one MuJoCo scene of rigid objects on a table, with exact save/restore.

Conventions (DESIGN section 3): metres, world frame z up, gravity along -z, table top at z = 0.
A pose is ``T_world_obj``, the 4x4 transform of the object's *model frame* (the body frame of its
free body; its centre of mass is ``model.center_of_mass`` in that frame). Objects are listed in
the order of the instances given to the constructor (``World.ids``); every vectorised method
uses that order. New objects start at the identity pose (the caller places them).

MuJoCo-specific behaviour worth knowing:

- Contacts are stiff (notes/engines.md section 2): solref ``(2 dt, 1)``, solimp from the config.
  They engage within a small margin (:func:`ssp.physics.mjcf.contact_margin`, 0.02 mm at
  dt = 5 ms) before the surfaces touch, so resting objects sit at their geometric contact and
  contacts may report a small negative depth (a gap).
- MuJoCo combines the friction of two touching geoms by taking the larger coefficient.
- Quasi-static stepping (the default) zeroes every velocity before each step, so an object at
  rest that feels a net acceleration ``a`` moves by ``a dt^2`` per step (semi-implicit Euler:
  ``v = a dt``, then ``x += v dt``); a free-falling object thus moves ``g dt^2`` per step
  (0.245 mm at dt = 5 ms), not the ``g dt^2 / 2`` of an exact fall.
- A disabled object keeps its pose and zero velocity exactly and has no contacts; enabling it
  restores its collisions. With ``PhysicsConfig.sleep_disabled`` (the default) it is put to
  sleep (MuJoCo's sleeping trees, ``mjENBL_SLEEP``), so a step skips its dynamics and costs what
  the enabled objects cost, not the whole world; a disabled object that cannot sleep (a wrench
  is applied to it), or every one with sleeping off, is restored after every step. The enabled
  objects never fall asleep (their countdown is reset before every step), and sleeping is off
  while every object is enabled.
- MuJoCo's warnings go to the ``ssp.physics.mujoco`` logger (each distinct text once per
  process), never to ``MUJOCO_LOG.TXT`` in the current folder; a contact or constraint buffer
  overflow in :meth:`World.step`, :meth:`World.contacts` or
  :meth:`World.acceleration_from_rest` raises :class:`PhysicsError`.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from ssp.config import PhysicsConfig
from ssp.errors import (
    DuplicateObjectError,
    PhysicsError,
    UnknownObjectError,
    WorldMismatchError,
)
from ssp.geometry import validate_pose
from ssp.library.model import ObjectInstance, ObjectModel
from ssp.physics.contacts import Contacts
from ssp.physics.mjcf import compiled_mjmodel

_STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
_W = mujoco.mjtWarning
#: MuJoCo warnings that mean the simulation result is not trustworthy.
_FATAL_WARNINGS = {
    int(_W.mjWARN_BADQACC): "NaN/Inf or huge acceleration (simulation diverged; MuJoCo reset it)",
    int(_W.mjWARN_BADQPOS): "NaN/Inf or huge position (simulation diverged; MuJoCo reset it)",
    int(_W.mjWARN_BADQVEL): "NaN/Inf or huge velocity (simulation diverged; MuJoCo reset it)",
    int(_W.mjWARN_CONTACTFULL): "contact buffer full (contacts were dropped)",
    int(_W.mjWARN_CNSTRFULL): "constraint buffer full (constraints were dropped)",
}
_FATAL_IDX = np.array(sorted(_FATAL_WARNINGS), dtype=int)
_SLEEP = int(mujoco.mjtEnableBit.mjENBL_SLEEP)
#: ``MjData.tree_asleep`` of a fully awake tree (MuJoCo counts it up to -1, "ready to sleep").
_AWAKE = -(1 + mujoco.mjMINAWAKE)
_world_serial = itertools.count(1)
_mujoco_log = logging.getLogger("ssp.physics.mujoco")
_logged_warnings: set[str] = set()


def _log_mujoco_warning(text: str) -> None:
    """MuJoCo's user warning handler: log each distinct message once (counters stay exact)."""
    text = str(text).strip()
    key = text.split("Time =")[0]
    if key not in _logged_warnings:
        _logged_warnings.add(key)
        _mujoco_log.warning("MuJoCo: %s (further identical warnings are not logged)", text)


def _install_warning_handler() -> None:
    """Route MuJoCo's warnings to logging instead of stdout and ./MUJOCO_LOG.TXT, unless the
    application has installed its own handler."""
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_log_mujoco_warning)


@dataclass(frozen=True, eq=False)
class WorldState:
    """A saved :class:`World` state: MuJoCo's full integration state plus the enabled flags.

    The integration state (``mjSTATE_INTEGRATION``) holds time, positions, velocities, the
    solver warm start and the applied wrenches, so restoring it and stepping reproduces the
    original trajectory bit for bit. Immutable: the array is a read-only copy. A state can only
    be restored into the world that saved it.
    """

    world_serial: int
    state: np.ndarray
    enabled: tuple[bool, ...]

    @property
    def time(self) -> float:
        """Simulated time at saving, s."""
        return float(self.state[0])


def _quat_product_map() -> np.ndarray:
    """(16, 9) matrix M with ``R.ravel() |q|^2 = (q q^T).ravel() @ M`` for q = (w, x, y, z)."""
    w, x, y, z = range(4)
    entries = [  # row-major R entries: (coefficient, i, j) terms of q_i q_j
        [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)],
        [(2, x, y), (-2, w, z)],
        [(2, x, z), (2, w, y)],
        [(2, x, y), (2, w, z)],
        [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)],
        [(2, y, z), (-2, w, x)],
        [(2, x, z), (-2, w, y)],
        [(2, y, z), (2, w, x)],
        [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)],
    ]
    M = np.zeros((16, 9))
    for col, terms in enumerate(entries):
        for c, i, j in terms:
            M[4 * i + j, col] += c
    return M


_QUAT_MAP = _quat_product_map()


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) from MuJoCo quaternions (n, 4) ``(w, x, y, z)``, not
    necessarily unit (few numpy calls: this runs on every data-force step)."""
    qq = (q[:, :, None] * q[:, None, :]).reshape(-1, 16)
    R = qq @ _QUAT_MAP
    R /= qq[:, ::5].sum(axis=1, keepdims=True)  # |q|^2 from the diagonal
    return R.reshape(-1, 3, 3)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (faster than np.cross for small n)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def _vec3(x, what: str) -> np.ndarray:
    try:
        v = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not numeric ({exc})") from exc
    if v.shape != (3,):
        raise ValueError(f"{what}: expected shape (3,), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{what}: contains NaN or infinite values")
    return v


class World:
    """Rigid objects on an (optional) infinite table, simulated by MuJoCo.

    Args:
        instances: the objects, each an :class:`ObjectInstance` with a unique ``id``. May be
            empty (table only).
        table: add the table, an infinite plane at z = 0.
        config: physics settings (defaults: ``PhysicsConfig()``).

    Raises:
        DuplicateObjectError: two instances share an id.
        PhysicsError: a model cannot be simulated (bad mass properties, degenerate hull).

    Each world owns one ``MjModel``/``MjData`` pair; worlds are independent of each other.
    """

    def __init__(
        self,
        instances: Sequence[ObjectInstance],
        *,
        table: bool = True,
        config: PhysicsConfig | None = None,
    ) -> None:
        instances = tuple(instances)
        for inst in instances:
            if not isinstance(getattr(inst, "model", None), ObjectModel) or not isinstance(
                getattr(inst, "id", None), str
            ):
                raise TypeError(f"expected ObjectInstance(id: str, model), got {inst!r:.80}")
        ids = tuple(inst.id for inst in instances)
        dups = sorted(i for i, count in Counter(ids).items() if count > 1)
        if dups:
            raise DuplicateObjectError(f"duplicate object ids in the world: {dups}")

        self._config = config if config is not None else PhysicsConfig()
        _install_warning_handler()
        self._instances = instances
        self._ids = ids
        self._index = {oid: k for k, oid in enumerate(ids)}
        self._has_table = bool(table)
        self._serial = next(_world_serial)

        m = compiled_mjmodel(instances, table=self._has_table, config=self._config)
        d = mujoco.MjData(m)
        self._m, self._d = m, d
        n = len(ids)
        self._n = n
        if m.nbody != n + 1 or m.nq != 7 * n or m.nv != 6 * n:
            raise PhysicsError("internal: unexpected MuJoCo model layout")

        # Views into MjData (stable for the lifetime of d).
        self._qpos = d.qpos.reshape(n, 7)
        self._qvel_flat = d.qvel
        self._qvel = d.qvel.reshape(n, 6)
        self._xfrc = d.xfrc_applied[1:]
        self._warn = d.warning.number

        self._geom_obj = np.asarray(m.geom_bodyid, dtype=int) - 1  # -1: table (world body)
        self._obj_geoms = [np.flatnonzero(self._geom_obj == k) for k in range(n)]
        self._contype0 = m.geom_contype.copy()
        self._conaffinity0 = m.geom_conaffinity.copy()
        self._com_local = np.array(m.body_ipos[1:], dtype=float)  # (n, 3) COM in body frame
        self._mass = np.array(m.body_mass[1:], dtype=float)
        self._friction0 = np.array(m.geom_friction[:, 0], dtype=float)
        self._friction_scale = 1.0
        self._enabled = np.ones(n, dtype=bool)
        self._enabled_ext = np.ones(n + 1, dtype=bool)  # index -1 (table) always enabled
        self._frozen_q = np.zeros(0, dtype=int)  # qpos indices of disabled objects
        self._frozen_v = np.zeros(0, dtype=int)  # qvel indices of disabled objects
        # Sleeping trees: object k is tree k (one free body each), body k + 1.
        self._sleep = bool(self._config.sleep_disabled) and np.array_equal(
            m.body_treeid[1:], np.arange(n)
        )
        self._awake_trees = np.arange(n)  # trees kept awake: the enabled objects
        self._sleep_synced = True
        self._state_size = mujoco.mj_stateSize(m, _STATE_SPEC)
        self._scratch = np.empty(self._state_size)
        self._forward_at_model_poses()

    def _forward_at_model_poses(self) -> None:
        """mj_forward of the freshly built (or reset) world, without collision detection.

        Every object then sits at the identity pose, all overlapping: their contacts would be
        meaningless and, for many-part models, overflow the arena. The next :meth:`contacts`
        or :meth:`step` computes them at the poses the caller has set.
        """
        m = self._m
        flags = m.opt.disableflags
        m.opt.disableflags = flags | int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        try:
            mujoco.mj_forward(m, self._d)
        finally:
            m.opt.disableflags = flags
        self._forward_current = False

    # ------------------------------------------------------------------ objects
    @property
    def ids(self) -> tuple[str, ...]:
        """Object ids in order (the order of every vectorised method)."""
        return self._ids

    def __len__(self) -> int:
        return self._n

    def __contains__(self, oid: object) -> bool:
        return oid in self._index

    def __repr__(self) -> str:
        return f"World({self._n} objects, table={self._has_table}, t={self.time:.4f} s)"

    @property
    def config(self) -> PhysicsConfig:
        return self._config

    @property
    def has_table(self) -> bool:
        return self._has_table

    @property
    def timestep(self) -> float:
        """Simulation step dt, s."""
        return float(self._m.opt.timestep)

    @property
    def time(self) -> float:
        """Simulated time, s."""
        return float(self._d.time)

    @property
    def masses(self) -> np.ndarray:
        """(n,) object masses, kg, in id order."""
        return self._mass.copy()

    @property
    def total_mass(self) -> float:
        """Sum of the object masses, kg."""
        return float(self._mass.sum())

    @property
    def model(self) -> mujoco.MjModel:
        """The MuJoCo model (engine-specific; for advanced use, do not restructure it)."""
        return self._m

    @property
    def data(self) -> mujoco.MjData:
        """The MuJoCo data (engine-specific; writing to it bypasses this class's bookkeeping)."""
        return self._d

    def index(self, oid: str) -> int:
        """Position of object ``oid`` in :attr:`ids`; :class:`UnknownObjectError` if absent."""
        try:
            return self._index[oid]
        except (KeyError, TypeError):
            known = ", ".join(repr(i) for i in self._ids[:10])
            if self._n > 10:
                known += f", ... ({self._n} in all)"
            raise UnknownObjectError(
                f"unknown object id {oid!r}; this world has: {known or 'no objects'}"
            ) from None

    def model_of(self, oid: str) -> ObjectModel:
        """The :class:`ObjectModel` of object ``oid``."""
        return self._instances[self.index(oid)].model

    # ------------------------------------------------------------------ poses
    def _write_pose(self, k: int, T: np.ndarray) -> None:
        q = self._qpos[k]
        q[:3] = T[:3, 3]
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(T[:3, :3]).ravel())
        q[3:] = quat
        self._qvel[k] = 0.0

    def set_pose(self, oid: str, T_world_obj: np.ndarray) -> None:
        """Place object ``oid`` at ``T_world_obj`` (4x4, model frame) and zero its velocity.

        Raises :class:`InvalidPoseError` for NaN/inf, a wrong shape or a non-rigid matrix.
        """
        k = self.index(oid)
        T = validate_pose(T_world_obj, what=f"pose of {oid!r}")
        self._write_pose(k, T)
        self._forward_current = False

    def set_poses(self, poses: Mapping[str, np.ndarray]) -> None:
        """Set several poses at once (all validated before any is written)."""
        items = [
            (self.index(oid), validate_pose(T, what=f"pose of {oid!r}")) for oid, T in poses.items()
        ]
        for k, T in items:
            self._write_pose(k, T)
        self._forward_current = False

    def get_pose(self, oid: str) -> np.ndarray:
        """Current ``T_world_obj`` (4x4) of object ``oid``."""
        k = self.index(oid)
        T = np.eye(4)
        T[:3, :3] = _quat_to_mat(self._qpos[k : k + 1, 3:])[0]
        T[:3, 3] = self._qpos[k, :3]
        return T

    def pose_array(self) -> np.ndarray:
        """All poses as an (n, 4, 4) array in id order."""
        T = np.zeros((self._n, 4, 4))
        T[:, :3, :3] = _quat_to_mat(self._qpos[:, 3:])
        T[:, :3, 3] = self._qpos[:, :3]
        T[:, 3, 3] = 1.0
        return T

    def configuration(self) -> np.ndarray:
        """(n, 7) copy of every object's ``[x, y, z, qw, qx, qy, qz]`` (m; unit quaternion),
        id order: a cheap snapshot to measure motion between steps."""
        return self._qpos.copy()

    def poses(self) -> dict[str, np.ndarray]:
        """``{id: T_world_obj}`` for every object."""
        return dict(zip(self._ids, self.pose_array(), strict=True))

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lin, ang)``, each (n, 3), world frame: centre-of-mass linear velocity (m/s) and
        angular velocity (rad/s) of every object, in id order."""
        return self._com_motion(self._qvel)

    def _com_motion(self, qv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Convert free-joint (origin linear world, angular body) rows to (COM linear, angular)
        in the world frame. Exact for accelerations only at zero angular velocity."""
        if self._n == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        R = _quat_to_mat(self._qpos[:, 3:])
        ang = (R @ qv[:, 3:, None])[:, :, 0]
        r = (R @ self._com_local[:, :, None])[:, :, 0]
        return qv[:, :3] + _cross(ang, r), ang

    # ------------------------------------------------------------------ enable / disable
    def is_enabled(self, oid: str) -> bool:
        return bool(self._enabled[self.index(oid)])

    @property
    def enabled(self) -> np.ndarray:
        """(n,) bool copy of the enabled flags, id order."""
        return self._enabled.copy()

    def set_enabled(self, oid: str, enabled: bool) -> None:
        """Enable or disable object ``oid``.

        A disabled object neither collides nor moves (it sleeps, or its pose and zero velocity
        are restored after every step; wrenches on it have no effect) and is left out of
        :meth:`contacts` and :meth:`acceleration_from_rest`. Enabling it restores its collisions.
        """
        k = self.index(oid)
        enabled = bool(enabled)
        if enabled == self._enabled[k]:
            return
        self._enabled[k] = enabled
        self._apply_enabled()
        if not enabled:
            self._qvel[k] = 0.0

    def _apply_enabled(self) -> None:
        m = self._m
        off = np.flatnonzero(~self._enabled)
        geoms = np.concatenate([self._obj_geoms[k] for k in off]) if len(off) else np.zeros(0, int)
        m.geom_contype[:] = self._contype0
        m.geom_conaffinity[:] = self._conaffinity0
        m.geom_contype[geoms] = 0
        m.geom_conaffinity[geoms] = 0
        self._enabled_ext[: self._n] = self._enabled
        self._frozen_q = (7 * off[:, None] + np.arange(7)).ravel()
        self._frozen_v = (6 * off[:, None] + np.arange(6)).ravel()
        self._awake_trees = np.flatnonzero(self._enabled)
        self._sleep_synced = False
        self._forward_current = False

    def _sync_sleep(self) -> None:
        """Make MuJoCo's sleeping trees follow the enabled flags; called before every step and
        forward computation after the flags changed.

        MuJoCo wakes a tree that feels an applied force at its next kinematics pass (and updates
        its sleep bookkeeping), so an enabled object that sleeps is woken by a momentary
        ``xfrc_applied`` around ``mj_kinematics`` (which changes no integration state). A
        disabled object that is awake is marked ready to sleep (-1): MuJoCo puts it to sleep in
        the next step before integrating, so it does not move. With every object enabled the
        flag is off, and MuJoCo wakes every tree at the next kinematics pass.
        """
        if self._sleep_synced:
            return
        self._sleep_synced = True
        if not self._sleep:
            return
        m, d = self._m, self._d
        if self._enabled.all():
            m.opt.enableflags &= ~_SLEEP
            return
        m.opt.enableflags |= _SLEEP
        asleep = d.tree_asleep
        wake = np.flatnonzero(self._enabled & (asleep >= 0))
        if len(wake):
            rows = wake + 1
            held = d.xfrc_applied[rows].copy()
            d.xfrc_applied[rows] = 1.0
            mujoco.mj_kinematics(m, d)
            d.xfrc_applied[rows] = held
        ready = np.flatnonzero(~self._enabled & (asleep < 0))
        asleep[ready] = -1

    @property
    def friction_scale(self) -> float:
        """Factor applied to every sliding friction coefficient (1 = the models' values)."""
        return self._friction_scale

    def set_friction_scale(self, scale: float) -> None:
        """Scale every geom's sliding friction (objects and table) by ``scale`` >= 0.

        A model parameter, not part of the saved state: :meth:`restore_state` leaves it as is.
        The search lowers it while the data forces align objects with the data (so a small
        pull can slide a resting object) and restores it before stability is judged.
        """
        scale = float(scale)
        if not (math.isfinite(scale) and scale >= 0):
            raise ValueError(f"friction scale must be finite and >= 0, got {scale}")
        if scale != self._friction_scale:
            self._m.geom_friction[:, 0] = self._friction0 * scale
            self._friction_scale = scale
            self._forward_current = False

    # ------------------------------------------------------------------ wrenches
    def apply_wrench(self, oid: str, force, torque) -> None:
        """External force (N, at the centre of mass) and torque (N m), world frame, on ``oid``.

        It acts on every following step until changed or :meth:`clear_wrenches`.
        """
        k = self.index(oid)
        self._xfrc[k, :3] = _vec3(force, f"force on {oid!r}")
        self._xfrc[k, 3:] = _vec3(torque, f"torque on {oid!r}")
        self._forward_current = False

    def apply_wrenches(self, forces: np.ndarray, torques: np.ndarray) -> None:
        """Set the wrenches of all objects at once: ``forces``, ``torques`` (n, 3), id order."""
        n = self._n
        f = np.asarray(forces, dtype=float)
        t = np.asarray(torques, dtype=float)
        if f.shape != (n, 3) or t.shape != (n, 3):
            raise ValueError(
                f"forces and torques must have shape ({n}, 3); got {f.shape} and {t.shape}"
            )
        if not math.isfinite(f.sum() + t.sum()):  # one cheap test for NaN/inf anywhere
            raise ValueError("forces/torques contain NaN or infinite values")
        self._xfrc[:, :3] = f
        self._xfrc[:, 3:] = t
        self._forward_current = False

    def wrenches(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the applied ``(forces, torques)``, each (n, 3), world frame."""
        return self._xfrc[:, :3].copy(), self._xfrc[:, 3:].copy()

    def clear_wrenches(self) -> None:
        """Remove every applied force and torque."""
        self._xfrc[:] = 0.0
        self._forward_current = False

    # ------------------------------------------------------------------ stepping
    def step(self, n: int = 1, *, quasi_static: bool = True) -> None:
        """Advance ``n`` steps of ``timestep``.

        ``quasi_static=True`` zeroes all velocities before each step (relaxation from rest, as
        the reference code does: the ``StepSimulation`` of the paper's Alg. 1 as DESIGN
        section 4 "Simulation" reads it); ``False`` is plain dynamics. Raises
        :class:`PhysicsError` if the simulation diverges or overflows its buffers; the state is
        then invalid and should be restored with :meth:`restore_state`.
        """
        n = int(n)
        if n < 0:
            raise ValueError(f"step count must be >= 0, got {n}")
        if n == 0:
            return
        m, d = self._m, self._d
        warn0 = self._warn[_FATAL_IDX].copy()
        qvel = self._qvel_flat
        fq, fv = self._frozen_q, self._frozen_v
        step = mujoco.mj_step
        if len(fq):
            self._sync_sleep()
            qpos = d.qpos
            held = qpos[fq].copy()
            asleep, awake = d.tree_asleep, self._awake_trees
            sleeping = self._sleep
            hold = True
            for i in range(n):
                if quasi_static:
                    qvel[:] = 0.0
                if sleeping:
                    asleep[awake] = _AWAKE  # an enabled object never counts down to sleep
                step(m, d)
                if hold:
                    qpos[fq] = held
                    qvel[fv] = 0.0
                    if sleeping and i == 0:
                        # every disabled object asleep: MuJoCo leaves them where they are
                        hold = int((asleep >= 0).sum()) != len(self._enabled) - len(awake)
        elif quasi_static:
            self._sync_sleep()
            for _ in range(n):
                qvel[:] = 0.0
                step(m, d)
        else:
            self._sync_sleep()
            step(m, d, n)
        self._forward_current = False
        self._check_health(warn0, n)

    def settle(
        self,
        *,
        min_s: float = 0.2,
        max_s: float = 2.0,
        chunk_s: float = 0.05,
        v_tol: float = 1e-3,
        w_tol: float = 1e-2,
    ) -> float | None:
        """Simulate plain dynamics until every object is at rest (all linear speeds below
        ``v_tol`` m/s and angular speeds below ``w_tol`` rad/s, checked every ``chunk_s`` s
        after ``min_s`` s); the simulated time (s), or None if still moving after ``max_s``."""
        n = max(1, round(chunk_s / self.timestep))
        t = 0.0
        while t < max_s - 1e-9:
            self.step(n, quasi_static=False)
            t += n * self.timestep
            if t >= min_s - 1e-9:
                lin, ang = self.velocities()
                if len(lin) == 0 or (np.abs(lin).max() < v_tol and np.abs(ang).max() < w_tol):
                    return t
        return None

    def _check_health(self, warn0: np.ndarray, n: int | None) -> None:
        """Raise PhysicsError if a fatal MuJoCo warning fired since ``warn0`` (counters) or the
        state is not finite; ``n`` steps were taken (None: a forward computation)."""
        grew = self._warn[_FATAL_IDX] > warn0
        bad_state = not (np.isfinite(self._d.qpos).all() and np.isfinite(self._d.qvel).all())
        if grew.any() or bad_state:
            what = [_FATAL_WARNINGS[int(w)] for w in _FATAL_IDX[grew]]
            if bad_state:
                what.append("non-finite positions or velocities")
            during = f"during {n} step(s) up to" if n is not None else "in the forward pass at"
            raise PhysicsError(
                f"physics failed {during} t = {self._d.time:.4f} s: "
                + "; ".join(what)
                + f" ({int(self._d.ncon)} contacts, arena {self._m.narena} bytes)"
                + ". Restore a saved state before continuing."
            )

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the freshly built state: model poses, zero velocities, no wrenches, every
        object enabled, full friction, time 0, no solver warm start. Stepping after a reset
        repeats bit for bit whatever the world did before (a reused world gives the same
        results as a new one)."""
        mujoco.mj_resetData(self._m, self._d)
        self._m.opt.enableflags &= ~_SLEEP
        if not self._enabled.all():
            self._enabled[:] = True
            self._apply_enabled()
        self.set_friction_scale(1.0)
        self._forward_at_model_poses()

    def save_state(self) -> WorldState:
        """Snapshot of the full integration state and the enabled flags."""
        buf = np.empty(self._state_size)
        mujoco.mj_getState(self._m, self._d, buf, _STATE_SPEC)
        buf.flags.writeable = False
        return WorldState(self._serial, buf, tuple(self._enabled.tolist()))

    def restore_state(self, state: WorldState) -> None:
        """Return exactly to ``state`` (saved by this world); stepping then repeats bit for bit.

        Raises :class:`WorldMismatchError` for a state of another world.
        """
        if not isinstance(state, WorldState):
            raise TypeError(f"expected a WorldState, got {type(state).__name__}")
        if state.world_serial != self._serial or len(state.state) != self._state_size:
            raise WorldMismatchError(
                "this WorldState was saved by a different World; states can only be restored "
                "into the world that saved them"
            )
        mujoco.mj_setState(self._m, self._d, state.state, _STATE_SPEC)
        if tuple(self._enabled.tolist()) != state.enabled:
            self._enabled[:] = state.enabled
            self._apply_enabled()
        self._forward_current = False

    def _forward_preserving_state(self) -> None:
        """mj_forward at the current state, leaving the integration state (incl. the solver
        warm start, which mj_forward overwrites) exactly as it was."""
        m, d = self._m, self._d
        buf = self._scratch
        self._sync_sleep()
        mujoco.mj_getState(m, d, buf, _STATE_SPEC)
        warn0 = self._warn[_FATAL_IDX].copy()
        mujoco.mj_forward(m, d)
        mujoco.mj_setState(m, d, buf, _STATE_SPEC)
        self._check_health(warn0, None)

    # ------------------------------------------------------------------ queries
    def acceleration_from_rest(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lin, ang)``, each (n, 3), world frame: the linear acceleration of each object's
        centre of mass (m/s^2) and its angular acceleration (rad/s^2) if every object were at
        rest at the current poses, under gravity, contacts and the applied wrenches (with the
        wrenches cleared, the ``a_o`` and ``alpha_o`` of the paper's Eq. 7-8; DESIGN section 4).

        Disabled objects report zeros. The world's state is not changed.
        """
        n = self._n
        if n == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        m, d = self._m, self._d
        buf = self._scratch
        self._sync_sleep()
        mujoco.mj_getState(m, d, buf, _STATE_SPEC)
        self._qvel_flat[:] = 0.0
        warn0 = self._warn[_FATAL_IDX].copy()
        mujoco.mj_forward(m, d)
        qacc = d.qacc.reshape(n, 6).copy()
        mujoco.mj_setState(m, d, buf, _STATE_SPEC)
        self._forward_current = False  # derived data now describe the zero-velocity state
        self._check_health(warn0, None)
        lin, ang = self._com_motion(qacc)  # exact: angular velocity is zero
        off = ~self._enabled
        lin[off] = 0.0
        ang[off] = 0.0
        return lin, ang

    def contacts(self) -> Contacts:
        """Contacts at the current state (the state itself is not changed).

        The table is always ``obj_b`` (-1); object pairs are ordered ``obj_a < obj_b``; normals
        point from a to b. Contacts of disabled objects are left out.
        """
        if not self._forward_current:
            self._forward_preserving_state()
            self._forward_current = True
        d = self._d
        nc = int(d.ncon)
        if nc == 0:
            return Contacts.empty(self._ids)
        con = d.contact
        geom = np.asarray(con.geom)
        a = self._geom_obj[geom[:, 0]]
        b = self._geom_obj[geom[:, 1]]
        keep = self._enabled_ext[a] & self._enabled_ext[b]
        normal = np.array(con.frame[:, :3])
        depth = -np.asarray(con.dist, dtype=float)
        pos = np.array(con.pos)
        adr = np.asarray(con.efc_address)
        force = np.zeros(nc)
        has = adr >= 0
        efc = d.efc_force
        if self._m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC:
            force[has] = efc[adr[has]]
        else:  # pyramidal: the normal force is the sum of the 2 (dim - 1) edge forces
            dim = np.asarray(con.dim)
            for k in np.flatnonzero(has):
                rows = 1 if dim[k] == 1 else 2 * (dim[k] - 1)
                force[k] = efc[adr[k] : adr[k] + rows].sum()
        swap = (a == -1) | ((b != -1) & (a > b))
        a, b = np.where(swap, b, a), np.where(swap, a, b)
        normal[swap] *= -1.0
        if keep.all():
            return Contacts(self._ids, a, b, pos, normal, depth, force)
        return Contacts(
            self._ids, a[keep], b[keep], pos[keep], normal[keep], depth[keep], force[keep]
        )
