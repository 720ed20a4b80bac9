"""Overlap-volume estimate of the collision term (paper Eq. 10).

The collision energy of an object is ``e_C = (d / eps_d) * (v_c / v_t)``: ``d`` is its
penetration depth, ``eps_d`` its diameter and ``v_c / v_t`` the fraction of its volume that lies
inside other objects (or inside the table). This module estimates that fraction: the object's
interior sample points (:attr:`ObjectModel.interior_points`, a regular grid inside the solid),
placed at its pose, are tested against the other objects' convex parts (the shapes the physics
engine collides with) and against the table, the half-space ``z < 0`` of the world frame (the
table top is the plane ``z = 0``). The fraction of points found inside something is the
estimate of ``v_c / v_t`` (the paper suggests an oriented-bounding-box intersection; DESIGN
section 4 allows this estimate).

A point ``p`` (metres, in a model's frame) is inside a convex part with facet planes
``n_k . p + b_k = 0`` (outward unit normals ``n_k``) when ``n_k . p + b_k <= tol`` for every
facet ``k``: ``tol`` (m) is a signed margin, positive to grow the solids, negative to shrink them.

Limits: the interior grid has ~4 mm spacing (``library.interior_spacing``), so the estimate has a
resolution of roughly one grid cell; in particular overlaps much thinner than the spacing read as
0. That is intended: the solver's resting penetration (~0.02 mm) must not count as a collision.
Only the convex parts of the *other* object are used (their union approximates its mesh), while
the points of the object itself come from its true mesh.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from ssp.jit import kernel_array, njit

if TYPE_CHECKING:
    import trimesh

    from ssp.library.model import ObjectModel

__all__ = [
    "HullSet",
    "load_kernels",
    "overlap_fraction_table",
    "overlap_fractions",
    "same_volume",
]

#: Decimals used to merge coplanar hull facets (Qhull triangulates each planar face).
_PLANE_DECIMALS = 9


def _bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius (m) of a sphere enclosing ``points`` (N, 3) (AABB centre)."""
    if len(points) == 0:
        return np.zeros(3), -np.inf
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    radius = float(np.sqrt(((points - centre) ** 2).sum(axis=1).max()))
    return centre, radius


