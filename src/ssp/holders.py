"""Could something undetected hold an object up? What the data says under it.

An object whose stability term says it would fall stays when its data is strong: something the
estimator did not detect may hold it up (:func:`ssp.verification.verify_final`; a cube on a
block nobody proposed). That holder would stand between the object's lowest point and the
table, and two things in the frame can rule it out:

* **its own instance segment reaches below it** (:func:`reaches_below`): an instance segment
  is one object, so that object reaches lower than the shape proposed for it (a cube fitted to
  the top of a can, seen from the side);
* **the camera sees its own segment under it** (:func:`seen_under`): the rays to the column
  under the object (its footprint, shrunk by :data:`UNDER_SHRINK` about its centre of mass, from
  :data:`BELOW_TOLERANCE` above the table to as far below the object) meet the object's own
  segment below it, where a holder would show its own surface. Seen from above, a can's side
  below a cube fitted to its top is a small share of the can's segment (and of the part of it
  the parser gives the cube), so the first test misses it; the rays under the cube still meet
  the can's side, which is the same instance. Free space under the object rules nothing out:
  a gripper holds an object from above. A holder the camera cannot see (hidden behind the
  object itself) leaves the rays uninformative, and the object is kept as before.

Both need the object's own instance segment (instance masks): a cluster of points near an
object says nothing of what lies below it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from ssp.library.model import ObjectModel
from ssp.visibility import CameraView

__all__ = [
    "BELOW_TOLERANCE",
    "REMEMBERED",
    "UNDER_FRACTION",
    "UNDER_MIN_RAYS",
    "UNDER_SHRINK",
    "UNDER_SPACING",
    "nothing_holds",
    "reaches_below",
    "seen_under",
    "under_column",
]

#: Segment points farther than this below an object's lowest point are below it (m); the column
#: under an object starts this far above the table and ends this far below the object.
BELOW_TOLERANCE = 0.01

#: The column's footprint: the object's horizontal hull shrunk by this factor about its
#: centre of mass, where a holder must stand (a support under an object holds it only where
#: it reaches under its centre of mass); a holder's sides lie outside the column, in front of
#: it from the camera.
UNDER_SHRINK = 0.5

#: How a ruling of an earlier frame is said (:func:`nothing_holds`).
REMEMBERED = "nothing held it there in an earlier frame"

#: Spacing of the samples on the column's sides (m).
UNDER_SPACING = 0.004

#: Rays that meet the column, or something below the object in front of it, needed to judge.
UNDER_MIN_RAYS = 10

#: Nothing holds the object when at least this share of those rays meets the object's own
#: segment below it.
UNDER_FRACTION = 0.5


def _bottom(model: ObjectModel, T_world_obj: np.ndarray) -> tuple[np.ndarray, float]:
    """The model's vertices in the world (V, 3; m) and their lowest z (m)."""
    T = np.asarray(T_world_obj, dtype=float)
    V = np.asarray(model.mesh.vertices, dtype=float) @ T[:3, :3].T + T[:3, 3]
    return V, float(V[:, 2].min())


def reaches_below(model: ObjectModel, T_world_obj: np.ndarray, segment: np.ndarray) -> float:
    """The fraction of an object's instance segment ``segment`` (M, 3; world points, m) lying
    more than :data:`BELOW_TOLERANCE` below the lowest point of ``model`` at ``T_world_obj``
    (4, 4; world z up); 0.0 for an empty segment (module docstring)."""
    if not len(segment):
        return 0.0
    _, bottom = _bottom(model, T_world_obj)
    return float(np.mean(np.asarray(segment)[:, 2] < bottom - BELOW_TOLERANCE))


