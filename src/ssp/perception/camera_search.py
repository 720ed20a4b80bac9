"""Finding a camera that jumped, and telling a right registration from a wrong one (issue 32).

BOP-style keyframes are 10-30 deg apart: the tracker's ICP from the predicted pose
(:mod:`ssp.perception.egomotion`) does not reach so far, and a search over turns with the
centroids matched did not either (a view from another side sees other faces: the centroids
lie centimetres apart, beyond the ICP's reach). Two pieces, each cheap:

* **Footprint correlation** (:func:`correlated_starts`): with the table plane fixed, a camera's
  motion is a turn about the vertical and a shift along the table. The points above the table
  seen from above (cells of :data:`CELL` m, occupied or not, the map's grown by one cell) are
  compared at every :data:`YAW_STEP` degrees of turn with every shift at once, by one FFT
  cross-correlation per turn; the best shift of each turn scores the overlap, and the
  :data:`STARTS` best turns (at least :data:`DISTINCT_STARTS` degrees apart) are the starts of
  the planar ICP. On the structure keyframes of development seeds 0-1 (38 frames), the best
  start converged to the right pose (within 3 mm at the objects) in every frame; the turns with
  matched centroids in 18 (a development script, not kept).
* **Free-space check** (:func:`seen_through`): a registration puts the map's points (surfaces
  seen in the frames before) in the new view; at the right pose the camera sees them where
  they are or something in front of them; at a wrong one it sees through many of them (the
  depth along their rays lies behind them, :class:`ssp.visibility.CameraView`). A fit that
  registers half of its points at a wrong place still puts the map where the camera sees
  empty space. A point counts as seen through only when every ray around it sees past it
  (:data:`THROUGH_RAYS`, :data:`THROUGH_REACH`): with the nearest ray alone, the map's points
  along silhouettes (the nearest ray passing beside the object, depth noise at its edge) made
  10 % of the map in view seen through at the right poses of the realistic keyframes
  (median; 17 % at the 95th percentile), which left little room below
  :data:`MAX_SEEN_THROUGH`; with the rays around them 1.6 % (8.7 %), the wrong fits' 5th
  percentile 14 % (development seeds 0-3, a script not kept). The tracker also forgets the
  map's points its located frames see through
  (:meth:`ssp.perception.egomotion.CameraTracker.update`): an object moved or taken away is
  seen through at its old place once, not in every frame after.

Why by hand: the 3-parameter search is a few lines of numpy FFT; Open3D's feature-based global
registration (FPFH + RANSAC) would be a large dependency for the same three parameters, and
the point-cloud registration libraries on PyPI (small_gicp, KISS-ICP) are local.
"""

from __future__ import annotations

import numpy as np

from ssp.geometry import yaw_pose
from ssp.visibility import OCCLUDED, SEEN, SEEN_THROUGH, CameraView

__all__ = [
    "CELL",
    "DISTINCT_STARTS",
    "FREE_SPACE_TOLERANCE",
    "GRID_CELLS",
    "MAX_CHECKED",
    "MAX_SEEN_THROUGH",
    "STARTS",
    "THROUGH_REACH",
    "THROUGH_RAYS",
    "YAW_STEP",
    "correlated_starts",
    "free_space_view",
    "seen_through",
    "seen_through_mask",
]

CELL = 0.005
"""Footprint cell, m (grown when the scene is too large for :data:`GRID_CELLS`)."""
GRID_CELLS = 256
"""Footprint grid side, cells (a power of two: the FFT's)."""
YAW_STEP = 4.0
"""Turn step of the correlation, degrees."""
STARTS = 4
"""Best turns of the correlation refined by ICP."""
DISTINCT_STARTS = 12.0
"""Starts are at least this far apart in turn, degrees."""
FREE_SPACE_TOLERANCE = 0.01
"""A map point is seen through when the depth along its ray lies farther than this behind
it, m (depth noise and the map's 3 mm voxels)."""
MAX_SEEN_THROUGH = 0.2
"""A registration is refused when the camera would see through more than this fraction of
the map's points in its view."""
MAX_CHECKED = 5000
"""Map points checked per registration (an even subsample)."""
THROUGH_RAYS = 8
"""A map point is seen through when this many rays nearest to its own ..."""
THROUGH_REACH = 2.0
"""... within this many angular resolutions (:attr:`ssp.visibility.CameraView.angular_resolution`)
all see past it (:func:`seen_through_mask`)."""


def free_space_view(points_cam: np.ndarray) -> CameraView:
    """The view of a frame's camera-frame points ``points_cam`` (N, 3; m) the registrations
    of :func:`seen_through` are checked in (built once per frame)."""
    return CameraView(
        np.asarray(points_cam, dtype=float), np.eye(4), depth_tolerance=FREE_SPACE_TOLERANCE
    )


