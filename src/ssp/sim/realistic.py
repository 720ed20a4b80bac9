"""A realistic pose-estimator stream: the structured ways real estimators fail, frame after frame.

Table I's hypotheses (:mod:`ssp.sim.hypotheses`) are zero-mean Gaussian, independent from
frame to frame, always present for a visible object and never wrong in class. Real estimators
(ObjRecRANSAC, PPF, FoundationPose, MegaPose) fail in structured ways; :class:`RealisticStream`
draws hypotheses that do, each failure with a documented rate and magnitude
(:class:`RealisticNoise`), seeded, per object and frame:

* **Persistent error.** Each object's error is a bias plus per-hypothesis white noise, both
  Gaussian with Table I's visibility-dependent sigmas (``sigma(v) = sigma(1) (1 + growth (1 -
  v))``), ``bias_share`` of the variance in the bias. The bias follows an AR(1) process with
  coefficient ``bias_rho`` from frame to frame while the view is unchanged, and is drawn anew
  when the object moves (more than 2 mm or 2 deg) or its visible fraction changes by more than
  0.1: averaging frames of a static scene does not remove it.
* **Gross outliers.** Each hypothesis is replaced with probability ``gross_rate`` by one that
  is wrong in one of two ways (half each): *in place* (the nominal position, turned by
  ``gross_rotation_deg``, uniform, about a random axis) or *displaced* (moved by
  ``gross_translation`` m, uniform, in a random direction, and turned likewise). It is scored
  as a mediocre hypothesis (as if 1.5-4.5 sigmas off), so it is sometimes the best-scored one.
* **Flips** (persistent misorientations). An object is *flipped* in a two-state Markov chain
  per object (stationary probability ``flip_rate``, persistence ``mode_persistence``); while
  flipped, each hypothesis is turned, with probability ``flip_share``, by one turn drawn when
  the state began (:func:`misorientations`): a near-symmetric turn of the model (about a
  bounding-box axis through the centre of mass, changing the shape by less than
  ``flip_max_change`` m) when it has one, else a quarter or half turn about a bounding-box axis
  that is not a symmetry. Every hypothesis also reports a uniformly random exact symmetric
  equivalent of its pose (as Table I's do).
* **Class confusions.** Classes of similar shape (:func:`confusable_classes`: aligned
  bounding-box IoU at least ``confusion_min_iou``) are confused: a per-object Markov state
  (stationary ``confusion_rate``, persistence ``mode_persistence``) in which each hypothesis is,
  with probability ``confusion_share``, of the most similar other class, aligned at the centre
  of mass and principal axes.
* **False positives.** Hypotheses of objects that are not there: ``false_positive_rate`` new
  sources per frame (Poisson), each lasting a geometric number of frames (mean
  ``false_positive_frames``) at a fixed pose with 1-3 hypotheses per frame; a share
  ``false_positive_implausible`` of them floats 0.05-1 m above the table or lies 1-30 m away,
  the others rest on the table at least 2 cm clear of every object. Distractors (objects not in
  the library, :mod:`ssp.sim.distractors`) get hypotheses of the most similar library class
  while a per-distractor Markov state (stationary ``distractor_rate``) is on.
* **Dropouts in runs.** A visible object starts a run of frames without any hypothesis with
  probability ``dropout_start`` per frame; runs last a geometric number of frames (mean
  ``dropout_frames``). Objects below ``hidden_below`` visible are never detected.

**The RGB estimator** (:meth:`RealisticNoise.rgb`, ``rgb_errors`` set; :mod:`ssp.sim.rgb_stream`)
replaces the per-object draw above: errors mostly in depth along the ray from the camera to
the object, heavy-tailed, far outliers, flips about model axes, misses by visibility and 1-5
hypotheses per object, with the rates and quantile tables measured on MegaPose's LM-O results
(``ssp bench rgb-calibration --data ../shared/data/lmo-megapose``, :mod:`ssp.eval.rgb_calibration`;
the figures are in :class:`~ssp.sim.rgb_stream.RgbErrors`), persistent over a static view.

Every hypothesis records its source object (None for false positives) and its kind
(``nominal``, ``gross``, ``flip``, ``confusion``, ``false_positive``, ``distractor``), for
evaluation only. Hypotheses carry the instance segment they came from when the caller gives the
objects' mask labels (a mask-based estimator knows its mask).

Randomness: object ``o`` in frame ``i`` draws from ``default_rng([seed, 3, i, crc32(o)])``, so
one object's noise does not depend on the others; false positives from ``default_rng([seed, 3,
i, 0])``.

:class:`SceneRealism` is the scene side of the realistic protocol (distractors, dynamic events,
mask defects), applied by :func:`ssp.sim.generate.generate_sequence`.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ssp.errors import ArgumentError
from ssp.library.model import ObjectModel
from ssp.probability import pose_change
from ssp.scene import Hypothesis
from ssp.sim.hypotheses import random_symmetry
from ssp.sim.rgb_stream import RgbErrors, RgbObjects

__all__ = [
    "KINDS",
    "DEFAULT_EVENTS",
    "RealisticNoise",
    "RealisticStream",
    "SceneRealism",
    "StreamHypothesis",
    "confusable_classes",
    "misorientations",
    "near_symmetries",
]

KINDS = ("nominal", "gross", "flip", "confusion", "false_positive", "distractor")
#: Random stream code of the estimator (see the module docstring).
_STREAM = 3
#: Default events per experiment (:mod:`ssp.sim.events`), after the static build-up stages.
DEFAULT_EVENTS = {"structure": ("move", "knock", "stack"), "isolated": ("move", "push", "move")}

#: An object moved (m, deg) or its view changed (visible fraction) by more than this: the
#: estimator's bias is drawn anew.
REDRAW_SHIFT = 0.002
REDRAW_TILT_DEG = 2.0
REDRAW_VISIBILITY = 0.1


@dataclass(frozen=True)
class RealisticNoise:
    """Rates and magnitudes of the realistic stream (module docstring). Units: m, deg.

    Calibrated against the built-in estimator (:mod:`ssp.perception`) on rendered depth with
    instance masks, development seeds 0-4 (structure) and 0-3 (isolated), measured with
    :mod:`ssp.eval.stream_stats` on both (``ssp bench stream``; docs/benchmarks.md has the
    figures side by side). Built-in estimator, then this stream, structure / isolated:

    * ``sigma_t``, ``sigma_r_deg``, ``growth``: the best-scored hypothesis, when not gross, is
      off by 0.68 / 0.47 mm and 0.78 / 0.51 deg on average (the stream: 0.52 / 0.46 mm,
      0.56 / 0.38 deg);
    * ``bias_share``, ``bias_rho``: 50 / 62 % of that error over a static scene is a
      persistent bias (40 / 57 %);
    * ``gross_rate``, ``flip_*``, ``mode_persistence``, ``confusion_*``: the best-scored
      hypothesis is gross (> 1 cm or > 10 deg off, or of the wrong class) in 10.9 / 9.7 % of
      the visible object-frames (9.7 / 9.0 %); 25 / 70 % of gross frames follow a gross frame
      (11 / 46 %); it is of the wrong class in 3.8 / 0 % (3.4 / 2.1 %: hammers are alike).

    Chosen, since the estimator on rendered depth with clean masks shows none of them:
    ``dropout_*`` (3 % of visible object-frames start a run of missed detections, 3 frames on
    average: 8 % of them missed), ``false_positive_*`` (0.3 new false objects per frame, 3
    frames each, a third of them floating or far away), ``distractor_rate`` (a distractor is
    taken for a library object 60 % of the time), ``gross_translation`` and
    ``gross_rotation_deg`` (the issue's 2-10 cm / 30-180 deg; the estimator's gross errors
    are mostly turns in place: median 17 mm, 89-177 deg).
    """

    k: int = 5
    sigma_t: float = 0.0003
    sigma_r_deg: float = 0.33
    growth: float = 2.0
    bias_share: float = 0.7
    bias_rho: float = 0.95
    hidden_below: float = 0.02
    gross_rate: float = 0.2
    gross_translation: tuple[float, float] = (0.02, 0.10)
    gross_rotation_deg: tuple[float, float] = (30.0, 180.0)
    flip_rate: float = 0.1
    flip_share: float = 0.8
    flip_max_change: float = 0.004
    mode_persistence: float = 0.85
    confusion_rate: float = 0.06
    confusion_share: float = 0.5
    confusion_min_iou: float = 0.2
    false_positive_rate: float = 0.3
    false_positive_frames: float = 3.0
    false_positive_implausible: float = 0.3
    distractor_rate: float = 0.6
    dropout_start: float = 0.03
    dropout_frames: float = 3.0
    score_temperature: float = 1.0
    score_jitter: float = 0.2
    rgb_errors: RgbErrors | None = None

    @classmethod
    def rgb(cls, persistence: float = 0.9) -> RealisticNoise:
        """The RGB-estimator stream (MegaPose-like; :mod:`ssp.sim.rgb_stream`): errors mostly in
        depth along the viewing ray, heavy-tailed, far outliers, flips about model axes, misses
        by visibility, 1-5 hypotheses per object, as measured on LM-O scene 2 by ``ssp bench
        rgb-calibration --data ../shared/data/lmo-megapose`` (:class:`RgbErrors` has the
        figures). It replaces the gross outliers, flips, class confusions, dropouts and false
        positives of the default stream (the measured far outliers, flips, misses and extra
        detections stand for them); distractors are still taken for library objects. The
        stream needs the camera pose (``RealisticStream(T_world_cam=...)``)."""
        return cls(
            rgb_errors=RgbErrors.megapose_lmo(persistence),
            gross_rate=0.0,
            flip_rate=0.0,
            confusion_rate=0.0,
            dropout_start=0.0,
            false_positive_rate=0.0,
        )

    def __post_init__(self) -> None:
        if int(self.k) != self.k or self.k < 1:
            raise ValueError(f"k must be a positive integer, got {self.k}")
        for name in (
            "bias_share", "bias_rho", "hidden_below", "gross_rate", "flip_rate", "flip_share",
            "mode_persistence", "confusion_rate", "confusion_share", "confusion_min_iou",
            "false_positive_implausible", "distractor_rate", "dropout_start", "score_jitter",
        ):  # fmt: skip
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        for name in ("sigma_t", "sigma_r_deg", "growth", "false_positive_rate", "flip_max_change"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        for name in ("false_positive_frames", "dropout_frames", "score_temperature"):
            if not getattr(self, name) >= 1.0 and name != "score_temperature":
                raise ValueError(f"{name} must be >= 1 frame, got {getattr(self, name)}")
        if not self.score_temperature > 0:
            raise ValueError("score_temperature must be > 0")

    def replace(self, **changes) -> RealisticNoise:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if self.rgb_errors is None:
            del d["rgb_errors"]  # the default stream's settings as before the RGB stream existed
        return d

    def sigma_scale(self, visib_fract: float) -> float:
        """``1 + growth (1 - v)``, ``v`` clipped to ``[0, 1]``."""
        return 1.0 + self.growth * (1.0 - float(np.clip(visib_fract, 0.0, 1.0)))


@dataclass(frozen=True)
class SceneRealism:
    """The scene side of the realistic protocol.

    Attributes:
        distractors: objects not in the library (:mod:`ssp.sim.distractors`) on the table.
        events: dynamic events after the build-up stages (:mod:`ssp.sim.events`), each
            followed by a static scene; None: :data:`DEFAULT_EVENTS` of the experiment.
        mask_defects: ``(lo, hi)`` fraction of each segment's pixels turned into edge bleeding
            and flying pixels (:mod:`ssp.sim.masks`), or None for clean masks.
    """

    distractors: int = 2
    events: tuple[str, ...] | None = None
    mask_defects: tuple[float, float] | None = (0.005, 0.03)

    def __post_init__(self) -> None:
        if int(self.distractors) != self.distractors or not 0 <= self.distractors <= 4:
            raise ValueError(f"distractors must be an integer in 0..4, got {self.distractors}")
        if self.mask_defects is not None:
            lo, hi = self.mask_defects
            if not 0.0 <= lo <= hi <= 0.5:
                raise ValueError(f"mask_defects must be 0 <= lo <= hi <= 0.5, got {lo}, {hi}")

    def events_for(self, experiment: str) -> tuple[str, ...]:
        return tuple(self.events) if self.events is not None else DEFAULT_EVENTS[experiment]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class StreamHypothesis:
    """A drawn hypothesis with what it is (for evaluation): its ``source`` object id (None
    for a false positive or a distractor's) and its ``kind`` (:data:`KINDS`)."""

    hypothesis: Hypothesis
    source: str | None
    kind: str


# ------------------------------------------------------------------------------ model shape
@lru_cache(maxsize=256)
def _principal_frame(model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3) columns = the axes of the minimum-volume oriented bounding box, extents
    along them (3,))``, axes sorted by decreasing extent, right-handed. (The box, not the
    inertia: a cube's inertia is isotropic and gives no axes.)"""
    vecs = np.asarray(model.mesh.bounding_box_oriented.primitive.transform, float)[:3, :3]
    p = (model.hull_vertices - model.center_of_mass) @ vecs
    ext = p.max(axis=0) - p.min(axis=0)
    order = np.argsort(-ext, kind="stable")
    R = vecs[:, order]
    if np.linalg.det(R) < 0:
        R[:, 2] *= -1
    return R, ext[order]


@lru_cache(maxsize=256)
def _near_symmetries(model: ObjectModel, max_change: float) -> tuple[np.ndarray, ...]:
    R, _ = _principal_frame(model)
    c = np.asarray(model.center_of_mass, dtype=float)
    pts = np.asarray(model.surface_points, dtype=float)
    if len(pts) > 2000:
        pts = pts[np.linspace(0, len(pts) - 1, 2000).astype(int)]
    tree = cKDTree(pts)
    nn, _ = tree.query(pts, k=2)
    cover = 2.0 * float(np.median(nn[:, 1]))  # about the farthest a surface point is from a sample
    surface = trimesh.proximity.ProximityQuery(model.mesh)
    out: list[np.ndarray] = []
    seen: list[np.ndarray] = []
    for axis in R.T:
        for n in (2, 3, 4, 6):
            for m in range(1, n):
                if math.gcd(m, n) != 1:
                    continue
                S = np.eye(4)
                S[:3, :3] = Rotation.from_rotvec(axis * 2 * math.pi * m / n).as_matrix()
                S[:3, 3] = c - S[:3, :3] @ c
                if any(np.allclose(S, t, atol=1e-6) for t in seen):
                    continue
                seen.append(S)
                _, dth = pose_change(np.eye(4), S, model.symmetry)
                if dth < math.radians(1.0):
                    continue  # an exact symmetry: not a flip
                # Hausdorff distance of the surface and its turned copy, both ways: the
                # samples turned by S and by S^-1, to the mesh surface
                # (the distance to the nearest sample bounds it from above, and from below
                # up to the samples' covering radius; the mesh is queried in between only)
                q = np.concatenate([pts @ S[:3, :3].T + S[:3, 3], (pts - S[:3, 3]) @ S[:3, :3]])
                d, _ = tree.query(q)
                if float(d.max()) > max_change + cover:
                    continue
                unsure = d > max_change
                if unsure.any():
                    d_exact = np.abs(surface.signed_distance(q[unsure]))
                    if float(d_exact.max()) > max_change:
                        continue
                out.append(S)
    return tuple(out)


def near_symmetries(model: ObjectModel, max_change: float) -> list[np.ndarray]:
    """Near-symmetric turns of ``model``: 4x4 model-frame transforms (about its centre of
    mass) by ``2 pi m / n`` (n = 2, 3, 4, 6) about an axis of its oriented bounding box whose
    Hausdorff distance between the surface and its turned copy (surface samples to the mesh,
    both ways) is at most ``max_change`` m, exact symmetries left out. Such turns change
    what a camera sees by a few mm at most: estimators confuse them."""
    return list(_near_symmetries(model, float(max_change)))


@lru_cache(maxsize=256)
def _box_turns(model: ObjectModel) -> tuple[np.ndarray, ...]:
    R, _ = _principal_frame(model)
    c = np.asarray(model.center_of_mass, dtype=float)
    out = []
    for axis in R.T:
        for quarter in (1, 2, 3):
            S = np.eye(4)
            S[:3, :3] = Rotation.from_rotvec(axis * quarter * math.pi / 2).as_matrix()
            S[:3, 3] = c - S[:3, :3] @ c
            if pose_change(np.eye(4), S, model.symmetry)[1] > math.radians(1.0):
                out.append(S)
    return tuple(out)


def misorientations(model: ObjectModel, max_change: float) -> list[np.ndarray]:
    """The turns an estimator persistently mistakes ``model``'s pose for (4x4, model frame,
    about its centre of mass): its :func:`near_symmetries` when it has any, else the quarter
    and half turns about its bounding-box axes that are not symmetries (a partial view leaves
    them ambiguous, e.g. a block standing or lying). Empty for a cube."""
    return near_symmetries(model, max_change) or list(_box_turns(model))


def _aligned_iou(a: ObjectModel, b: ObjectModel) -> float:
    _, ea = _principal_frame(a)
    _, eb = _principal_frame(b)
    inter = float(np.prod(np.minimum(ea, eb)))
    return inter / (float(np.prod(ea)) + float(np.prod(eb)) - inter)


def alignment(a: ObjectModel, b: ObjectModel) -> np.ndarray:
    """``T_a_b`` (4x4): model ``b`` placed on model ``a`` with their centres of mass and
    principal axes (sorted by extent) aligned."""
    Ra, _ = _principal_frame(a)
    Rb, _ = _principal_frame(b)
    T = np.eye(4)
    T[:3, :3] = Ra @ Rb.T
    T[:3, 3] = np.asarray(a.center_of_mass) - T[:3, :3] @ np.asarray(b.center_of_mass)
    return T


def confusable_classes(library: Mapping[str, ObjectModel], min_iou: float) -> dict[str, str]:
    """Class -> the most similar other class of ``library`` (aligned bounding-box IoU, at
    least ``min_iou``); classes without one are left out."""
    names = list(library)
    out: dict[str, str] = {}
    for a in names:
        best, best_iou = None, min_iou
        for b in names:
            if b == a:
                continue
            iou = _aligned_iou(library[a], library[b])
            if iou >= best_iou:
                best, best_iou = b, iou
        if best is not None:
            out[a] = best
    return out


def most_similar(model: ObjectModel, library: Mapping[str, ObjectModel]) -> str:
    """The library class most similar in shape to ``model`` (aligned bounding-box IoU)."""
    return max(library, key=lambda n: (_aligned_iou(model, library[n]), n))


# ------------------------------------------------------------------------------ the stream
@dataclass
class _ObjectState:
    T: np.ndarray
    visib: float
    bias: np.ndarray  # (6,) in units of the object's sigmas: translation (3), rotation (3)
    flip: np.ndarray | None = None  # the turn while flipped
    flipped: bool | None = None  # None: a new view (the modes start from their stationary odds)
    confused: bool | None = None
    dropout_left: int = 0


@dataclass
class _FalsePositive:
    class_name: str
    T: np.ndarray
    frames_left: int
    n: int


@dataclass
class RealisticStream:
    """The realistic estimator over one sequence (module docstring); call :meth:`draw` once
    per frame, in order.

    Args:
        library: class name -> model (the classes hypotheses may name).
        noise: rates and magnitudes.
        seed: the sequence's seed.
        classes: classes for false positives (default: every class of ``library``).
        resting_pose: ``(model, rng) -> T_world_obj`` a random resting pose on the table in
            the workspace, for plausible false positives (None: they float instead).
        T_world_cam: the camera pose (4x4); the RGB stream (``noise.rgb_errors``) needs it: its
            errors are along and across the ray from the camera to each object.
    """

    library: Mapping[str, ObjectModel]
    noise: RealisticNoise
    seed: int
    classes: Sequence[str] | None = None
    resting_pose: Callable[[ObjectModel, np.random.Generator], np.ndarray] | None = None
    T_world_cam: np.ndarray | None = None
    _objects: dict[str, _ObjectState] = field(default_factory=dict, init=False)
    _distractors: dict[str, bool] = field(default_factory=dict, init=False)
    _false: list[_FalsePositive] = field(default_factory=list, init=False)
    _confusable: dict[str, str] = field(default_factory=dict, init=False)
    _rgb: RgbObjects | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        self.classes = list(self.classes) if self.classes is not None else list(self.library)
        if self.noise.rgb_errors is not None:
            if self.T_world_cam is None:
                raise ArgumentError("the RGB estimator stream needs the camera pose T_world_cam")
            redraw = (REDRAW_SHIFT, REDRAW_TILT_DEG, REDRAW_VISIBILITY)
            self._rgb = RgbObjects(self.noise.rgb_errors, self.noise.bias_rho, redraw)
        self._confusable = confusable_classes(
            {c: self.library[c] for c in self.classes}, self.noise.confusion_min_iou
        )

    def _rng(self, frame: int, key: int) -> np.random.Generator:
        return np.random.default_rng([int(self.seed), _STREAM, int(frame), int(key)])

    # ---------------------------------------------------------------- per object
    def _state(self, oid: str, T: np.ndarray, v: float, rng) -> _ObjectState:
        st = self._objects.get(oid)
        nz = self.noise
        innovation = rng.standard_normal(6)
        if st is None:
            st = _ObjectState(T.copy(), v, innovation)
            self._objects[oid] = st
            return st
        dt, dth = pose_change(st.T, T)
        moved = dt > REDRAW_SHIFT or math.degrees(dth) > REDRAW_TILT_DEG
        if moved or abs(v - st.visib) > REDRAW_VISIBILITY:
            st.bias = innovation  # a new view: a new bias, flips and confusions re-drawn
            st.flip, st.flipped, st.confused = None, None, None
        else:
            st.bias = nz.bias_rho * st.bias + math.sqrt(1.0 - nz.bias_rho**2) * innovation
        st.T, st.visib = T.copy(), v
        return st

    def _markov(self, on: bool | None, rate: float, u: float) -> bool:
        """Next state of a two-state chain with stationary probability ``rate`` and
        persistence ``mode_persistence`` (the chance a state carries over); ``on`` None: a new
        chain, drawn from the stationary distribution."""
        p = self.noise.mode_persistence
        if on is None:
            return u < rate
        if on:
            return u < p + (1.0 - p) * rate
        return u < (1.0 - p) * rate

    def _perturb(self, T: np.ndarray, bias: np.ndarray, s: float, rng) -> tuple[np.ndarray, float]:
        """One noisy copy of ``T``: the ``bias`` (6,) plus white noise, in units of the sigmas
        times ``s``, rotation about the model origin; and its normalised error (in sigmas,
        for the score)."""
        nz = self.noise
        b = math.sqrt(nz.bias_share)
        w = math.sqrt(1.0 - nz.bias_share)
        e = b * bias + w * rng.standard_normal(6)
        st_, sr = nz.sigma_t * s, math.radians(nz.sigma_r_deg) * s
        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec(e[3:] * sr).as_matrix() @ T[:3, :3]
        out[:3, 3] = T[:3, 3] + e[:3] * st_
        return out, 0.5 * (float(np.linalg.norm(e[:3])) + float(np.linalg.norm(e[3:])))

    def _score(self, v: float, err: float, rng) -> float:
        nz = self.noise
        jitter = rng.uniform(1.0 - nz.score_jitter, 1.0 + nz.score_jitter)
        return float(np.clip(v * math.exp(-err / nz.score_temperature) * jitter, 0.0, 1.0))

    def _gross(self, T: np.ndarray, model: ObjectModel, rng) -> np.ndarray:
        """A gross outlier of pose ``T``: turned about the model's centre of mass by
        ``gross_rotation_deg`` (at least the lower bound from every symmetric equivalent; a
        few draws at most), and half the time displaced by ``gross_translation``."""
        nz = self.noise
        centre = np.asarray(model.center_of_mass, dtype=float)
        lo = math.radians(nz.gross_rotation_deg[0])
        for _ in range(8):
            axis = rng.standard_normal(3)
            axis /= np.linalg.norm(axis)
            angle = math.radians(rng.uniform(*nz.gross_rotation_deg))
            turn = Rotation.from_rotvec(axis * angle).as_matrix()
            R = np.eye(4)
            R[:3, :3] = turn
            if pose_change(np.eye(4), R, model.symmetry)[1] >= lo:
                break
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        shift = rng.uniform(*nz.gross_translation)
        displaced = rng.random() < 0.5
        out = np.eye(4)
        out[:3, :3] = T[:3, :3] @ turn  # turned in the model frame, as a wrong match would be
        p = T[:3, :3] @ centre + T[:3, 3] + (d * shift if displaced else 0.0)
        out[:3, 3] = p - out[:3, :3] @ centre
        return out

    def _object(self, oid, cls, T, v, frame, segment) -> list[StreamHypothesis]:
        nz = self.noise
        rng = self._rng(frame, zlib.crc32(oid.encode()))
        model = self.library[cls]
        if self._rgb is not None:
            return self._rgb_object(oid, cls, model, np.asarray(T, dtype=float), v, segment, rng)
        st = self._state(oid, np.asarray(T, dtype=float), v, rng)
        u_drop, u_flip, u_conf = rng.random(3)
        flips = misorientations(model, nz.flip_max_change) if nz.flip_rate > 0 else []
        if flips:
            st.flipped = self._markov(st.flipped, nz.flip_rate, u_flip)
            if st.flipped and st.flip is None:
                st.flip = flips[int(rng.integers(len(flips)))]
            elif not st.flipped:
                st.flip = None
        other = self._confusable.get(cls)
        if other is not None:
            st.confused = self._markov(st.confused, nz.confusion_rate, u_conf)
        if v < nz.hidden_below:
            return []
        if st.dropout_left > 0:
            st.dropout_left -= 1
            return []
        if u_drop < nz.dropout_start:
            st.dropout_left = int(rng.geometric(1.0 / nz.dropout_frames)) - 1
            return []
        s = nz.sigma_scale(v)
        out: list[StreamHypothesis] = []
        for _ in range(int(nz.k)):
            u_kind, u_flip_h, u_conf_h = rng.random(3)
            kind, base, name = "nominal", np.asarray(T, dtype=float), cls
            if st.flip is not None and u_flip_h < nz.flip_share:
                kind, base = "flip", base @ st.flip
            if st.confused and u_conf_h < nz.confusion_share:
                kind, name = "confusion", other
                base = base @ alignment(model, self.library[other])
            Th, err = self._perturb(base, st.bias, s, rng)
            if u_kind < nz.gross_rate:
                kind = "gross"
                Th = self._gross(Th, model, rng)
                err = float(rng.uniform(1.5, 4.5))  # scored like a mediocre hypothesis
            sym = self.library[name].symmetry
            if sym.is_symmetric:
                Th = Th @ random_symmetry(sym, rng)
            score = self._score(v, err, rng)
            out.append(StreamHypothesis(Hypothesis(name, Th, score, segment=segment), oid, kind))
        return out

    def _rgb_object(self, oid, cls, model, T, v, segment, rng) -> list[StreamHypothesis]:
        """The RGB stream's hypotheses of one object (:class:`RgbObjects`)."""
        assert self._rgb is not None and self.T_world_cam is not None
        if v < self.noise.hidden_below:
            return []
        axes, _ = _principal_frame(model)
        centre = np.asarray(model.center_of_mass, dtype=float)
        drawn = self._rgb.draw(oid, T, v, centre, axes, self.T_world_cam, rng)
        out = []
        for Th, score, kind in drawn:
            if model.symmetry.is_symmetric:
                Th = Th @ random_symmetry(model.symmetry, rng)
            out.append(StreamHypothesis(Hypothesis(cls, Th, score, segment=segment), oid, kind))
        return out

    # ---------------------------------------------------------------- false positives
    def _false_positives(self, frame: int, gt) -> list[StreamHypothesis]:
        nz = self.noise
        rng = self._rng(frame, 0)
        for fp in self._false:
            fp.frames_left -= 1
        self._false = [fp for fp in self._false if fp.frames_left > 0]
        for _ in range(int(rng.poisson(nz.false_positive_rate))):
            cls = self.classes[int(rng.integers(len(self.classes)))]
            model = self.library[cls]
            T = self._false_pose(model, gt, rng)
            if T is None:
                continue
            life = int(rng.geometric(1.0 / nz.false_positive_frames))
            self._false.append(_FalsePositive(cls, T, life, int(rng.integers(1, 4))))
        out = []
        for fp in self._false:
            bias = rng.standard_normal(6)
            for _ in range(fp.n):
                Th, _ = self._perturb(fp.T, bias, 1.0, rng)
                score = float(rng.uniform(0.2, 0.9))
                h = Hypothesis(fp.class_name, Th, score)
                out.append(StreamHypothesis(h, None, "false_positive"))
        return out

    def _false_pose(self, model: ObjectModel, gt, rng) -> np.ndarray | None:
        nz = self.noise
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
        if self.resting_pose is None or rng.random() < nz.false_positive_implausible:
            if rng.random() < 0.5:  # floating above the workspace
                T[:3, 3] = [rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(0.05, 1)]
            else:  # far away
                a = rng.uniform(0, 2 * math.pi)
                r = math.exp(rng.uniform(0.0, math.log(30.0)))
                T[:3, 3] = [r * math.cos(a), r * math.sin(a), rng.uniform(0.0, 1.0)]
            return T
        centres = [np.asarray(Tg)[:3, 3] for _, Tg in gt.values()]
        for _ in range(50):
            T = self.resting_pose(model, rng)
            if all(np.linalg.norm(T[:2, 3] - p[:2]) > model.diameter / 2 + 0.02 for p in centres):
                return T
        return None

    # ---------------------------------------------------------------- the frame
    def draw(
        self,
        frame: int,
        gt: Mapping[str, tuple[str, np.ndarray]],
        visib_fract: Mapping[str, float],
        *,
        segments: Mapping[str, int] | None = None,
        distractors: Mapping[str, tuple[ObjectModel, np.ndarray]] | None = None,
        T_world_cam: np.ndarray | None = None,
    ) -> list[StreamHypothesis]:
        """The hypotheses of frame ``frame`` (best score first).

        Args:
            gt: instance id -> ``(class, T_world_obj)`` of the library objects present.
            visib_fract: instance id -> visible fraction (missing: 0).
            segments: instance id (objects and distractors) -> mask label, to tag hypotheses.
            distractors: distractor id -> ``(model, T_world_obj)`` (objects not in the library).
            T_world_cam: this frame's camera pose when the camera moves (it becomes the
                stream's: the RGB errors follow its rays); None: the stream's.
        """
        if T_world_cam is not None:
            self.T_world_cam = np.asarray(T_world_cam, dtype=float)
        segments = segments or {}
        out: list[StreamHypothesis] = []
        for oid, (cls, T) in gt.items():
            v = float(visib_fract.get(oid, 0.0))
            out += self._object(oid, cls, T, v, frame, segments.get(oid))
        for did, (model, T) in (distractors or {}).items():
            out += self._distractor(did, model, np.asarray(T, dtype=float), frame, segments)
        out += self._false_positives(frame, gt)
        order = sorted(range(len(out)), key=lambda i: (-out[i].hypothesis.score, i))
        return [out[i] for i in order]

    def _distractor(self, did, model, T, frame, segments) -> list[StreamHypothesis]:
        nz = self.noise
        rng = self._rng(frame, zlib.crc32(did.encode()))
        on = self._markov(self._distractors.get(did), nz.distractor_rate, rng.random())
        self._distractors[did] = on
        if not on:
            return []
        cls = most_similar(model, {c: self.library[c] for c in self.classes})
        base = T @ alignment(model, self.library[cls])
        bias = rng.standard_normal(6)
        out = []
        for _ in range(int(rng.integers(1, 4))):
            Th, _ = self._perturb(base, bias, 1.0, rng)
            h = Hypothesis(cls, Th, float(rng.uniform(0.3, 0.9)), segment=segments.get(did))
            out.append(StreamHypothesis(h, None, "distractor"))
        return out
