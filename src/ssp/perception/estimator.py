"""Pose hypotheses for a segment from oriented point pairs, in ObjRecRANSAC's role.

The paper's pipeline gets several poses per object from ObjRecRANSAC (Papazov & Burschka
2010): RANSAC over oriented point pairs. This module does the same on a CPU in numpy:

1. **Model pair table** (once per model, cached): the model's surface samples thinned to a
   voxel of ``sampling x diameter`` (at most ``max_model_points``), every ordered pair's
   point-pair feature ``F = (|d|, angle(n1, d), angle(n2, d), angle(n1, n2))`` (Drost et al.
   2010) quantised and sorted into a hash table. Coplanar pairs (both normals perpendicular to
   ``d`` and parallel to each other) are flagged: a box has thousands of them, all alike, and
   they fix only a plane. The features and the pair poses are compiled (:mod:`ssp.jit`).
2. **Scene pairs**: ``pair_samples`` random non-coplanar pairs of the thinned segment; each is
   looked up, and up to ``matches_per_pair`` model pairs with the same feature give a pose each
   (the frame of ``(p1, n1, p2)`` of the model pair mapped onto the scene pair's).
3. **Scoring** every candidate on a dilated occupancy grid of the segment (voxel
   ``score_voxel``): the number of camera-facing model samples in occupied voxels. This is
   ObjRecRANSAC's acceptance test, compiled (:func:`_coarse_kernel`, a few nanoseconds per
   candidate and sample).
4. **Refinement**: the best candidates that differ (symmetry-aware), and the best candidate of
   each other orientation (``alternatives``), are refined by point-to-plane ICP on the segment
   points near them (:func:`ssp.registration.grid_icp`: the model's dense samples looked up
   in a :class:`~ssp.sample_grid.SampleGrid` in the model frame, compiled), and scored by the
   F1 of *fit* (facing samples with a segment point within ``inlier_distance``) and *coverage*
   (segment points within that distance of the model, tested exactly on the same grid). The
   class with the best score wins;
   its ``k`` hypotheses are the best pose, the other orientations that explain the segment
   nearly as well (:func:`_diverse`), then the rest by score.
5. **Several objects per segment**: the points the winner explains are removed and the rest is
   searched again (touching blocks form one segment when no labels are given).

Why written here rather than taken from a library: OpenCV's PPF detector trains for minutes per
model and matches in about a minute (measured, ``notes/anchors.md``); PCL's needs C++; Open3D's
FPFH + RANSAC registration aligns one object and brings a large binary dependency.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from ssp.cells import load_kernels as load_cell_kernels
from ssp.components import load_kernels as load_component_kernels
from ssp.config import PerceptionConfig
from ssp.errors import PerceptionError, UnknownObjectError
from ssp.forces import load_kernels as load_force_kernels
from ssp.jit import kernel_array, njit
from ssp.kdtree import KDTree
from ssp.library.model import ObjectModel
from ssp.overlap import load_kernels as load_overlap_kernels
from ssp.perception.cleaning import robust_extent
from ssp.registration import even_rows, facing_mask, grid_icp, load_kernels
from ssp.sample_grid import SampleGrid
from ssp.scene import Hypothesis
from ssp.visibility import load_kernels as load_visibility_kernels

__all__ = ["HypothesisEstimator", "ModelPairs", "SegmentResult", "compile_kernels", "voxel_thin"]

log = logging.getLogger(__name__)


#: The two ICP stages of the refinement (step 4): segment points within ``near`` (m) of the
#: model (its dense samples, exactly), at most ``n_points`` of them, are matched to
#: ``n_samples`` evenly spaced model samples within ``max_distance`` (m), for at most
#: ``iterations`` Gauss-Newton steps.
_COARSE_ICP = dict(near=0.012, max_distance=0.012, iterations=8, n_samples=400, n_points=500)
_FINE_ICP = dict(near=0.008, max_distance=0.005, iterations=10, n_samples=800, n_points=1000)

#: The :class:`SampleGrid` of the dense samples and of each stage's samples: reach (m, the
#: largest ``near`` and ``max_distance`` above) and voxel (m).
_GRID_REACH = 0.012
_GRID_VOXEL = 0.002

#: About this many model samples score each candidate pose (step 3).
_COARSE_SAMPLES = 96

#: A class with more candidates is prescreened: every candidate is scored on a third of those
#: samples, and only this many, the best of them, on all (four times the 40 x ``refine`` that
#: refinement looks at). Fewer save more time but change what is refined: 400 lost two
#: correct best-scored block hypotheses, and with 600 the parser's worst object of Table I's
#: structures went from 10 to 20 mm (docs/perception.md).
_PRESCREEN_KEEP = 800

#: Occupied voxels of side v per v^2 of surface, averaged over orientations (about 1.3).
_VOXEL_AREA_FACTOR = 1.3


def voxel_thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied voxel of side ``voxel`` (m): the first, in order."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    ijk = np.floor(np.asarray(points) / voxel).astype(np.int64)
    ijk -= ijk.min(0)
    span = ijk.max(0) + 1
    keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
    _, first = np.unique(keys, return_index=True)
    return np.sort(first)


@njit
def _features(points, normals, first, second, dist_step, angle_step):
    """Quantised point-pair features of the oriented pairs ``(first[k], second[k])`` of
    ``points, normals (P, 3)`` (m, unit normals), compiled (scene and model pairs both go
    through this function, so equal features get equal keys).

    Returns ``(keys (M,) int64, coplanar (M,) bool, dist (M,) m)``; the coplanar flag is the
    key's lowest bit, so coplanar and non-coplanar pairs never match each other.
    """
    M = first.shape[0]
    keys = np.empty(M, dtype=np.int64)
    coplanar = np.empty(M, dtype=np.bool_)
    dist = np.empty(M)
    nb = int(np.ceil(np.pi / angle_step)) + 1
    r20 = np.radians(20.0)
    half_pi = 0.5 * np.pi
    for k in range(M):
        i, j = first[k], second[k]
        d0 = points[j, 0] - points[i, 0]
        d1 = points[j, 1] - points[i, 1]
        d2 = points[j, 2] - points[i, 2]
        r = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        s = 1.0 / max(r, 1e-12)
        u0, u1, u2 = d0 * s, d1 * s, d2 * s
        m0, m1, m2 = normals[i, 0], normals[i, 1], normals[i, 2]
        e0, e1, e2 = normals[j, 0], normals[j, 1], normals[j, 2]
        a1 = np.arccos(min(max(m0 * u0 + m1 * u1 + m2 * u2, -1.0), 1.0))
        a2 = np.arccos(min(max(e0 * u0 + e1 * u1 + e2 * u2, -1.0), 1.0))
        a3 = np.arccos(min(max(m0 * e0 + m1 * e1 + m2 * e2, -1.0), 1.0))
        flat = a3 < r20 and abs(a1 - half_pi) < r20
        q1 = int(np.floor(a1 / angle_step))
        q2 = int(np.floor(a2 / angle_step))
        q3 = int(np.floor(a3 / angle_step))
        qd = int(np.floor(r / dist_step))
        keys[k] = (((qd * nb + q1) * nb + q2) * nb + q3) * 2 + (1 if flat else 0)
        coplanar[k] = flat
        dist[k] = r
    return keys, coplanar, dist


@njit
def _pair_poses(scene_p, scene_n, a, b, model_p, model_n, mi, mj):
    """Poses ``R (K, 3, 3)``, ``t (K, 3)`` mapping model pair ``(mi[k], mj[k])`` onto scene
    pair ``(a[k], b[k])``, compiled: each pair's frame has its origin at the first point, x
    along its normal and y toward the second point, and ``T = F_scene F_model^-1``."""
    K = a.shape[0]
    R = np.empty((K, 3, 3))
    t = np.empty((K, 3))
    Fs = np.empty((3, 3))
    Fm = np.empty((3, 3))
    for k in range(K):
        _pair_frame(scene_p, scene_n, a[k], b[k], Fs)
        _pair_frame(model_p, model_n, mi[k], mj[k], Fm)
        for r in range(3):
            for c in range(3):
                R[k, r, c] = Fs[r, 0] * Fm[c, 0] + Fs[r, 1] * Fm[c, 1] + Fs[r, 2] * Fm[c, 2]
        for r in range(3):
            t[k, r] = scene_p[a[k], r] - (
                R[k, r, 0] * model_p[mi[k], 0]
                + R[k, r, 1] * model_p[mi[k], 1]
                + R[k, r, 2] * model_p[mi[k], 2]
            )
    return R, t


@njit
def _pair_frame(p, n, i, j, F):
    """The rotation ``F (3, 3)`` (columns x, y, z) of the oriented pair ``(i, j)`` of ``p, n``:
    x = the unit normal of ``i``, y toward ``j`` orthogonal to x."""
    x0, x1, x2 = n[i, 0], n[i, 1], n[i, 2]
    s = 1.0 / np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0, x1, x2 = x0 * s, x1 * s, x2 * s
    d0, d1, d2 = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2]
    dx = d0 * x0 + d1 * x1 + d2 * x2
    y0, y1, y2 = d0 - dx * x0, d1 - dx * x1, d2 - dx * x2
    s = 1.0 / max(np.sqrt(y0 * y0 + y1 * y1 + y2 * y2), 1e-12)
    y0, y1, y2 = y0 * s, y1 * s, y2 * s
    F[0, 0], F[1, 0], F[2, 0] = x0, x1, x2
    F[0, 1], F[1, 1], F[2, 1] = y0, y1, y2
    F[0, 2], F[1, 2], F[2, 2] = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0


@dataclass
class ModelPairs:
    """A model's point-pair table (step 1 of the module docstring).

    Attributes:
        name: class name. diameter: m. area: surface area, m^2. voxel: sample spacing, m.
        points, normals: ``(P, 3)`` thinned model samples and unit normals (model frame).
        keys: ``(Q,)`` sorted quantised features; ``first``, ``second``: ``(Q,)`` indices of the
            pair's points. symmetries: ``(S, 3, 3)`` symmetry rotations (identity first).
    """

    name: str
    diameter: float
    area: float
    voxel: float
    points: np.ndarray
    normals: np.ndarray
    dense_points: np.ndarray
    dense_normals: np.ndarray
    keys: np.ndarray
    first: np.ndarray
    second: np.ndarray
    symmetries: np.ndarray
    dist_step: float
    angle_step: float
    min_dist: float
    max_dist: float
    #: The distinct ``keys``, the index of each one's first pair and its number of pairs.
    unique_keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    unique_first: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    unique_count: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    #: :class:`SampleGrid` of ``dense_points`` (model frame), built on first use.
    _grid: SampleGrid | None = field(default=None, repr=False)
    #: ``n`` -> the :class:`SampleGrid` (with normals) of ``n`` evenly spaced surface samples
    #: (the ICP stages' samples), built on first use.
    _icp_grids: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if len(self.keys) and not len(self.unique_keys):
            self.unique_keys, self.unique_first, self.unique_count = np.unique(
                self.keys, return_index=True, return_counts=True
            )

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(first (M,), count (M,))``: where the pairs with each of ``keys (M,)`` start in
        the sorted table and how many there are (count 0: none; first is then meaningless)."""
        if len(self.unique_keys) == 0:
            return np.zeros(len(keys), np.int64), np.zeros(len(keys), np.int64)
        pos = np.minimum(np.searchsorted(self.unique_keys, keys), len(self.unique_keys) - 1)
        found = self.unique_keys[pos] == keys
        return self.unique_first[pos], np.where(found, self.unique_count[pos], 0)

    def grid(self) -> SampleGrid:
        """The nearest-sample grid of the dense samples in the model frame (built once)."""
        if self._grid is None:
            self._grid = SampleGrid(self.dense_points, _GRID_REACH, _GRID_VOXEL)
        return self._grid

    def icp_grid(self, model: ObjectModel, n: int) -> SampleGrid:
        """The :class:`SampleGrid` (with normals) of at most ``n`` evenly spaced surface
        samples of ``model`` (as :func:`ssp.registration.icp_refine` takes them), built once."""
        if n not in self._icp_grids:
            pts, nrm = even_rows(
                n,
                np.asarray(model.surface_points, dtype=float),
                np.asarray(model.surface_normals, dtype=float),
            )
            self._icp_grids[n] = SampleGrid(pts, _GRID_REACH, _GRID_VOXEL, normals=nrm)
        return self._icp_grids[n]

    @classmethod
    def build(cls, model: ObjectModel, cfg: PerceptionConfig) -> ModelPairs:
        diameter = float(model.diameter)
        pts = np.asarray(model.surface_points, dtype=float)
        nrm = np.asarray(model.surface_normals, dtype=float)
        dense_p, dense_n = (np.array(a, order="C") for a in even_rows(1500, pts, nrm))
        voxel = cfg.sampling * diameter
        sel = voxel_thin(pts, voxel)
        while len(sel) > cfg.max_model_points:
            voxel *= 1.15
            sel = voxel_thin(pts, voxel)
        pts, nrm = pts[sel], nrm[sel]
        n = len(pts)
        i, j = (np.ascontiguousarray(a) for a in np.nonzero(~np.eye(n, dtype=bool)))
        angle_step = np.radians(cfg.angle_step_deg)
        dist_step = voxel
        keys, _, dist = _features(pts, nrm, i, j, dist_step, angle_step)
        min_dist, max_dist = 0.15 * diameter, 0.9 * diameter
        ok = (dist >= min_dist) & (dist <= max_dist)
        keys, i, j = keys[ok], i[ok], j[ok]
        order = np.argsort(keys, kind="stable")
        sym = model.symmetry.transforms(np.radians(10.0))[:, :3, :3]
        return cls(
            model.name,
            diameter,
            float(model.mesh.area),
            voxel,
            pts,
            nrm,
            dense_p,
            dense_n,
            keys[order],
            i[order].astype(np.int32),
            j[order].astype(np.int32),
            sym,
            dist_step,
            angle_step,
            min_dist,
            max_dist,
        )


