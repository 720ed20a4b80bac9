"""Depth correction before judging: slide a hypothesis along its viewing ray to the depth its
data is at (DESIGN section 6's verification judges the corrected pose).

An RGB pose estimator (MegaPose, FoundationPose without depth, CosyPose) sees an object's
silhouette well and its distance poorly: on LM-O, MegaPose's translation error along the
camera ray has median 14 mm and 75th percentile 35 mm, against 5 mm across it
(``shared/data/lmo-megapose``). The data forces (paper Eq. 13-14) reach
``forces.max_distance`` (2 cm), and verification judges a hypothesis where it is: a model 3 cm
behind its object is "occluded" by its own surface, 3 cm in front of it "seen through", and
the object is rejected although its silhouette fits.

For each hypothesis of a frame with a camera pose, :func:`correct_hypothesis`:

1. looks along the rays of the model's camera-facing samples
   (:meth:`ssp.visibility.CameraView.lookup`): the *silhouette samples* are those whose ray
   meets the object's observed surface: with instance labels the points of the hypothesis'
   own segment (:attr:`ssp.scene.Hypothesis.segment`), else of the label most of its facing
   rays meet; with clusters or no labels every observed point that is not table or
   background;
2. finds the shift ``s`` along the viewing ray ``u`` (camera centre to the model origin) that
   puts most silhouette samples on the observed surface: sample ``i`` at depth ``z_i`` whose
   ray sees depth ``o_i`` is on the surface after the shift when
   ``|o_i - z_i - s u_z| <= temporal.depth_tolerance`` (a translation along ``u`` changes every
   sample's depth by ``s u_z``), so ``s`` is the densest window of ``(o_i - z_i) / u_z``
   (:func:`ray_shift`);
3. keeps the shift when it is at least ``correction.min_shift`` (smaller ones are the data
   forces' work), at most ``correction.max_shift``, puts at least ``correction.min_support`` of
   the silhouette samples on the surface and ``correction.gain`` times as many as the
   estimator's depth did; checked again at the shifted pose (the rays move a little with it);
4. with ``correction.align``, aligns the shifted model to the observed surface (point-to-plane
   ICP, :func:`ssp.registration.icp_refine`, within ``correction.align_distance``: a wider
   basin than the data forces' after the shift), kept when it puts more facing samples on the
   object's surface;
5. believes the corrected pose only when it explains what the camera sees of it
   (:func:`_doubt`): at least ``correction.min_fit`` of its facing samples that nothing hides
   on the surface, at most ``correction.max_seen_through`` of them seen through, and with
   instance labels its silhouette covering ``correction.min_coverage`` of its segment; and
   never slides a hypothesis onto a segment another hypothesis already explains
   (:func:`claimed_labels`). On the realistic depth-estimator stream the slides these refuse
   are gross hypotheses (fit 0.2-0.5 after the slide) that would otherwise be made plausible;
   on the RGB stream nearly every true depth error fits 0.8-1.0 after it (each refusal is a
   debug line: ``ssp -vv bench table1 --sequences 1 --noise realistic|rgb --methods ssp``).

A hypothesis whose depth already fits, or whose silhouette meets no observed surface, is left
as it is. The corrected hypothesis replaces the estimator's in the frame's hypotheses before
association, so tracking, verification and the search all see the corrected pose; each
correction is reported (:class:`Correction`, the object's reason).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ssp.config import SSPConfig
from ssp.geometry import transform_points
from ssp.library.model import ObjectModel
from ssp.registration import icp_refine
from ssp.scene import Frame, Hypothesis
from ssp.visibility import CameraView, RayLookup

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "Correction",
    "camera_view",
    "claimed_labels",
    "correct_frame",
    "correct_hypotheses",
    "correct_hypothesis",
    "correction_note",
    "correction_of",
    "median_slide",
    "ray_shift",
]

log = logging.getLogger(__name__)

#: Model samples looked up per hypothesis (evenly spread over the model's surface samples).
LOOKUP_SAMPLES = 300


@dataclass(frozen=True)
class Correction:
    """How one hypothesis was corrected.

    Attributes:
        shift: m along the viewing ray (positive: away from the camera).
        moved: m, how far the correction moved the model origin in all (the alignment too).
        support_before: fraction of the facing samples on the object's observed surface at the
            estimator's pose.
        support_after: the same at the corrected pose.
        aligned: the alignment after the shift was kept.
        label: the instance label whose surface it was corrected to, or None.
    """

    shift: float
    moved: float
    support_before: float
    support_after: float
    aligned: bool
    label: int | None

    def as_dict(self) -> dict:
        return {
            "shift_mm": round(1000 * self.shift, 1),
            "moved_mm": round(1000 * self.moved, 1),
            "support_before": round(self.support_before, 3),
            "support_after": round(self.support_after, 3),
            "aligned": self.aligned,
            "label": self.label,
        }


def camera_view(frame: Frame, config: SSPConfig) -> CameraView | None:
    """The frame's :class:`~ssp.visibility.CameraView` (None without a camera pose)."""
    if frame.T_world_cam is None:
        return None
    return CameraView(
        frame.points,
        frame.T_world_cam,
        labels=frame.labels,
        depth_tolerance=config.temporal.depth_tolerance,
    )


