"""Camera egomotion when no camera pose is given (issue 32; DESIGN "The world frame is the
table's, and stays put").

A camera that moves with no pose given (a BOP test scene without ``cam_R_w2c``, a wrist
camera without tf) must be located in the world frame of its first frame, or the camera's
motion becomes the objects'. The table plane fixes three of the six degrees of freedom exactly
(tilt and height: :func:`ssp.perception.table.table_frame`); the other three (the turn about
the table's normal and the position along the table) come from registering the frame's points
above the table to what is known static: a map of the points above the table in the frames
located before (world frame, one point per :data:`MAP_VOXEL` voxel: the first frame's that saw
it, so every frame registers to the oldest views of what it sees and errors do not pile up
frame to frame as they did against the last five frames only).

The registration is :func:`planar_icp`: point-to-plane ICP in those three degrees of freedom
with Tukey weights over coarse-to-fine correspondence distances (:data:`ICP_SCALES`), of the
points whose surface is not horizontal (:func:`_sides`: a top face registers wherever it
slides), so objects that moved and new ones, which find no surface of the map near them, are
what does not register. It starts from the constant-velocity prediction of the camera; when
under half of the points register, also from the last pose (a hand-held camera's shake) and
from the prediction turned by :data:`LOCAL_TURNS`. A fit is accepted when half of the points
register, or, while the camera is tracked, :data:`NEAR_MIN_INLIERS` within
:data:`PREDICTED_SHIFT` of a start, and when it passes the free-space check: the camera at
that pose sees through at most :data:`~ssp.perception.camera_search.MAX_SEEN_THROUGH` of the
map's points in its view (:func:`ssp.perception.camera_search.seen_through`; a fit that
registers its points at a wrong place puts the map where the camera sees empty space).
Objects moved since the map saw them are seen through at the right pose too (their old
places): the map forgets what each located frame's camera sees through (:meth:`_carve`), so
that is counted in one frame, not in every one after. Where objects moved or went away that
cover more than :data:`~ssp.perception.camera_search.MAX_SEEN_THROUGH` of the map in view, a
fit at the prediction of a tracked camera that registers :data:`TRUSTED_INLIERS` of the points
is taken up to :data:`MOVED_SEEN_THROUGH`; beyond, or registering fewer, the frame is refused
(a restart in ``ssp run``), not located wrongly. A fit that keeps the
camera where it was (:data:`KEEP_SHIFT`) is not checked, so a static camera whose objects are
taken away keeps its world (and its map forgets them, ready for the camera to move). With
``search`` (as ``ssp run`` locates cameras), a frame not tracked so, or tracked far from
where the camera was heading (a jump: BOP-style keyframes 10-30 deg apart), is searched
globally: the starts of a footprint correlation over every turn and shift
(:func:`ssp.perception.camera_search.correlated_starts`), each registered, those passing the
free-space check compared (the lowest cost, unless another turned :data:`DISTINCT_YAW` away
registers about as many points). When none passes, or none that passes registers
:data:`SEARCH_TRUSTED_INLIERS` of the points, the starts are also registered turned by
:data:`LOCAL_TURNS` (the correlation's turns are 4 deg apart and an ICP from one may stop a
few degrees short, centimetres off), and at an event frame, whose map still holds the surfaces
of objects just moved, a solution registering :data:`SEARCH_TRUSTED_INLIERS` is judged by the
rays around each map point (:meth:`CameraTracker._search`). A frame whose camera is not
located so is refused (:class:`CameraNotLocatedError`), not guessed (``ssp run`` then starts
the world frame again: :mod:`ssp.pipeline.world`).

The last pose is kept bit for bit (:attr:`CameraFix.how` ``"kept"``) when the registration
moves the points above the table by less than :data:`KEEP_SHIFT` on average from where the last
pose puts them, or when the last pose fits them at least as well (the truncated point-to-plane
cost the registration minimises, :class:`_Fit`): a static camera keeps one world frame. Of
the registrations from the starts tried, the lowest cost wins.

Why not a registration library: small_gicp's GICP (``small_gicp.align``, frame to map, 6
degrees of freedom) was tried with a one-off script (not kept) on the simulated orbit
(structure, development seed 0): the world frame drifted to 35 mm and 1.2 deg at the camera
over 20 frames, then failed; the table's points, most of every frame, constrain only the three
degrees the plane fixes anyway, and the library's Python interface has no robust kernel for
the points that moved. The three-parameter ICP here: ``ssp bench camera`` (docs/benchmarks.md,
moving cameras).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ssp.errors import PerceptionError
from ssp.geometry import yaw_pose
from ssp.perception.camera_search import (
    MAX_SEEN_THROUGH,
    correlated_starts,
    free_space_view,
    seen_through,
    seen_through_mask,
)
from ssp.perception.estimator import voxel_thin
from ssp.perception.normals import estimate_normals
from ssp.perception.table import table_frame
from ssp.visibility import CameraView

__all__ = [
    "ABOVE_TABLE",
    "CLOUD_POINTS",
    "ICP_SCALES",
    "KEEP_SHIFT",
    "LOCAL_TURNS",
    "MAP_VOXEL",
    "MIN_INLIERS",
    "MIN_INLIER_POINTS",
    "NEAR_MIN_INLIERS",
    "PREDICTED_SHIFT",
    "SEARCH_INLIERS",
    "SEARCH_TRUSTED_INLIERS",
    "SIDE_TILT_DEG",
    "CameraFix",
    "CameraNotLocatedError",
    "CameraTracker",
    "planar_icp",
    "table_pose",
]

log = logging.getLogger(__name__)

ABOVE_TABLE = 0.004
"""Points higher than this above the table plane (m), and than three robust standard
deviations of the table's own points (a far table's depth noise), are registered (the rest is
the table: :func:`_above_table`)."""
ICP_SCALES = (0.03, 0.01, 0.005)
"""Correspondence distances of the coarse-to-fine ICP, m."""
INLIER_DISTANCE = 0.003
"""A registered point within this point-to-plane distance of the map is an inlier, m."""
MIN_INLIERS = 0.3
"""Fewest inlier fraction of the points above the table for a camera tracked from its
prediction (new objects, which the map does not hold yet, do not register)."""
MIN_INLIER_POINTS = 100
"""... and fewest inlier points."""
NEAR_MIN_INLIERS = 0.15
"""Fewest inlier fraction of a solution within :data:`PREDICTED_SHIFT` of the prediction or
the last pose while the camera is tracked (the two frames before located, the last from the
one before it: a prediction worth the name), as when new objects stacked on the old ones hide
most of what the map holds."""
LOCAL_TURNS = (0.0, -4.0, 4.0, -8.0, 8.0)
"""Turns about the map's centre (degrees) added to the prediction, each a start of the
tracking ICP (the lowest cost wins): a camera that speeds up or turns."""
TRUSTED_INLIERS = 0.8
"""A fit near the prediction while the camera is tracked (:data:`PREDICTED_SHIFT`) that
registers at least this fraction of the points above the table may see through up to
:data:`MOVED_SEEN_THROUGH` of the map in view: at an event frame the places of objects moved or
taken away are seen through at the right pose (development seed 21 of the orbit, frame 24:
84 % registered, 20 % seen through, refused, so the scene was forgotten); a registration at a
wrong place near the prediction leaves most points unregistered (those refused on ``ssp bench
camera --seed 2000`` registered up to 80 %, none near the prediction)."""
MOVED_SEEN_THROUGH = 0.5
"""... at most this fraction (more than half of the map in view gone: refused all the same)."""
SEARCH_INLIERS = 0.5
"""Fewest inlier fraction of a tracked solution far from the prediction (else the other
local starts are tried too, and the solution must lie near a start)."""
PREDICTED_SHIFT = 0.01
"""A tracked solution that registers less than :data:`SEARCH_INLIERS` of the points (new
objects in view) is taken when it moves them less than this from the prediction or the last
pose on average, m; farther (a jump, BOP keyframes: perhaps a wrong minimum) it is refused,
and with ``search`` it competes with the global search's solution."""
SEARCH_TRUSTED_INLIERS = 0.7
"""A global search's solution that registers at least this fraction of the points above the
table is trusted (:meth:`CameraTracker._search`). When no solution that passes the free-space
check by each map point's nearest ray is trusted, the starts are also registered turned by
:data:`LOCAL_TURNS`, and a trusted solution may pass by the rays around each point (the
tracked fits' check): at an event frame the map holds the surfaces of objects just moved,
which the right view sees through, and the nearest ray sees through 20-38 % of the map at
the right poses (the realistic keyframes, development seeds 0-9: 6 of their 8 restarts, every
one whose starts reached the right pose); the solutions more than 5 mm off in those frames
register at most 57 %."""
SEARCH_MARGIN = 0.15
"""A global solution is ambiguous when another this close in inlier fraction ..."""
DISTINCT_YAW = 20.0
"""... is turned at least this far from it, degrees."""
KEEP_SHIFT = 0.002
"""A registration that moves the points above the table by less than this on average (m) from
where the last pose puts them keeps the last pose exactly (the registration's own noise is
about a millimetre)."""
SIDE_TILT_DEG = 45.0
"""Registered points' normals lean from the vertical by more than this, degrees."""
MAP_VOXEL = 0.003
"""Voxel size of the map of points above the table, m."""
MAX_POINTS = 6000
"""Points above the table registered per frame (an even subsample)."""
CLOUD_POINTS = 60000
"""A frame's cloud is thinned to about this many points (every k-th) for the table fit (a
640 x 480 frame has 300 000; the registration takes all the points above the table)."""


