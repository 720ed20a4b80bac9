"""Could the camera see an object at a given pose? Ray-wise comparison with the observed cloud.

The scene parser uses this to decide what happened to an object that the detector no longer
reports: it is *occluded* (something observed lies in front of it: keep it, as "ephemeral"), it
is *gone* (its volume is seen empty: the surface behind where it would be is observed), or it is
*visible* (observed points lie on its surface: the detector simply missed it).

Method
------
The camera intrinsics are not known; only the world-frame scene points captured by the camera
and the camera pose ``T_world_cam`` are. Every observed point is moved into the camera frame
(OpenCV: x right, y down, z forward) and stored by its ray direction, the *normalised image
coordinates* ``(x/z, y/z)``, with its depth ``z`` (m). For a pinhole camera, pixels are evenly
spaced in these coordinates (spacing ``1/f`` for a focal length ``f`` in pixels), so distances
between rays there are pixel distances up to the unknown scale ``f``; near the optical axis they
are also angles in radians.

For each model sample (a surface point and its outward normal, placed at the queried pose) that
faces the camera (``normal . (camera - point) > 0``) and lies in front of it (``z > 0``), the
observed point whose ray is nearest to the sample's ray, within ``angular_resolution``, is
looked up (one KD-tree query for all samples), and its depth compared to the sample's depth:

* ``|depth_obs - depth| <= depth_tolerance``: **seen**, the surface is where the model says;
* ``depth_obs < depth - depth_tolerance``: **occluded**, something is in front of it;
* ``depth_obs > depth + depth_tolerance``: **seen through**, the camera saw past where the
  surface would be, so that space is empty;
* no observed point within the radius: **unknown** (missing data, or outside the view).

:meth:`CameraView.in_view` tells the two kinds of unknown apart as far as the cloud allows: a
ray outside the span of the observed rays (the image's extent) is outside the field of view;
a camera that moves looks away from objects it saw before, which says nothing about them.

Limits
------
* No intrinsics: the field of view is known only through the observed points, so "unknown"
  cannot tell a hole in the depth image (e.g. a black or shiny surface) from a ray outside the
  image. The lookup radius must be about one pixel; where the cloud is sparser than that (e.g.
  after down-sampling), samples come out unknown. By default the radius is estimated from the
  cloud itself (see :class:`CameraView`).
* One depth per ray: a depth image holds one depth per pixel, so the observed point nearest in
  angle is used, not the nearest in depth. At depth discontinuities (silhouette edges) the
  answer for a sample within a pixel of the edge may come from either side; such samples are a
  small fraction of an object's facing samples.
* ``depth_tolerance`` (m) absorbs sensor noise and small pose errors; surfaces seen at grazing
  angles change depth quickly from pixel to pixel and may need a larger tolerance.
* Self-occlusion: with ``self_spacing`` (the samples are one object's, that far apart on its
  surface), a facing sample whose ray passes within :data:`SELF_COVER` sample spacings of
  another facing sample of the object that lies in front of it (closer by ``depth_tolerance``,
  and off its tangent plane by as much, so neighbours on one smooth surface seen at a grazing
  angle do not hide each other) is :data:`SELF_HIDDEN`: the object's own parts hide it, as
  the handle of a mug hides the wall behind it. Without it only the facing test applies
  (exact for convex objects).
* Depth is compared along the optical axis (``z``), as in a depth image; for points on the same
  ray this orders them exactly as range does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ssp.cells import cell_sort
from ssp.geometry import invert, transform_points, validate_pose
from ssp.jit import kernel_array, njit
from ssp.kdtree import KDTree

#: Smallest camera-frame depth (m) taken as "in front of the camera"; avoids dividing by ~0.
MIN_DEPTH = 1e-6

#: Default lookup radius factor: 1.5 x the median nearest-neighbour ray distance of the cloud.
#: On a regular pixel grid that distance is one pixel, so 1.5 px reaches the 8 neighbouring
#: pixels (diagonal: 1.41 px) and lets a ray between pixels always find one.
RESOLUTION_FACTOR = 1.5

#: Largest number of rays whose nearest-neighbour distance enters the estimate (a strided subset;
#: 1,000 give the median of 5,000 to 2e-6 relative on the real Kinect clouds of
#: ``shared/data/real-dev`` (190-240k points) and exactly on a 62k-point rendered image).
ESTIMATE_MAX_QUERIES = 1_000

#: Sample states of :meth:`CameraView.classify`.
NOT_FACING, SEEN, OCCLUDED, SEEN_THROUGH, UNKNOWN, BEHIND_OWN, SELF_HIDDEN = 0, 1, 2, 3, 4, 5, 6

#: A sample is hidden by one of its object's own samples whose ray passes within this many
#: sample spacings (at the occluder's depth) of its own: samples ``s`` apart on a surface leave
#: no ray through it farther than about ``0.71 s`` from one of them.
SELF_COVER = 0.75

#: Neighbours (in the image) searched for a sample's self-occluders.
SELF_NEIGHBOURS = 16

#: Leaf size of the ray tree (pykdtree, exact nearest neighbours): larger leaves build in
#: about a third of the time of scipy's tree and keep the queries as fast.
RAY_TREE_LEAF = 64

#: Lookup radius (normalised image coordinates, ~rad) used when the cloud has too few points
#: (fewer than 2 distinct rays) to estimate one: about one pixel of a 640 px wide, 60 deg camera.
FALLBACK_ANGULAR_RESOLUTION = 0.002


@dataclass(frozen=True)
class VisibilityReport:
    """How the facing samples of an object at a pose compare with what the camera observed.

    The four fractions sum to 1 when ``n_facing > 0``; all are 0.0 when ``n_facing == 0``.
    """

    #: Samples facing the camera (``normal . (cam - p) > 0``) and in front of it (``z > 0``).
    n_facing: int
    #: Fraction of facing samples with an observed point at about their depth.
    seen: float
    #: Fraction with an observed point clearly in front of them (something hides them).
    occluded: float
    #: Fraction whose ray has an observed point clearly behind them (free space where they are).
    seen_through: float
    #: Fraction with no observed point along their ray (missing data, outside the view).
    unknown: float


@dataclass(frozen=True)
class RayLookup:
    """What :meth:`CameraView.lookup` found along the rays of an object's F facing samples.

    Attributes:
        index: (F,) indices of the facing samples among the queried ones.
        depth: (F,) their camera-frame depths (m, along the optical axis).
        observed: (F,) the observed depth along each one's ray (m), NaN where none.
        label: (F,) the observed point's label, -1 where none or without labels.
    """

    index: np.ndarray
    depth: np.ndarray
    observed: np.ndarray
    label: np.ndarray


def _as_points(a: np.ndarray, what: str) -> np.ndarray:
    """``a`` as a finite float64 (n, 3) array, or ``ValueError``."""
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not a numeric (n, 3) array ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{what}: expected shape (n, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what}: contains NaN or infinite values")
    return arr


def _positive(value: float, what: str, *, allow_zero: bool) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not a number ({value!r})") from exc
    if not np.isfinite(v) or v < 0.0 or (v == 0.0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{what}: must be finite and {bound}, got {value!r}")
    return v


def _self_hidden(
    p_cam: np.ndarray, p_world: np.ndarray, n_world: np.ndarray, spacing: float, tol: float
) -> np.ndarray:
    """(F,) bool: which of one object's facing samples (camera frame ``p_cam`` (F, 3), world
    ``p_world`` and normals ``n_world``) lie behind another of them (module docstring,
    "Self-occlusion"). ``spacing``: sample spacing on the surface (m); ``tol``: m. A sample's
    occluders are sought among its :data:`SELF_NEIGHBOURS` nearest other samples in the image
    (:func:`_self_hidden_kernel`)."""
    n = len(p_cam)
    if n < 2 or spacing <= 0.0:
        return np.zeros(n, dtype=bool)
    depth = np.ascontiguousarray(p_cam[:, 2])
    rays = np.zeros((n, 3))  # in the plane z = 0, for ssp.cells' sort
    rays[:, :2] = p_cam[:, :2] / depth[:, None]
    cover = SELF_COVER * spacing / depth  # each sample's footprint radius in the image
    nrm = n_world / np.maximum(np.linalg.norm(n_world, axis=1, keepdims=True), 1e-12)
    return _self_hidden_kernel(
        rays, depth, kernel_array(cover), kernel_array(p_world), kernel_array(nrm), float(tol),
        min(SELF_NEIGHBOURS + 1, n), SELF_MAX_CELLS,
    )  # fmt: skip


#: :func:`_self_hidden_kernel` bins the rays in at most this many cells (larger cells beyond).
SELF_MAX_CELLS = 1 << 16


def load_kernels() -> None:
    """Compile the self-occlusion test's kernel, or load it from numba's cache
    (:func:`ssp.perception.estimator.compile_kernels`: ``make install`` runs it)."""
    p = np.array([[0.0, 0.0, 1.0], [0.001, 0.0, 0.9], [0.0, 0.001, 1.1]])
    _self_hidden(p, p, -p, 0.01, 0.005)


@njit
def _self_hidden_kernel(rays, depth, cover, p_world, nrm, tol, k, max_cells):
    """:func:`_self_hidden`, compiled: sample ``i`` (ray ``rays[i, :2]``, normalised image
    coordinates, ``rays[i, 2] = 0``; optical depth ``depth[i]``, m) is hidden when one of its
    ``k`` nearest rays (itself included; distance, then index) closer than ``b = max(cover)``,
    ray ``j``, lies within ``cover[j]`` of it, ``j`` is in front of it by more than ``tol``
    (m) and off its tangent plane (world point ``p_world[i]``, unit normal ``nrm[i]``) by more
    than ``tol`` (what a KD-tree's ``k``-nearest query bounded by ``b`` finds; the same
    verdicts). The rays are sorted into cells of side at least ``b``
    (:func:`ssp.cells.cell_sort`), so those closer than ``b`` lie in the 3 x 3 around a ray's."""
    n = rays.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    b = cover.max()
    cells = cell_sort(rays, np.arange(n), b, max_cells)
    near_d2 = np.empty(k)  # the k nearest: squared distances and indices, ascending
    near_j = np.empty(k, dtype=np.int64)
    for i in range(n):
        m = _k_nearest(i, rays, cells, b * b, near_d2, near_j)
        for q in range(m):
            j = near_j[q]
            if not math.sqrt(near_d2[q]) <= cover[j]:  # outside the occluder's footprint
                continue
            if not depth[j] < depth[i] - tol:  # not in front of the sample
                continue
            off = (
                (p_world[j, 0] - p_world[i, 0]) * nrm[i, 0]
                + (p_world[j, 1] - p_world[i, 1]) * nrm[i, 1]
                + (p_world[j, 2] - p_world[i, 2]) * nrm[i, 2]
            )
            if off > tol:  # not a neighbour on the sample's own smooth surface
                out[i] = True
                break
    return out