class _Occupancy:
    """Dilated boolean voxel grid of a point set: a fast "is there a point near here" test."""

    def __init__(self, points: np.ndarray, voxel: float, dilate: int = 1) -> None:
        self.voxel = voxel
        self.lo = points.min(0) - (dilate + 1) * voxel
        idx = np.floor((points - self.lo) / voxel).astype(np.int64)
        self.shape = idx.max(0) + dilate + 2
        grid = np.zeros(tuple(self.shape), dtype=bool)
        # the dilation by a (2 dilate + 1)^3 cube: every voxel within dilate of an occupied
        # one (the margins keep them inside the grid), as ndimage.binary_dilation with a 3^3
        # structure and dilate iterations gives, from the occupied voxels only
        cells = np.unique((idx[:, 0] * self.shape[1] + idx[:, 1]) * self.shape[2] + idx[:, 2])
        r = np.arange(-dilate, dilate + 1)
        steps = (r[:, None, None] * self.shape[1] + r[None, :, None]) * self.shape[2]
        steps = (steps + r[None, None, :]).ravel()
        grid.ravel()[(cells[:, None] + steps[None, :]).ravel()] = True
        self.grid = grid

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """``q (..., 3)`` -> bool ``(...)``: the voxel of each query is occupied."""
        # out-of-grid queries are clipped onto the border voxels, which are always empty
        ix, iy, iz = (
            np.clip(((q[..., a] - self.lo[a]) * (1.0 / self.voxel)).astype(np.int64), 0, n - 1)
            for a, n in enumerate(self.shape)
        )
        return self.grid.ravel()[(ix * int(self.shape[1]) + iy) * int(self.shape[2]) + iz]