def ray_shift(residual: np.ndarray, tolerance: float, max_shift: float) -> tuple[float, int, int]:
    """The shift along the ray that puts most samples on the observed surface.

    Args:
        residual: (n,) ``(o_i - z_i) / u_z`` per silhouette sample, m: how far along the ray
            the model must move for the sample to lie at its observed depth.
        tolerance: half-width of "on the surface", m along the ray.
        max_shift: the largest shift considered, m.

    Returns:
        ``(shift, count, count_at_zero)``: the median residual of the densest window of width
        ``2 tolerance`` (ties: the smallest shift), the samples in it, and the samples within
        ``tolerance`` of no shift.
    """
    v = np.sort(np.asarray(residual, dtype=float))
    at_zero = int(np.count_nonzero(np.abs(v) <= tolerance))
    if v.size == 0:
        return 0.0, 0, 0
    ends = np.searchsorted(v, v + 2.0 * tolerance, side="right")
    starts = np.arange(v.size)
    counts = ends - starts
    # the median of the sorted window v[i:j]: its middle element(s)
    centres = 0.5 * (v[(starts + ends - 1) // 2] + v[(starts + ends) // 2])
    ok = np.abs(centres) <= max_shift
    if not ok.any():
        return 0.0, 0, at_zero
    counts = np.where(ok, counts, 0)
    best = counts.max()
    tied = np.flatnonzero(counts == best)
    k = tied[np.argmin(np.abs(centres[tied]))]
    return float(centres[k]), int(best), at_zero


def _samples(model: ObjectModel) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Up to :data:`LOOKUP_SAMPLES` surface samples and normals (model frame), and their
    spacing for the self-occlusion test (None without samples)."""
    p = np.asarray(model.surface_points, dtype=float)
    n = np.asarray(model.surface_normals, dtype=float)
    if len(p) > LOOKUP_SAMPLES:
        sel = np.linspace(0, len(p) - 1, LOOKUP_SAMPLES).astype(int)
        p, n = p[sel], n[sel]
    spacing = float(np.sqrt(model.mesh.area / len(p))) if len(p) else None
    return p, n, spacing


def _look(view: CameraView, model: ObjectModel, T: np.ndarray) -> RayLookup:
    p, n, spacing = _samples(model)
    if model.convexity_excess <= view.depth_tolerance:
        spacing = None
    return view.lookup(transform_points(T, p), n @ T[:3, :3].T, self_spacing=spacing)


def _silhouette(look: RayLookup, label: int | None, instance: bool) -> np.ndarray:
    """(F,) bool: the facing samples whose ray meets the object's observed surface."""
    found = np.isfinite(look.observed)
    if instance and label is not None:
        return found & (look.label == label)
    return found & (look.label >= 0) if instance or (look.label >= 0).any() else found


def _silhouette_label(look: RayLookup, given: int | None, share: float) -> int | None:
    """The instance label the hypothesis' silhouette lies on: its own segment when given,
    else the label that at least ``share`` of its facing rays that meet an object meet (None
    when no label does: the silhouette straddles objects, as one hidden behind another's
    does; table and background do not count: a thin handle's silhouette a few millimetres
    off meets the table beside it)."""
    if given is not None:
        return given
    found = np.isfinite(look.observed)
    hit = look.label[found & (look.label >= 0)]
    if hit.size == 0:
        return None
    (label, count), *_ = Counter(hit.tolist()).most_common(1)
    return int(label) if count >= share * hit.size else None


def _support(look: RayLookup, sil: np.ndarray, tolerance: float) -> float:
    """Fraction of the facing samples that lie on the object's observed surface."""
    if len(look.index) == 0:
        return 0.0
    on = sil & (np.abs(look.observed - look.depth) <= tolerance)
    return int(np.count_nonzero(on)) / len(look.index)


def _fit(look: RayLookup, sil: np.ndarray, tolerance: float) -> float:
    """Fraction of the facing samples *not hidden by something in front of them* that lie on
    the object's observed surface: how well the pose explains what the camera can see of it
    (occlusion does not lower it; a pose slid onto a surface it does not match, across the
    ray or in orientation, leaves most of its unhidden samples off the surface)."""
    with np.errstate(invalid="ignore"):
        hidden = look.observed < look.depth - tolerance
    unhidden = int(np.count_nonzero(~hidden))
    if unhidden == 0:
        return 0.0
    on = sil & (np.abs(look.observed - look.depth) <= tolerance)
    return int(np.count_nonzero(on)) / unhidden


def _through(look: RayLookup, tolerance: float) -> float:
    """Fraction of the facing samples whose ray sees past them (their space is empty)."""
    if len(look.index) == 0:
        return 0.0
    with np.errstate(invalid="ignore"):
        past = look.observed > look.depth + tolerance
    return int(np.count_nonzero(past)) / len(look.index)


def _coverage(view: CameraView, model: ObjectModel, T: np.ndarray, points: np.ndarray) -> float:
    """Fraction of the observed ``points`` (an instance segment, world frame) whose ray passes
    through the model's silhouette at ``T`` (within a sample spacing of a facing sample's
    ray): with the fraction of the model's rays that meet the segment, how well the two
    silhouettes agree."""
    if not len(points):
        return 0.0
    p, n, spacing_or_none = _samples(model)
    spacing = spacing_or_none or 0.0
    T_cam_world = np.linalg.inv(view.T_world_cam)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    pw = transform_points(T, p)
    facing = np.einsum("ij,ij->i", n @ T[:3, :3].T, view.T_world_cam[:3, 3] - pw) > 0.0
    pc = pw[facing] @ R.T + t
    pc = pc[pc[:, 2] > 1e-6]
    if not len(pc):
        return 0.0
    sel = points[:: max(1, len(points) // LOOKUP_SAMPLES)]
    qc = sel @ R.T + t
    qc = qc[qc[:, 2] > 1e-6]
    if not len(qc):
        return 0.0
    reach = spacing / float(np.median(pc[:, 2])) + view.angular_resolution
    tree = cKDTree(pc[:, :2] / pc[:, 2:3])
    d, _ = tree.query(qc[:, :2] / qc[:, 2:3], k=1, distance_upper_bound=reach)
    return float(np.count_nonzero(np.isfinite(d))) / len(qc)


def _surface_points(frame: Frame, label: int | None, instance: bool) -> np.ndarray:
    """The observed points the alignment may use: the label's (instance labels), else every
    point that is not table or background."""
    pts = np.asarray(frame.points, dtype=float)
    if frame.labels is None:
        return pts
    labels = np.asarray(frame.labels)
    if instance and label is not None:
        return pts[labels == label]
    return pts[labels >= 0]


def _doubt(
    view: CameraView,
    model: ObjectModel,
    T: np.ndarray,
    look: RayLookup,
    frame: Frame,
    config: SSPConfig,
    label: int | None,
) -> tuple[str | None, float]:
    """Why the corrected pose ``T`` (its lookup ``look``) is not believed (None: it is), and
    the fraction of its unhidden samples that fit. Not believed: too few of
    its unhidden samples fit (``correction.min_fit``), too much of it is seen through
    (``correction.max_seen_through``), or with instance labels its silhouette covers too
    little of its segment (``correction.min_coverage``)."""
    cfg, tol = config.correction, view.depth_tolerance
    instance = frame.instance_masks
    fit = _fit(look, _silhouette(look, label, instance), tol)
    if fit < cfg.min_fit:
        return f"{fit:.2f} of its unhidden samples fit", fit
    through = _through(look, tol)
    if through > cfg.max_seen_through:
        return f"{through:.2f} seen through", fit
    if instance and label is not None:
        covered = _coverage(view, model, T, _surface_points(frame, label, True))
        if covered < cfg.min_coverage:
            return f"its silhouette covers {covered:.2f} of segment {label}", fit
    return None, fit


def correct_hypothesis(
    h: Hypothesis,
    model: ObjectModel,
    view: CameraView,
    frame: Frame,
    config: SSPConfig,
    taken: Collection[int] = (),
    look: RayLookup | None = None,
) -> tuple[Hypothesis, Correction] | None:
    """The hypothesis slid along its viewing ray to its data's depth and aligned (module
    docstring), with what was done; None when it needs no correction or none is supported.
    ``taken``: instance labels another hypothesis already fits where it is
    (:func:`claimed_labels`); ``look``: its :func:`_look` at ``h``'s pose when already made."""
    cfg = config.correction
    tol = view.depth_tolerance
    instance = frame.instance_masks
    T = np.asarray(h.T_world_obj, dtype=float)
    look = _look(view, model, T) if look is None else look
    label = _silhouette_label(look, h.segment, cfg.min_silhouette) if instance else None
    if instance and label is None or label in taken:
        log.debug("%s: no correction: silhouette label %s (taken: %s)", h.class_name, label,
                  sorted(taken))  # fmt: skip
        return None
    sil = _silhouette(look, label, instance)
    n = int(np.count_nonzero(sil))
    if n < cfg.min_samples:
        return None
    T_cam_world = np.linalg.inv(view.T_world_cam)
    centre_cam = T_cam_world[:3, :3] @ T[:3, 3] + T_cam_world[:3, 3]
    u_cam = centre_cam / np.linalg.norm(centre_cam)
    if u_cam[2] <= 0.1:  # the object is beside or behind the camera: no usable ray
        return None
    residual = (look.observed[sil] - look.depth[sil]) / u_cam[2]
    shift, count, at_zero = ray_shift(residual, tol / u_cam[2], cfg.max_shift)
    if (
        abs(shift) < cfg.min_shift
        or count < cfg.min_support * n
        or count < cfg.gain * max(at_zero, 1)
    ):
        log.debug("%s: no correction: shift %.1f mm, %d of %d samples there, %d at 0",
                  h.class_name, 1000 * shift, count, n, at_zero)  # fmt: skip
        return None
    before = _support(look, sil, tol)
    T1 = T.copy()
    T1[:3, 3] += shift * (view.T_world_cam[:3, :3] @ u_cam)
    look1 = _look(view, model, T1)
    after = _support(look1, _silhouette(look1, label, instance), tol)
    if after <= before:
        log.debug("%s: no correction: support %.2f -> %.2f at %.1f mm", h.class_name, before,
                  after, 1000 * shift)  # fmt: skip
        return None
    aligned = False
    if cfg.align:
        pts = _surface_points(frame, label, instance)
        if len(pts):
            T2 = icp_refine(
                model, T1, pts, view.T_world_cam[:3, 3], max_distance=cfg.align_distance
            )
            look2 = _look(view, model, T2)
            aligned_support = _support(look2, _silhouette(look2, label, instance), tol)
            if aligned_support > after:
                T1, after, aligned = T2, aligned_support, True
                look1 = look2
    doubt, fit = _doubt(view, model, T1, look1, frame, config, label)
    if doubt is not None:
        log.debug("%s: no correction at %.1f mm: %s", h.class_name, 1000 * shift, doubt)
        return None
    log.debug("%s: %.2f of its unhidden samples fit at %.1f mm", h.class_name, fit, 1000 * shift)
    moved = float(np.linalg.norm(T1[:3, 3] - T[:3, 3]))
    fix = Correction(shift, moved, before, after, aligned, label)
    return replace(h, T_world_obj=T1), fix


def median_slide(
    h: Hypothesis, model: ObjectModel, view: CameraView, frame: Frame
) -> np.ndarray | None:
    """The simplest depth fix a user could write, for comparison (the ``ray_slide`` baseline):
    ``h``'s pose slid along its viewing ray by the median of ``(o_i - z_i) / u_z`` over its
    silhouette samples (step 1 of the module docstring, no window, no checks), or None when
    its silhouette meets no observed object surface. (4, 4), m."""
    instance = frame.instance_masks
    T = np.asarray(h.T_world_obj, dtype=float)
    look = _look(view, model, T)
    label = _silhouette_label(look, h.segment, 0.5) if instance else None
    sil = _silhouette(look, label, instance)
    if not sil.any():
        return None
    T_cam_world = np.linalg.inv(view.T_world_cam)
    centre_cam = T_cam_world[:3, :3] @ T[:3, 3] + T_cam_world[:3, 3]
    u_cam = centre_cam / np.linalg.norm(centre_cam)
    if u_cam[2] <= 0.1:
        return None
    shift = float(np.median(look.observed[sil] - look.depth[sil])) / u_cam[2]
    out = T.copy()
    out[:3, 3] += shift * (view.T_world_cam[:3, :3] @ u_cam)
    return out


def claimed_labels(
    hypotheses: Sequence[Hypothesis],
    library: Mapping[str, ObjectModel],
    view: CameraView,
    frame: Frame,
    config: SSPConfig,
    looks: Sequence[RayLookup] | None = None,
) -> set[int]:
    """The instance labels that a hypothesis fits where it is (at least
    ``correction.claim_support`` of its facing samples on the label's surface). One instance
    segment is one object, and a hypothesis already explains this one: no other hypothesis is
    slid onto it. Another object's (the lower block of a stack, hidden behind the cube on it,
    is not moved onto the cube), or a worse hypothesis of the same object (a gross one,
    centimetres off across the ray too: slid onto the surface it would still be wrong, a
    duplicate beside the object). Empty without instance labels. ``looks``: each hypothesis'
    :func:`_look` when already made."""
    claims: set[int] = set()
    if not frame.instance_masks:
        return claims
    cfg = config.correction
    for i, h in enumerate(hypotheses):
        look = (
            looks[i]
            if looks is not None
            else _look(view, library[h.class_name], np.asarray(h.T_world_obj, dtype=float))
        )
        label = _silhouette_label(look, h.segment, cfg.min_silhouette)
        if label is None:
            continue
        if (
            _support(look, _silhouette(look, label, True), view.depth_tolerance)
            >= cfg.claim_support
        ):
            claims.add(label)
    return claims


def correct_hypotheses(
    hypotheses: Sequence[Hypothesis],
    library: Mapping[str, ObjectModel],
    view: CameraView,
    frame: Frame,
    config: SSPConfig,
) -> tuple[list[Hypothesis], list[tuple[Hypothesis, Correction]]]:
    """Every hypothesis through :func:`correct_hypothesis`: the frame's hypotheses with the
    corrected ones in their place (same order), and each corrected one with its
    :class:`Correction`."""
    out: list[Hypothesis] = []
    done: list[tuple[Hypothesis, Correction]] = []
    looks = [
        _look(view, library[h.class_name], np.asarray(h.T_world_obj, dtype=float))
        for h in hypotheses
    ]
    taken = claimed_labels(hypotheses, library, view, frame, config, looks)
    for h, look in zip(hypotheses, looks, strict=True):
        fixed = correct_hypothesis(h, library[h.class_name], view, frame, config, taken, look)
        if fixed is None:
            out.append(h)
            continue
        out.append(fixed[0])
        done.append(fixed)
        log.debug(
            "%s corrected %.0f mm along its ray (support %.2f -> %.2f)",
            h.class_name, 1000 * fixed[1].shift, fixed[1].support_before,
            fixed[1].support_after,
        )  # fmt: skip
    return out, done


def correction_note(fix: Correction) -> str:
    """The words an object's reason gets for a corrected hypothesis."""
    aligned = " and aligned" if fix.aligned else ""
    return (
        f"its estimate corrected {1000 * fix.shift:+.0f} mm along the viewing ray{aligned} "
        f"(on its observed surface: {100 * fix.support_before:.0f} -> "
        f"{100 * fix.support_after:.0f} %)"
    )


def correction_of(ctx: FrameContext, oid: str) -> Correction | None:
    """The correction of object ``oid``'s best corrected hypothesis this frame, or None.
    (Association copies hypotheses to set their ids; the pose array is the one the
    correction made, so it identifies them.)"""
    fixed = {id(h.T_world_obj): fix for h, fix in ctx.corrections}
    for h in ctx.groups.get(oid, ()):
        fix = fixed.get(id(h.T_world_obj))
        if fix is not None:
            return fix
    return None


# ------------------------------------------------------------------ the parser's stage
def correct_frame(ctx: FrameContext) -> None:
    """Stage *depth correction*: the frame's camera view (:func:`camera_view`) and, with
    ``correction.enabled``, every hypothesis corrected along its viewing ray
    (:func:`correct_hypotheses`) before association.

    Sets ``view``, ``hypotheses`` and ``corrections``.
    """
    ctx.view = camera_view(ctx.frame, ctx.config)
    ctx.hypotheses = list(ctx.frame.hypotheses)
    if ctx.view is None or not ctx.config.correction.enabled or not ctx.hypotheses:
        return
    ctx.hypotheses, ctx.corrections = correct_hypotheses(
        ctx.hypotheses, ctx.library, ctx.view, ctx.frame, ctx.config
    )