class CameraNotLocatedError(PerceptionError):
    """The camera of a frame could not be located in the world frame (module docstring)."""


@dataclass(frozen=True)
class CameraFix:
    """Where a frame's camera is.

    Attributes:
        T_world_cam: (4, 4) camera pose in the world frame of the first frame.
        how: ``"table"`` (the first frame: the table defines the world), ``"kept"`` (the
            camera did not move), ``"tracked"`` (registered from its predicted pose) or
            ``"searched"`` (registered by the global search).
        inliers: fraction of the points above the table that registered (None: first).
        residual_mm: RMS point-to-plane distance of those inliers, mm (None: first).
        points: points above the table registered.
    """

    T_world_cam: np.ndarray
    how: str
    inliers: float | None = None
    residual_mm: float | None = None
    points: int = 0

    def as_dict(self) -> dict:
        return {
            "how": self.how,
            "inliers": None if self.inliers is None else round(self.inliers, 4),
            "residual_mm": None if self.residual_mm is None else round(self.residual_mm, 3),
            "points": int(self.points),
        }


def planar_icp(
    q: np.ndarray,
    tree: cKDTree,
    normals: np.ndarray,
    G0: np.ndarray,
    scales=ICP_SCALES,
    iterations: int = 12,
) -> np.ndarray:
    """The planar motion ``G`` (4, 4: a turn about z and a shift in x, y) that puts points
    ``q`` (N, 3; m, z up, the table at z = 0) on the surface of the map (``tree`` over its
    points, ``normals`` (M, 3) unit), starting from ``G0``: Gauss-Newton on point-to-plane
    distances with Tukey weights (scale a third of each correspondence distance of
    ``scales``)."""
    target = tree.data
    th = float(np.arctan2(G0[1, 0], G0[0, 0]))
    tx, ty = float(G0[0, 3]), float(G0[1, 3])
    for d in scales:
        for _ in range(iterations):
            G = yaw_pose(th, (tx, ty, 0.0))
            s = q @ G[:3, :3].T + G[:3, 3]
            dist, idx = tree.query(s, distance_upper_bound=d)
            ok = np.isfinite(dist)
            if np.count_nonzero(ok) < 10:
                return yaw_pose(th, (tx, ty, 0.0))
            n, t, p = normals[idx[ok]], target[idx[ok]], s[ok]
            r = np.einsum("ij,ij->i", n, p - t)
            d_th = np.stack([-(p[:, 1] - ty), p[:, 0] - tx], axis=1)  # d p / d theta (x, y)
            J = np.stack([np.einsum("ij,ij->i", n[:, :2], d_th), n[:, 0], n[:, 1]], axis=1)
            w = np.clip(1.0 - (r / (d / 3.0)) ** 2, 0.0, None) ** 2
            A = J.T @ (J * w[:, None]) + 1e-9 * np.eye(3)
            step = np.linalg.solve(A, -J.T @ (w * r))
            th, tx, ty = th + step[0], tx + step[1], ty + step[2]
            if np.abs(step).max() < 1e-7:
                break
    return yaw_pose(th, (tx, ty, 0.0))


