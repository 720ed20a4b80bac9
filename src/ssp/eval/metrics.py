"""Table I metrics: estimates matched to ground truth, accuracy, precision, induced noise.

Definitions (paper section "Experiments"; DESIGN section 5):

* **Matching.** Per frame and per class, the estimated objects are assigned to the ground-truth
  objects by :func:`scipy.optimize.linear_sum_assignment` on the translation distance; a pair
  farther apart than ``gate`` (5 cm by default) is not allowed. A ground-truth object left
  without an estimate is *missed*, an estimate left without a ground-truth object is a *false
  positive*; both are counted, neither enters the errors. Estimators' instance ids are their
  own and never compared with the ground truth's.
* **Error** of a matched pair: ``(|T_est c - T_gt c|`` in mm with ``c`` the model's centre of
  mass, the smallest rotation angle between the two poses over the model's symmetries in deg)
  from :func:`ssp.probability.pose_change`. Distances are measured at the centre, not at the
  mesh origin, so that a model whose origin lies off its body does not turn a rotation error
  into a translation error (or a miss); matching uses the same centre distance.
* **Accuracy**: the errors of every matched object in every frame, occluded ones included (as
  the paper), as ``mean`` and ``std``.
* **Precision**: the spread of an object's estimates over the repeated frames of one static
  scene (``SimFrame.static_group``). For each ground-truth object and static group with at
  least two matched estimates: the translation deviation of each estimate is ``|t - mean t|``;
  for the rotation, each estimate is first snapped to the symmetric equivalent closest to the
  first one (:func:`ssp.temporal.snap_symmetric`), the snapped rotations are averaged (chordal
  L2 mean: the rotation nearest to the mean matrix) and the deviation is the symmetry-aware
  angle to that mean. ``mean`` and ``std`` are over all deviations pooled.
* **Induced noise**: the error of every pose hypothesis against the ground-truth object it was
  drawn from (the generator's record, ``SimSequence.info["hypothesis_sources"]``, when there
  is one), else against the nearest ground-truth object of its class; a hypothesis of no
  object, or farther than ``gate`` from all of them, is an *outlier*, counted and left out.

All ``std`` are population standard deviations (``ddof = 0``); an empty set gives ``None``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from ssp.library.symmetry import Symmetry
from ssp.probability import pose_change
from ssp.temporal import snap_symmetric

__all__ = [
    "DEFAULT_GATE",
    "FrameMatch",
    "Match",
    "centre_position",
    "chordal_mean_rotation",
    "hypothesis_errors",
    "match_frame",
    "plus_minus",
    "pose_error",
    "precision_deviations",
    "summarize",
]

#: Largest translation distance of a matched estimate / hypothesis to its ground truth, m.
DEFAULT_GATE = 0.05

#: Ground truth of one frame: instance id -> (class name, T_world_obj).
GroundTruth = Mapping[str, tuple[str, np.ndarray]]
#: Symmetry source: class name -> Symmetry, or an object library (models with ``.symmetry``).
Symmetries = Mapping[str, Any]


def _symmetry(symmetries: Symmetries | None, class_name: str) -> Symmetry | None:
    if symmetries is None or class_name not in symmetries:
        return None
    value = symmetries[class_name]
    return getattr(value, "symmetry", value)


def _centre(symmetries: Symmetries | None, class_name: str) -> np.ndarray | None:
    """The model's centre of mass (model frame, m) when ``symmetries`` holds models."""
    if symmetries is None or class_name not in symmetries:
        return None
    c = getattr(symmetries[class_name], "center_of_mass", None)
    return None if c is None else np.asarray(c, dtype=float)


def pose_error(
    T_gt: np.ndarray,
    T_est: np.ndarray,
    symmetry: Symmetry | None = None,
    centre: np.ndarray | None = None,
) -> tuple[float, float]:
    """Symmetry-aware error ``(translation mm, rotation deg)`` of ``T_est`` against ``T_gt``;
    the translation is that of the model point ``centre`` (m; None: the origin)."""
    dt, dth = pose_change(T_gt, T_est, symmetry, centre)
    return 1000.0 * dt, float(np.degrees(dth))


