"""Support plane (table top) of a cloud by RANSAC, and the world frame it defines.

:func:`fit_plane` finds the table as a plane ``normal . p + offset = 0`` (m), and
:func:`T_world_cam_from_plane` turns it into a camera pose with world z up and the table at
``z = 0`` (the frame convention of the whole package). :func:`table_frame` does both.

Algorithm (:func:`fit_plane`)
-----------------------------
1. Vectorised RANSAC: ``iterations`` 3-point samples are drawn at once, half uniformly from the
   whole cloud and half *locally* (an anchor and two of its 32 nearest neighbours in a random
   subset), so that a plane holding only ~10 % of the cloud is still sampled. All samples are
   scored together on a random subset of 2000 points; the 5 best are re-scored on all points.
2. Least-squares refit (eigen-decomposition of the inliers' covariance, i.e. the SVD of the
   centred inliers; at most 20k of them) and a new inlier pass, repeated until the inlier
   count changes by less than 0.1 % (at most 10 rounds); the last pass gives the inliers.
3. Sequential search: the plane's inliers are removed and steps 1-2 repeated, for up to 3
   qualifying planes (4 tries), while the remaining points could still form one. When no plane
   qualifies yet, steps 1-2 are retried twice with fresh samples before giving up.

A plane *qualifies* with at least ``min_inliers`` inliers, at least ``min_fraction`` of the
finite points, a width of at least ``min_extent`` (rejects the faces of a lone object, which are
planes too), and, when ``up_hint`` is given, a normal within ``max_tilt_deg`` of it (tilted
samples are discarded before scoring, so walls are never chosen).

Which plane is the support
--------------------------
The qualifying plane with the most inliers, except when it looks like the top of a large object
standing on the support: if another qualifying plane is parallel to it (within 10 deg) and lies
*below* it (away from the camera, or against ``up_hint``) by more than ``2 distance`` and at most
:data:`MAX_SUPPORT_STEP` (0.35 m, taller than any table-top object), the lower plane is chosen
(the largest such one). A lower plane farther down (a floor seen past the table's edge) is not
taken. What is not handled: without ``up_hint``, a wall with more inliers than the table wins
(pass ``up_hint``, e.g. the camera's ``-y`` axis for an upright camera, to reject walls); a
floor with more inliers than the table wins too; a box top whose table holds less than
``min_fraction`` of the cloud is taken for the table.

A cloud with no table
---------------------
The largest plane of a cloud without a table is an object's face (or coplanar faces of
several). :func:`table_frame` refuses it (:func:`not_a_table`: narrower than
:data:`FACE_MAX_EXTENT` with more points behind it than in front, where a table has the
objects in front of it) with a :class:`~ssp.errors.TableNotFoundError` that says so: the
frame fails rather than getting a world frame, and gravity, along that face (another face
next frame: the objects would churn). Falling back to the camera frame is no answer either:
the physics needs to know where down is, and a guess would be as wrong, silently.

Why not a library: open3d's ``segment_plane`` would pull a large binary dependency (~460 MB with
its Python dependencies, needs glibc >= 2.35) for one function; scikit-learn's
``RANSACRegressor`` fits a height field ``z = f(x, y)`` (not a plane in 3-D, and fails for planes
seen edge-on in the camera frame) and scores one sample at a time. Here all samples are scored
in one array operation, and no BLAS call touches the whole cloud (see :func:`_near`): about
25-30 ms for a 640 x 480 cloud.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from ssp.errors import PerceptionError, TableNotFoundError
from ssp.geometry import invert, make_pose
from ssp.kdtree import KDTree

__all__ = [
    "FACE_BEYOND_FRACTION",
    "FACE_MAX_EXTENT",
    "MAX_SUPPORT_STEP",
    "Plane",
    "TableTracker",
    "T_world_cam_from_plane",
    "fit_plane",
    "not_a_table",
    "table_frame",
]

log = logging.getLogger(__name__)

#: Largest height (m) of a parallel plane above the support that is taken for an object's top.
MAX_SUPPORT_STEP = 0.35
#: A fitted plane narrower than this (m) with more points behind it than in front is an
#: object's face, not a table (:func:`not_a_table`).
FACE_MAX_EXTENT = 0.5
#: ... when at least this fraction of the cloud lies behind it.
FACE_BEYOND_FRACTION = 0.1

_SUBSET = 2000  # points every RANSAC sample is scored on
_TOP = 5  # best samples re-scored on all points
_LOCAL_K = 32  # neighbours of a local sample's anchor (in the subset)
_REFITS = 10  # most least-squares refit rounds (they stop once the inliers stop growing)
_REFIT_MAX = 20000  # most inliers a refit uses
_MAX_PLANES = 3  # qualifying planes found by the sequential search
_MAX_ATTEMPTS = 4  # planes tried by the sequential search
_RETRIES = 2  # fresh RANSAC batches before giving up without a plane
_PARALLEL_DEG = 10.0  # planes closer than this in angle are parallel
_STRAIGHT_DOWN = 1e-3  # |view direction projected on the table| below this: looking straight down


@dataclass(eq=False)
class Plane:
    """A plane ``normal . p + offset = 0`` (m) and the points that lie on it.

    Attributes:
        normal: ``(3,)`` unit normal.
        offset: ``d`` (m); ``-offset`` is the signed distance of the plane from the origin.
        inliers: ``(N,)`` bool, the points of the fitted cloud within ``distance`` of the plane.
    """

    normal: np.ndarray
    offset: float
    inliers: np.ndarray

    @property
    def n_inliers(self) -> int:
        """Number of inliers."""
        return int(np.count_nonzero(self.inliers))

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance ``(N,)`` (m) of ``points`` ``(N, 3)``, positive on the normal's side."""
        return np.asarray(points, dtype=float) @ self.normal + self.offset