def _coarse_hits(R, t, cp, cn, cam, occ: _Occupancy) -> tuple[np.ndarray, np.ndarray]:
    """Coarse score of candidate poses ``R (M, 3, 3)``, ``t (M, 3)`` on model samples ``cp,
    cn (P, 3)``: ``(hits (M,), facing (M,))``, the numbers of camera-facing samples (all when
    ``cam`` is None) that fall in an occupied voxel of ``occ``, and of facing samples."""
    if len(R) == 0 or len(cp) == 0:
        return np.zeros(len(R), dtype=np.int64), np.zeros(len(R), dtype=np.int64)
    return _coarse_kernel(
        kernel_array(R),
        kernel_array(t),
        kernel_array(cp),
        kernel_array(cn),
        np.zeros(3) if cam is None else kernel_array(cam),
        cam is not None,
        occ.grid.ravel(),
        occ.lo,
        1.0 / occ.voxel,
        occ.shape,
    )


@njit
def _coarse_kernel(R, t, cp, cn, cam, use_cam, grid, lo, inv_voxel, shape):
    """:func:`_coarse_hits`, compiled: per pose, the samples facing ``cam`` (``n . (R^T (cam -
    t)) > n . p``, all unless ``use_cam``) and those of them in an occupied voxel of ``grid``
    (flat, ``shape``, corner ``lo``); out-of-grid samples are misses. Each pose's voxel
    coordinates and facing values are computed in one branch-free pass (which vectorises),
    then counted."""
    M, P = R.shape[0], cp.shape[0]
    hits = np.zeros(M, dtype=np.int64)
    facing = np.zeros(M, dtype=np.int64)
    n0, n1, n2 = shape[0], shape[1], shape[2]
    f0, f1, f2 = float(n0), float(n1), float(n2)
    X, Y, Z = cp[:, 0].copy(), cp[:, 1].copy(), cp[:, 2].copy()
    NX, NY, NZ = cn[:, 0].copy(), cn[:, 1].copy(), cn[:, 2].copy()
    pn = NX * X + NY * Y + NZ * Z
    W0, W1, W2, F = np.empty(P), np.empty(P), np.empty(P), np.empty(P)
    for i in range(M):
        d0, d1, d2 = cam[0] - t[i, 0], cam[1] - t[i, 1], cam[2] - t[i, 2]
        c0 = R[i, 0, 0] * d0 + R[i, 1, 0] * d1 + R[i, 2, 0] * d2
        c1 = R[i, 0, 1] * d0 + R[i, 1, 1] * d1 + R[i, 2, 1] * d2
        c2 = R[i, 0, 2] * d0 + R[i, 1, 2] * d1 + R[i, 2, 2] * d2
        a00, a01, a02 = R[i, 0, 0] * inv_voxel, R[i, 0, 1] * inv_voxel, R[i, 0, 2] * inv_voxel
        a10, a11, a12 = R[i, 1, 0] * inv_voxel, R[i, 1, 1] * inv_voxel, R[i, 1, 2] * inv_voxel
        a20, a21, a22 = R[i, 2, 0] * inv_voxel, R[i, 2, 1] * inv_voxel, R[i, 2, 2] * inv_voxel
        o0 = (t[i, 0] - lo[0]) * inv_voxel
        o1 = (t[i, 1] - lo[1]) * inv_voxel
        o2 = (t[i, 2] - lo[2]) * inv_voxel
        for k in range(P):
            x, y, z = X[k], Y[k], Z[k]
            F[k] = NX[k] * c0 + NY[k] * c1 + NZ[k] * c2 - pn[k]
            W0[k] = a00 * x + a01 * y + a02 * z + o0
            W1[k] = a10 * x + a11 * y + a12 * z + o1
            W2[k] = a20 * x + a21 * y + a22 * z + o2
        h = 0
        f = 0
        for k in range(P):
            if use_cam and F[k] <= 0.0:
                continue
            f += 1
            w0, w1, w2 = W0[k], W1[k], W2[k]
            if w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0 and w0 < f0 and w1 < f1 and w2 < f2:
                if grid[(int(w0) * n1 + int(w1)) * n2 + int(w2)]:
                    h += 1
        hits[i] = h
        facing[i] = f
    return hits, facing