def under_column(model: ObjectModel, T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Samples on the sides of the column under ``model`` at ``T_world_obj`` (4, 4; world z up,
    the table at z = 0; module docstring) and their outward normals: two (S, 3) arrays (m),
    empty when the object is less than twice :data:`BELOW_TOLERANCE` above the table."""
    V, bottom = _bottom(model, T_world_obj)
    z = np.arange(BELOW_TOLERANCE, bottom - BELOW_TOLERANCE, UNDER_SPACING)
    empty = np.zeros((0, 3))
    if not len(z):
        return empty, empty
    try:
        hull = ConvexHull(V[:, :2])
    except QhullError:  # a footprint without area (a thin plate standing on its edge)
        return empty, empty
    ring = V[hull.vertices, :2]  # counter-clockwise (scipy's 2-D hulls)
    T = np.asarray(T_world_obj, dtype=float)
    com = (T[:3, :3] @ model.center_of_mass + T[:3, 3])[:2]
    ring = com + UNDER_SHRINK * (ring - com)
    pts, nrm = [], []
    for a, b in zip(ring, np.roll(ring, -1, axis=0), strict=True):
        edge = b - a
        length = float(np.linalg.norm(edge))
        if length < 1e-9:
            continue
        n = max(1, round(length / UNDER_SPACING))
        xy = a + ((np.arange(n) + 0.5) / n)[:, None] * edge
        out = np.array([edge[1], -edge[0]]) / length  # outward for a counter-clockwise ring
        grid = np.column_stack([np.repeat(xy, len(z), axis=0), np.tile(z, len(xy))])
        pts.append(grid)
        nrm.append(np.tile([out[0], out[1], 0.0], (len(grid), 1)))
    if not pts:
        return empty, empty
    return np.concatenate(pts), np.concatenate(nrm)


def seen_under(
    model: ObjectModel,
    T_world_obj: np.ndarray,
    view: CameraView,
    own_label: int,
    column: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[int, int]:
    """``(rays, unheld)``: of the rays to the column under the object (:func:`under_column`)
    that tell something (module docstring), how many meet the object's own instance segment
    (label ``own_label``) below it. A ray that sees past the column (free space: a gripper may
    hold it from above), meets the column's side at its depth, or meets something below the
    object in front of it tells something; only the object's own segment there rules a holder
    out. A ray hidden by something at the object's height or above (the object itself) tells
    nothing. ``column``: :func:`under_column`'s samples when already made."""
    pts, nrm = under_column(model, T_world_obj) if column is None else column
    if not len(pts):
        return 0, 0
    _, bottom = _bottom(model, T_world_obj)
    ray = view.lookup(pts, nrm)
    seen = np.isfinite(ray.observed)
    tol = view.depth_tolerance
    diff = np.where(seen, ray.observed - ray.depth, 0.0)
    cam = view.T_world_cam[:3, 3]
    ratio = np.where(seen, ray.observed / ray.depth, 1.0)
    z_obs = cam[2] + (pts[ray.index, 2] - cam[2]) * ratio  # the observed point's height
    own = ray.label == own_label
    through = seen & (diff > tol)
    at = seen & (np.abs(diff) <= tol)
    below = seen & (diff < -tol) & (z_obs < bottom - BELOW_TOLERANCE)
    rays = int(np.count_nonzero(through | at | below))
    unheld = int(np.count_nonzero((at | below) & own))
    return rays, unheld


def nothing_holds(
    model: ObjectModel,
    T_world_obj: np.ndarray,
    segment: np.ndarray,
    view: CameraView | None,
    own_label: int | None,
    below_limit: float,
    before: Sequence[tuple[np.ndarray, str]] = (),
    near: float = 0.0,
) -> str | None:
    """Why nothing undetected can hold ``model`` up at ``T_world_obj`` (4, 4; m), or None
    (module docstring): more than ``below_limit`` of its own instance segment ``segment``
    (M, 3; world, m) lies below it (``verification.fallback_below``), or the ``view`` shows
    that segment under it (:func:`seen_under`). When the view tells nothing under it (fewer
    than :data:`UNDER_MIN_RAYS` rays: seen from above), a ruling of the frame before stands:
    ``before`` holds ``(T_world_obj, why)`` of objects of its class the previous frame
    rejected as falling with nothing shown to hold them (``Rejected.unheld``), and one whose
    centre of mass lies within ``near`` (m) of this one's, horizontally, is the same spot (the
    search may have let it fall there): a moving camera that saw under it one frame looks
    from above the next, and a holder does not appear under an object unseen. None without an
    instance label (``own_label``) or on the table."""
    if own_label is None:
        return None
    below = reaches_below(model, T_world_obj, segment)
    if below > below_limit:
        return f"{100 * below:.0f} % of its own segment lies below it"
    column = under_column(model, T_world_obj)
    if not len(column[0]):
        return None  # on the table: nothing needs to hold it
    rays = unheld = 0
    if view is not None:
        rays, unheld = seen_under(model, T_world_obj, view, own_label, column)
    if rays >= UNDER_MIN_RAYS:
        if unheld < UNDER_FRACTION * rays:
            return None  # something under it may be a holder
        return (
            f"the camera sees its own segment under it: {unheld} of {rays} rays to where a "
            "holder would stand meet it"
        )

    def centre(T: np.ndarray) -> np.ndarray:  # of mass, horizontally (m)
        T = np.asarray(T, dtype=float)
        return (T[:3, :3] @ model.center_of_mass + T[:3, 3])[:2]

    for T, why in before:
        if np.linalg.norm(centre(T_world_obj) - centre(T)) < near:
            # the first frame's ruling, however many frames it has stood since
            return why if why.startswith(REMEMBERED) else f"{REMEMBERED} ({why})"
    return None
