"""Data-guiding forces (paper section IV-A: Eq. 13, ``eq:point_data_force``, and Eq. 14,
``eq:total_data_force``, the ``GenForce`` of Alg. 1; DESIGN section 4 "Data forces").

Every model surface sample ``p_c`` (world frame) is paired with its nearest point ``p_d`` of the
object's own scene segment. A pair closer than ``d_t`` pulls with the kernel

    f = (p_d - p_c) (d_t - r) / (d_t^2 / 4),   r = |p_d - p_c| <= d_t   (0 beyond d_t),  (13)

whose magnitude ``r (d_t - r) / (d_t^2/4)`` is 0 at r = 0, peaks at 1 for r = d_t / 2 and falls
smoothly back to 0 at r = d_t. The pairs are combined into a force at the centre of mass and a
torque about it,

    F = F_max / M * sum_i f_i,    tau = F_max / M * sum_i (p_c,i - p_cog) x f_i,  (14)

with M the number of (used) model samples and ``F_max = f m g`` (``ForcesConfig``:
``gravity_fraction`` f, ``max_distance`` d_t = 2 cm). The paper's maximum force is one constant;
here F_max is *proportional* to the mass (DESIGN section 4; the reference code multiplied by the
inverse mass, a bug), so every object is guided with the same acceleration scale;
``|F| <= F_max`` always, with equality only when every sample sits exactly d_t / 2 from its
target, all in the same direction.

Cost (notes/engines.md section 1): the nearest-neighbour queries dominate, not the arithmetic.
So a :class:`SegmentField` (one KD-tree per segment) is built once per frame, and
:class:`DataForces` can reuse its correspondences for ``refresh_every`` calls: in between, the
cached *world-frame targets* are kept and only the model samples move (batched matmul, a
hand-written cross product; no queries). The trade-off: between refreshes a sample is pulled
towards a fixed scene point, an ICP-like spring, rather than towards the nearest point of the
segment, so sliding along the segment's surface is slightly resisted, and samples that were
farther than d_t at the last refresh feel nothing until the next one. With the quasi-static
stepping of the simulation (about 0.1-0.3 mm per step) a cadence of a few steps changes little.
With a camera, only the samples facing it are queried (the others never pull). The wrench of
the matched pairs is one compiled call (``_wrenches``), bit-identical to the numpy expressions
it replaced: the same arithmetic per pair and numpy's summation order.

The KD-tree is pykdtree (measured 2-3x faster than scipy's cKDTree for 500 queries into 0.5k-20k
points, and 3x faster to build); OpenMP threading makes small queries 10-20x slower on few cores,
so it comes from :mod:`ssp.kdtree`, which sets ``OMP_NUM_THREADS`` to 1 unless already set. If
pykdtree is missing, scipy's cKDTree with ``workers=1`` is used.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ssp.config import ForcesConfig
from ssp.jit import njit, pairwise_sum
from ssp.library.model import ObjectModel

if TYPE_CHECKING:
    from ssp.kdtree import KDTree

    _PyKDTree: type[KDTree] | None
try:  # pragma: no branch
    from ssp.kdtree import KDTree as _PyKDTree
except ImportError:  # pragma: no cover - pykdtree is a dependency; scipy is the fallback
    _PyKDTree = None
from scipy.spatial import cKDTree

__all__ = ["DataForces", "SegmentField", "load_kernels", "point_pair_forces"]


def load_kernels() -> None:
    """Compile the wrench kernel of :meth:`DataForces.compute`, or load it from numba's cache
    (:class:`ssp.parser.SceneParser` does it when built, not in its first frame)."""
    z = np.zeros
    _wrenches(z((1, 3, 1)), z((1, 1)), z((1, 3, 1)), z((1, 3)), z(1, dtype=np.int64), z(1),
              0.02, z((1, 3)), z((1, 3)), z((6, 1)))  # fmt: skip


def point_pair_forces(p_c: np.ndarray, p_d: np.ndarray, max_distance: float) -> np.ndarray:
    """Kernel of Eq. 13 (``point_data_force``) for (M, 3) model points ``p_c``, targets ``p_d``.

    Returns (M, 3) ``(p_d - p_c) (d_t - r) / (d_t^2 / 4)`` for ``r <= d_t``, else 0 (unitless;
    magnitude 1 at ``r = d_t / 2``). Non-finite targets give 0.
    """
    p_c = np.asarray(p_c, dtype=float)
    p_d = np.asarray(p_d, dtype=float)
    diff = p_d - p_c
    r = np.sqrt((diff * diff).sum(axis=-1))
    ok = np.isfinite(r) & (r <= max_distance)
    w = np.where(ok, (max_distance - np.where(ok, r, 0.0)) / (max_distance**2 / 4.0), 0.0)
    return np.where(ok[..., None], diff, 0.0) * w[..., None]


def _check_points(points, what: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what}: expected shape (K, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{what}: contains NaN or infinite values")
    return np.ascontiguousarray(p)


class SegmentField:
    """Nearest-point look-up into one object's scene segment, built once per frame.

    Args:
        points: (K, 3) scene points of the segment, world frame, m. K = 0 is allowed (nothing
            is ever matched).
        max_distance: d_t; queries farther than this find nothing.
    """

    def __init__(self, points: np.ndarray, max_distance: float = 0.02) -> None:
        self.points = _check_points(points, "segment points")
        self.points.flags.writeable = False
        if not max_distance > 0:
            raise ValueError(f"max_distance must be > 0, got {max_distance}")
        self.max_distance = float(max_distance)
        k = len(self.points)
        if k == 0:
            self._tree = None
        elif _PyKDTree is not None:
            self._tree = _PyKDTree(self.points)
        else:  # pragma: no cover
            self._tree = cKDTree(self.points)

    def __len__(self) -> int:
        return len(self.points)

    def __repr__(self) -> str:
        return f"SegmentField({len(self)} points, d_t={self.max_distance:g} m)"

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest segment point of each query point (M, 3), within ``max_distance``.

        Returns ``(targets (M, 3), dist (M,))``. A point with no segment point within
        ``max_distance`` gets ``dist = inf`` and its own position as target (zero force).
        """
        return self._nearest(_check_points(points, "query points"))

    def _nearest(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`nearest` of (M, 3) finite, C-contiguous float points (not checked again)."""
        m = len(q)
        if self._tree is None or m == 0:
            return q.copy(), np.full(m, np.inf)
        if _PyKDTree is not None:
            dist, idx = self._tree.query(q, k=1, distance_upper_bound=self.max_distance)
        else:  # pragma: no cover
            tree = cast(cKDTree, self._tree)  # built by scipy when pykdtree is missing
            dist, idx = tree.query(q, k=1, distance_upper_bound=self.max_distance, workers=1)
        dist = np.asarray(dist, dtype=float)
        idx = np.asarray(idx, dtype=np.int64)
        hit = idx < len(self.points)
        targets = q.copy()
        targets[hit] = self.points[idx[hit]]
        dist = np.where(hit, dist, np.inf)
        return targets, dist


class DataForces:
    """Data-guiding wrenches for a fixed list of objects during one frame.

    Args:
        models: the objects' models, in the order of the poses given to :meth:`compute`
            (use the world's id order: ``[world.model_of(i) for i in world.ids]``).
        fields: one :class:`SegmentField` per object, or ``None`` for an object without a
            data force (e.g. undetected).
        config: d_t and f (default ``ForcesConfig()``).
        max_points: use at most this many surface samples per object (a fixed, seeded random
            subset, so results are deterministic). Cost is linear in the number of samples; the
            force is an average, so ~500 samples give nearly the same wrench as thousands.
            ``None``: all samples.
        refresh_every: query the segments on every ``refresh_every``-th call of
            :meth:`compute` (the first call always queries) and reuse the cached world-frame
            targets in between (see the module docstring for the trade-off). 1 = every call.
        masses: override the models' masses (kg), e.g. ``world.masses``.
        seed: seed of the sample subset.
        camera_position: (3,) world position of the camera, m, or None. When given, only the
            samples whose surface normal faces the camera pull (re-decided at each refresh):
            the far side of an object was never seen, and pulling it toward the nearest seen
            points would bias the pose toward the camera.
        sample_filter: optional ``f(k, points (M, 3), normals (M, 3)) -> bool (M,)``, world
            frame, called on the first refresh after each :meth:`reset`: samples where it is
            False do not pull (e.g. samples hidden behind another object,
            :meth:`ssp.visibility.CameraView.hidden_by_others`).

    Objects are packed into padded (n, 3, M_max) arrays once; :meth:`compute` is then a few
    batched numpy operations plus one KD-tree query per object on refresh calls.
    """

    def __init__(
        self,
        models: Sequence[ObjectModel],
        fields: Sequence[SegmentField | None],
        *,
        config: ForcesConfig | None = None,
        max_points: int | None = None,
        refresh_every: int = 1,
        masses: Sequence[float] | np.ndarray | None = None,
        seed: int = 0,
        camera_position: np.ndarray | None = None,
        sample_filter=None,
    ) -> None:
        self.sample_filter = sample_filter
        self._pose_targets: dict[int, np.ndarray] = {}
        self._filter_cache: dict[int, np.ndarray] = {}
        # sample_filter results and segment matches by the exact pose they were computed at
        # (pure functions of it: a hit returns what the computation would): the objects a
        # test does not move start every candidate's window at the same pose
        # (a (targets, distances) pair under "nearest", a bool mask under "filter")
        self._by_pose: dict[tuple[int, str, bytes], Any] = {}
        models = list(models)
        fields = list(fields)
        if len(models) != len(fields):
            raise ValueError(f"{len(models)} models but {len(fields)} segment fields")
        cfg = config if config is not None else ForcesConfig()
        self.max_distance = float(cfg.max_distance)
        self.gravity_fraction = float(cfg.gravity_fraction)
        refresh_every = int(refresh_every)
        if refresh_every < 1:
            raise ValueError(f"refresh_every must be >= 1, got {refresh_every}")
        self.refresh_every = refresh_every
        if max_points is not None and int(max_points) < 1:
            raise ValueError(f"max_points must be >= 1 or None, got {max_points}")
        n = len(models)
        self.n = n
        self.fields = fields
        m = np.array([mo.mass for mo in models], dtype=float) if masses is None else masses
        self.masses = np.asarray(m, dtype=float).reshape(n)

        rng = np.random.default_rng(seed)
        samples, normals = [], []
        for mo in models:
            p = np.asarray(mo.surface_points, dtype=float)
            nrm = np.asarray(mo.surface_normals, dtype=float)
            if max_points is not None and len(p) > int(max_points):
                keep = np.sort(rng.choice(len(p), int(max_points), replace=False))
                p, nrm = p[keep], nrm[keep]
            samples.append(p - np.asarray(mo.center_of_mass, dtype=float))
            normals.append(nrm)
        counts = np.array([len(p) for p in samples], dtype=int)
        self.counts = counts
        mmax = int(counts.max()) if n else 0
        # Samples relative to the COM, model axes, padded: (n, 3, M_max).
        q = np.zeros((n, 3, mmax))
        nq = np.zeros((n, 3, mmax))
        for k, (p, nrm) in enumerate(zip(samples, normals, strict=True)):
            q[k, :, : len(p)] = p.T
            nq[k, :, : len(p)] = nrm.T
        self._q = q
        self._normals = nq
        self.camera_position = (
            None if camera_position is None else np.asarray(camera_position, float).reshape(3)
        )
        self._com = np.array([np.asarray(mo.center_of_mass, float) for mo in models]).reshape(n, 3)
        self._active = np.array([f is not None and len(f) > 0 for f in fields], dtype=bool)
        self._targets = np.zeros((n, 3, mmax))
        self._matched = np.zeros((n, mmax))  # 1.0 where the cached target is a real match
        self._pairs = np.zeros((6, mmax))  # the kernel's per-pair forces and torques
        self._calls = 0

    def __repr__(self) -> str:
        return (
            f"DataForces({self.n} objects, {int(self._active.sum())} with data, "
            f"refresh_every={self.refresh_every})"
        )

    def set_pose_target(self, k: int, T_target: np.ndarray | None) -> None:
        """Pull object ``k`` toward a whole pose instead of its segment: every sample is paired
        with its own position at ``T_target`` (4, 4), world frame (the reference code's
        cached-ICP force mode: a spring in pose space, same kernel and F_max). ``None`` returns
        the object to nearest-point pairs. Kept across :meth:`reset`."""
        if T_target is None:
            self._pose_targets.pop(k, None)
            return
        T = np.asarray(T_target, dtype=float)
        mk = self.counts[k]
        R = T[:3, :3]
        com = R @ self._com[k] + T[:3, 3]
        self._pose_targets[k] = (R @ self._q[k, :, :mk]) + com[:, None]

    def reset(self) -> None:
        """Forget the cached correspondences: the next :meth:`compute` queries again (call it
        when a pose was changed discontinuously, e.g. a new hypothesis was set). The
        ``sample_filter`` is evaluated once after each reset and kept until the next."""
        self._calls = 0
        self._filter_cache.clear()

    def _world_samples(self, T: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sample offsets from the COM ``(len(idx), 3, M)`` and COMs ``(len(idx), 3)`` of the
        objects ``idx`` at poses ``T`` (n, 4, 4), world axes."""
        R = T[idx, :3, :3]
        r = R @ self._q[idx]
        cog = (R @ self._com[idx, :, None])[:, :, 0] + T[idx, :3, 3]
        return r, cog

    def _enabled_indices(self, enabled: np.ndarray | None) -> np.ndarray:
        if enabled is None:
            return np.arange(self.n)
        return np.flatnonzero(np.asarray(enabled, dtype=bool))

    def refresh(self, T_world_obj: np.ndarray, enabled: np.ndarray | None = None) -> None:
        """Query the segments at poses ``T_world_obj`` (n, 4, 4) and cache the targets
        (only for the ``enabled`` objects, (n,) bool, when given)."""
        T = self._check_poses(T_world_obj)
        idx = self._enabled_indices(enabled)
        r, cog = self._world_samples(T, idx)
        self._refresh(r, cog, T, idx)

    def _refresh(self, r: np.ndarray, cog: np.ndarray, T: np.ndarray, idx: np.ndarray) -> None:
        """Targets of the objects ``idx`` (their samples ``r``, ``cog`` from
        :meth:`_world_samples`); every other object's are dropped until the next refresh."""
        self._matched[:] = 0.0
        facing = None
        nw = (
            T[idx, :3, :3] @ self._normals[idx]
            if self.camera_position is not None or self.sample_filter
            else None
        )
        if self.camera_position is not None:
            to_cam = self.camera_position[None, :, None] - (r + cog[:, :, None])
            facing = (nw * to_cam).sum(axis=1) > 0.0
        if len(self._by_pose) > 50 * max(self.n, 1):
            self._by_pose.clear()
        for j, k in enumerate(idx.tolist()):
            mk = self.counts[k]
            if k in self._pose_targets:
                self._targets[k, :, :mk] = self._pose_targets[k]
                self._matched[k, :mk] = 1.0
                continue
            if not self._active[k]:
                continue
            pose = T[k].tobytes()
            pts = np.ascontiguousarray((r[j, :, :mk] + cog[j, :, None]).T)
            hit = self._by_pose.get((k, "nearest", pose))
            if hit is None:
                hit = self._by_pose[(k, "nearest", pose)] = self._match(k, pts, facing, j)
            tgt, dist = hit
            self._targets[k, :, :mk] = tgt.T
            ok = np.isfinite(dist)
            if facing is not None:
                ok &= facing[j, :mk]
            if self.sample_filter is not None and ok.any():
                keep = self._filter_cache.get(k)
                if keep is None:  # once per reset(): visibility changes little within a window
                    keep = self._by_pose.get((k, "filter", pose))
                    if keep is None:
                        assert nw is not None  # computed whenever there is a sample_filter
                        keep = np.asarray(self.sample_filter(k, pts, nw[j, :, :mk].T), dtype=bool)
                        self._by_pose[(k, "filter", pose)] = keep
                    self._filter_cache[k] = keep
                ok &= keep
            self._matched[k, :mk] = ok

    def _match(
        self, k: int, pts: np.ndarray, facing: np.ndarray | None, j: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """``fields[k]._nearest`` of the samples ``pts`` (M, 3) that face the camera (row ``j``
        of ``facing``; all without a camera). The others, which do not pull, keep their own
        position as target and an infinite distance, as an unmatched sample does."""
        field = self.fields[k]
        assert field is not None  # _refresh matches only the objects with data (_active)
        if facing is None:
            return field._nearest(pts)
        sel = np.flatnonzero(facing[j, : len(pts)])
        if len(sel) == len(pts):
            return field._nearest(pts)
        tgt = pts.copy()
        dist = np.full(len(pts), np.inf)
        if len(sel):
            tgt[sel], dist[sel] = field._nearest(np.ascontiguousarray(pts[sel]))
        return tgt, dist

    def _check_poses(self, T_world_obj) -> np.ndarray:
        T = np.asarray(T_world_obj, dtype=float)
        if T.shape != (self.n, 4, 4):
            raise ValueError(f"poses must have shape ({self.n}, 4, 4), got {T.shape}")
        return T

    def compute(
        self, T_world_obj: np.ndarray, g: float = 9.81, enabled: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Wrenches at poses ``T_world_obj`` (n, 4, 4): ``(forces (n, 3) N, torques (n, 3) N m)``,
        world frame, force at the centre of mass (as ``World.apply_wrenches`` expects).

        ``g`` is the gravity magnitude (m/s^2) of ``F_max = f m g``. Queries the segments on
        every ``refresh_every``-th call, else reuses the cached targets. ``enabled`` ((n,) bool,
        optional): only these objects are queried on a refresh; the others pull nothing until
        the next refresh.
        """
        T = self._check_poses(T_world_obj)
        n = self.n
        forces, torques = np.zeros((n, 3)), np.zeros((n, 3))
        if n == 0:
            return forces, torques
        idx = self._enabled_indices(enabled)  # a disabled object is frozen: no wrench
        r, cog = self._world_samples(T, idx)
        if self._calls % self.refresh_every == 0:
            self._refresh(r, cog, T, idx)
        self._calls += 1

        dt = self.max_distance
        # Per-pair weight: kernel (d_t - r)/(d_t^2/4) times F_max / M, zero beyond d_t.
        scale = (
            self.gravity_fraction * float(g) * self.masses[idx] / np.maximum(self.counts[idx], 1)
        )
        _wrenches(
            self._targets, self._matched, r, cog, idx, scale / (dt * dt / 4.0), dt,
            forces, torques, self._pairs,
        )  # fmt: skip
        return forces, torques


@njit
def _wrenches(targets, matched, r, cog, idx, coef, dt, forces, torques, pairs):
    """Eq. 14 (``total_data_force``) of the objects ``idx``: ``forces[k]``, ``torques[k]`` (3,) from
    their samples' offsets ``r`` (m, 3, M) from the COMs ``cog`` (m, 3), the cached targets
    (n, 3, M), the match flags (n, M) and the per-object ``coef`` (m,) = F_max / M / (d_t^2/4).
    Each pair's arithmetic and the sums' order (numpy's, :func:`ssp.jit.pairwise_sum`, over
    all M padded samples) are those of the numpy expressions it replaced, so the wrenches are
    bit-identical to them. ``pairs`` (6, M) is scratch."""
    mmax = r.shape[2]
    for j in range(idx.shape[0]):
        k = idx[j]
        c = coef[j]
        c0, c1, c2 = cog[j, 0], cog[j, 1], cog[j, 2]
        for e in range(mmax):
            rx, ry, rz = r[j, 0, e], r[j, 1, e], r[j, 2, e]
            dx = (targets[k, 0, e] - rx) - c0
            dy = (targets[k, 1, e] - ry) - c1
            dz = (targets[k, 2, e] - rz) - c2
            v = dt - math.sqrt((dx * dx + dy * dy) + dz * dz)
            if v < 0.0:
                v = 0.0
            w = (v * matched[k, e]) * c
            fx, fy, fz = dx * w, dy * w, dz * w
            pairs[0, e] = fx
            pairs[1, e] = fy
            pairs[2, e] = fz
            pairs[3, e] = ry * fz - rz * fy
            pairs[4, e] = rz * fx - rx * fz
            pairs[5, e] = rx * fy - ry * fx
        for a in range(3):
            forces[k, a] = pairwise_sum(pairs[a], mmax)
            torques[k, a] = pairwise_sum(pairs[3 + a], mmax)
