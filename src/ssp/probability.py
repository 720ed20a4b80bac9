"""Per-object probability terms of the scene score, in natural-log space.

Every function returns ``log P`` (natural log) so that a scene score is a plain sum over
objects and terms (DESIGN section 4: "All probabilities are combined as sums of logs").
Functions are pure numpy and vectorised over objects: inputs of shape ``(n, ...)`` give
outputs of shape ``(n,)``.

Paper equations (``paper/ssp-paper.tex``, section III "Scene Probability Formulation"; the
numbers are those of the compiled paper, docs/algorithm.md):

* stability  ``P_B``  Eq. 9 (``eq:stability_probability``) of ``beta_t`` (Eq. 7) and
  ``beta_R`` (Eq. 8), with DESIGN section 4's two corrections: the logistic *decreases* with
  instability, and ``beta_R = |alpha| / alpha_max`` with ``alpha_max = m g d_max / I_pivot``
  (``ObjectModel.max_angular_acceleration``; the paper's Eq. 8 inverts this ratio);
* collision  ``P_C``  Eq. 10 (``eq:collision_probability``), decreasing in the severity as
  DESIGN section 4 writes it (the paper's printed sign, as in Eq. 9, would make it increase);
* support    ``P_S``  Eq. 11 (section III-C "Support Contribution");
* data       ``P_D``  Eq. 12 (section III-D "Pose Data Fitness");
* transition ``P_T``  Eq. 6 (``eq:scene_transition_probability``; the Gaussian form is ours,
  DESIGN section 4).

Their sum over objects is the log of the scene score of Eq. 4
(``eq:scene_probability_simplified``), Eq. 5 (``eq:physical_consistency_probability``) being
its physical part (:mod:`ssp.scoring`).

``L(x) = 1 / (1 + e^-x)`` is the logistic function throughout.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ssp.config import (
    CollisionConfig,
    DataConfig,
    StabilityConfig,
    SupportConfig,
    TransitionConfig,
)
from ssp.library.symmetry import Symmetry

__all__ = [
    "ObjectTerms",
    "collision_severity",
    "data_fit_fraction",
    "log_collision",
    "log_data",
    "log_logistic",
    "log_stability",
    "log_support",
    "log_transition",
    "log_transition_from_poses",
    "pose_change",
]


def log_logistic(x: np.ndarray | float) -> np.ndarray:
    """``log L(x) = log(1 / (1 + e^-x)) = -softplus(-x)``, numerically stable.

    Dimensionless in, natural log out (``<= 0``). Finite for any finite ``x``:
    ``log_logistic(-1e6) == -1e6`` and ``log_logistic(1e6) == -0.0``.
    """
    return -np.logaddexp(0.0, -np.asarray(x, dtype=float))


# --------------------------------------------------------------------------------------------
# Stability (Eq. 7-9)
# --------------------------------------------------------------------------------------------


def log_stability(
    lin_acc: np.ndarray,
    ang_acc: np.ndarray,
    alpha_max: np.ndarray | float,
    g: float,
    cfg: StabilityConfig,
) -> np.ndarray:
    """``log P_B`` per object, paper Eq. 9 with DESIGN section 4's corrections (the sign;
    ``alpha_max`` the inverse of Eq. 8's ``beta_R_max``).

    ``P_B = L(-s_B (a_t beta_t - a_B)) * L(-s_B (a_R beta_R - a_B))`` with
    ``beta_t = |a| / g`` (Eq. 7) and ``beta_R = |alpha| / alpha_max`` (Eq. 8; both
    dimensionless), so the probability *decreases* as the object accelerates from rest.

    Args:
        lin_acc: ``(n, 3)`` linear accelerations from rest, m/s^2 (a single ``(3,)`` is allowed).
        ang_acc: ``(n, 3)`` angular accelerations from rest, rad/s^2.
        alpha_max: ``(n,)`` or scalar, the object's maximum angular acceleration under gravity,
            rad/s^2 (:meth:`ObjectModel.max_angular_acceleration`); must be positive.
        g: gravity magnitude, m/s^2; must be positive.
        cfg: steepness ``s_B``, midpoint ``a_B``, weights ``a_t``, ``a_R``.

    Returns:
        ``(n,)`` natural-log probabilities (``<= 0``).
    """
    a = np.asarray(lin_acc, dtype=float).reshape(-1, 3)
    w = np.asarray(ang_acc, dtype=float).reshape(-1, 3)
    if a.shape != w.shape:
        raise ValueError(f"lin_acc {a.shape} and ang_acc {w.shape} must have the same shape")
    amax = np.broadcast_to(np.asarray(alpha_max, dtype=float), (len(a),))
    if not g > 0:
        raise ValueError(f"gravity must be positive, got {g}")
    if np.any(~(amax > 0)):
        raise ValueError(f"alpha_max must be positive, got {amax}")
    beta_t = np.linalg.norm(a, axis=1) / g
    beta_r = np.linalg.norm(w, axis=1) / amax
    s, mid = cfg.steepness, cfg.midpoint
    return log_logistic(-s * (cfg.translation_weight * beta_t - mid)) + log_logistic(
        -s * (cfg.rotation_weight * beta_r - mid)
    )


# --------------------------------------------------------------------------------------------
# Collision (Eq. 10)
# --------------------------------------------------------------------------------------------


def collision_severity(
    depth: np.ndarray | float,
    overlap_fraction: np.ndarray | float,
    diameter: np.ndarray | float,
) -> np.ndarray:
    """Collision severity ``e_C = (d / eps_d) * (v_c / v_t)`` of paper Eq. 10 (dimensionless).

    Args:
        depth: ``(n,)`` deepest penetration ``d`` of each object, m; negative values
            (separation) are clipped to 0.
        overlap_fraction: ``(n,)`` ``v_c / v_t``, the fraction of the object's volume inside
            other objects, clipped to ``[0, 1]``.
        diameter: ``(n,)`` ``eps_d``, the object's diameter (:attr:`ObjectModel.diameter`), m;
            must be positive.

    Returns:
        ``(n,)`` severities ``>= 0``.
    """
    d = np.clip(np.atleast_1d(np.asarray(depth, dtype=float)), 0.0, None)
    f = np.clip(np.atleast_1d(np.asarray(overlap_fraction, dtype=float)), 0.0, 1.0)
    eps = np.atleast_1d(np.asarray(diameter, dtype=float))
    if np.any(~(eps > 0)):
        raise ValueError(f"diameter must be positive, got {eps}")
    return (d / eps) * f


def log_collision(e_c: np.ndarray | float, cfg: CollisionConfig) -> np.ndarray:
    """``log P_C = log L(-s_c (e_C - a_c))``, paper Eq. 10 with DESIGN section 4's sign.

    Args:
        e_c: ``(n,)`` severities from :func:`collision_severity` (dimensionless).
        cfg: steepness ``s_c`` and midpoint ``a_c`` (dimensionless).

    Returns:
        ``(n,)`` natural-log probabilities, decreasing in ``e_C``.
    """
    e = np.atleast_1d(np.asarray(e_c, dtype=float))
    return log_logistic(-cfg.steepness * (e - cfg.midpoint))


# --------------------------------------------------------------------------------------------
# Support (Eq. 11)
# --------------------------------------------------------------------------------------------


def log_support(supported_fraction_sum: np.ndarray | float, cfg: SupportConfig) -> np.ndarray:
    """``log P_S = log L(s_s * sum_i F_S,i + a_s)``, paper Eq. 11 as printed (``a_s`` an
    offset, not a midpoint; DESIGN section 4).

    Args:
        supported_fraction_sum: ``(n,)`` ``sum_i F_S,i``: for each object, the sum over the
            objects it supports of the fraction (0..1, dimensionless) of their weight it carries.
        cfg: steepness ``s_s`` and offset ``a_s``.

    Returns:
        ``(n,)`` natural-log probabilities, increasing in the supported sum.
    """
    f = np.atleast_1d(np.asarray(supported_fraction_sum, dtype=float))
    return log_logistic(cfg.steepness * f + cfg.offset)


# --------------------------------------------------------------------------------------------
# Data fitness (Eq. 12)
# --------------------------------------------------------------------------------------------


def data_fit_fraction(
    surface_points_world: np.ndarray,
    segment_points: np.ndarray | cKDTree,
    radius: float,
) -> float:
    """``c``: fraction of model surface samples with a segment point within ``radius`` (Eq. 12).

    Args:
        surface_points_world: ``(M, 3)`` the model's surface samples placed at the hypothesis
            pose, world frame, m.
        segment_points: ``(K, 3)`` the object's segment of the scene cloud, world frame, m, or a
            prebuilt :class:`scipy.spatial.cKDTree` over them (reuse it across hypotheses).
        radius: ``r_c``, m (:attr:`DataConfig.inlier_radius`); a distance equal to ``radius``
            counts as within.

    Returns:
        ``c`` in ``[0, 1]``; 0.0 when the segment or the sample set is empty.
    """
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    pts = np.asarray(surface_points_world, dtype=float).reshape(-1, 3)
    if isinstance(segment_points, cKDTree):
        tree = segment_points
        if tree.n == 0:
            return 0.0
    else:
        seg = np.asarray(segment_points, dtype=float).reshape(-1, 3)
        if len(seg) == 0:
            return 0.0
        tree = cKDTree(seg)
    if len(pts) == 0:
        return 0.0
    # cKDTree's bound is strict (d < bound); nudge it so that d == radius counts as within.
    dist, _ = tree.query(
        pts, k=1, distance_upper_bound=float(np.nextafter(radius, np.inf)), workers=1
    )
    return float(np.count_nonzero(np.isfinite(dist))) / len(pts)


def log_data(fit_fraction: np.ndarray | float, cfg: DataConfig) -> np.ndarray:
    """``log P_D = log L(s_d (min(c / C_max, 1) - a_d))``, paper Eq. 12 (DESIGN section 4).

    ``C_max`` is the fit fraction counted as full: one camera sees at most about half of an
    object's surface, so a fit above ``C_max`` says nothing more about the pose, only about the
    view; ``c / C_max`` is therefore capped at 1 (a decision of ours; the paper leaves it open).

    Args:
        fit_fraction: ``(n,)`` ``c`` from :func:`data_fit_fraction` (dimensionless, 0..1).
        cfg: steepness ``s_d``, midpoint ``a_d``, ``C_max``.

    Returns:
        ``(n,)`` natural-log probabilities, increasing in ``c``.
    """
    c = np.atleast_1d(np.asarray(fit_fraction, dtype=float))
    return log_logistic(cfg.steepness * (np.minimum(c / cfg.c_max, 1.0) - cfg.midpoint))


# --------------------------------------------------------------------------------------------
# Transition (Eq. 6)
# --------------------------------------------------------------------------------------------


def _angles_mod_axis(R_rel: np.ndarray, axis: np.ndarray | None) -> np.ndarray:
    """Rotation angle (rad) of each ``R_rel`` (k, 3, 3), minimised over rotations about ``axis``.

    Without an axis: ``atan2(sin, cos)`` with ``2 sin = |vee(R - R^T)|`` and ``2 cos = tr R -
    1`` (accurate near 0 and near pi; a few numpy operations for all k at once). With one: for
    ``q = (v, w)`` the unit quaternion of ``R_rel`` and ``q_phi = (a sin(phi/2),
    cos(phi/2))``, the scalar part of ``q q_phi`` is ``w cos(phi/2) - (v.a) sin(phi/2)``, whose
    largest magnitude over ``phi`` is ``sqrt(w^2 + (v.a)^2)``; the remaining vector part has
    norm ``|v - (v.a) a|``. The angle is ``2 atan2(|vector|, |scalar|)``.
    """
    R = np.asarray(R_rel, dtype=float)
    if axis is None:
        r = R.reshape(-1, 9).T  # rows: the matrices' entries 00, 01, ..., 22
        v0, v1, v2 = r[7] - r[5], r[2] - r[6], r[3] - r[1]  # vee(R - R^T)
        sin = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        cos = r[0] + r[4] + r[8] - 1.0
        return np.arctan2(sin, cos)
    q = Rotation.from_matrix(R).as_quat()  # (k, 4), x y z w
    v, w = q[:, :3], q[:, 3]
    va = v @ axis
    cos_half = np.sqrt(w**2 + va**2)
    sin_half = np.linalg.norm(v - va[:, None] * axis[None, :], axis=1)
    return 2.0 * np.arctan2(sin_half, cos_half)


def pose_change(
    T_prev: np.ndarray,
    T_cur: np.ndarray,
    symmetry: Symmetry | None = None,
    centre: np.ndarray | None = None,
) -> tuple[float, float]:
    """World-frame motion ``(dt, dtheta)`` between two poses of one object (for Eq. 6).

    ``dt`` (m) is the displacement of the model point ``centre`` (model frame, m; e.g. the
    centre of mass), ``|T_cur c - T_prev c|``; without ``centre``, of the model-frame origin,
    ``|t_cur - t_prev|`` (a mesh whose origin lies far from its body then turns a rotation
    into a translation). Symmetries map the centre of mass onto itself, so ``dt`` at the
    centre of mass does not depend on them. ``dtheta`` (rad, in ``[0, pi]``) is the smallest
    rotation angle of ``R_prev^T R_cur'`` over the symmetric equivalents ``T_cur @ S``:
    discrete symmetries are enumerated; a continuous axis is handled exactly (closed form, no
    sampling); two non-parallel continuous axes (a sphere) make every orientation equivalent,
    so ``dtheta = 0``. Symmetry offsets affect only translations and are ignored for ``dt``.

    Args:
        T_prev, T_cur: ``(4, 4)`` world-from-model poses, metres.
        symmetry: the model's symmetries, or None for an asymmetric object.
        centre: ``(3,)`` model-frame point whose displacement is ``dt`` (None: the origin).
    """
    T_prev = np.asarray(T_prev, dtype=float)
    T_cur = np.asarray(T_cur, dtype=float)
    if centre is None:
        dt = float(np.linalg.norm(T_cur[:3, 3] - T_prev[:3, 3]))
    else:
        c = np.asarray(centre, dtype=float)
        d = T_cur[:3, :3] @ c + T_cur[:3, 3] - T_prev[:3, :3] @ c - T_prev[:3, 3]
        dt = math.sqrt(float(d @ d))  # np.linalg.norm's sum, without its overhead
    R_base = T_prev[:3, :3].T @ T_cur[:3, :3]
    if symmetry is None:
        return dt, float(_angles_mod_axis(R_base[None], None)[0])
    axes = [np.asarray(c.axis, dtype=float) for c in symmetry.continuous]
    if len(axes) > 1 and any(np.linalg.norm(np.cross(axes[0], a)) > 1e-6 for a in axes[1:]):
        return dt, 0.0
    R_all = R_base[None] @ symmetry.discrete[:, :3, :3]  # (S, 3, 3)
    angles = _angles_mod_axis(R_all, axes[0] if axes else None)
    return dt, float(angles.min())


def log_transition(
    dt: np.ndarray | float, dtheta: np.ndarray | float, cfg: TransitionConfig
) -> np.ndarray | float:
    """``log P_T = max(-dt^2 / (2 s_t^2) - dtheta^2 / (2 s_r^2), floor)``, paper Eq. 6
    in DESIGN section 4's Gaussian form, with a floor: a Gaussian mixed with a small uniform
    part, so that no transition is impossible and the data can overturn an orientation it
    keeps contradicting.

    Args:
        dt: translation since the previous frame's best pose, m (scalar or ``(n,)``).
        dtheta: symmetry-aware rotation angle since then, rad (scalar or ``(n,)``).
        cfg: ``sigma_t`` (m), ``sigma_r`` (rad), ``floor``.

    Returns:
        Natural-log probability (``<= 0``), same shape as the broadcast inputs.
    """
    dt = np.asarray(dt, dtype=float)
    dtheta = np.asarray(dtheta, dtype=float)
    out = -(dt**2) / (2.0 * cfg.sigma_translation**2) - dtheta**2 / (2.0 * cfg.sigma_rotation**2)
    out = np.maximum(out, cfg.floor)
    return float(out) if out.ndim == 0 else out


def log_transition_from_poses(
    T_prev: np.ndarray | None,
    T_cur: np.ndarray,
    cfg: TransitionConfig,
    symmetry: Symmetry | None = None,
    centre: np.ndarray | None = None,
) -> float:
    """``log P_T`` of one object from its previous best pose (Eq. 6); 0.0 for a new object.

    Args:
        T_prev: ``(4, 4)`` previous frame's best world pose, or None when the object is new in
            this frame (``P_T = 1``, DESIGN section 4).
        T_cur: ``(4, 4)`` current hypothesis pose, m.
        cfg: transition widths and floor.
        symmetry: the model's symmetries (see :func:`pose_change`).
        centre: the model point whose motion counts (the centre of mass; None: the origin).
    """
    if T_prev is None:
        return 0.0
    dt, dtheta = pose_change(T_prev, T_cur, symmetry, centre)
    return float(log_transition(dt, dtheta, cfg))


# --------------------------------------------------------------------------------------------
# Container
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObjectTerms:
    """The five natural-log terms of one object's probability (each ``<= 0``)."""

    stability: float
    collision: float
    support: float
    data: float
    transition: float

    @property
    def total(self) -> float:
        """``log P = log P_B + log P_C + log P_S + log P_D + log P_T`` (the object's factor
        of Eq. 4)."""
        return float(self.stability + self.collision + self.support + self.data + self.transition)

    def as_dict(self) -> dict[str, float]:
        """The five terms as plain floats (``ObjectTerms(**d)`` round-trips)."""
        return {k: float(v) for k, v in asdict(self).items()}