@dataclass
class _Pool:
    """Candidate poses of one class for one segment: rotations ``R (M, 3, 3)``, translations
    ``t (M, 3)``, coarse scores ``(M,)`` and the best coarse fraction (``quality``, 0..1)."""

    table: ModelPairs
    R: np.ndarray
    t: np.ndarray
    coarse: np.ndarray
    quality: float


@dataclass
class SegmentResult:
    """Hypotheses found in one segment: per object found, its ``k`` ranked hypotheses."""

    objects: list[list[Hypothesis]] = field(default_factory=list)
    seconds: float = 0.0
    candidates: int = 0
    #: Why no (further) object was found, in words ("" when the segment was fully explained).
    stopped: str = ""
    #: the hypotheses of an earlier frame, kept: the segment is unchanged
    #: (:mod:`ssp.perception.reuse`)
    reused: bool = False
    #: per object found: the fraction of the segment's points its best hypothesis explains
    #: (within ``inlier_distance``; of its points thinned to 3 mm that the objects found
    #: before it left)
    coverage: list[float] = field(default_factory=list)
    #: per object found: the best score of a refined pose whose orientation differs from the
    #: best one's by over ``alternative_deg`` (symmetry-aware; 0 when none): how nearly the
    #: view allows another orientation
    rival: list[float] = field(default_factory=list)

    @property
    def hypotheses(self) -> list[Hypothesis]:
        return [h for obj in self.objects for h in obj]