def centre_position(T: np.ndarray, centre: np.ndarray | None) -> np.ndarray:
    """World position ``(3,)`` of the model point ``centre`` at pose ``T`` (origin if None)."""
    T = np.asarray(T, dtype=float)
    return T[:3, 3] if centre is None else T[:3, :3] @ centre + T[:3, 3]


@dataclass(frozen=True)
class Match:
    """A ground-truth object and the estimate matched to it, with the error."""

    gt_id: str
    class_name: str
    est_index: int
    trans_mm: float
    rot_deg: float


@dataclass(frozen=True)
class FrameMatch:
    """Result of :func:`match_frame`.

    Attributes:
        matches: matched pairs, in ground-truth order.
        missed: ground-truth ids without an estimate.
        false_positives: indices of the estimates matched to no ground-truth object.
    """

    matches: list[Match] = field(default_factory=list)
    missed: list[str] = field(default_factory=list)
    false_positives: list[int] = field(default_factory=list)

    def by_gt(self) -> dict[str, Match]:
        return {m.gt_id: m for m in self.matches}


def match_frame(
    gt: GroundTruth,
    estimates: Sequence[tuple[str, np.ndarray]],
    symmetries: Symmetries | None = None,
    gate: float = DEFAULT_GATE,
) -> FrameMatch:
    """Match one frame's estimates ``[(class_name, T_world_obj, ...), ...]`` to the ground truth.

    Per class, a Hungarian assignment on the distance between centres (pairs beyond ``gate``,
    m, forbidden); errors from :func:`pose_error` with the class's symmetry (``symmetries`` maps
    class names to a :class:`Symmetry` or to models with ``.symmetry`` and
    ``.center_of_mass``, e.g. the library; with bare symmetries the origin is the centre).
    """
    gt_ids = list(gt)
    matched: dict[str, Match] = {}
    used: set[int] = set()
    for cls in sorted({c for c, _ in gt.values()}):
        rows = [g for g in gt_ids if gt[g][0] == cls]
        cols = [j for j, e in enumerate(estimates) if e[0] == cls]
        if not cols:
            continue
        centre = _centre(symmetries, cls)
        t_gt = np.array([centre_position(gt[g][1], centre) for g in rows])
        t_est = np.array([centre_position(estimates[j][1], centre) for j in cols])
        dist = np.linalg.norm(t_gt[:, None, :] - t_est[None, :, :], axis=2)
        cost = np.where(dist <= gate, dist, 1e6)
        sym = _symmetry(symmetries, cls)
        for r, c in zip(*linear_sum_assignment(cost), strict=True):
            if dist[r, c] > gate:
                continue
            j = cols[c]
            mm, deg = pose_error(gt[rows[r]][1], estimates[j][1], sym, centre)
            matched[rows[r]] = Match(rows[r], cls, j, mm, deg)
            used.add(j)
    return FrameMatch(
        matches=[matched[g] for g in gt_ids if g in matched],
        missed=[g for g in gt_ids if g not in matched],
        false_positives=[j for j in range(len(estimates)) if j not in used],
    )