def fit_plane(
    points: np.ndarray,
    *,
    distance: float = 0.006,
    iterations: int = 300,
    seed: int = 0,
    min_inliers: int = 500,
    min_fraction: float = 0.1,
    up_hint: np.ndarray | None = None,
    max_tilt_deg: float = 45.0,
    min_extent: float = 0.15,
) -> Plane:
    """The support plane (table top) of a cloud; see the module docstring for the algorithm.

    Args:
        points: ``(N, 3)`` cloud (m), any frame; non-finite rows are ignored (never inliers).
        distance: inlier threshold (m), distance from the plane.
        iterations: RANSAC samples (all scored at once).
        seed: random seed; the result is deterministic for a seed.
        min_inliers: fewest inliers of a qualifying plane.
        min_fraction: fewest inliers of a qualifying plane, as a fraction of the finite points.
        up_hint: ``(3,)`` rough table normal in the cloud's frame (need not be unit); planes
            tilted more than ``max_tilt_deg`` from it are rejected.
        max_tilt_deg: largest angle (deg) between a plane's normal and ``up_hint``.
        min_extent: smallest width (m) of a qualifying plane's inliers (``sqrt(12 lambda)``,
            ``lambda`` their smaller in-plane variance): rejects the faces of single objects,
            which are planes too, when there is no table in the cloud.

    Returns:
        The :class:`Plane`; its normal points along ``up_hint`` when given, else toward the
        origin of the cloud's frame (the camera, for a camera-frame cloud).

    Raises:
        TableNotFoundError: too few points, or no plane qualifies.
    """
    pts, finite = _finite_points(points)
    distance, iterations = float(distance), int(iterations)
    if not distance > 0 or iterations < 1:
        raise ValueError(f"need distance > 0 and iterations >= 1, got {distance}, {iterations}")
    up = _unit(up_hint, "up_hint") if up_hint is not None else None
    cos_tilt = math.cos(math.radians(float(max_tilt_deg)))
    m = len(pts)
    need = max(int(min_inliers), math.ceil(float(min_fraction) * m), 3)
    if m < need:
        raise TableNotFoundError(
            f"too few points to find a table: {m} finite points (of {len(finite)}), a table "
            f"needs at least {need} inliers (min_inliers={min_inliers}, "
            f"min_fraction={min_fraction})"
        )
    rng = np.random.default_rng(seed)
    planes, rejected = _find_planes(
        pts, rng, distance, iterations, up, cos_tilt, need, float(min_extent)
    )
    if not planes:
        raise TableNotFoundError(
            _not_found(rejected, m, need, distance, min_extent, up, max_tilt_deg)
            + f" (min_inliers={min_inliers}, min_fraction={min_fraction})"
        )
    support = _choose_support(planes, up, distance)
    inliers = np.zeros(len(finite), dtype=bool)
    inliers[finite] = support.mask
    log.debug(
        "table plane: normal %s, offset %.4f m, %d inliers of %d points",
        np.round(support.n, 4),
        support.d,
        support.count,
        m,
    )
    return Plane(normal=support.n, offset=support.d, inliers=inliers)