@njit
def _k_nearest(i, rays, cells, b2, near_d2, near_j):
    """The ``k = len(near_j)`` rays nearest ray ``i`` closer than ``sqrt(b2)`` (distance, then
    index), searched in the 3 x 3 cells of :func:`ssp.cells.cell_sort` (``cells``) around its
    own, into ``near_d2`` (squared distances) and ``near_j``, ascending; returns how many."""
    lo, dims, _, inv_h, start, order = cells
    k = near_j.shape[0]
    ix = min(int((rays[i, 0] - lo[0]) * inv_h), dims[0] - 1)
    iy = min(int((rays[i, 1] - lo[1]) * inv_h), dims[1] - 1)
    m = 0
    for ax in range(max(ix - 1, 0), min(ix + 2, dims[0])):
        for ay in range(max(iy - 1, 0), min(iy + 2, dims[1])):
            c = (ax * dims[1] + ay) * dims[2]  # the one cell of z = 0
            for s in range(start[c], start[c + 1]):
                j = order[s]
                dx, dy = rays[j, 0] - rays[i, 0], rays[j, 1] - rays[i, 1]
                d2 = dx * dx + dy * dy
                if not d2 < b2 or (m == k and (d2, j) > (near_d2[k - 1], near_j[k - 1])):
                    continue
                p = min(m, k - 1)  # insertion into the sorted k nearest
                while p > 0 and (near_d2[p - 1], near_j[p - 1]) > (d2, j):
                    if p < k:
                        near_d2[p], near_j[p] = near_d2[p - 1], near_j[p - 1]
                    p -= 1
                near_d2[p], near_j[p] = d2, j
                m = min(m + 1, k)
    return m


