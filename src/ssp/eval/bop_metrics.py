"""The BOP Challenge 2019 pose-error functions and their average recall (AR).

Definitions follow the BOP toolkit (``bop_toolkit_lib/pose_error.py``, ``visibility.py``,
``pose_matching.py``, ``scripts/eval_bop19_pose.py``, ``scripts/eval_calc_scores.py``), in
metres instead of millimetres:

* **MSSD** (maximum symmetry-aware surface distance): ``min over symmetries S of max over model
  vertices x of |T_est x - T_gt S x|``, m; correct below ``th x diameter`` for ``th`` in
  :data:`MSSD_THRESHOLDS` (0.05, 0.10, ..., 0.50).
* **MSPD** (maximum symmetry-aware projection distance): the same with the vertices projected
  into the image, pixels, scaled by ``640 / image width``; correct below :data:`MSPD_THRESHOLDS`
  (5, 10, ..., 50 px).
* **VSD** (visible surface discrepancy, ``step`` cost, BOP19 visibility): the model rendered
  alone at the estimated and at the true pose; *distance* images (range, not z); the visible
  masks ``V_gt = (d_gt > 0) & ((d_gt - d_test <= delta) | d_test == 0)`` and ``V_est`` the
  same for ``d_est``, or'ed with ``V_gt & (d_est > 0)``; ``e = (#(|d_est - d_gt| >= tau x
  diameter on V_est & V_gt) + #(V_est xor V_gt)) / #(V_est | V_gt)``, 1 when the union is
  empty; ``delta`` = 15 mm, ``tau`` in :data:`VSD_TAUS` (0.05, ..., 0.50 of the diameter);
  correct below :data:`VSD_THRESHOLDS` (0.05, ..., 0.50). Pairs whose bounding spheres do not
  overlap in the image get ``e = 1`` without rendering, as the toolkit does (our spheres are
  the object's bounding sphere about its centre of mass, so no overlapping pair is skipped).
* **Symmetries**: the model's declared ones; a continuous axis is sampled in
  ``ceil(pi / 0.01)`` steps (``max_sym_disc_step`` = 0.01).
* **Poses as published**: rotations (ground truth and estimates) are replaced by their nearest
  rotation (SVD) before scoring, as the renderer needs (LM-O's ground truth is orthonormal
  only to about 1e-3), with one warning per evaluator when one deviates more than
  :data:`ssp.io.bop.ROTATION_WARN`; one farther than :data:`ssp.io.bop.ROTATION_MAX` (or a
  reflection) is an error. The toolkit scores the rotations as given; on LM-O scene 2 the
  recalls agree with its own within 3 of 1,445 targets (tests/test_bop_toolkit_agreement.py).
* **Targets**: the ground-truth instances at least :data:`MIN_VISIB` (10 %) visible, as in the
  BOP19 test targets. Per image and class, the estimates (best score first) are cut to the
  number of targets of that class (``n_top = -1``) and greedily matched, best score first, to
  the not yet matched target with the lowest error below the threshold (hidden, non-target
  instances take no part).
* **Recall** of one threshold: matched targets / all targets, over the whole run. ``AR_VSD``,
  ``AR_MSSD``, ``AR_MSPD``: the mean recall over their thresholds (VSD: over every ``tau`` and
  threshold); ``AR``: the mean of the three.

Depth images here are ``z`` images (m, 0 = no depth) of a pinhole :class:`~ssp.camera.Camera`;
they are turned into distance images as the toolkit does.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ssp.camera import Camera
from ssp.errors import InvalidPoseError
from ssp.geometry import invert, nearest_rotation
from ssp.io.bop import ROTATION_MAX, ROTATION_WARN, rotation_deviation
from ssp.library.symmetry import Symmetry
from ssp.sim.render import ImageWindow, image_window, render

__all__ = [
    "MIN_VISIB",
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "VSD_DELTA",
    "VSD_TAUS",
    "VSD_THRESHOLDS",
    "BopEvaluator",
    "bop_symmetries",
    "greedy_match",
    "mspd",
    "mssd",
    "vsd",
]

#: Correctness thresholds of BOP19: MSSD (x diameter), MSPD (px at 640 width), VSD (error).
MSSD_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(1, 11))
MSPD_THRESHOLDS = tuple(float(5 * i) for i in range(1, 11))
VSD_THRESHOLDS = MSSD_THRESHOLDS
#: VSD misalignment tolerances (x diameter) and visibility tolerance delta (m).
VSD_TAUS = MSSD_THRESHOLDS
VSD_DELTA = 0.015
#: Ground-truth instances less visible than this are not targets (BOP19 test targets).
MIN_VISIB = 0.1
log = logging.getLogger(__name__)

#: Largest step along a continuous symmetry, as a fraction of pi x diameter (BOP's 0.01).
MAX_SYM_DISC_STEP = 0.01


def bop_symmetries(symmetry: Symmetry | None) -> np.ndarray:
    """``(S, 4, 4)`` symmetry transforms as BOP samples them: the discrete ones (identity
    first), each combined with ``ceil(pi / 0.01)`` rotations about the first continuous axis."""
    if symmetry is None:
        return np.eye(4)[None]
    if not symmetry.continuous:
        return np.asarray(symmetry.discrete, dtype=float)
    n = int(math.ceil(math.pi / MAX_SYM_DISC_STEP))
    cont = np.stack([symmetry.continuous[0].transform(2.0 * math.pi * i / n) for i in range(n)])
    return np.einsum("bij,ajk->abik", cont, symmetry.discrete).reshape(-1, 4, 4)


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points ``(..., n, 3)`` under transforms ``T`` ``(..., 4, 4)``."""
    return pts @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def mssd(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray, syms: np.ndarray) -> float:
    """MSSD, m: ``min_S max_x |T_est x - T_gt S x|`` over model points ``(n, 3)`` (model
    frame, m) and symmetries ``(S, 4, 4)`` (:func:`bop_symmetries`)."""
    pts = np.asarray(points, dtype=float)
    p_est = _apply(np.asarray(T_est, dtype=float), pts)
    p_gt = _apply(np.asarray(T_gt, dtype=float) @ syms, pts)  # (S, n, 3)
    return float(np.linalg.norm(p_gt - p_est[None], axis=2).max(axis=1).min())