def T_world_cam_from_plane(plane: Plane, points_cam: np.ndarray) -> np.ndarray:
    """Camera pose ``T_world_cam`` (4, 4) in the frame the table defines.

    World z is the plane normal, oriented toward the camera (the origin of ``points_cam``'s
    frame, which is above the table); the world origin is the inlier centroid projected onto
    the plane; world x is the camera's viewing direction (its z axis) projected onto the plane,
    or its x axis when it looks straight down; world y completes a right-handed frame.

    Args:
        plane: a plane fitted to ``points_cam`` (its ``inliers`` index them).
        points_cam: ``(N, 3)`` the cloud in the camera frame (m).
    """
    p = np.asarray(points_cam, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) != len(plane.inliers):
        raise PerceptionError(
            f"points_cam must have shape ({len(plane.inliers)}, 3) (the cloud the plane was "
            f"fitted to), got {p.shape}"
        )
    idx = np.flatnonzero(np.asarray(plane.inliers, dtype=bool))
    if len(idx) == 0:
        raise PerceptionError("the plane has no inliers: cannot place the world origin")
    n = np.asarray(plane.normal, dtype=float)
    n = n / np.linalg.norm(n)
    d = float(plane.offset)
    if d < 0:  # the camera (origin) must be on the positive side
        n, d = -n, -d
    if d < 1e-6:
        raise PerceptionError("the camera lies in the table plane: cannot tell up from down")
    c = np.array([p[idx, j].mean() for j in range(3)])  # column-wise: ~5x faster than axis=0
    origin = c - (n @ c + d) * n
    x = _in_plane(np.array([0.0, 0.0, 1.0]), n)
    if x is None:  # looking straight down: camera x is in the plane
        x = _in_plane(np.array([1.0, 0.0, 0.0]), n)
    y = np.cross(n, x)
    return invert(make_pose(np.column_stack([x, y, n]), origin))


def table_frame(points_cam: np.ndarray, **kw) -> tuple[np.ndarray, Plane]:
    """``(T_world_cam (4, 4), plane)``: :func:`fit_plane` of a camera-frame cloud ``(N, 3)``
    (m; keywords are passed on) and :func:`T_world_cam_from_plane`.

    Raises:
        TableNotFoundError: no plane qualifies, or the plane found is not a support but the
            face of an object (:func:`not_a_table`): the frame is refused rather than given a
            world frame (and gravity) along an object's face, which would change from frame
            to frame with the face found.
    """
    plane = fit_plane(points_cam, **kw)
    doubt = not_a_table(points_cam, plane, float(kw.get("distance", 0.006)))
    if doubt is not None:
        raise TableNotFoundError(doubt)
    return T_world_cam_from_plane(plane, points_cam), plane


def not_a_table(points_cam: np.ndarray, plane: Plane, distance: float = 0.006) -> str | None:
    """Why the plane fitted to a camera-frame cloud is the face of an object and not a table,
    or None when it may be the table.

    Objects stand on a table, between it and the camera; the rest of an object lies behind
    its own face. So the plane is taken for an object's face when more of the points lie
    beyond it (away from the camera, more than ``2 distance``) than in front of it, those are
    at least :data:`FACE_BEYOND_FRACTION` of the cloud, and the plane is narrower than
    :data:`FACE_MAX_EXTENT` (an object's size, not a table's; a floor seen past a wide table's
    edge is beyond it too).
    """
    pts, finite = _finite_points(points_cam)
    inl = np.asarray(plane.inliers, dtype=bool)[finite]
    if len(pts) == 0 or np.count_nonzero(inl) < 3:
        return None
    n = np.asarray(plane.normal, dtype=float)
    n, d = n / np.linalg.norm(n), float(plane.offset) / float(np.linalg.norm(n))
    if d < 0:  # the camera (origin) on the positive side
        n, d = -n, -d
    sd = pts @ n + d
    beyond = float(np.count_nonzero(sd < -2 * distance)) / len(pts)
    front = float(np.count_nonzero(sd > 2 * distance)) / len(pts)
    _, _, extent = _inlier_fit(pts, inl)
    if beyond > front and beyond >= FACE_BEYOND_FRACTION and extent < FACE_MAX_EXTENT:
        return (
            f"no table: the plane found ({np.count_nonzero(inl)} points, "
            f"{100 * np.count_nonzero(inl) / len(pts):.0f} % of the cloud, {extent:.2f} m wide) "
            f"has {100 * beyond:.0f} % of the points behind it and {100 * front:.0f} % in front "
            "of it: it is the face of an object, not a table the objects stand on; without a "
            "table ssp cannot tell where gravity points: give the camera pose (scene.json "
            "T_world_cam, a BOP scene's cam_R_w2c/cam_t_w2c, a bag's --world-frame) or a cloud "
            "that shows the table"
        )
    return None