def estimate_angular_resolution(rays: np.ndarray, tree: KDTree | None = None) -> float:
    """Lookup radius for rays ``(n, 2)`` in normalised image coordinates (~rad).

    :data:`RESOLUTION_FACTOR` x the median distance from each ray (at most
    :data:`ESTIMATE_MAX_QUERIES` of them, evenly strided) to its nearest other distinct ray
    (exact duplicates are ignored). :data:`FALLBACK_ANGULAR_RESOLUTION` when there are fewer
    than 2 distinct rays.
    """
    rays = np.ascontiguousarray(rays, dtype=float)
    if len(rays) < 2:
        return FALLBACK_ANGULAR_RESOLUTION
    if tree is None:
        tree = KDTree(rays, leafsize=RAY_TREE_LEAF)
    # The median over an evenly strided subset (every point of a small cloud) keeps this cheap
    # on full depth images; a few neighbours so duplicated rays do not hide the real spacing.
    queries = rays[:: -(-len(rays) // ESTIMATE_MAX_QUERIES)]
    k = min(len(rays), 4)
    dist, _ = tree.query(np.ascontiguousarray(queries), k=k)
    dist = dist.reshape(len(queries), k)
    dist = np.where(dist > 0.0, dist, np.inf)  # drops the ray itself and its duplicates
    nearest = dist.min(axis=1)
    nearest = nearest[np.isfinite(nearest)]
    if nearest.size == 0:
        return FALLBACK_ANGULAR_RESOLUTION
    return float(RESOLUTION_FACTOR * np.median(nearest))


class CameraView:
    """The observed scene of one frame, indexed by ray direction; built once per frame.

    Args:
        points_world: (N, 3) scene points (m, world frame) captured by this camera; may be empty.
        T_world_cam: (4, 4) camera pose (maps OpenCV camera coordinates to world).
        angular_resolution: lookup radius around a sample's ray, in normalised image coordinates
            (~rad; about one pixel, ``1/f``). ``None``: estimated from the cloud as
            :data:`RESOLUTION_FACTOR` x the median nearest-neighbour ray distance.
        depth_tolerance: |observed - model| depth (m) still counted as the same surface.

    Only points in front of the camera (``z > MIN_DEPTH``) are kept.
    """

    def __init__(
        self,
        points_world: np.ndarray,
        T_world_cam: np.ndarray,
        *,
        angular_resolution: float | None = None,
        depth_tolerance: float = 0.005,
        labels: np.ndarray | None = None,
    ) -> None:
        pts = _as_points(points_world, "points_world")
        if labels is not None:
            labels = np.asarray(labels).reshape(-1)
            if len(labels) != len(pts):
                raise ValueError(f"labels: {len(labels)} for {len(pts)} points")
        self._T_world_cam = validate_pose(T_world_cam, "T_world_cam")
        self._T_cam_world = invert(self._T_world_cam)
        self._depth_tolerance = _positive(depth_tolerance, "depth_tolerance", allow_zero=True)

        p_cam = transform_points(self._T_cam_world, pts)
        front = p_cam[:, 2] > MIN_DEPTH
        if not front.all():  # (a copy of the whole cloud otherwise)
            p_cam = p_cam[front]
            labels = None if labels is None else labels[front]
        self._labels = labels
        self._depths = p_cam[:, 2].copy()
        rays = np.ascontiguousarray(p_cam[:, :2] / p_cam[:, 2:3])
        self._tree = KDTree(rays, leafsize=RAY_TREE_LEAF) if len(rays) else None
        # the field of view as the observed rays span it (x_min, y_min, x_max, y_max)
        self._bounds = None
        if len(rays):  # column by column: 7x faster than numpy's reduction along axis 0 here
            x, y = rays[:, 0], rays[:, 1]
            self._bounds = np.array([x.min(), y.min(), x.max(), y.max()])

        if angular_resolution is None:
            self._resolution = estimate_angular_resolution(rays, self._tree)
        else:
            self._resolution = _positive(angular_resolution, "angular_resolution", allow_zero=False)

    @property
    def n_points(self) -> int:
        """Number of observed points in front of the camera."""
        return int(len(self._depths))

    @property
    def angular_resolution(self) -> float:
        """Lookup radius (normalised image coordinates, ~rad)."""
        return self._resolution

    @property
    def depth_tolerance(self) -> float:
        """Same-surface depth tolerance (m)."""
        return self._depth_tolerance

    @property
    def T_world_cam(self) -> np.ndarray:
        """Camera pose (4, 4), a copy."""
        return self._T_world_cam.copy()

    def classify(
        self,
        points_world: np.ndarray,
        normals_world: np.ndarray,
        own_label: int | None = None,
        *,
        self_spacing: float | None = None,
    ) -> np.ndarray:
        """Per-sample state ``(M,)`` int8 of model samples placed in the world:
        :data:`NOT_FACING` (facing away or behind the camera), :data:`SEEN`,
        :data:`OCCLUDED`, :data:`SEEN_THROUGH` or :data:`UNKNOWN` (module docstring); with
        ``own_label`` (the object's instance label; needs ``labels``), a sample hidden only
        by points of that label is :data:`BEHIND_OWN`: the object's own observed surface lies
        in front of it, so the model is too small there or placed inside what was seen; with
        ``self_spacing``, a facing sample behind the object's own surface is
        :data:`SELF_HIDDEN` (module docstring, "Self-occlusion").

        Args:
            points_world: (M, 3) surface samples (m, world frame).
            normals_world: (M, 3) their outward normals (world frame; need not be unit length;
                a zero normal never faces the camera).
            own_label: the object's label in the cloud, or None.
            self_spacing: spacing of the samples on the object's surface (m) when they are
                one object's; None: no self-occlusion test.
        """
        facing, self_hidden, p_cam = self._facing(points_world, normals_world, self_spacing)
        out = np.full(len(facing), NOT_FACING, dtype=np.int8)
        out[self_hidden] = SELF_HIDDEN
        if not facing.any():
            return out
        if self._tree is None:
            out[facing] = UNKNOWN
            return out
        p_cam = p_cam[facing]
        depth = p_cam[:, 2]
        found, idx = self._nearest_rays(p_cam)
        diff = np.full(len(depth), np.nan)
        diff[found] = self._depths[idx[found]] - depth[found]
        tol = self._depth_tolerance
        state = np.full(len(depth), UNKNOWN, dtype=np.int8)
        state[found & (np.abs(diff) <= tol)] = SEEN
        state[found & (diff < -tol)] = OCCLUDED
        state[found & (diff > tol)] = SEEN_THROUGH
        if own_label is not None and self._labels is not None:
            j = np.where(found, idx, 0)
            state[found & (diff < -tol) & (self._labels[j] == own_label)] = BEHIND_OWN
        out[facing] = state
        return out

    def _facing(
        self, points_world: np.ndarray, normals_world: np.ndarray, self_spacing: float | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(facing, self_hidden, p_cam)``: (M,) bool, the samples facing the camera in front
        of it and not behind the object's own surface (``self_spacing``, :func:`_self_hidden`);
        (M,) bool, those behind it; (M, 3) the samples in the camera frame (m)."""
        pts = _as_points(points_world, "points_world")
        nrm = _as_points(normals_world, "normals_world")
        if nrm.shape != pts.shape:
            raise ValueError(
                f"normals_world: shape {nrm.shape} does not match points_world {pts.shape}"
            )
        cam_centre = self._T_world_cam[:3, 3]
        facing = np.einsum("ij,ij->i", nrm, cam_centre - pts) > 0.0
        p_cam = transform_points(self._T_cam_world, pts)
        facing &= p_cam[:, 2] > MIN_DEPTH
        self_hidden = np.zeros(len(pts), dtype=bool)
        if self_spacing is not None and facing.any():
            hidden = _self_hidden(
                p_cam[facing], pts[facing], nrm[facing], float(self_spacing), self._depth_tolerance
            )
            self_hidden[np.flatnonzero(facing)[hidden]] = True
            facing &= ~self_hidden
        return facing, self_hidden, p_cam

    def least_depth(self, points_world: np.ndarray, k: int, reach: float) -> np.ndarray:
        """(M,) the least observed depth (m) among the ``k`` observed rays nearest to the ray
        of each point ``points_world`` (M, 3; m, world frame) within ``reach`` x the angular
        resolution; ``inf`` where none is (or the point is not in front of the camera). What
        the camera saw nearest along any ray around a point: a point whose least depth lies
        behind it was seen through by every ray around it, not only by one at a
        silhouette's edge."""
        out = np.full(len(points_world), np.inf)
        if self._tree is None or not len(points_world):
            return out
        p_cam = transform_points(self._T_cam_world, _as_points(points_world, "points_world"))
        front = p_cam[:, 2] > MIN_DEPTH
        if not front.any():
            return out
        rays = np.ascontiguousarray(p_cam[front, :2] / p_cam[front, 2:3])
        dist, idx = self._tree.query(rays, k=int(k), distance_upper_bound=reach * self._resolution)
        dist, idx = dist.reshape(len(rays), -1), idx.reshape(len(rays), -1)
        found = np.isfinite(dist)
        depths = np.where(found, self._depths[np.where(found, idx, 0)], np.inf)
        out[front] = depths.min(axis=1)
        return out

    def in_view(self, points_world: np.ndarray) -> np.ndarray:
        """(M,) bool: which points (M, 3; m, world frame) lie in the camera's field of view:
        in front of the camera, their ray within the span of the observed rays (the image, as
        far as the cloud shows it; module docstring "Limits") widened by the angular
        resolution. A point outside it could not have been seen at all: a moving camera
        looked elsewhere. None are without observed points."""
        pts = _as_points(points_world, "points_world")
        if self._bounds is None or not len(pts):
            return np.zeros(len(pts), dtype=bool)
        p_cam = transform_points(self._T_cam_world, pts)
        out = p_cam[:, 2] > MIN_DEPTH
        rays = p_cam[out, :2] / p_cam[out, 2:3]
        r = self._resolution
        inside = np.all((rays >= self._bounds[:2] - r) & (rays <= self._bounds[2:] + r), axis=1)
        out[out] = inside
        return out

    def _nearest_rays(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(found, idx)`` per camera-frame point (N, 3) in front of the camera: whether an
        observed point's ray is within the angular resolution of its ray, and that point's
        index. Nearest ray in angle, not the smallest depth: a depth image holds one depth per
        pixel. Needs observed points."""
        assert self._tree is not None
        rays = np.ascontiguousarray(p_cam[:, :2] / p_cam[:, 2:3])
        dist, idx = self._tree.query(rays, k=1, distance_upper_bound=self._resolution)
        return np.isfinite(dist), idx

    def lookup(
        self,
        points_world: np.ndarray,
        normals_world: np.ndarray,
        *,
        self_spacing: float | None = None,
    ) -> RayLookup:
        """What the camera observed along the ray of each facing sample of one object.

        Args:
            points_world: (M, 3) surface samples (m, world frame).
            normals_world: (M, 3) their outward normals (world frame).
            self_spacing: as for :meth:`classify`: samples behind the object's own surface do
                not face the camera.

        Returns:
            :class:`RayLookup` over the F facing samples (camera-facing, in front of the
            camera, not hidden by the object itself): their indices, camera-frame depths, the
            depth observed along their rays (NaN where none is within the lookup radius) and
            the observed point's label (-1 where none or without labels).
        """
        facing, _, p_cam = self._facing(points_world, normals_world, self_spacing)
        index = np.flatnonzero(facing)
        depth = p_cam[index, 2].copy()
        observed = np.full(len(index), np.nan)
        label = np.full(len(index), -1, dtype=np.int64)
        if self._tree is not None and len(index):
            found, idx = self._nearest_rays(p_cam[index])
            observed[found] = self._depths[idx[found]]
            if self._labels is not None:
                label[found] = self._labels[idx[found]]
        return RayLookup(index, depth, observed, label)

    def report(
        self,
        points_world: np.ndarray,
        normals_world: np.ndarray,
        *,
        self_spacing: float | None = None,
    ) -> VisibilityReport:
        """Fractions of the facing model samples in each state (:meth:`classify`; samples
        hidden behind the object's own surface, with ``self_spacing``, do not face the camera)."""
        state = self.classify(points_world, normals_world, self_spacing=self_spacing)
        n = int(np.count_nonzero((state != NOT_FACING) & (state != SELF_HIDDEN)))
        if n == 0:
            return VisibilityReport(0, 0.0, 0.0, 0.0, 0.0)
        counts = [int(np.count_nonzero(state == k)) for k in (SEEN, OCCLUDED, SEEN_THROUGH)]
        return VisibilityReport(
            n, counts[0] / n, counts[1] / n, counts[2] / n, (n - sum(counts)) / n
        )

    def hidden_by_others(self, points_world: np.ndarray, own_label: int) -> np.ndarray:
        """(M,) bool: the sample's ray meets an observed point clearly in front of it
        (``depth_tolerance``) that carries another label than ``own_label``: the sample is
        hidden behind another object, so the data says nothing about it. Needs ``labels``.
        An object's own observed surface in front of a misplaced sample does not count."""
        if self._labels is None:
            raise ValueError("hidden_by_others needs the labels of the scene points")
        pts = _as_points(points_world, "points_world")
        out = np.zeros(len(pts), dtype=bool)
        if self._tree is None or not len(pts):
            return out
        p_cam = transform_points(self._T_cam_world, pts)
        ok = p_cam[:, 2] > MIN_DEPTH
        depth = p_cam[ok, 2]
        found, idx = self._nearest_rays(p_cam[ok])
        hidden = np.zeros(len(depth), dtype=bool)
        j = idx[found]
        hidden[found] = (self._depths[j] < depth[found] - self._depth_tolerance) & (
            self._labels[j] != own_label
        )
        out[ok] = hidden
        return out

    def report_pose(
        self, model_points: np.ndarray, model_normals: np.ndarray, T_world_obj: np.ndarray
    ) -> VisibilityReport:
        """Classify model samples ``(M, 3)`` (model frame, m) placed at pose ``T_world_obj``."""
        pts = _as_points(model_points, "model_points")
        nrm = _as_points(model_normals, "model_normals")
        if nrm.shape != pts.shape:
            raise ValueError(
                f"model_normals: shape {nrm.shape} does not match model_points {pts.shape}"
            )
        T = validate_pose(T_world_obj, "T_world_obj")
        R = T[:3, :3]
        return self.report(pts @ R.T + T[:3, 3], nrm @ R.T)