def seen_through_mask(
    view: CameraView,
    T_world_cam: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    around: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """``(through, in_view)``, (M,) bools: which of the world points ``points`` (M, 3; m)
    with outward ``normals`` a camera at ``T_world_cam`` (4, 4) sees through, and which face
    it and fall on a ray of its frame (``view``: :func:`free_space_view`). A point is seen
    through when its ray's depth lies farther than :data:`FREE_SPACE_TOLERANCE` behind it,
    and so does every one of the :data:`THROUGH_RAYS` rays nearest to it within
    :data:`THROUGH_REACH` angular resolutions (:meth:`ssp.visibility.CameraView.least_depth`):
    a map point at a silhouette's edge, where the nearest ray may pass beside the object, is
    not seen through. ``around`` False: by its nearest ray alone (stricter)."""
    T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=float))
    pc = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    nc = normals @ T_cam_world[:3, :3].T
    state = view.classify(pc, nc)
    through = state == SEEN_THROUGH
    in_view = through | (state == SEEN) | (state == OCCLUDED)
    if around and through.any():
        least = view.least_depth(pc[through], THROUGH_RAYS, THROUGH_REACH)
        through[through] = least - pc[through, 2] > FREE_SPACE_TOLERANCE
    return through, in_view


def seen_through(
    view: CameraView,
    T_world_cam: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    around: bool = True,
) -> tuple[float, int]:
    """``(fraction, n)``: of the world points ``points`` (M, 3; m) with outward ``normals``
    that face a camera at ``T_world_cam`` (4, 4) and fall on a ray of its frame
    (``view``: :func:`free_space_view`), ``n``, the fraction the camera sees through
    (:func:`seen_through_mask`, ``around`` as there); ``(0.0, 0)`` when none falls in the
    view. At most
    :data:`MAX_CHECKED` points, evenly spaced."""
    if len(points) > MAX_CHECKED:
        keep = np.linspace(0, len(points) - 1, MAX_CHECKED).astype(int)
        points, normals = points[keep], normals[keep]
    through, in_view = seen_through_mask(view, T_world_cam, points, normals, around)
    n = int(np.count_nonzero(in_view))
    return (int(np.count_nonzero(through)) / n if n else 0.0), n


def _footprint(xy: np.ndarray, lo: np.ndarray, cell: float, n: int) -> np.ndarray:
    """(n, n) occupancy (0 or 1) of the points ``xy`` (K, 2; m) in cells of ``cell`` m from
    the corner ``lo``; points outside are left out."""
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < n), axis=1)
    grid = np.zeros((n, n))
    grid[ij[ok, 0], ij[ok, 1]] = 1.0
    return grid


def _grown(grid: np.ndarray) -> np.ndarray:
    """``grid`` with each occupied cell's eight neighbours occupied too (the cells around
    its edge wrap, which the correlation's padding makes harmless)."""
    out = grid.copy()
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if dx or dy:
                out = np.maximum(out, np.roll(grid, (dx, dy), axis=(0, 1)))
    return out


def correlated_starts(map_points: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
    """Planar motions ``G`` (4, 4; a turn about the vertical and a shift along the table)
    that put the points ``q`` (N, 3; a frame's table frame, m) over the map's points
    ``map_points`` (M, 3; world, m), best first (module docstring): the :data:`STARTS` turns
    whose best shift overlaps the map's footprint most, at least :data:`DISTINCT_STARTS`
    apart. Empty when either has no point."""
    if not len(map_points) or not len(q):
        return []
    mc = map_points[:, :2].mean(axis=0)
    qc = q[:, :2].mean(axis=0)
    reach = max(float(np.abs(map_points[:, :2] - mc).max()), float(np.abs(q[:, :2] - qc).max()))
    cell = max(CELL, 4.0 * (reach + 0.02) / GRID_CELLS)  # the shifts need the padding
    n = GRID_CELLS
    lo = mc - n * cell / 2.0
    spectrum = np.fft.rfft2(_grown(_footprint(map_points[:, :2], lo, cell, n)))
    scored = []
    for deg in np.arange(0.0, 360.0, YAW_STEP):
        R = yaw_pose(np.radians(deg))[:2, :2]
        grid = _footprint((q[:, :2] - qc) @ R.T + mc, lo, cell, n)
        corr = np.fft.irfft2(spectrum * np.conj(np.fft.rfft2(grid)), s=(n, n))
        k = int(np.argmax(corr))
        i, j = divmod(k, n)
        shift = np.array([i if i < n // 2 else i - n, j if j < n // 2 else j - n]) * cell
        scored.append((float(corr.flat[k]) / max(float(grid.sum()), 1.0), float(deg), shift))
    scored.sort(key=lambda s: (-s[0], s[1]))
    starts: list[np.ndarray] = []
    taken: list[float] = []
    for _, deg, shift in scored:
        if any(abs((deg - d + 180.0) % 360.0 - 180.0) < DISTINCT_STARTS for d in taken):
            continue
        G = yaw_pose(np.radians(deg))
        G[:2, 3] = mc + shift - G[:2, :2] @ qc  # x' = R (x - qc) + mc + shift
        starts.append(G)
        taken.append(deg)
        if len(starts) == STARTS:
            break
    return starts