def _surface(model) -> tuple[np.ndarray, np.ndarray]:
    """``(points (K, 3), unit normals (K, 3))`` on an object model's surface, model frame."""
    return (
        np.asarray(model.surface_points, dtype=float),
        np.asarray(model.surface_normals, dtype=float),
    )


def _turned(G: np.ndarray, degrees: float, centre: np.ndarray) -> np.ndarray:
    """Planar motion ``G`` followed by a turn of ``degrees`` about the vertical through
    ``centre``."""
    R = yaw_pose(np.radians(degrees))
    C = np.eye(4)
    C[:2, 3] = centre[:2]
    return C @ R @ np.linalg.inv(C) @ G


def _snap(T: np.ndarray, T_plane: np.ndarray) -> np.ndarray:
    """``T`` (world from camera) turned by the least rotation that gives it ``T_plane``'s up
    direction, at ``T_plane``'s height: the plane's tilt and height, ``T``'s turn and place."""
    up, up_p = T[2, :3], T_plane[2, :3]  # world z in camera coordinates
    v = np.cross(up, up_p)
    s, c = float(np.linalg.norm(v)), float(up @ up_p)
    R = np.eye(3)
    if s > 1e-12:
        k = v / s
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        R = np.eye(3) + s * K + (1.0 - c) * K @ K
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ R.T
    out[2, 3] = T_plane[2, 3]
    return out