class HullSet:
    """Half-space form of one model's convex parts (built once per model and cached).

    Attributes:
        planes: list, one ``(F_k, 4)`` float64 array per part: rows ``(n_x, n_y, n_z, b)`` with
            outward unit normal ``n`` and offset ``b`` (m); inside is ``n . p + b <= 0``.
        part_centres: (P, 3) bounding-sphere centres of the parts, m, model frame.
        part_radii: (P,) bounding-sphere radii, m.
        centre, radius: bounding sphere of all parts together (``radius = -inf`` when there
            are no parts).

    Degenerate parts (flat, fewer than 4 points: no volume) are dropped; they contain nothing.
    """

    _cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def __init__(self, convex_parts: Iterable[trimesh.Trimesh]):
        planes: list[np.ndarray] = []
        centres: list[np.ndarray] = []
        radii: list[float] = []
        all_vertices: list[np.ndarray] = []
        for part in convex_parts:
            v = np.asarray(part.vertices, dtype=np.float64)
            if len(v) < 4:
                continue
            try:
                eq = ConvexHull(v).equations
            except (QhullError, ValueError):
                continue  # flat or degenerate: zero volume
            # Qhull splits planar faces into triangles: keep one row per distinct plane
            eq = np.unique(np.round(eq, _PLANE_DECIMALS), axis=0)
            planes.append(np.ascontiguousarray(eq))
            c, r = _bounding_sphere(v)
            centres.append(c)
            radii.append(r)
            all_vertices.append(v)
        self.planes = planes
        self.part_centres = np.array(centres, dtype=np.float64).reshape(-1, 3)
        self.part_radii = np.array(radii, dtype=np.float64)
        self.centre, self.radius = _bounding_sphere(
            np.concatenate(all_vertices) if all_vertices else np.zeros((0, 3))
        )
        # the planes of every part in one array, part k's rows start[k]:start[k + 1] (kernel)
        self._planes = np.ascontiguousarray(
            np.concatenate(planes) if planes else np.zeros((0, 4)), dtype=np.float64
        )
        self._start = np.concatenate([[0], np.cumsum([len(eq) for eq in planes])]).astype(np.int64)

    @classmethod
    def of(cls, model: ObjectModel) -> HullSet:
        """The (cached) :class:`HullSet` of ``model.convex_parts``.

        The cache holds models weakly and compares them by identity (``ObjectModel`` is immutable
        and hashes by identity), so the hulls are computed once per model object.
        """
        hs = cls._cache.get(model)
        if hs is None:
            hs = cls(model.convex_parts)
            cls._cache[model] = hs
        return hs

    @property
    def n_parts(self) -> int:
        """Number of (non-degenerate) convex parts."""
        return len(self.planes)

    def contains(self, points_local: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Which points lie inside any convex part.

        Args:
            points_local: (M, 3) points in the model frame, m.
            tol: margin, m: a point is inside a part when every ``n . p + b <= tol`` and it
                lies within the part's bounding sphere grown by ``max(tol, 0)`` (a grown part's
                sharp corners reach beyond it).

        Returns:
            (M,) bool.
        """
        p = kernel_array(np.asarray(points_local, dtype=np.float64).reshape(-1, 3))
        if len(p) == 0 or not self.planes:
            return np.zeros(len(p), dtype=bool)
        return _contains(
            p, self.centre, float(self.radius), self._planes, self._start,
            self.part_centres, self.part_radii, float(tol),
        )  # fmt: skip


def load_kernels() -> None:
    """Compile :meth:`HullSet.contains`' kernel, or load it from numba's cache
    (:class:`ssp.parser.SceneParser` does it when built, not in its first frame)."""
    z = np.zeros
    _contains(z((1, 3)), z(3), 1.0, z((1, 4)), z(2, dtype=np.int64), z((1, 3)), z(1), 0.0)


@njit
def _contains(p, centre, radius, planes, start, part_centres, part_radii, tol):
    """:meth:`HullSet.contains`, compiled: per point (model frame), inside the model's bounding
    sphere grown by ``max(tol, 0)``, inside a part's grown sphere, and then on the inner side
    (``n . p + b <= tol``) of every plane of that part (``planes[start[k]:start[k + 1]]``);
    the first part that holds it ends its search."""
    m = p.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    grow = max(tol, 0.0)
    reach = (radius + grow) ** 2
    for i in range(m):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        d0, d1, d2 = x - centre[0], y - centre[1], z - centre[2]
        if not d0 * d0 + d1 * d1 + d2 * d2 <= reach:
            continue
        for k in range(part_radii.shape[0]):
            e0, e1, e2 = x - part_centres[k, 0], y - part_centres[k, 1], z - part_centres[k, 2]
            r = part_radii[k] + grow
            if not e0 * e0 + e1 * e1 + e2 * e2 <= r * r:
                continue
            inside = True
            for f in range(start[k], start[k + 1]):
                if not planes[f, 0] * x + planes[f, 1] * y + planes[f, 2] * z + planes[f, 3] <= tol:
                    inside = False
                    break
            if inside:
                out[i] = True
                break
    return out


_sphere_cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _points_sphere(model: ObjectModel) -> tuple[np.ndarray, float]:
    """Cached bounding sphere of ``model.interior_points`` (model frame)."""
    s = _sphere_cache.get(model)
    if s is None:
        s = _bounding_sphere(np.asarray(model.interior_points, dtype=np.float64).reshape(-1, 3))
        _sphere_cache[model] = s
    return s


def _check_poses(poses: np.ndarray, n: int) -> np.ndarray:
    T = np.asarray(poses, dtype=np.float64)
    if T.shape != (n, 4, 4):
        raise ValueError(f"poses: expected shape ({n}, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("poses: contain NaN or infinite values")
    return T


def overlap_fraction_table(model: ObjectModel, pose: np.ndarray, *, tol: float = 0.0) -> float:
    """Fraction of ``model``'s interior points below the table plane at ``pose``.

    Args:
        model: the object.
        pose: (4, 4) ``T_world_obj`` (m); the table top is the world plane ``z = 0``.
        tol: margin, m: a point counts when its world ``z <= tol``.

    Returns:
        Fraction in [0, 1] (the table part of ``v_c / v_t`` in Eq. 10); 0 without interior points.
    """
    T = _check_poses(np.asarray(pose)[None], 1)[0]
    pts = np.asarray(model.interior_points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0
    z = pts @ T[2, :3] + T[2, 3]
    return float(np.count_nonzero(z <= tol)) / len(pts)


def overlap_fractions(
    models: Sequence[ObjectModel],
    poses: np.ndarray,
    *,
    table: bool = True,
    pairs: Iterable[tuple[int, int]] | None = None,
    tol: float = 0.0,
) -> np.ndarray:
    """Fraction ``v_c / v_t`` (Eq. 10) of each object's volume inside other objects or the table.

    For object ``i`` it is the fraction of its interior points that lie inside a convex part of
    another object ``j`` or (``table=True``) below the table plane ``z = 0``. A point inside
    several others counts once.

    Args:
        models: n object models.
        poses: (n, 4, 4) ``T_world_obj``, m.
        table: also count points below the table plane ``z = 0`` (world frame).
        pairs: optional iterable of index pairs ``(i, j)`` to test, e.g. the pairs in contact.
            A pair is unordered: ``i``'s points are tested against ``j`` and ``j``'s against
            ``i``. Default: all pairs. Either way pairs whose bounding spheres do not overlap
            are skipped (they cannot overlap).
        tol: margin, m: positive grows the other solids (and raises the table), negative
            shrinks them.

    Returns:
        (n,) float64 in [0, 1]; 0 for objects without interior points.

    The cost is one matmul per tested pair and direction to move ``i``'s points into ``j``'s
    frame, then, compiled, the planes of ``j``'s convex parts whose bounding spheres hold each
    point (:meth:`HullSet.contains`).
    """
    n = len(models)
    T = _check_poses(poses, n)
    out = np.zeros(n, dtype=np.float64)
    if n == 0:
        return out
    hulls = [HullSet.of(m) for m in models]
    local = [np.asarray(m.interior_points, dtype=np.float64).reshape(-1, 3) for m in models]
    R = T[:, :3, :3]
    t = T[:, :3, 3]

    # world bounding spheres: of the interior points (the tested side) and of the hulls
    p_sph = [_points_sphere(m) for m in models]
    p_centre = np.array([R[i] @ c + t[i] for i, (c, _) in enumerate(p_sph)])
    p_radius = np.array([r for _, r in p_sph])
    h_centre = np.array([R[i] @ h.centre + t[i] for i, h in enumerate(hulls)])
    h_radius = np.array([h.radius for h in hulls])
    margin = max(tol, 0.0)

    # ordered (points of i, solid j) tests
    if pairs is None:
        targets = _all_targets(p_centre, p_radius, h_centre, h_radius, margin)
    else:
        targets = _pair_targets(pairs, n, p_centre, p_radius, h_centre, h_radius, margin)

    for i in range(n):
        pts = local[i]
        k = len(pts)
        if k == 0:
            continue
        covered = np.zeros(k, dtype=bool)
        if table and p_centre[i, 2] - p_radius[i] <= tol:
            covered |= pts @ R[i, 2] + t[i, 2] <= tol
        _cover(covered, pts, i, targets[i], R, t, hulls, tol)
        out[i] = np.count_nonzero(covered) / k
    return out


def _all_targets(
    p_centre: np.ndarray,
    p_radius: np.ndarray,
    h_centre: np.ndarray,
    h_radius: np.ndarray,
    margin: float,
) -> list[list[int]]:
    """For each object ``i``, the other objects ``j`` whose hull sphere (``h_centre``,
    ``h_radius``) meets ``i``'s points sphere (``p_centre``, ``p_radius``) grown by ``margin``."""
    targets: list[list[int]] = [[] for _ in range(len(p_centre))]
    d = np.linalg.norm(p_centre[:, None, :] - h_centre[None, :, :], axis=-1)
    ok = d <= p_radius[:, None] + h_radius[None, :] + margin
    np.fill_diagonal(ok, False)
    for i, j in zip(*np.nonzero(ok), strict=True):
        targets[int(i)].append(int(j))
    return targets