def hypothesis_errors(
    gt: GroundTruth,
    hypotheses: Iterable[Any],
    symmetries: Symmetries | None = None,
    gate: float = DEFAULT_GATE,
    sources: Sequence[str | None] | None = None,
) -> tuple[list[tuple[float, float]], int]:
    """``([(mm, deg) per hypothesis], outliers)``: each hypothesis (``.class_name``,
    ``.T_world_obj``) against its ground-truth object, left out and counted as an outlier when
    it has none.

    With ``sources`` (the ground-truth id each hypothesis was drawn from, as a generator
    records it; None for a hypothesis of no object) that object is used, whatever the
    distance. Without, the nearest ground-truth object of the hypothesis's class (distance
    between centres), if within ``gate``.
    """
    hypotheses = list(hypotheses)
    if sources is not None and len(sources) != len(hypotheses):
        raise ValueError(f"{len(sources)} sources for {len(hypotheses)} hypotheses")
    by_class: dict[str, list[np.ndarray]] = {}
    for cls, T in gt.values():
        by_class.setdefault(cls, []).append(np.asarray(T, dtype=float))
    errors, outliers = [], 0
    for n, h in enumerate(hypotheses):
        T_h = np.asarray(h.T_world_obj, dtype=float)
        if sources is not None:
            src = sources[n]
            if src is None or src not in gt or gt[src][0] != h.class_name:
                outliers += 1
                continue
            T_gt = np.asarray(gt[src][1], dtype=float)
        else:
            cands = by_class.get(h.class_name)
            if not cands:
                outliers += 1
                continue
            c = _centre(symmetries, h.class_name)
            p_h = centre_position(T_h, c)
            d = [float(np.linalg.norm(centre_position(T, c) - p_h)) for T in cands]
            k = int(np.argmin(d))
            if d[k] > gate:
                outliers += 1
                continue
            T_gt = cands[k]
        cls = h.class_name
        errors.append(pose_error(T_gt, T_h, _symmetry(symmetries, cls), _centre(symmetries, cls)))
    return errors, outliers


def chordal_mean_rotation(rotations: Sequence[np.ndarray]) -> np.ndarray:
    """The rotation closest (Frobenius) to the mean of the matrices ``rotations`` (the chordal
    L2 mean; for clustered rotations it agrees with the quaternion mean)."""
    M = np.mean(np.asarray(rotations, dtype=float).reshape(-1, 3, 3), axis=0)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt))) or 1.0])
    return U @ D @ Vt


def precision_deviations(
    poses: Sequence[np.ndarray], symmetry: Symmetry | None = None
) -> tuple[list[float], list[float]]:
    """Deviations ``([mm], [deg])`` of each pose of one object in one static scene from the
    mean pose (see the module docstring); empty lists for fewer than two poses."""
    if len(poses) < 2:
        return [], []
    Ts = [np.asarray(T, dtype=float) for T in poses]
    t = np.array([T[:3, 3] for T in Ts])
    t_mean = t.mean(axis=0)
    trans = (1000.0 * np.linalg.norm(t - t_mean, axis=1)).tolist()
    snapped = [Ts[0]] + [snap_symmetric(Ts[0], T, symmetry) for T in Ts[1:]]
    T_mean = np.eye(4)
    T_mean[:3, :3] = chordal_mean_rotation([T[:3, :3] for T in snapped])
    T_mean[:3, 3] = t_mean
    rot = [float(np.degrees(pose_change(T_mean, T, symmetry)[1])) for T in Ts]
    return trans, rot


def summarize(trans_mm: Sequence[float], rot_deg: Sequence[float]) -> dict[str, float | None]:
    """``{"trans_mm_mean", "trans_mm_std", "rot_deg_mean", "rot_deg_std"}`` (``None`` when
    empty; population std)."""

    def ms(values: Sequence[float]) -> tuple[float | None, float | None]:
        if len(values) == 0:
            return None, None
        a = np.asarray(values, dtype=float)
        return float(a.mean()), float(a.std())

    tm, ts = ms(trans_mm)
    rm, rs = ms(rot_deg)
    return {"trans_mm_mean": tm, "trans_mm_std": ts, "rot_deg_mean": rm, "rot_deg_std": rs}


def plus_minus(mean: float | None, std: float | None, digits: int = 2) -> str:
    """``"mean ± std"`` with ``digits`` decimals, or ``"n/a"`` when ``mean`` is None."""
    if mean is None:
        return "n/a"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"