def _rotation_distances(Rs: np.ndarray, R_b: np.ndarray, sym: np.ndarray) -> np.ndarray:
    """Smallest angles (rad, ``(n,)``) between each of ``Rs (n, 3, 3)`` and ``R_b S`` over
    symmetry rotations ``S``."""
    A = R_b[None] @ sym[:, :3, :3]  # (S, 3, 3); trace(Rs^T A) = sum of the products
    tr = (Rs.reshape(len(Rs), 9) @ A.reshape(len(A), 9).T).max(1)
    return np.arccos(np.clip((tr - 1) / 2, -1, 1))


def _rotation_distance(R_a: np.ndarray, R_b: np.ndarray, sym: np.ndarray) -> float:
    """Smallest angle (rad) between ``R_a`` and ``R_b S`` over symmetry rotations ``S``."""
    return float(_rotation_distances(R_a[None], R_b, sym)[0])


class HypothesisEstimator:
    """ObjRecRANSAC-style pose hypotheses for segments of a cloud (module docstring).

    Args:
        library: class name -> :class:`ObjectModel`.
        config: :class:`PerceptionConfig`.
        seed: seed of the pair sampling (the same segment and seed give the same output).
    """

    def __init__(
        self,
        library: Mapping[str, ObjectModel],
        config: PerceptionConfig | None = None,
        seed: int = 0,
    ) -> None:
        self.library = library
        self.cfg = config if config is not None else PerceptionConfig()
        self.seed = int(seed)
        self._tables: dict[str, ModelPairs] = {}

    def table(self, name: str) -> ModelPairs:
        """The (cached) pair table of class ``name``."""
        if name not in self._tables:
            if name not in self.library:
                raise UnknownObjectError(name)
            self._tables[name] = ModelPairs.build(self.library[name], self.cfg)
        return self._tables[name]

    def prepare(self, classes: Iterable[str], *, kernels: bool = True) -> None:
        """Build everything :meth:`estimate` caches for ``classes`` now (pair tables, their
        sample grids and, with ``kernels``, the compiled kernels), so that processes forked
        afterwards share it instead of each building its own (:mod:`ssp.lanes`), and threads
        never build it at once (numba compiles or loads a kernel under its own lock: threads
        need no ``kernels``)."""
        if kernels:
            compile_kernels()
        for name in dict.fromkeys(classes):
            table = self.table(name)
            table.grid()
            for stage in (_COARSE_ICP, _FINE_ICP):
                table.icp_grid(self.library[name], stage["n_samples"])

    # ------------------------------------------------------------------ one segment
    def estimate(  # noqa: C901
        self,
        points: np.ndarray,
        normals: np.ndarray,
        classes: Iterable[str],
        camera_position: np.ndarray | None = None,
        *,
        single_object: bool = False,
        seed: int | None = None,
    ) -> SegmentResult:
        """Hypotheses for the objects in one segment.

        Args:
            points: ``(N, 3)`` segment points, world frame, m. normals: ``(N, 3)`` unit
                normals (facing the camera).
            classes: candidate class names.
            camera_position: ``(3,)`` camera centre (world) for the facing tests; None: all
                samples count.
            single_object: the segment is one object (an instance label): stop after one,
                and skip classes smaller than the segment.
            seed: overrides the estimator's seed for this call.
        """
        t0 = time.perf_counter()
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
        if len(pts) != len(nrm):
            raise PerceptionError(f"{len(pts)} points but {len(nrm)} normals")
        names = list(dict.fromkeys(classes))
        if not names:
            raise PerceptionError("no candidate classes for the segment")
        cfg = self.cfg
        rng = np.random.default_rng(self.seed if seed is None else seed)
        cam = None if camera_position is None else np.asarray(camera_position, dtype=float)
        result = SegmentResult()
        remaining = np.ones(len(pts), dtype=bool)
        limit = 1 if single_object else cfg.max_objects_per_segment
        for _ in range(limit):
            if remaining.sum() < cfg.min_segment_points:
                if not result.objects:
                    result.stopped = f"fewer than {cfg.min_segment_points} points"
                break
            p, n = pts[remaining], nrm[remaining]
            extent = robust_extent(p)
            occ = _Occupancy(p, cfg.score_voxel)  # shared by every class's coarse scoring
            seg_area = len(voxel_thin(p, cfg.score_voxel)) * cfg.score_voxel**2
            seg_area /= _VOXEL_AREA_FACTOR
            pools = []
            too_small = []
            for name in names:
                table = self.table(name)
                if single_object and extent > 1.3 * table.diameter:
                    too_small.append(name)  # the segment is larger than this class
                    continue
                pool = self._candidates(table, p, n, cam, rng, occ, seg_area)
                if pool is not None:
                    result.candidates += len(pool.R)
                    pools.append(pool)
            if not pools:
                if too_small and len(too_small) == len(names):
                    biggest = max(self.table(c).diameter for c in names)
                    result.stopped = (
                        f"larger than every candidate class ({1000 * extent:.0f} mm across, "
                        f"the largest class {1000 * biggest:.0f} mm)"
                    )
                else:
                    result.stopped = "no candidate pose of any class matched its point pairs"
                break
            # class screening: only classes whose coarse score is near the best are refined
            top = max(pool.quality for pool in pools)
            pools = [pool for pool in pools if pool.quality >= cfg.class_screen * top]
            pools = sorted(pools, key=lambda pool: -pool.quality)[: cfg.max_classes]
            best: tuple[list, str] | None = None
            thin = p[voxel_thin(p, 0.003)]
            for pool in pools:
                found = self._refine(pool, thin, cam)
                if found and (best is None or found[0][0] > best[0][0][0]):
                    best = (found, pool.table.name)
            if best is None or best[0][0][0] < cfg.min_score:
                if not result.objects:
                    score = 0.0 if best is None else best[0][0][0]
                    result.stopped = (
                        f"no pose explained it: best score {score:.2f} < {cfg.min_score:.2f}"
                    )
                break
            found, name = best
            kept = _diverse(found, cfg.hypotheses_per_object, cfg, self.table(name).symmetries)
            result.objects.append([Hypothesis(name, T, score=s) for s, T, _ in kept])
            result.coverage.append(float(found[0][2]))
            result.rival.append(_rival(found, cfg, self.table(name).symmetries))
            explained = self._explained(self.table(name), found[0][1], pts)
            if (remaining & explained).sum() < cfg.min_segment_points:
                break
            remaining &= ~explained
        result.seconds = time.perf_counter() - t0
        return result

    def _candidates(
        self, table: ModelPairs, p, n, cam, rng, occ: _Occupancy, seg_area: float
    ) -> _Pool | None:
        """Poses from matched point pairs with their coarse scores (steps 2-3), or None.

        ``occ``: the occupancy grid of the segment ``p``; ``seg_area``: its surface area, m^2.
        """
        cfg = self.cfg
        sel = voxel_thin(p, table.voxel)
        if len(sel) < 4:
            return None
        sp, sn = p[sel], n[sel]
        m = cfg.pair_samples
        a = rng.integers(0, len(sp), 6 * m)
        b = rng.integers(0, len(sp), 6 * m)
        keys, coplanar, dist = _features(sp, sn, a, b, table.dist_step, table.angle_step)
        ok = np.flatnonzero((dist >= table.min_dist) & (dist <= table.max_dist))
        lo, count = table.lookup(keys[ok])
        # matched pairs only; non-coplanar first (they fix a pose), coplanar ones fill up (a
        # single visible face)
        has = np.flatnonzero(count > 0)
        has = has[np.argsort(coplanar[ok[has]], kind="stable")][:m]
        if len(has) == 0:
            return None
        a, b, lo, count = a[ok[has]], b[ok[has]], lo[has], count[has]
        c = cfg.matches_per_pair
        draw = np.minimum(
            (rng.random((len(a), c)) * count[:, None]).astype(np.int64), count[:, None] - 1
        )
        use = (np.arange(c)[None, :] < count[:, None]).ravel()  # no repeats in small bins
        mp = (lo[:, None] + draw).ravel()[use]
        pair = np.repeat(np.arange(len(a)), c)[use]  # the scene pair of each match
        mi, mj = table.first[mp], table.second[mp]
        R, t = _pair_poses(sp, sn, a[pair], b[pair], table.points, table.normals, mi, mj)
        # coarse score: facing samples in occupied voxels of the segment
        step = max(1, len(table.points) // _COARSE_SAMPLES)
        cp, cn = table.points[::step], table.normals[::step]
        if len(R) > _PRESCREEN_KEEP:
            # a third of the samples first, the full score for the best of them only (the
            # others' coarse score is 0: never refined, never an alternative)
            pre, _ = _coarse_hits(R, t, cp[::3], cn[::3], cam, occ)
            top = np.sort(np.argsort(-pre, kind="stable")[:_PRESCREEN_KEEP])
            coarse = np.zeros(len(R), dtype=np.int64)
            facing = np.zeros(len(R), dtype=np.int64)
            coarse[top], facing[top] = _coarse_hits(R[top], t[top], cp, cn, cam, occ)
        else:
            coarse, facing = _coarse_hits(R, t, cp, cn, cam, occ)
        # quality for class screening: F1 of the fraction of facing samples explained and an
        # estimate of the fraction of the segment's surface explained (hit samples x area per
        # sample / segment area); the second keeps small classes from winning inside large
        # segments
        fit = coarse / np.maximum(facing, 8)
        cover = np.minimum(1.0, coarse * (table.area / len(cp)) / max(seg_area, 1e-12))
        f1 = 2 * fit * cover / np.maximum(fit + cover, 1e-12)
        return _Pool(table, R, t, coarse, float(f1.max()))

    def _refine(self, pool: _Pool, p: np.ndarray, cam) -> list[tuple[float, np.ndarray, float]]:
        """Ranked ``[(score, T_world_obj, coverage)]`` of distinct ICP-refined poses (step 4).

        The ``refine`` best distinct candidates are refined, and also up to ``alternatives``
        more whose orientation differs by over ``alternative_deg`` from all of those (the
        best of each such orientation): when most of an object is hidden, the seen part often
        fits several orientations, and the true one need not have the best coarse score.
        """
        cfg, table = self.cfg, pool.table
        R, t, coarse = pool.R, pool.t, pool.coarse
        sym = table.symmetries
        order = np.argsort(-coarse, kind="stable")[: 40 * cfg.refine]
        chosen: list[int] = []  # distinct candidates, best coarse score first
        near, turn = 0.1 * table.diameter, np.radians(15)
        for idx in order:
            if coarse[idx] == 0:
                break
            # distinct: from every chosen one, farther than `near` or turned by over `turn`
            if chosen:
                close = np.flatnonzero(np.linalg.norm(t[chosen] - t[idx], axis=1) <= near)
                if (
                    len(close)
                    and (
                        _rotation_distances(R[np.asarray(chosen)[close]], R[idx], sym) <= turn
                    ).any()
                ):
                    continue
            chosen.append(int(idx))
            if len(chosen) >= cfg.refine:
                break
        if chosen and cfg.alternatives:
            # the best candidate of each other orientation, best first
            apart = np.radians(cfg.alternative_deg)
            floor = max(cfg.alternative_coarse * coarse[chosen[0]], 1)
            rest = np.flatnonzero(coarse >= floor)
            rest = rest[np.argsort(-coarse[rest], kind="stable")]
            far = np.ones(len(rest), dtype=bool)
            for o in chosen:
                far &= _rotation_distances(R[rest], R[o], sym) > apart
            extra = 0
            while far.any() and extra < cfg.alternatives:
                idx = int(rest[np.argmax(far)])
                chosen.append(idx)
                extra += 1
                far &= _rotation_distances(R[rest], R[idx], sym) > apart
        poses: list[np.ndarray] = []
        for idx in chosen:  # coarse ICP, then drop the candidates that met
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[idx], t[idx]
            T = self._icp_stage(table, T, p, cam, _COARSE_ICP)
            if not any(_same_pose(T, U, table.symmetries) for U in poses):
                poses.append(T)
        tree = KDTree(p)
        refined = []
        for T in poses:  # fine ICP
            T = self._icp_stage(table, T, p, cam, _FINE_ICP)
            refined.append((*self._score(table, T, p, tree, cam), T))
        refined.sort(key=lambda r: -r[0])
        out: list[tuple[float, np.ndarray, float]] = []
        for s, cover, T in refined:
            if not any(_same_pose(T, U, table.symmetries) for _, U, _ in out):
                out.append((s, T, cover))
        return out

    def _icp_stage(self, table: ModelPairs, T, p, cam, stage: dict) -> np.ndarray:
        """``T`` refined by :func:`ssp.registration.grid_icp` with the settings ``stage``
        (:data:`_COARSE_ICP`) on the points of ``p`` within ``stage["near"]`` of the model."""
        near = self._near(table, T, p, stage["near"])
        return grid_icp(
            table.icp_grid(self.library[table.name], stage["n_samples"]),
            T,
            p[near],
            cam,
            max_distance=stage["max_distance"],
            iterations=stage["iterations"],
            n_points=stage["n_points"],
        )

    def _near(self, table: ModelPairs, T, p, radius: float) -> np.ndarray:
        """Mask of segment points ``p (N, 3)`` within ``radius`` (m) of the dense model
        samples at ``T`` (the points are moved into the model frame, whose tree is cached)."""
        return table.grid().within(p, radius, T)

    def _score(self, table: ModelPairs, T, p, tree: KDTree, cam) -> tuple[float, float]:
        """``(score, coverage)``: the score is the F1 of fit (facing samples with a segment
        point within ``inlier_distance``) and coverage (segment points within that distance of
        the model surface). ``tree``: KD-tree of ``p``."""
        r = self.cfg.inlier_distance
        wp = table.dense_points @ T[:3, :3].T + T[:3, 3]
        face = facing_mask(wp, table.dense_normals @ T[:3, :3].T, cam)
        if not face.any():
            return 0.0, 0.0
        fit = float(np.mean(_within(tree, wp[face], r)))
        cover = float(self._explained(table, T, p).mean())
        return (0.0 if fit + cover == 0 else 2 * fit * cover / (fit + cover)), cover

    def _explained(self, table: ModelPairs, T, p) -> np.ndarray:
        """Mask of points ``p`` within ``inlier_distance`` of the model surface at ``T``."""
        return self._near(table, T, p, self.cfg.inlier_distance)


def compile_kernels() -> None:
    """Compile the estimator's kernels, the exact ICP's (:mod:`ssp.registration`), the data
    forces' (:mod:`ssp.forces`), the volume test's (:mod:`ssp.overlap`), the self-occlusion
    test's (:mod:`ssp.visibility`), the cells' nearest points (:mod:`ssp.cells`: the label
    votes) and the connected components' (:mod:`ssp.components`: the cleaning) for the
    argument types they are passed, or load them from numba's cache (``make install`` runs
    this once: a first compile takes some 30 s; a kernel left out compiled in the first frame
    of the first run after an install, 0.5-1.8 s each)."""
    rng = np.random.default_rng(0)
    p = rng.normal(0.0, 0.02, (64, 3))
    n = p / np.linalg.norm(p, axis=1, keepdims=True)
    i = np.arange(63)
    _features(p, n, i, i + 1, 0.004, 0.2)
    _pair_poses(p, n, i, i + 1, p, n, i.astype(np.int32), (i + 1).astype(np.int32))
    _coarse_hits(np.repeat(np.eye(3)[None], 2, 0), np.zeros((2, 3)), p, n, np.ones(3),
                 _Occupancy(p, 0.004))  # fmt: skip
    grid = SampleGrid(p, _GRID_REACH, _GRID_VOXEL, normals=n)
    grid.within(p, 0.005, np.eye(4))
    grid.nearest_within(p, 0.005)  # the parser's surface lookups (ssp.segments.surface_grid)
    grid_icp(grid, np.eye(4), p, np.ones(3), max_distance=0.012, iterations=2, n_points=50)
    load_kernels()  # the exact ICP: the parser's polish and the icp baseline
    load_force_kernels()  # the parser's data forces
    load_overlap_kernels()  # the parser's volume test
    load_visibility_kernels()  # the self-occlusion test of the correction and the evidence
    load_cell_kernels()  # the label votes' nearest points
    load_component_kernels()  # the cleaning's and the clusters' connected components


def _within(tree: KDTree, q: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the queries ``q (N, 3)`` with a point of ``tree`` within ``radius`` (m)."""
    if len(q) == 0:
        return np.zeros(0, dtype=bool)
    d, _ = tree.query(np.ascontiguousarray(q, dtype=float), k=1, distance_upper_bound=radius)
    return np.isfinite(d)


def _diverse(found: list, k: int, cfg: PerceptionConfig, sym: np.ndarray) -> list:
    """The ``k`` hypotheses kept of ``found`` (``[(score, T, coverage)]``, best first).

    The best, then the poses whose orientation differs by over ``alternative_deg`` from every
    kept one and that explain the segment nearly as well (coverage at least the best's minus
    ``alternative_coverage``), best score first; then the rest by score. Fit alone favours
    the pose that puts the most surface where points are seen, which for a mostly hidden
    object is often the wrong orientation; the scene parser's occlusion-aware data term,
    collisions and support then choose among them.
    """
    if not found:
        return []
    apart = np.radians(cfg.alternative_deg)
    floor = found[0][2] - cfg.alternative_coverage
    kept = [0]
    for i in range(1, len(found)):
        if len(kept) >= k:
            break
        R = found[i][1][:3, :3]
        if found[i][2] >= floor and all(
            _rotation_distance(found[j][1][:3, :3], R, sym) > apart for j in kept
        ):
            kept.append(i)
    kept += [i for i in range(len(found)) if i not in kept][: max(0, k - len(kept))]
    kept.sort()
    return [(float(found[i][0]), found[i][1], float(found[i][2])) for i in kept]


def _rival(found: list, cfg: PerceptionConfig, sym: np.ndarray) -> float:
    """The best score in ``found`` (``[(score, T, coverage)]``, best first) of a pose turned
    by over ``alternative_deg`` from the first (symmetry-aware); 0 when there is none."""
    apart = np.radians(cfg.alternative_deg)
    R = found[0][1][:3, :3]
    others = [s for s, T, _ in found[1:] if _rotation_distance(T[:3, :3], R, sym) > apart]
    return float(max(others, default=0.0))


def _same_pose(T: np.ndarray, U: np.ndarray, sym: np.ndarray) -> bool:
    """Poses within 2 mm and 3 deg of each other (symmetry-aware)."""
    return bool(
        np.linalg.norm(T[:3, 3] - U[:3, 3]) <= 0.002
        and _rotation_distance(U[:3, :3], T[:3, :3], sym) <= np.radians(3)
    )