@dataclass(frozen=True)
class _Fit:
    """A planar motion ``G`` (4, 4) of the points above the table and how they register:
    ``inliers`` (fraction within :data:`INLIER_DISTANCE` of the map's surface), ``rms_mm``
    (their RMS distance, mm) and ``cost`` (the mean squared point-to-plane distance, each
    truncated at :data:`INLIER_DISTANCE`, m^2: what the registration minimises, lower is
    better; a point that finds no surface costs the truncation)."""

    G: np.ndarray
    inliers: float
    rms_mm: float
    cost: float

    @property
    def yaw(self) -> float:
        return float(np.arctan2(self.G[1, 0], self.G[0, 0]))

    def tracks(self, n: int, floor: float = MIN_INLIERS) -> bool:
        """Enough of the ``n`` points register: a fraction ``floor`` and
        :data:`MIN_INLIER_POINTS`."""
        return self.inliers >= floor and self.inliers * n >= MIN_INLIER_POINTS

    def refused(self) -> _Fit:
        """The same motion, not accepted (no inliers)."""
        return _Fit(self.G, 0.0, self.rms_mm, float("inf"))


def _fit(q: np.ndarray, tree: cKDTree, normals: np.ndarray, G: np.ndarray) -> _Fit:
    """How points ``q`` (N, 3) moved by ``G`` register to the map (:class:`_Fit`)."""
    s = q @ G[:3, :3].T + G[:3, 3]
    dist, idx = tree.query(s, distance_upper_bound=ICP_SCALES[-1])
    ok = np.isfinite(dist)
    r = np.full(len(q), INLIER_DISTANCE)
    r[ok] = np.abs(np.einsum("ij,ij->i", normals[idx[ok]], s[ok] - tree.data[idx[ok]]))
    inl = r < INLIER_DISTANCE
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) * 1000.0 if inl.any() else float("nan")
    cost = float(np.mean(np.minimum(r, INLIER_DISTANCE) ** 2))
    return _Fit(G, float(inl.mean()), rms, cost)


