"""Object symmetries in the BOP ``models_info`` convention, in metres.

A symmetry is a transform ``T_sym`` in the model frame that leaves the object's shape unchanged:
``T_world_obj @ T_sym`` is the same physical pose as ``T_world_obj``. Discrete symmetries are a
finite group (identity included): whatever set is given is closed under composition
(:func:`close_group`), so two generators of a square bar's symmetries give its 8 elements.
Continuous ones are rotation axes (through ``offset``).

Declared symmetries are read as published (:func:`snap_symmetry`): a rotation a few digits off
an exact turn ``360 k / n`` degrees is snapped to it (silently when the difference is rounding,
with a warning naming the object and the angle when it is up to :data:`SNAP_TOLERANCE_DEG`: LM-O
publishes its eggbox's half turn as 179.81 degrees and its glue's as 178.47); one farther from
any such turn is an error. Elements that are each near a group element but about slightly
different axes are used as given when they close within the tolerance (:func:`close_group`).

:func:`detect_symmetries` finds approximate symmetries of a shape in the BOP way: a candidate
transform is a symmetry when the maximum surface distance it causes (MSSD: the largest distance
of a moved surface point from the surface) is at most a tolerance in metres. Candidates are the
rotations by 2 pi k / n (n = 2..8) about the principal axes of inertia through the centre of
mass (and about the model axes, for shapes whose principal axes are not unique).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ssp.errors import ModelError
from ssp.geometry import nearest_rotation

log = logging.getLogger(__name__)

#: Two transforms are one symmetry when their rotations differ by less than this (Frobenius)
#: and their translations by less than this many metres.
SAME_ROTATION = 1e-6
SAME_TRANSLATION = 1e-7
#: A closure larger than this is logged as large (a cube's rotation group has 24 elements).
LARGE_GROUP = 48
#: A closure that reaches this size is taken as infinite (e.g. a rotation by 1 degree... or by
#: an angle that is not 360/n): an error.
MAX_GROUP = 360
#: Rotation orders tried by :func:`detect_symmetries` (2 pi / n).
DETECT_ORDERS = tuple(range(2, 9))
#: Surface points used as references by :func:`detect_symmetries` (dense random samples).
DETECT_REFERENCE_POINTS = 40_000
#: Default MSSD tolerance of the detection, m.
DETECT_TOLERANCE = 0.002
#: A declared discrete symmetry whose rotation misses an exact turn ``360 k / n`` degrees
#: (``n`` in :data:`SNAP_ORDERS`) by at most this many degrees is snapped to that turn, with a
#: warning; farther from every such turn it is an error. Why 2 degrees: LM-O's published glue
#: misses its half turn by 1.53 degrees (the eggbox by 0.19), so published files load with a
#: margin; distinct turns of orders up to 8 are at least 360 / 56 = 6.4 degrees apart, so the turn
#: within 2 degrees is never ambiguous; and a 2 degree snap moves a surface point by at most
#: 2 sin(1 deg) r, 1.7 % of the diameter: a third of BOP's strictest MSSD threshold (5 % of the
#: diameter), about what a symmetry measured on a scan is uncertain by. A wider tolerance would
#: quietly accept a typo (a 175 degree turn) as a half turn.
SNAP_TOLERANCE_DEG = 2.0
#: The orders ``n`` a near turn is snapped to (1: a near-identity, dropped).
SNAP_ORDERS = (1, *DETECT_ORDERS)
#: A rotation this close (rad) to a turn ``360 k / n`` is that turn written with six decimals
#: (a published 60 degrees: cos 0.5, sin 0.866025; they are off by at most about 1e-6 rad),
#: snapped without a warning. Orders above those of :data:`SNAP_ORDERS` (up to
#: :data:`MAX_GROUP`: a declared 1 degree turn) are accepted only this close: tight, as nearly
#: any angle is within 5e-5 rad of some turn of order up to 360.
ROUNDING_TOLERANCE = 2e-6
#: A declared symmetry's rotation may deviate from orthonormal by this much (max |R R^T - I|,
#: six published digits give 1e-6); it is re-orthonormalised (nearest rotation, SVD).
RIGID_TOLERANCE = 1e-3
#: Length (m) that turns the angle tolerance into a translation tolerance when the object's
#: size is not known (a tabletop object's radius); BOP models give their diameter.
DEFAULT_REACH = 0.1


def rotation_transform(
    axis: Sequence[float] | np.ndarray,
    angle_deg: float,
    offset: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """4x4 rotation by ``angle_deg`` degrees about ``axis`` through the point ``offset``."""
    a = np.asarray(axis, dtype=float)
    n = float(np.linalg.norm(a))
    if not np.isfinite(n) or n < 1e-12:
        raise ModelError(f"rotation axis must be non-zero, got {list(axis)}")
    R = Rotation.from_rotvec(a / n * np.radians(float(angle_deg))).as_matrix()
    # snap float noise of exact quarter turns (cos 90 = 6e-17) to exact values
    R[np.abs(R) < 1e-15] = 0.0
    T = np.eye(4)
    T[:3, :3] = R
    o = np.asarray(offset, dtype=float)
    T[:3, 3] = o - R @ o
    return T


def _same(A: np.ndarray, B: np.ndarray) -> bool:
    return bool(
        np.linalg.norm(A[:3, :3] - B[:3, :3]) < SAME_ROTATION
        and np.linalg.norm(A[:3, 3] - B[:3, 3]) < SAME_TRANSLATION
    )


def _nearest_turn(angle: float, tolerance: float) -> tuple[int, int, bool] | None:
    """``(k, n, quiet)`` of the turn ``2 pi k / n`` that ``angle`` (rad, in [0, pi]) stands
    for: the nearest of order in :data:`SNAP_ORDERS` within ``tolerance`` (rad; smallest order
    first), else one of order up to :data:`MAX_GROUP` within :data:`ROUNDING_TOLERANCE`; None
    when there is none. ``quiet``: within :data:`ROUNDING_TOLERANCE` (printed digits)."""
    err, n = min(
        (abs(angle - 2.0 * np.pi * round(angle * n / (2.0 * np.pi)) / n), n) for n in SNAP_ORDERS
    )
    if err <= tolerance:
        return int(round(angle * n / (2.0 * np.pi))), n, err <= ROUNDING_TOLERANCE
    frac = Fraction(angle / (2.0 * np.pi)).limit_denominator(MAX_GROUP)
    if abs(angle - 2.0 * np.pi * float(frac)) <= ROUNDING_TOLERANCE:
        return frac.numerator, frac.denominator, True
    return None


def _rigid_rotation(T: np.ndarray, what: str) -> np.ndarray:
    """The nearest rotation (SVD) of ``T``'s 3x3 block; ModelError when it is no rigid
    motion within :data:`RIGID_TOLERANCE` (or not finite, or a reflection)."""
    R = T[:3, :3]
    if not np.all(np.isfinite(T)):
        raise ModelError(f"{what} is not finite")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > RIGID_TOLERANCE or np.linalg.det(R) <= 0:
        raise ModelError(
            f"{what} is not a rigid transform (|R R^T - I| = {err:.1e}, "
            f"det {np.linalg.det(R):.3f}; a reflection is not a rigid motion)"
        )
    return nearest_rotation(R)


def snap_symmetry(
    T: np.ndarray,
    what: str,
    tolerance_deg: float = SNAP_TOLERANCE_DEG,
    reach: float = DEFAULT_REACH,
) -> np.ndarray:
    """A declared discrete symmetry ``T`` (4x4, m) as the exact group element it stands for.

    Its rotation (re-orthonormalised, SVD) turns by ``angle`` about ``axis``; when ``angle`` is
    within :data:`ROUNDING_TOLERANCE` of a turn ``360 k / n`` (``n`` <= :data:`MAX_GROUP`) it is
    snapped to it silently, else to the turn of order ``n`` in :data:`SNAP_ORDERS` within
    ``tolerance_deg`` degrees, with a warning naming ``what`` and both angles. The snapped
    transform keeps the rotation axis (the line ``T`` leaves fixed) and drops any shift along
    it (a screw motion generates an infinite group), which must be within
    ``tolerance_deg`` (rad) x ``reach`` (m: the object's radius).

    Raises:
        ModelError: not a rigid motion, or farther from every such turn (or screwing farther)
            than the tolerance: no finite group is near it. The message names ``what``.
    """
    T = np.asarray(T, dtype=float).reshape(4, 4)
    R = _rigid_rotation(T, what)
    rotvec = Rotation.from_matrix(R).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    axis = rotvec / angle if angle > 1e-12 else np.array([0.0, 0.0, 1.0])
    t = T[:3, 3]
    tol = np.radians(float(tolerance_deg))
    turn = _nearest_turn(angle, tol)
    if turn is None:
        raise ModelError(
            f"{what} turns by {np.degrees(angle):.2f} deg about {np.round(axis, 3).tolist()}, "
            f"more than {tolerance_deg:g} deg from every turn 360 k / n (n <= "
            f"{SNAP_ORDERS[-1]}): it does not close into a finite group"
        )
    k, n, quiet = turn
    shift = float(axis @ t) if angle > 1e-12 else float(np.linalg.norm(t))
    if angle < 1e-12 and abs(shift) <= SAME_TRANSLATION:
        return T
    if abs(shift) > tol * reach:
        raise ModelError(
            f"{what} shifts by {1000 * shift:.2f} mm along its rotation axis (a screw motion, "
            f"more than {tolerance_deg:g} deg x {1000 * reach:.0f} mm): it does not close into "
            "a finite group"
        )
    exact = 2.0 * np.pi * k / n
    if quiet and abs(angle - exact) < 1e-12 and abs(shift) <= 1e-12:
        return T
    # the point of the axis: (I - R) o = t across the axis (least squares; o orthogonal to it)
    o = np.linalg.lstsq(np.eye(3) - R, t - shift * axis, rcond=None)[0] if angle > 1e-12 else t
    out = rotation_transform(axis, np.degrees(exact), o)
    if not quiet or abs(shift) > SAME_TRANSLATION:
        log.warning(
            "%s turns by %.2f deg about %s, not an exact turn: snapped to %s (%.6g deg%s; "
            "tolerance %g deg)",
            what,
            np.degrees(angle),
            np.round(axis, 4).tolist(),
            "the identity (dropped)" if n == 1 else "the half turn" if n == 2 else f"{k}/{n} turn",
            np.degrees(exact),
            f", {1000 * shift:.3f} mm shift along the axis dropped" if abs(shift) > 1e-9 else "",
            tolerance_deg,
        )
    return out


def _same_within(A: np.ndarray, B: np.ndarray, angle: float, shift: float) -> bool:
    """Whether rigid ``A`` and ``B`` differ by at most ``angle`` (rad) and ``shift`` (m)."""
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
    return bool(
        np.arccos(np.clip(c, -1.0, 1.0)) <= angle and np.linalg.norm(A[:3, 3] - B[:3, 3]) <= shift
    )


def _already_closed(transforms) -> np.ndarray | None:
    """The set with the identity first when it already is a group (vectorised check), else
    None. Keeps the common case (a declared group, e.g. a cube's 24) cheap."""
    d = np.asarray(transforms, dtype=float).reshape(-1, 4, 4)
    ident = np.array([_same(T, np.eye(4)) for T in d])
    d = np.concatenate([np.eye(4)[None], d[~ident]])
    prod = np.einsum("aij,bjk->abik", d, d).reshape(-1, 1, 4, 4)
    rot = np.linalg.norm(prod[..., :3, :3] - d[None, :, :3, :3], axis=(2, 3))
    trans = np.linalg.norm(prod[..., :3, 3] - d[None, :, :3, 3], axis=2)
    found = (rot < SAME_ROTATION) & (trans < SAME_TRANSLATION)
    if not found.any(axis=1).all():
        return None
    # and no duplicates among the elements themselves
    if (found.reshape(len(d), len(d), len(d)).sum(axis=2) > 1).any():
        return None
    return d


def close_group(
    transforms: Sequence[np.ndarray] | np.ndarray,
    what: str = "symmetries",
    max_elements: int | None = None,
    *,
    tolerance_deg: float = 0.0,
    reach: float = DEFAULT_REACH,
):
    """The group ``(S, 4, 4)`` generated by rigid ``transforms`` (identity first, then the
    given ones in order, then their products in the order found); tolerance-based dedup.

    Logs a warning when it has more than :data:`LARGE_GROUP` elements. With ``tolerance_deg``,
    transforms that generate no finite group exactly (near turns about slightly different
    axes) but do within twice that angle (and twice that angle, rad, x ``reach`` m of
    translation) give that approximate group, with a warning: the elements as found, as the
    BOP toolkit uses the listed ones.

    Raises:
        ModelError: it does not close within ``max_elements`` (default :data:`MAX_GROUP`)
            elements (an angle that is not 360/n degrees, or generators of an infinite group).
    """
    cap = MAX_GROUP if max_elements is None else int(max_elements)
    closed = _already_closed(transforms)
    if closed is not None:
        return closed
    gens = [
        np.asarray(T, dtype=float).reshape(4, 4) for T in np.asarray(transforms).reshape(-1, 16)
    ]
    try:
        group = _closure(gens, _same, cap, what)
    except ModelError:
        if tolerance_deg <= 0:
            raise
        tol = 2.0 * np.radians(tolerance_deg)

        def near(A: np.ndarray, B: np.ndarray) -> bool:
            return _same_within(A, B, tol, tol * reach)

        group = _closure(gens, near, min(cap, 2 * LARGE_GROUP), what)
        log.warning(
            "%s are a group only within %g deg (%d elements): used as listed, as the BOP "
            "toolkit does",
            what,
            tolerance_deg,
            len(group),
        )
    if len(group) > LARGE_GROUP:
        log.warning("%s generate %d elements (a large group); check them", what, len(group))
    return np.stack(group)


def _closure(gens: list[np.ndarray], same, cap: int, what: str) -> list[np.ndarray]:
    """Identity, ``gens`` and their products, deduplicated by ``same(A, B)``; ModelError when
    ``cap`` elements are reached."""
    group: list[np.ndarray] = [np.eye(4)]

    def add(T: np.ndarray) -> bool:
        if any(same(T, G) for G in group):
            return False
        group.append(T)
        if len(group) >= cap:
            raise ModelError(
                f"{what} do not close into a finite group within {cap} elements; is a "
                "rotation angle not 360/n degrees, or are two axes at an odd angle?"
            )
        return True

    for G in gens:
        add(G)
    frontier = list(group[1:])
    while frontier:
        new = []
        for A in frontier:
            for G in gens:
                T = G @ A
                T[3] = (0.0, 0.0, 0.0, 1.0)
                if add(T):
                    new.append(T)
        frontier = new
    return group


@dataclass(frozen=True)
class ContinuousSymmetry:
    """Rotation by any angle about ``axis`` (unit, model frame) through ``offset`` (m)."""

    axis: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def transform(self, angle: float) -> np.ndarray:
        """4x4 model-frame transform of the rotation by ``angle`` (rad)."""
        R = Rotation.from_rotvec(self.axis * angle).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = self.offset - R @ self.offset
        return T


@dataclass(frozen=True)
class Symmetry:
    """Discrete transforms ``(S, 4, 4)`` (first one the identity) and continuous axes.

    ``approximate``: the discrete transforms are a group only within a tolerance (declared
    near turns about slightly different axes, :func:`close_group`): taken as they are."""

    discrete: np.ndarray = field(default_factory=lambda: np.eye(4)[None])
    continuous: tuple[ContinuousSymmetry, ...] = ()
    approximate: bool = field(default=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        d = np.asarray(self.discrete, dtype=float).reshape(-1, 4, 4)
        if not np.allclose(d[0], np.eye(4), atol=1e-9):
            ident = np.all(np.isclose(d, np.eye(4), atol=1e-9), axis=(1, 2))
            d = np.concatenate([np.eye(4)[None], d[~ident]])
        R = d[:, :3, :3]
        if not np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-5):
            raise ModelError("discrete symmetries must be rigid transforms")
        if len(d) > 1 and not self.approximate:
            closed = close_group(d[1:], "discrete symmetries")
            if len(closed) > len(d):
                log.info(
                    "%d discrete symmetries (identity included) closed into a group of %d",
                    len(d),
                    len(closed),
                )
            d = closed if len(closed) > len(d) else d
        object.__setattr__(self, "discrete", d)
        cont = []
        for c in self.continuous:
            axis = np.asarray(c.axis, dtype=float)
            n = np.linalg.norm(axis)
            if not np.isfinite(n) or n < 1e-9:
                raise ModelError(f"continuous symmetry axis must be non-zero, got {axis}")
            cont.append(ContinuousSymmetry(axis / n, np.asarray(c.offset, dtype=float)))
        object.__setattr__(self, "continuous", tuple(cont))

    @property
    def is_symmetric(self) -> bool:
        return len(self.discrete) > 1 or bool(self.continuous)

    def transforms(self, continuous_step: float = np.radians(5.0)) -> np.ndarray:
        """All symmetry transforms ``(n, 4, 4)``: discrete x sampled continuous rotations.

        Continuous axes are sampled every ``continuous_step`` rad (BOP samples likewise); with
        several continuous axes (a sphere) only the first is sampled, as in bop_toolkit.
        """
        if not self.continuous:
            return self.discrete.copy()
        n = max(1, int(np.ceil(2 * np.pi / continuous_step)))
        rots = np.stack([self.continuous[0].transform(2 * np.pi * i / n) for i in range(n)])
        return np.einsum("aij,bjk->abik", self.discrete, rots).reshape(-1, 4, 4)

    @classmethod
    def from_bop(cls, info: dict, scale: float = 1.0, name: str = "") -> Symmetry:
        """From a BOP ``models_info`` entry; ``scale`` converts its units to metres (mm: 1e-3).

        Its discrete symmetries are read as published (:func:`snap_symmetry`: near turns
        snapped with a warning naming ``name``, e.g. ``"models_info.json: obj_id 10"``), the
        entry's ``diameter`` giving the translation tolerance.

        Raises:
            ModelError: a malformed entry, or symmetries far from any finite group.
        """
        try:
            discrete = [
                np.asarray(s, dtype=float).reshape(4, 4)
                for s in info.get("symmetries_discrete", [])
            ]
            for T in discrete:
                T[:3, 3] *= scale
            continuous = tuple(
                ContinuousSymmetry(
                    np.asarray(c["axis"], dtype=float),
                    np.asarray(c.get("offset", [0, 0, 0]), dtype=float) * scale,
                )
                for c in info.get("symmetries_continuous", [])
            )
            diameter = float(info.get("diameter", 0.0)) * scale
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"malformed symmetry description {info!r}: {exc}") from exc
        reach = diameter / 2 if np.isfinite(diameter) and diameter > 0 else DEFAULT_REACH
        return cls._declared(discrete, continuous, name, reach)

    @classmethod
    def _declared(
        cls,
        discrete: Sequence[np.ndarray],
        continuous: tuple[ContinuousSymmetry, ...],
        name: str,
        reach: float,
    ) -> Symmetry:
        """The symmetries of declared discrete generators (m), snapped and closed."""
        what = f"{name}: " if name else ""
        gens = [
            snap_symmetry(T, f"{what}discrete symmetry {i + 1}", reach=reach)
            for i, T in enumerate(discrete)
        ]
        gens = [G for G in gens if not _same(G, np.eye(4))]
        if not gens:
            return cls(np.eye(4)[None], continuous)
        closed = close_group(
            gens,
            f"{what}discrete symmetries",
            tolerance_deg=SNAP_TOLERANCE_DEG,
            reach=reach,
        )
        exact = _already_closed(closed) is not None
        return cls(closed, continuous, approximate=not exact)

    @classmethod
    def from_generators(
        cls,
        discrete: Sequence[np.ndarray] = (),
        continuous: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
        scale: float | Sequence[float] | np.ndarray = 1.0,
        name: str = "",
    ) -> Symmetry:
        """The group generated by ``discrete`` 4x4 transforms and the ``continuous``
        ``(axis, offset)`` pairs, all in file units; ``scale`` (one or three factors) converts
        them to metres (a non-uniform scale must keep every rotation rigid). Near turns are
        snapped as in :meth:`from_bop` (warnings name ``name``).

        Raises:
            ModelError: a transform is not rigid (after scaling) or the group is infinite.
        """
        S = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
        Sm, Si = np.diag([*S, 1.0]), np.diag([*(1.0 / S), 1.0])
        gens = []
        for i, T in enumerate(discrete):
            T = np.asarray(T, dtype=float).reshape(4, 4)
            U = Sm @ T @ Si
            if not np.allclose(U[:3, :3] @ U[:3, :3].T, np.eye(3), atol=RIGID_TOLERANCE):
                raise ModelError(
                    f"symmetry {i} is not a rigid transform"
                    + ("" if np.all(S == S[0]) else " after the non-uniform scale")
                )
            gens.append(U)
        cont = tuple(
            ContinuousSymmetry(S * np.asarray(axis, dtype=float), S * np.asarray(offset, float))
            for axis, offset in continuous
        )
        return cls._declared(gens, cont, name, DEFAULT_REACH)

    def to_bop(self, scale: float = 1.0) -> dict:
        """BOP ``models_info`` keys; ``scale`` converts metres to the file's units."""
        out: dict = {}
        if len(self.discrete) > 1:
            ds = self.discrete[1:].copy()
            ds[:, :3, 3] *= scale
            out["symmetries_discrete"] = [d.reshape(-1).tolist() for d in ds]
        if self.continuous:
            out["symmetries_continuous"] = [
                {"axis": c.axis.tolist(), "offset": (c.offset * scale).tolist()}
                for c in self.continuous
            ]
        return out


@dataclass(frozen=True)
class AxisSymmetry:
    """Rotations about one candidate axis (through the centre of mass) within the tolerance.

    ``orders``: the n (2..8) whose every turn 360 k / n is within the tolerance; ``order``: the
    one chosen (the largest of those whose worst turn is within a quarter of the tolerance of
    the best order's, so an exact 6-fold axis gives 6 and a near-continuous one its most exact
    order); ``mssd``: the worst MSSD of the chosen order's turns, m; ``near_continuous``: every
    order 2..8 is within the tolerance (the shape is nearly a body of revolution about it).
    """

    axis: np.ndarray
    label: str
    orders: tuple[int, ...]
    order: int
    mssd: float
    near_continuous: bool
    #: Worst MSSD (m) of the turns of every order in ``orders``, same order.
    order_mssd: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        return {
            "axis": [round(float(x), 6) for x in self.axis],
            "label": self.label,
            "orders_within_tolerance": list(self.orders),
            "mssd_mm_by_order": [round(1000 * m, 3) for m in self.order_mssd],
            "order": self.order,
            "mssd_mm": round(1000 * self.mssd, 3),
            "near_continuous": self.near_continuous,
        }


@dataclass(frozen=True)
class SymmetryDetection:
    """The outcome of :func:`detect_symmetries` (all lengths m, model frame).

    ``group``: the verified discrete symmetries (S, 4, 4), identity first; ``axes``: the axes
    with rotations within the tolerance; ``tolerance``: the MSSD tolerance; ``floor``: the
    sampling floor subtracted from every distance.
    """

    group: np.ndarray
    axes: tuple[AxisSymmetry, ...]
    tolerance: float
    floor: float

    def to_dict(self) -> dict:
        return {
            "tolerance_mm": round(1000 * self.tolerance, 3),
            "sampling_floor_mm": round(1000 * self.floor, 3),
            "discrete_symmetries": int(len(self.group)),
            "axes": [a.to_dict() for a in self.axes],
        }


#: Points per batch of :func:`surface_distance` (it stops at the first batch over the limit).
DISTANCE_BATCH = 1000


def surface_distance(
    tree: cKDTree,
    points: np.ndarray,
    T: np.ndarray,
    floor: float = 0.0,
    limit: float | None = None,
) -> float:
    """MSSD of ``T``: the largest distance of the moved ``points`` (N, 3) from the surface
    sampled by ``tree`` (minus the sampling ``floor``, at least 0), m.

    With ``limit``, stops at the first batch of :data:`DISTANCE_BATCH` points whose distance
    exceeds it and returns that (a value above ``limit``, not the full maximum)."""
    moved = points @ T[:3, :3].T + T[:3, 3]
    worst = 0.0
    for a in range(0, len(moved), DISTANCE_BATCH):
        d, _ = tree.query(moved[a : a + DISTANCE_BATCH])
        worst = max(worst, float(d.max()) - floor)
        if limit is not None and worst > limit:
            break
    return max(0.0, worst)


def _candidate_axes(inertia: np.ndarray) -> list[tuple[np.ndarray, str]]:
    """Principal axes of ``inertia`` (3x3); with (nearly) equal principal moments, whose axes
    are not unique, the model axes as well."""
    vals, vecs = np.linalg.eigh(0.5 * (inertia + inertia.T))
    axes = [(vecs[:, i] / np.linalg.norm(vecs[:, i]), f"principal axis {i}") for i in range(3)]
    if np.min(np.diff(vals)) < 0.01 * float(vals.max()):
        for i, name in enumerate("xyz"):
            e = np.eye(3)[i]
            if all(abs(float(e @ a)) < 1 - 1e-6 for a, _ in axes):
                axes.append((e, f"model axis {name}"))
    return axes


#: Query and reference sample counts of :func:`detect_symmetries`.
DETECT_QUERY_POINTS = 10_000


def detect_symmetries(
    mesh,
    center_of_mass: np.ndarray,
    inertia: np.ndarray,
    tolerance: float,
    seed: int = 0,
) -> SymmetryDetection:
    """Approximate discrete symmetries of ``mesh`` whose MSSD is at most ``tolerance`` (m).

    BOP-style: the MSSD of a transform is the largest distance of a moved surface point from
    the surface, here over :data:`DETECT_QUERY_POINTS` random surface points against
    :data:`DETECT_REFERENCE_POINTS` others, minus the sampling floor (the identity's MSSD).
    Candidates: rotations by ``360 k / n`` degrees (n in :data:`DETECT_ORDERS`) about the
    candidate axes (:func:`_candidate_axes`) through ``center_of_mass``. Each axis contributes
    the cyclic group of its chosen order (:class:`AxisSymmetry`); the groups of the axes are
    closed together (best axis first) and every new element is verified, an axis whose
    products leave the tolerance being left out. The result is always a group of verified
    symmetries. Deterministic for a given ``seed``.
    """
    import trimesh

    rng = np.random.default_rng(seed)
    reference, _ = trimesh.sample.sample_surface(mesh, DETECT_REFERENCE_POINTS, seed=rng)
    points, _ = trimesh.sample.sample_surface(mesh, DETECT_QUERY_POINTS, seed=rng)
    tree = cKDTree(reference)
    floor = surface_distance(tree, points, np.eye(4))
    com = np.asarray(center_of_mass, dtype=float)
    axes: list[tuple[AxisSymmetry, np.ndarray]] = []
    for axis, label in _candidate_axes(np.asarray(inertia, dtype=float)):
        mssd: dict[float, float] = {}
        worst: dict[int, float] = {}
        for n in DETECT_ORDERS:
            turns = []
            for k in range(1, n):
                angle = round(360.0 * k / n, 9)
                if angle not in mssd:
                    T = rotation_transform(axis, angle, com)
                    mssd[angle] = surface_distance(tree, points, T, floor, tolerance)
                turns.append(mssd[angle])
                if turns[-1] > tolerance:
                    break
            if max(turns) <= tolerance:
                worst[n] = max(turns)
        if not worst:
            continue
        best = min(worst.values())
        order = max(n for n, w in worst.items() if w <= best + 0.25 * tolerance)
        cyclic = np.stack([rotation_transform(axis, 360.0 * k / order, com) for k in range(order)])
        info = AxisSymmetry(
            axis=axis,
            label=label,
            orders=tuple(sorted(worst)),
            order=order,
            mssd=worst[order],
            near_continuous=len(worst) == len(DETECT_ORDERS),
            order_mssd=tuple(worst[n] for n in sorted(worst)),
        )
        axes.append((info, cyclic))
    axes.sort(key=lambda a: (a[0].mssd, -a[0].order))
    group = np.eye(4)[None]
    used: list[AxisSymmetry] = []
    for info, cyclic in axes:
        try:
            trial = close_group(
                [*group[1:], *cyclic[1:]], "detected symmetries", max_elements=2 * LARGE_GROUP
            )
        except ModelError:
            continue
        new = [G for G in trial if not any(_same(G, H) for H in group)]
        if all(surface_distance(tree, points, G, floor, tolerance) <= tolerance for G in new):
            group = trial
            used.append(info)
    return SymmetryDetection(group, tuple(used), float(tolerance), floor)