# ------------------------------------------------------------------------------------------
# helpers


def _finite_points(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(finite rows (M, 3) float64, finite mask (N,))``; PerceptionError on a wrong shape."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise PerceptionError(f"points must have shape (N, 3), got {p.shape}")
    finite = np.isfinite(p[:, 0] + p[:, 1] + p[:, 2])  # NaN and inf propagate; faster than all()
    if finite.all():
        return np.ascontiguousarray(p), finite
    return p.take(np.flatnonzero(finite), axis=0), finite


def _not_found(
    best: _Candidate | None,
    m: int,
    need: int,
    distance: float,
    min_extent: float,
    up: np.ndarray | None,
    max_tilt_deg: float,
) -> str:
    """The message of a failed search: what the best plane had and what a table needs."""
    tilt = f" within {max_tilt_deg:g} deg of up_hint {np.round(up, 3)}" if up is not None else ""
    if best is None:
        return f"no table plane found: no plane{tilt} in {m} points"
    return (
        f"no table plane found: the best plane{tilt} has {best.count} inliers "
        f"({100.0 * best.count / m:.1f} % of {m} points) within {1000 * distance:g} mm and is "
        f"{best.extent:.3f} m wide; a table needs at least {need} inliers and a width of at "
        f"least {min_extent:g} m"
    )


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    """``v`` (3,) normalised; ValueError when it is not a finite non-zero 3-vector."""
    v = np.asarray(v, dtype=float).reshape(-1)
    norm = float(np.linalg.norm(v)) if v.shape == (3,) else 0.0
    if not (math.isfinite(norm) and norm > 1e-12):
        raise ValueError(f"{what} must be a finite non-zero 3-vector, got {v}")
    return v / norm


def _in_plane(v: np.ndarray, n: np.ndarray) -> np.ndarray | None:
    """Unit projection of ``v`` (3,) onto the plane of unit normal ``n``; None if ~parallel."""
    w = v - (v @ n) * n
    norm = float(np.linalg.norm(w))
    return w / norm if norm > _STRAIGHT_DOWN else None


@dataclass(eq=False)
class _Candidate:
    """A plane found by the sequential search: ``n . p + d = 0``, inlier mask ``(M,)`` over the
    finite points, inlier centroid ``(3,)``, inlier count and in-plane extent (m)."""

    n: np.ndarray
    d: float
    mask: np.ndarray
    centroid: np.ndarray
    count: int
    extent: float

    def oriented(self, up: np.ndarray | None) -> _Candidate:
        """This plane with its normal along ``up``, or toward the origin when ``up`` is None."""
        flip = (self.n @ up < 0) if up is not None else (self.d < 0)
        if not flip:
            return self
        return replace(self, n=-self.n, d=-self.d)


def _find_planes(
    pts: np.ndarray,
    rng: np.random.Generator,
    distance: float,
    iterations: int,
    up: np.ndarray | None,
    cos_tilt: float,
    need: int,
    min_extent: float,
) -> tuple[list[_Candidate], _Candidate | None]:
    """Sequential RANSAC: up to :data:`_MAX_PLANES` qualifying planes in order of discovery,
    and the largest plane rejected for its size (for error messages).

    Planes too small in extent, or tilted too far by the refit, are removed from the search
    and it goes on (up to :data:`_MAX_ATTEMPTS` planes in all); it stops at the first plane
    with too few inliers, since RANSAC finds the largest remaining plane first, but before
    giving up without any plane it draws fresh samples up to :data:`_RETRIES` times.
    """
    planes: list[_Candidate] = []
    rejected: _Candidate | None = None
    xyz = np.ascontiguousarray(pts.T)  # (3, M): distances by contiguous element-wise passes
    remaining = np.arange(len(pts))
    attempts, retries = 0, _RETRIES
    while attempts < _MAX_ATTEMPTS and len(planes) < _MAX_PLANES and len(remaining) >= need:
        if len(remaining) == len(pts):
            rem_pts, rem_xyz = pts, xyz
        else:
            rem_pts, rem_xyz = pts.take(remaining, axis=0), xyz.take(remaining, axis=1)
        sample = _ransac(rem_pts, rem_xyz, rng, distance, iterations, up, cos_tilt)
        if sample is None:
            break
        plane = _refine(pts, xyz, *sample, distance)
        tilted = up is not None and abs(plane.n @ up) < cos_tilt
        if plane.count >= need and plane.extent >= min_extent and not tilted:
            planes.append(plane)
        elif not tilted and (rejected is None or plane.count > rejected.count):
            rejected = plane
        if plane.count < need:
            if planes or retries == 0:
                break
            retries -= 1
            log.debug("table: best plane has %d inliers, drawing new samples", plane.count)
            continue
        attempts += 1
        remaining = remaining[~plane.mask[remaining]]
    return planes, rejected


def _ransac(
    pts: np.ndarray,
    xyz: np.ndarray,
    rng: np.random.Generator,
    distance: float,
    iterations: int,
    up: np.ndarray | None,
    cos_tilt: float,
) -> tuple[np.ndarray, float] | None:
    """Best 3-point plane ``(normal, offset)`` of ``pts`` (M, 3) (``xyz`` is its transpose), or
    None if every sample is degenerate or too tilted."""
    m = len(pts)
    sub = pts[rng.choice(m, size=min(m, _SUBSET), replace=False)]
    n_local = iterations // 2
    a, b, c = _global_samples(pts, rng, iterations - n_local)
    la, lb, lc = _local_samples(sub, rng, n_local)
    a, b, c = np.vstack([a, la]), np.vstack([b, lb]), np.vstack([c, lc])
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12
    normals = normals / np.where(ok, norm, 1.0)[:, None]
    if up is not None:
        ok &= np.abs(normals @ up) >= cos_tilt
    if not ok.any():
        return None
    normals, offsets = normals[ok], -np.einsum("ij,ij->i", normals[ok], a[ok])
    # einsum's own loop, not BLAS: see _near
    score = np.count_nonzero(
        np.abs(np.einsum("sk,hk->sh", sub, normals) + offsets) < distance, axis=0
    )
    top = np.argsort(-score, kind="stable")[:_TOP]
    full = [np.count_nonzero(_near(xyz, normals[i], offsets[i], distance)) for i in top]
    i = top[int(np.argmax(full))]
    return normals[i], float(offsets[i])


def _global_samples(
    pts: np.ndarray, rng: np.random.Generator, count: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` triples of points drawn uniformly from ``pts``, as three ``(count, 3)``."""
    idx = rng.integers(0, len(pts), size=(count, 3))
    return pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]


def _local_samples(
    sub: np.ndarray, rng: np.random.Generator, count: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` triples: a random anchor of ``sub`` and two of its nearest neighbours."""
    k = min(_LOCAL_K, len(sub))
    if count == 0 or k < 3:
        empty = np.empty((0, 3))
        return empty, empty, empty
    anchors = rng.integers(0, len(sub), size=count)
    _, nbr = KDTree(sub).query(sub[anchors], k=k)
    cols = rng.integers(1, k, size=(count, 2))
    rows = np.arange(count)
    return sub[anchors], sub[nbr[rows, cols[:, 0]]], sub[nbr[rows, cols[:, 1]]]


def _refine(
    pts: np.ndarray, xyz: np.ndarray, n: np.ndarray, d: float, distance: float
) -> _Candidate:
    """Least-squares refits of a plane on its inliers in ``pts`` (M, 3) (``xyz`` is its
    transpose), each followed by a new inlier pass, until the inlier count changes by less than
    0.1 % (at most :data:`_REFITS` rounds)."""
    mask = _near(xyz, n, d, distance)
    count = int(np.count_nonzero(mask))
    for _ in range(_REFITS):
        if count < 3:
            break
        c, n_fit, _ = _inlier_fit(pts, mask)
        n_fit = n_fit if n_fit @ n >= 0 else -n_fit
        d_fit = float(-(n_fit @ c))
        n, d = n_fit, d_fit
        mask = _near(xyz, n, d, distance)
        new_count = int(np.count_nonzero(mask))
        converged = abs(new_count - count) <= 1e-3 * count
        count = new_count
        if converged:
            break
    c, _, extent = _inlier_fit(pts, mask) if count >= 3 else (-d * n, n, 0.0)
    return _Candidate(n, d, mask, c, int(np.count_nonzero(mask)), extent)


def _inlier_fit(pts: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(centroid (3,), unit normal (3,), extent (m))`` of the least-squares plane of the
    points ``pts[mask]`` (at least 3).

    The fit uses at most :data:`_REFIT_MAX` of them (an even stride): the normal of 20k points
    spread over a table is already exact to ~1e-4 rad. The extent is ``sqrt(12 lambda)``,
    ``lambda`` the smaller of the two in-plane variances: the width of the narrow side of a
    uniformly covered rectangle.
    """
    idx = np.flatnonzero(mask)
    inl = pts.take(idx[:: -(-len(idx) // _REFIT_MAX)], axis=0)
    c = inl.mean(axis=0)
    x = inl - c
    vals, vecs = np.linalg.eigh(np.einsum("ni,nj->ij", x, x) / len(x))
    return c, np.ascontiguousarray(vecs[:, 0]), math.sqrt(12.0 * max(float(vals[1]), 0.0))


def _near(xyz: np.ndarray, n: np.ndarray, d: float, distance: float) -> np.ndarray:
    """``(M,)`` bool: which points ``xyz`` (3, M) lie within ``distance`` of plane ``(n, d)``.

    Element-wise on contiguous rows rather than a BLAS product: multi-threaded OpenBLAS is
    10-20x slower for this on a loaded 2-core machine unless ``OMP_NUM_THREADS=1`` (and its
    spinning threads then slow everything else down), so this module avoids BLAS calls.
    """
    r = n[0] * xyz[0]
    r += n[1] * xyz[1]
    r += n[2] * xyz[2]
    r += d
    np.abs(r, out=r)
    return r < distance


def _choose_support(planes: list[_Candidate], up: np.ndarray | None, distance: float) -> _Candidate:
    """The support among qualifying planes (see the module docstring), oriented up: along
    ``up`` when given, else toward the origin."""
    planes = [p.oriented(up) for p in planes]
    main = max(planes, key=lambda p: p.count)
    cos_par = math.cos(math.radians(_PARALLEL_DEG))
    lower = [
        p
        for p in planes
        if p is not main
        and p.n @ main.n >= cos_par
        and 2 * distance < float(p.n @ main.centroid + p.d) <= MAX_SUPPORT_STEP
    ]
    if not lower:
        return main
    best = max(lower, key=lambda p: p.count)
    log.info(
        "table: the largest plane (%d inliers) lies %.3f m above a parallel plane with %d "
        "inliers; taking it for an object's top and the lower plane for the support",
        main.count,
        float(best.n @ main.centroid + best.d),
        best.count,
    )
    return best


# ------------------------------------------------------------------------------------------
# a world frame that stays put while the camera does


class TableTracker:
    """The world frame of a camera with no pose given, from the table plane, kept fixed while
    the table stays where it was.

    Each frame's table is fitted (:func:`table_frame`); while the fitted plane agrees with the
    kept one (normals within ``max_angle_deg``, and the kept world origin within
    ``max_offset`` m of the new plane), the kept ``T_world_cam`` is used again, so a static
    camera gives one world frame for the whole sequence (a frame-by-frame fit moves the world
    origin by the fit's noise, and every object with it). When the plane moved (the camera
    moved), the new fit is kept and :attr:`changes` counts it.
    """

    def __init__(self, distance: float, max_angle_deg: float = 1.0, max_offset: float = 0.005):
        self.distance = float(distance)
        self.max_angle_deg = float(max_angle_deg)
        self.max_offset = float(max_offset)
        self.T_world_cam: np.ndarray | None = None
        self.changes = 0

    def update(self, points_cam: np.ndarray) -> tuple[np.ndarray, bool]:
        """``(T_world_cam (4, 4), moved)`` for a camera-frame cloud ``(N, 3)`` (m); ``moved``:
        the world frame was refitted (first frame: False). PerceptionError when no table."""
        T_new, plane = table_frame(points_cam, distance=self.distance)
        if self.T_world_cam is None:
            self.T_world_cam = T_new
            return T_new, False
        T_cw_old = np.linalg.inv(self.T_world_cam)
        up_old = self.T_world_cam[2, :3]  # world z in camera coordinates (row 2 of R_wc)
        up_new = T_new[2, :3]
        angle = np.degrees(np.arccos(np.clip(float(up_old @ up_new), -1.0, 1.0)))
        origin_cam = T_cw_old[:3, 3]  # the kept world origin, in camera coordinates
        n = np.asarray(plane.normal, dtype=float)
        offset = abs(float(n @ origin_cam + plane.offset)) / float(np.linalg.norm(n))
        if angle <= self.max_angle_deg and offset <= self.max_offset:
            return self.T_world_cam, False
        self.T_world_cam = T_new
        self.changes += 1
        return T_new, True