def _sides(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(points, unit normals)`` of the surfaces that fix a planar motion: ``points`` (N, 3;
    table frame, m) thinned to one per :data:`MAP_VOXEL` voxel, those whose normal leans from
    the vertical by more than :data:`SIDE_TILT_DEG` (a top face registers wherever it slides:
    it would count as registered at any wrong place)."""
    if len(points) < 3:
        return np.zeros((0, 3)), np.zeros((0, 3))
    p = points[voxel_thin(points, MAP_VOXEL)]
    n = estimate_normals(p, k=12)
    side = np.abs(n[:, 2]) < np.cos(np.radians(SIDE_TILT_DEG))
    return p[side], n[side]


def _thinned(points_cam: np.ndarray) -> np.ndarray:
    """``points_cam`` (N, 3) as float, every k-th point: about :data:`CLOUD_POINTS`."""
    p = np.asarray(points_cam, dtype=float)
    return p[:: max(1, -(-len(p) // CLOUD_POINTS))]


def table_pose(points_cam: np.ndarray, table_distance: float) -> np.ndarray:
    """``T_world_cam`` (4, 4) of the frame whose table (fitted on about :data:`CLOUD_POINTS`
    of the camera-frame points ``points_cam`` (N, 3), m, inliers within ``table_distance``
    m) is the world's z = 0: a first frame's world, or a frame's own.

    Raises:
        TableNotFoundError: no table in the frame.
    """
    return table_frame(_thinned(points_cam), distance=table_distance)[0]


def _registered(p: np.ndarray, T_plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(points, unit normals)`` of camera-frame ``p`` (N, 3) a frame registers by: in the
    table's frame ``T_plane`` (4, 4, from the camera), above the table, on side surfaces
    (:func:`_sides`), at most :data:`MAX_POINTS` (an even subsample)."""
    q = p @ T_plane[:3, :3].T + T_plane[:3, 3]
    q, n = _sides(q[_above_table(q[:, 2])])
    if len(q) > MAX_POINTS:
        keep = np.linspace(0, len(q) - 1, MAX_POINTS).astype(int)
        q, n = q[keep], n[keep]
    return q, n


def _above_table(z: np.ndarray) -> np.ndarray:
    """Which heights ``z`` (N,; m above the table plane) are above the table
    (:data:`ABOVE_TABLE`) and below a metre."""
    near = z[np.abs(z) < 0.02][:: max(1, len(z) // CLOUD_POINTS)]
    cut = ABOVE_TABLE
    if len(near) >= 100:
        mid = float(np.median(near))
        cut = max(cut, mid + 3.0 * 1.4826 * float(np.median(np.abs(near - mid))))
    return (z > cut) & (z < 1.0)


def _shift(q: np.ndarray, G: np.ndarray, H: np.ndarray) -> float:
    """Mean distance (m) between points ``q`` (N, 3) moved by ``G`` and by ``H`` (4, 4)."""
    D = G - H
    return float(np.linalg.norm(q @ D[:3, :3].T + D[:3, 3], axis=1).mean())


class CameraTracker:
    """``T_world_cam`` of each frame of a camera with no pose given (module docstring).

    Args:
        table_distance: the table fit's inlier distance, m.
        search: run the global search when the frame does not track from the prediction or
            the last pose, or tracks far from it (module docstring; ``ssp run`` does).
    """

    def __init__(self, table_distance: float = 0.006, search: bool = True) -> None:
        self.table_distance = float(table_distance)
        self.search = bool(search)
        self.T_world_cam: np.ndarray | None = None
        self._before: np.ndarray | None = None  # the pose before the last
        self._map = np.zeros((0, 3))  # world points above the table, oldest first
        self._map_normals = np.zeros((0, 3))  # their unit normals
        self._known: tuple[np.ndarray, np.ndarray] | None = None  # model points, normals
        self._checked: dict | None = None  # the last given pose's check
        self._tracking = False  # the last frame was located from the one before

    def know(self, objects) -> None:
        """The objects known static, ``[(model, T_world_obj (4, 4))]``
        (:class:`~ssp.library.model.ObjectModel`): their whole surfaces (``surface_points``,
        ``surface_normals``) join the map as the next frames' reference (a view from another
        side sees faces no frame before saw), and the registration is refined on them alone
        when enough points register there. An empty list forgets them. Exact objects make the
        camera exact (``ssp bench camera``, ``egomotion_known``); objects estimated in the
        frames before carry those frames' camera errors (:mod:`ssp.pipeline.world`)."""
        pts, nrm = [], []
        for model, T in objects:
            T = np.asarray(T, dtype=float)
            p, n = _surface(model)
            pts.append(p @ T[:3, :3].T + T[:3, 3])
            nrm.append(n @ T[:3, :3].T)
        self._known = (np.concatenate(pts), np.concatenate(nrm)) if pts else None

    def update(self, points_cam: np.ndarray) -> CameraFix:
        """Locate the camera of a frame from its cloud ``points_cam`` (N, 3; camera frame, m).

        Raises:
            TableNotFoundError: no table in the frame.
            CameraNotLocatedError: the frame's points above the table do not register to the
                map from any start (the tracker is unchanged).
        """
        p = np.asarray(points_cam, dtype=float)
        T_plane = table_pose(p, self.table_distance)
        if self.T_world_cam is None:
            self._add(T_plane, T_plane, *_registered(p, T_plane))
            return CameraFix(T_plane, "table")
        q, q_normals = _registered(p, T_plane)
        target, normals = self._map, self._map_normals
        if self._known is not None:
            target = np.concatenate([target, self._known[0]])
            normals = np.concatenate([normals, self._known[1]])
        if len(q) < 10 or len(target) < 10:
            raise CameraNotLocatedError(
                f"nothing above the table to locate the camera by ({len(q)} points in the "
                f"frame, {len(target)} in the map of the frames before)"
            )
        tree = cKDTree(target)
        last = self.T_world_cam
        tracking, self._tracking = self._tracking, False  # until this frame is located
        G_last = last @ np.linalg.inv(T_plane)  # where the last pose puts the points
        fit, near = self._tracked(q, tree, normals, T_plane)
        near = near and tracking  # a start that means something: tracked just before
        how, n = "tracked", len(q)
        registered = fit.inliers  # the best start's, for the message
        floor = NEAR_MIN_INLIERS if near else MIN_INLIERS
        views: list[CameraView] = []  # the frame's free-space view, built once when needed

        checked: dict[tuple[bytes, bool], float] = {}  # each motion's check, made once

        def clear(f: _Fit, nearest: bool = False) -> float:
            """The fraction of the map in view that ``f`` makes the camera see through;
            ``nearest``: judged by each point's nearest ray alone (the stricter form, for the
            global search's candidates, which no prediction backs: :meth:`_search`)."""
            key = (f.G.tobytes(), nearest)
            if key not in checked:
                if not views:
                    views.append(free_space_view(_thinned(p)))
                checked[key] = seen_through(
                    views[0], f.G @ T_plane, self._map, self._map_normals, around=not nearest
                )[0]
            return checked[key]

        through = None
        if fit.tracks(n, floor) and (fit.inliers >= SEARCH_INLIERS or near):
            # a fit that leaves the camera where it was keeps a pose located before: nothing
            # to check (objects taken away are seen through there, and must not restart it)
            if _shift(q, fit.G, G_last) >= KEEP_SHIFT:
                through = clear(fit)
            limit = (
                MOVED_SEEN_THROUGH if near and fit.inliers >= TRUSTED_INLIERS else MAX_SEEN_THROUGH
            )
            if through is not None and through > limit:  # at a wrong place
                log.info("camera fit refused: it sees through %.0f %% of the map in view",
                         100 * through)  # fmt: skip
                fit = fit.refused()
        else:
            fit = fit.refused()
        # not tracked, or far from where the camera was heading (a jump: perhaps a local
        # minimum that registers half of the points): the global search, the lower cost wins
        if self.search and not (near and fit.tracks(n, floor)):
            found = self._search(q, tree, normals, clear)
            if found is not None and (not fit.tracks(n, floor) or found.cost < fit.cost):
                fit, floor, how = found, MIN_INLIERS, "searched"
        if not fit.tracks(n, floor):
            raise CameraNotLocatedError(
                f"the camera could not be located: from the starts tried {100 * registered:.0f} "
                f"% of the {n} points above the table register to the map (at least "
                f"{100 * NEAR_MIN_INLIERS:.0f} % needed near the predicted pose, "
                f"{100 * SEARCH_INLIERS:.0f} % farther)"
                + ("" if through is None else f", or the camera would see through "
                   f"{100 * through:.0f} % of the map in view")
                + (", and no start of the global search registers unambiguously with the map "
                   "in view" if self.search else "")
            )  # fmt: skip
        tree, normals, fit = self._refined(q, tree, normals, fit)
        G = fit.G
        moved = _shift(q, G, G_last)
        log.debug("camera registered: points moved %.2f mm on average", 1000 * moved)
        T = G @ T_plane
        if moved < KEEP_SHIFT or _fit(q, tree, normals, G_last).cost <= fit.cost:
            T, how = last, "kept"
        # the map forgets what the located camera sees through (moved or gone since)
        self._carve(views[0] if views else free_space_view(_thinned(p)), T)
        self._add(T, T_plane, q, q_normals)
        self._tracking = True
        return CameraFix(T.copy(), how, fit.inliers, fit.rms_mm, len(q))

    def check(self, points_cam: np.ndarray, T_world_cam: np.ndarray) -> dict:
        """How a given camera pose ``T_world_cam`` (4, 4; its world z up with the table at
        z = 0) agrees with the frame's points ``points_cam`` (N, 3; camera frame, m) and the
        frames given before: ``tilt_deg`` and ``height_mm`` (between the given world's z = 0
        and the table plane fitted here), ``shift_mm`` (how far a registration of the points
        above the table to the map of the frames before moves them from where the given pose
        puts them, on average; None without a map or enough points to register) and
        ``inliers`` (registered there). The frame then joins the map at the given pose. A pose
        equal to the frame before's is not checked again (its check is returned).

        Raises:
            TableNotFoundError: no table in the frame (the tracker is unchanged).
        """
        T = np.asarray(T_world_cam, dtype=float)
        if self._checked is not None and np.array_equal(T, self.T_world_cam):
            return dict(self._checked)  # the same pose as the frame before: checked there
        p = np.asarray(points_cam, dtype=float)
        T_plane = table_pose(p, self.table_distance)
        tilt = float(np.degrees(np.arccos(np.clip(T[2, :3] @ T_plane[2, :3], -1.0, 1.0))))
        out = {"how": "given", "tilt_deg": round(tilt, 3),
               "height_mm": round(1000.0 * float(T[2, 3] - T_plane[2, 3]), 2),
               "shift_mm": None, "inliers": None}  # fmt: skip
        q, q_normals = _registered(p, T_plane)
        if len(self._map) >= 10 and len(q) >= MIN_INLIER_POINTS:
            tree = cKDTree(self._map)
            G_given = _snap(T, T_plane) @ np.linalg.inv(T_plane)
            G = planar_icp(q, tree, self._map_normals, G_given, scales=ICP_SCALES[1:])
            fit = _fit(q, tree, self._map_normals, G)
            if fit.tracks(len(q), NEAR_MIN_INLIERS):
                out["shift_mm"] = round(1000.0 * _shift(q, G, G_given), 2)
                out["inliers"] = round(fit.inliers, 4)
        self._add(T, T_plane, q, q_normals)
        self._checked, self._tracking = out, False  # given, not tracked
        return out

    def _tracked(self, q, tree, normals, T_plane) -> tuple[_Fit, bool]:
        """The best registration of the points ``q`` from the local starts (module
        docstring): the constant-velocity prediction; when under half register, also the last
        pose and the prediction turned by :data:`LOCAL_TURNS`. And whether it lies within
        :data:`PREDICTED_SHIFT` of the prediction or the last pose."""
        last = self.T_world_cam
        assert last is not None
        pred = last if self._before is None else last @ np.linalg.inv(self._before) @ last
        G0 = _snap(pred, T_plane) @ np.linalg.inv(T_plane)
        c = tree.data.mean(axis=0)
        fit = self._register(q, tree, normals, G0)  # from the constant-velocity prediction
        G_still = _snap(last, T_plane) @ np.linalg.inv(T_plane)  # the camera as it was
        # fewer than half registered: perhaps a wrong minimum; the other starts too
        if self._before is not None and fit.inliers < SEARCH_INLIERS:
            fit = min(fit, self._register(q, tree, normals, G_still), key=lambda f: f.cost)
        for deg in LOCAL_TURNS[1:] if fit.inliers < SEARCH_INLIERS else ():
            fit = min(fit, self._register(q, tree, normals, _turned(G0, deg, c)),
                      key=lambda f: f.cost)  # fmt: skip
        near = min(_shift(q, fit.G, G0), _shift(q, fit.G, G_still)) < PREDICTED_SHIFT
        return fit, near

    def _refined(self, q, tree, normals, fit) -> tuple[cKDTree, np.ndarray, _Fit]:
        """``(tree, normals, fit)``: the known objects' exact surfaces (:meth:`know`) with
        the fit refined on them when enough points register there, else as given."""
        if self._known is None:
            return tree, normals, fit
        ktree, kn = cKDTree(self._known[0]), self._known[1]
        fit_k = _fit(q, ktree, kn, planar_icp(q, ktree, kn, fit.G, scales=ICP_SCALES[1:]))
        if fit_k.inliers * len(q) >= MIN_INLIER_POINTS:
            return ktree, kn, fit_k
        return tree, normals, fit

    def _register(self, q, tree, normals, G0, scales=ICP_SCALES) -> _Fit:
        """:func:`planar_icp` from ``G0`` and how well it registers (:func:`_fit`)."""
        return _fit(q, tree, normals, planar_icp(q, tree, normals, G0, scales))

    def _search(self, q, tree, normals, clear) -> _Fit | None:
        """The global search (module docstring): each start of the footprint correlation
        (:func:`ssp.perception.camera_search.correlated_starts`) registered, those that
        register :data:`MIN_INLIERS` of the points and make the camera see through at most
        :data:`~ssp.perception.camera_search.MAX_SEEN_THROUGH` of the map in view
        (``clear(fit, True)``: by each map point's nearest ray, the stricter form of the
        check: a jump has no prediction to back it; on the realistic keyframes of
        development seeds 0-9 the check by the rays around each point let a turn 46 mm off
        win where objects had moved) compared: the lowest cost, unless another turned
        :data:`DISTINCT_YAW` or more from it registers within :data:`SEARCH_MARGIN` of its
        inliers (a scene of a few cubes looks alike from several sides): then None. When none
        passes, or none that passes registers :data:`SEARCH_TRUSTED_INLIERS` of the points (a
        minimum a few degrees from the right pose), each start that registers
        :data:`MIN_INLIERS` is also registered turned by :data:`LOCAL_TURNS`, and every
        solution that passes the check by the rays around each map point (``clear(fit)``, as
        the tracked fits') is a rival; those of them that pass by the nearest ray too, or
        register :data:`SEARCH_TRUSTED_INLIERS` of the points, are compared so (an event
        frame's map holds surfaces of objects moved since, which the right view sees through)."""
        n = len(q)
        fits = [self._register(q, tree, normals, G0) for G0 in correlated_starts(tree.data, q)]
        ok = [f for f in fits if f.tracks(n, MIN_INLIERS) and clear(f, True) <= MAX_SEEN_THROUGH]
        if all(f.inliers < SEARCH_TRUSTED_INLIERS for f in ok):
            # no clear solution, or only doubtful ones (perhaps a minimum a few degrees off):
            # each start that registers, turned a little
            c = tree.data.mean(axis=0)
            turned = [_turned(f.G, deg, c) for f in fits if f.tracks(n, MIN_INLIERS)
                      for deg in LOCAL_TURNS[1:]]  # fmt: skip
            fits += [self._register(q, tree, normals, G0) for G0 in turned]
            # an event frame's map holds surfaces moved since: judged by the rays around each
            # map point, a solution that registers SEARCH_TRUSTED_INLIERS may pass as well
            rivals = [f for f in fits if f.tracks(n, MIN_INLIERS) and clear(f) <= MAX_SEEN_THROUGH]
            ok = [
                f
                for f in rivals
                if f.inliers >= SEARCH_TRUSTED_INLIERS or clear(f, True) <= MAX_SEEN_THROUGH
            ]
        else:
            rivals = ok
        if not ok:
            return None
        best = min(ok, key=lambda f: f.cost)
        for other in rivals:
            turn = abs((other.yaw - best.yaw + np.pi) % (2 * np.pi) - np.pi)
            if turn >= np.radians(DISTINCT_YAW) and other.inliers > best.inliers - SEARCH_MARGIN:
                log.info("camera search ambiguous: %.2f and %.2f inliers %.0f deg apart",
                         best.inliers, other.inliers, np.degrees(turn))  # fmt: skip
                return None
        return best

    def checked(self, T: np.ndarray, p: np.ndarray, check: dict) -> None:
        """A resumed run's frame whose given pose ``T`` was checked (``check``: what
        :meth:`check` returned, from the frame's record): as :meth:`check` left the tracker."""
        T = np.asarray(T, dtype=float)
        if self._checked is not None and np.array_equal(T, self.T_world_cam):
            return
        self.accept(T, p)
        self._checked = dict(check)

    def accept(self, T: np.ndarray, p: np.ndarray, tracked: bool = False) -> None:
        """Keep ``T`` (4, 4) as the pose of the frame of camera-frame points ``p`` (N, 3; m)
        and its registered points in the map, as :meth:`update` does with a located frame: a
        resumed run's frames committed before (``tracked``: located from the frame before,
        not the first or a restart; the map forgets what it sees through, as there).

        Raises:
            TableNotFoundError: no table in the frame.
        """
        p = np.asarray(p, dtype=float)
        T_plane = table_pose(p, self.table_distance)
        T = np.asarray(T, dtype=float)
        if tracked:
            self._carve(free_space_view(_thinned(p)), T)
        self._add(T, T_plane, *_registered(p, T_plane))
        self._tracking = tracked

    def _carve(self, view: CameraView, T: np.ndarray) -> None:
        """Drop the map's points that the frame's camera at its located pose ``T`` sees
        through (``view``: :func:`~ssp.perception.camera_search.free_space_view`): surfaces
        that were there when an earlier frame saw them and are gone (an object moved or
        taken away), which the next frames' free-space checks would otherwise hold against
        the right pose."""
        through, _ = seen_through_mask(view, T, self._map, self._map_normals)
        if through.any():
            log.debug("camera map: %d points seen through forgotten", int(through.sum()))
            self._map, self._map_normals = self._map[~through], self._map_normals[~through]

    def _add(self, T: np.ndarray, T_plane: np.ndarray, q: np.ndarray, normals: np.ndarray) -> None:
        """Keep ``T`` as the frame's camera pose and its registered points ``q`` (N, 3; in the
        frame's table frame ``T_plane``) with their ``normals`` in the map (world frame); a
        voxel keeps its first point, the oldest frame's."""
        M = T @ np.linalg.inv(T_plane)  # the world from the frame's table frame
        if len(q):
            pts = np.concatenate([self._map, q @ M[:3, :3].T + M[:3, 3]])
            nrm = np.concatenate([self._map_normals, normals @ M[:3, :3].T])
            keep = voxel_thin(pts, MAP_VOXEL)
            self._map, self._map_normals = pts[keep], nrm[keep]
        self._before, self.T_world_cam = self.T_world_cam, T.copy()