def _project(K: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    z = p_cam[..., 2:3]
    return (p_cam[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])


def mspd(
    T_est: np.ndarray,
    T_gt: np.ndarray,
    points: np.ndarray,
    syms: np.ndarray,
    camera: Camera,
    T_world_cam: np.ndarray,
) -> float:
    """MSPD, pixels (unscaled): ``min_S max_x |pi(T_est x) - pi(T_gt S x)|`` with ``pi`` the
    projection of ``camera`` at ``T_world_cam`` (poses are world frame)."""
    T_cw = invert(np.asarray(T_world_cam, dtype=float))
    K = _intrinsics(camera)
    pts = np.asarray(points, dtype=float)
    q_est = _project(K, _apply(T_cw @ np.asarray(T_est, dtype=float), pts))
    q_gt = _project(K, _apply(T_cw @ np.asarray(T_gt, dtype=float) @ syms, pts))
    return float(np.linalg.norm(q_gt - q_est[None], axis=2).max(axis=1).min())


def _intrinsics(camera: Camera) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def vsd(
    dist_est: np.ndarray,
    dist_gt: np.ndarray,
    dist_test: np.ndarray,
    diameter: float,
    delta: float = VSD_DELTA,
    taus: Sequence[float] = VSD_TAUS,
) -> list[float]:
    """VSD errors, one per ``tau`` (x ``diameter``), of aligned distance images (m, 0 = none)
    of the model alone at the estimated pose, at the true pose, and of the test scene."""
    d_est = np.asarray(dist_est, dtype=float)
    d_gt = np.asarray(dist_gt, dtype=float)
    d_test = np.asarray(dist_test, dtype=float)
    visib_gt = (d_gt > 0) & ((d_gt - d_test <= delta) | (d_test == 0))
    visib_est = (d_est > 0) & ((d_est - d_test <= delta) | (d_test == 0))
    visib_est |= visib_gt & (d_est > 0)
    inter = visib_gt & visib_est
    union_count = int(np.count_nonzero(visib_gt | visib_est))
    if union_count == 0:
        return [1.0] * len(taus)
    comp_count = union_count - int(np.count_nonzero(inter))
    dists = np.abs(d_gt[inter] - d_est[inter]) / diameter
    return [(int(np.count_nonzero(dists >= tau)) + comp_count) / union_count for tau in taus]


def greedy_match(errors: np.ndarray, threshold: float) -> int:
    """Number of targets matched (BOP ``match_poses``): ``errors`` ``(n_est, n_targets)``
    with the estimates sorted by decreasing score; each estimate takes the unmatched target
    with the lowest error below ``threshold``."""
    errors = np.asarray(errors, dtype=float)
    taken = np.zeros(errors.shape[1], dtype=bool)
    for row in errors:
        cand = np.where(~taken & (row < threshold), row, np.inf)
        if len(cand) and np.isfinite(cand.min()):
            taken[int(np.argmin(cand))] = True
    return int(np.count_nonzero(taken))


# ---------------------------------------------------------------------------- rendering
def _distance_factor(camera: Camera, u0: int, v0: int, h: int, w: int) -> np.ndarray:
    """Range / depth ratio of the pixels of the window ``(v0, u0, h, w)``."""
    v, u = np.mgrid[v0 : v0 + h, u0 : u0 + w]
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    return np.sqrt(x * x + y * y + 1.0)


def _render_window(mesh, T_world_obj: np.ndarray, T_world_cam, camera: Camera, win: ImageWindow):
    """Depth (z, m) of ``mesh`` alone at ``T_world_obj``, in window ``win`` of ``camera``."""
    return render([("o", mesh, T_world_obj)], T_world_cam, win.camera(camera), table=False).depth


# ---------------------------------------------------------------------------- evaluator
@dataclass
class _Counts:
    targets: int = 0
    mssd: np.ndarray = field(default_factory=lambda: np.zeros(len(MSSD_THRESHOLDS), int))
    mspd: np.ndarray = field(default_factory=lambda: np.zeros(len(MSPD_THRESHOLDS), int))
    vsd: np.ndarray = field(
        default_factory=lambda: np.zeros((len(VSD_TAUS), len(VSD_THRESHOLDS)), int)
    )


class BopEvaluator:
    """Accumulates BOP19 recalls over frames (module docstring); one per method.

    Args:
        library: class name -> model (``mesh``, ``hull_vertices``, ``diameter``, ``symmetry``).
        vsd: compute VSD (needs the frames' depth images and one render per estimate-instance
            pair whose image footprints overlap).
    """

    def __init__(self, library: Mapping, *, vsd: bool = True) -> None:
        self.library = library
        self.use_vsd = bool(vsd)
        self._syms: dict[str, np.ndarray] = {}
        self._counts = _Counts()
        self._per_class: dict[str, _Counts] = {}
        self._gt_cache: dict[tuple, tuple] = {}
        #: The largest deviation from orthonormal of a pose re-orthonormalised so far.
        self.worst_rotation_deviation = 0.0

    def _symmetries(self, cls: str) -> np.ndarray:
        if cls not in self._syms:
            self._syms[cls] = bop_symmetries(self.library[cls].symmetry)
        return self._syms[cls]

    def add_frame(
        self,
        gt: Mapping[str, tuple[str, np.ndarray]],
        visib_fract: Mapping[str, float],
        estimates: Sequence[tuple[str, np.ndarray, float]],
        camera: Camera,
        T_world_cam: np.ndarray,
        depth: np.ndarray | None = None,
        targets: Mapping[str, int] | None = None,
    ) -> None:
        """One frame: ground truth ``id -> (class, T_world_obj)``, its visible fractions,
        the method's estimates ``(class, T_world_obj, score)`` and the test depth ``(H, W)``
        (z, m; needed for VSD).

        ``targets``: the image's BOP19 test targets, ``class -> inst_count`` (a dataset's
        ``test_targets_bop19.json``: :func:`ssp.io.bop.read_targets`); the targets of a class
        are then its ``inst_count`` most visible instances, as the toolkit takes them
        (``visib_gt_min = -1``). Without it, every instance at least :data:`MIN_VISIB` visible
        (LM-O's published targets leave out 29 of scene 2's 1,474 such instances).

        Raises:
            InvalidPoseError: a pose that is not a finite 4x4 matrix (a 3x2 "rotation" is
                never scored) or whose rotation is far from one (module docstring), naming
                the estimate or ground-truth instance.
        """
        if self.use_vsd and depth is None:
            raise ValueError("VSD needs the frame's depth image")
        gt, estimates, worst = _published_poses(gt, estimates)
        self._note_rotations(worst)
        T_cw = invert(np.asarray(T_world_cam, dtype=float))
        for cls in sorted({c for c, _ in gt.values()}):
            gids = _targets(gt, visib_fract, cls, targets)
            n_top = len(gids)
            per = self._per_class.setdefault(cls, _Counts())
            for c in (self._counts, per):
                c.targets += n_top
            if n_top == 0:
                continue
            ests = [(float(s), i, T) for i, (c, T, s) in enumerate(estimates) if c == cls]
            ests.sort(key=lambda e: (-e[0], e[1]))  # best score first, then output order
            ests = ests[:n_top]
            if not ests:
                continue
            model = self.library[cls]
            syms = self._symmetries(cls)
            T_gts = [np.asarray(gt[g][1], dtype=float) for g in gids]
            e_mssd = np.array(
                [[mssd(T, Tg, model.hull_vertices, syms) for Tg in T_gts] for _, _, T in ests]
            )
            verts = np.asarray(model.mesh.vertices, dtype=float)
            scale = 640.0 / camera.width
            e_mspd = scale * np.array(
                [
                    [mspd(T, Tg, verts, syms, camera, T_world_cam) for Tg in T_gts]
                    for _, _, T in ests
                ]
            )
            d = model.diameter
            for c in (self._counts, per):
                for k, th in enumerate(MSSD_THRESHOLDS):
                    c.mssd[k] += greedy_match(e_mssd, th * d)
                for k, th in enumerate(MSPD_THRESHOLDS):
                    c.mspd[k] += greedy_match(e_mspd, th)
            if not self.use_vsd:
                continue
            e_vsd = np.ones((len(ests), len(gids), len(VSD_TAUS)))
            for a, (_, _, T) in enumerate(ests):
                for b, (g, Tg) in enumerate(zip(gids, T_gts, strict=True)):
                    e_vsd[a, b] = self._vsd_pair(model, T, g, Tg, T_cw, T_world_cam, camera, depth)
            for c in (self._counts, per):
                for t in range(len(VSD_TAUS)):
                    for k, th in enumerate(VSD_THRESHOLDS):
                        c.vsd[t, k] += greedy_match(e_vsd[:, :, t], th)

    def _note_rotations(self, worst: float) -> None:
        """Keep the largest deviation from orthonormal met; warn the first time it is over
        :data:`ssp.io.bop.ROTATION_WARN`."""
        if worst > ROTATION_WARN >= self.worst_rotation_deviation:
            log.warning(
                "rotations orthonormal only to %.1e: each replaced by its nearest rotation "
                "(SVD) before scoring (said once)",
                worst,
            )
        self.worst_rotation_deviation = max(self.worst_rotation_deviation, worst)

    def _vsd_pair(self, model, T_est, gid, T_gt, T_cw, T_wc, camera, depth) -> list[float]:
        """VSD errors of one estimate against one ground-truth instance."""
        c = np.asarray(model.center_of_mass, dtype=float)
        p_e = T_cw[:3, :3] @ (T_est[:3, :3] @ c + T_est[:3, 3]) + T_cw[:3, 3]
        p_g = T_cw[:3, :3] @ (T_gt[:3, :3] @ c + T_gt[:3, 3]) + T_cw[:3, 3]
        if not _spheres_overlap(model.d_max, p_e, p_g):
            return [1.0] * len(VSD_TAUS)
        key = (model.name, gid, np.asarray(T_gt).tobytes(), np.asarray(T_wc).tobytes(), camera)
        hit = self._gt_cache.get(key)
        if hit is None:
            win_g = image_window(_apply(T_gt, model.hull_vertices), T_wc, camera)
            if win_g is None:
                return [1.0] * len(VSD_TAUS)
            hit = (win_g, _render_window(model.mesh, T_gt, T_wc, camera, win_g))
            if len(self._gt_cache) > 256:
                self._gt_cache.clear()
            self._gt_cache[key] = hit
        win_g, d_gt = hit
        win_e = image_window(_apply(T_est, model.hull_vertices), T_wc, camera)
        win = win_g if win_e is None else win_g.union(win_e)
        d_est = (
            np.zeros((win.h, win.w))
            if win_e is None
            else _render_window(model.mesh, T_est, T_wc, camera, win)
        )
        gt_full = np.zeros((win.h, win.w))
        gv, gu = win_g.v0 - win.v0, win_g.u0 - win.u0
        gt_full[gv : gv + win_g.h, gu : gu + win_g.w] = d_gt
        test = np.asarray(depth, dtype=float)[win.v0 : win.v0 + win.h, win.u0 : win.u0 + win.w]
        f = _distance_factor(camera, win.u0, win.v0, win.h, win.w)
        return vsd(d_est * f, gt_full * f, test * f, model.diameter)

    # ------------------------------------------------------------------ merging
    def counts(self) -> tuple[bool, _Counts, dict[str, _Counts]]:
        """The accumulated counts (picklable, without the library): ``(vsd, all, per class)``,
        for :meth:`add_counts` of another evaluator (frames evaluated elsewhere)."""
        return self.use_vsd, self._counts, self._per_class

    def add_counts(self, counts: tuple[bool, _Counts, dict[str, _Counts]]) -> None:
        """Add the :meth:`counts` of another evaluator: as if its frames were added here."""
        _, total, per_class = counts
        for mine, theirs in ((self._counts, total),) + tuple(
            (self._per_class.setdefault(k, _Counts()), v) for k, v in per_class.items()
        ):
            mine.targets += theirs.targets
            mine.mssd += theirs.mssd
            mine.mspd += theirs.mspd
            mine.vsd += theirs.vsd

    # ------------------------------------------------------------------ results
    @staticmethod
    def _summary(c: _Counts) -> dict:
        n = max(c.targets, 1)
        r_mssd = c.mssd / n
        r_mspd = c.mspd / n
        r_vsd = c.vsd / n
        return {
            "targets": int(c.targets),
            "AR_MSSD": float(r_mssd.mean()),
            "AR_MSPD": float(r_mspd.mean()),
            "AR_VSD": float(r_vsd.mean()),
            "recall_MSSD": [float(x) for x in r_mssd],
            "recall_MSPD": [float(x) for x in r_mspd],
        }

    def result(self, *, vsd: bool | None = None) -> dict:
        """JSON-ready recalls: ``AR``, ``AR_VSD``, ``AR_MSSD``, ``AR_MSPD``, the recall per
        threshold, the number of targets, and the same per class (``per_class``)."""
        use_vsd = self.use_vsd if vsd is None else vsd
        keys = ["AR_VSD", "AR_MSSD", "AR_MSPD"] if use_vsd else ["AR_MSSD", "AR_MSPD"]

        def finish(s: dict) -> dict:
            if not use_vsd:
                s.pop("AR_VSD")
            s["AR"] = float(np.mean([s[k] for k in keys]))
            return s

        out = finish(self._summary(self._counts))
        out["AR_parts"] = [k[3:] for k in keys]
        out["per_class"] = {}
        for cls, c in sorted(self._per_class.items()):
            s = self._summary(c)
            del s["recall_MSSD"], s["recall_MSPD"]
            out["per_class"][cls] = finish(s)
        return out


def _targets(
    gt: Mapping[str, tuple[str, np.ndarray]],
    visib_fract: Mapping[str, float],
    cls: str,
    targets: Mapping[str, int] | None,
) -> list[str]:
    """The target instances of class ``cls`` in a frame (:meth:`BopEvaluator.add_frame`)."""
    if targets is None:
        return [g for g in gt if gt[g][0] == cls and visib_fract.get(g, 0.0) >= MIN_VISIB]
    ids = [g for g in gt if gt[g][0] == cls]
    ids.sort(key=lambda g: -visib_fract.get(g, 0.0))  # stable: file order on ties
    return ids[: int(targets.get(cls, 0))]


def _published_poses(
    gt: Mapping[str, tuple[str, np.ndarray]], estimates: Sequence
) -> tuple[dict[str, tuple[str, np.ndarray]], list[tuple[str, np.ndarray, float]], float]:
    """The frame's ground truth and estimates with each rotation replaced by its nearest
    rotation (SVD), and the largest deviation from orthonormal (``max |R R^T - I|``) met.

    Raises:
        InvalidPoseError: a pose that is not a finite 4x4 matrix, or whose rotation is a
            reflection or farther than :data:`ssp.io.bop.ROTATION_MAX` from orthonormal.
    """
    worst = 0.0

    def clean(what: str, T: np.ndarray) -> np.ndarray:
        nonlocal worst
        M = np.array(T, dtype=float)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise InvalidPoseError(
                f"{what}: a pose must be a finite 4x4 matrix, got shape {M.shape}"
            )
        dev, det = float(rotation_deviation(M[:3, :3])), float(np.linalg.det(M[:3, :3]))
        if det <= 0 or dev > ROTATION_MAX:
            raise InvalidPoseError(
                f"{what}: not a rotation (|R R^T - I| = {dev:.2g}, det {det:.3f})"
            )
        worst = max(worst, dev)
        if dev > 0:
            M[:3, :3] = nearest_rotation(M[:3, :3])
        return M

    g = {k: (c, clean(f"ground truth {k!r}", T)) for k, (c, T) in gt.items()}
    e = [(c, clean(f"estimate {i}", T), s) for i, (c, T, s) in enumerate(estimates)]
    return g, e, worst


def _spheres_overlap(radius: float, p1: np.ndarray, p2: np.ndarray) -> bool:
    """Do the image projections of two spheres of ``radius`` (m) at camera-frame centres
    ``p1``, ``p2`` overlap? (the toolkit's approximate pre-check before rendering VSD)"""
    if p1[2] <= 0 or p2[2] <= 0:
        return False
    q1, q2 = p1[:2] / p1[2], p2[:2] / p2[2]
    return bool(np.linalg.norm(q1 - q2) < radius * (1.0 / p1[2] + 1.0 / p2[2]))