def _pair_targets(
    pairs: Iterable[tuple[int, int]],
    n: int,
    p_centre: np.ndarray,
    p_radius: np.ndarray,
    h_centre: np.ndarray,
    h_radius: np.ndarray,
    margin: float,
) -> list[list[int]]:
    """:func:`_all_targets` among the unordered ``pairs`` only (each direction once)."""
    targets: list[list[int]] = [[] for _ in range(n)]
    seen: set[tuple[int, int]] = set()
    for a, b in pairs:
        a, b = int(a), int(b)
        if not (0 <= a < n and 0 <= b < n):
            raise IndexError(f"pair ({a}, {b}) out of range for {n} objects")
        if a == b:
            continue
        for i, j in ((a, b), (b, a)):
            if (i, j) in seen:
                continue
            seen.add((i, j))
            dist = float(np.linalg.norm(p_centre[i] - h_centre[j]))
            if dist <= p_radius[i] + h_radius[j] + margin:
                targets[i].append(j)
    return targets


def _cover(
    covered: np.ndarray,
    pts: np.ndarray,
    i: int,
    targets: list[int],
    R: np.ndarray,
    t: np.ndarray,
    hulls: Sequence[HullSet],
    tol: float,
) -> None:
    """Mark in ``covered`` the points ``pts`` of object ``i`` (its frame) that lie inside a
    convex part of one of the objects ``targets`` (poses ``R``, ``t``), in place."""
    for j in targets:
        idx = np.flatnonzero(~covered)
        if len(idx) == 0:
            break
        # i's points in j's frame: R_j^T (R_i p + t_i - t_j), one matmul
        R_ji = R[j].T @ R[i]
        t_ji = R[j].T @ (t[i] - t[j])
        q = pts[idx] @ R_ji.T + t_ji
        covered[idx[hulls[j].contains(q, tol)]] = True


def same_volume(model: ObjectModel, T_a: np.ndarray, T_b: np.ndarray, fraction: float) -> bool:
    """Do two poses of ``model`` share at least ``fraction`` of its volume (interior points at
    ``T_a`` inside the convex parts at ``T_b``)? Two objects cannot share a volume, so two such
    hypotheses are alternative poses of one object (``temporal.merge_overlap``)."""
    if np.linalg.norm(np.asarray(T_a)[:3, 3] - np.asarray(T_b)[:3, 3]) > model.diameter:
        return False
    frac = overlap_fractions([model, model], np.stack([T_a, T_b]), table=False, pairs=[(0, 1)])
    return bool(frac[0] >= fraction)
