"""What a 3D recording (:mod:`ssp.viz.record`) draws, as plain arrays: no rerun here.

* :func:`split_cloud`: a frame's cloud in three parts (object segments, table, background),
  each an evenly spaced (deterministic) subset of its own size;
* :data:`CLASSES` / :func:`mode_class`: the recording's classes (one ``AnnotationContext``
  entry each: background, table and the five transition modes), so the viewer's key is
  bounded by the number of classes, never by the number of objects or hypotheses;
* :func:`object_top` and :func:`place_labels`: where an object's one label goes (above the
  top of its posed mesh, raised clear of its neighbours' labels);
* :func:`depth_millimetres`: a depth image (m) as the ``uint16`` millimetres logged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ssp.scene import TransitionMode

__all__ = [
    "BACKGROUND_CLASS",
    "BACKGROUND_SHARE",
    "CLASSES",
    "CloudParts",
    "LABEL_CLEARANCE",
    "LABEL_MARGIN",
    "LABEL_STEP",
    "MODE_COLOURS",
    "TABLE_BAND",
    "TABLE_CLASS",
    "TABLE_SHARE",
    "depth_millimetres",
    "evenly",
    "object_top",
    "place_labels",
    "mode_class",
    "split_cloud",
]

#: Object colour (RGB) per transition mode.
MODE_COLOURS: dict[TransitionMode, tuple[int, int, int]] = {
    TransitionMode.ADDED: (60, 200, 90),
    TransitionMode.STATIC: (90, 140, 230),
    TransitionMode.PERTURBED: (245, 160, 40),
    TransitionMode.SUPPORT_RETAINED: (190, 90, 220),
    TransitionMode.REMOVED: (230, 60, 60),
}
#: Class ids of the points of no object segment: far from the table, and on it.
BACKGROUND_CLASS, TABLE_CLASS = 0, 1
#: The recording's classes, ``(class id, name, RGB)``: background and table (dim greys), then
#: one per transition mode (:data:`MODE_COLOURS`), ids 2-6.
CLASSES: tuple[tuple[int, str, tuple[int, int, int]], ...] = (
    (BACKGROUND_CLASS, "background", (70, 70, 70)),
    (TABLE_CLASS, "table", (95, 95, 95)),
    *((2 + k, str(m), MODE_COLOURS[m]) for k, m in enumerate(MODE_COLOURS)),
)
#: Unsegmented points within this height of the table top (z = 0, world frame, m) are table.
TABLE_BAND = 0.01
#: Table and background points kept per frame, as fractions of the recorder's ``max_points``
#: (the object segments may use all of it).
TABLE_SHARE, BACKGROUND_SHARE = 0.2, 0.05
#: Labels (:func:`place_labels`): height above the object's top, vertical spacing of the labels
#: of neighbours, and the x-y distance within which objects are neighbours (m).
LABEL_MARGIN, LABEL_STEP, LABEL_CLEARANCE = 0.01, 0.03, 0.07
#: A depth image's largest value as uint16 millimetres (m); deeper pixels become "no return".
MAX_DEPTH_MM = 65535


def mode_class(mode: TransitionMode | str) -> int:
    """The class id (:data:`CLASSES`) of transition mode ``mode``."""
    return 2 + list(MODE_COLOURS).index(TransitionMode(mode))


def evenly(index: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` of ``index`` (1-D), evenly spaced and in order (all when ``k`` >= its
    length): the same input, the same subset."""
    index = np.asarray(index)
    if len(index) <= k:
        return index
    if k <= 0:
        return index[:0]
    return index[np.linspace(0, len(index) - 1, k).astype(np.int64)]


@dataclass(frozen=True)
class CloudParts:
    """Row indices into a frame's ``points`` ``(N, 3)``: ``objects`` (a label >= 0: in an
    object segment), ``table`` and ``background`` (no segment; within :data:`TABLE_BAND` of
    z = 0, and the rest), each already cut to its budget (:func:`split_cloud`)."""

    objects: np.ndarray
    table: np.ndarray
    background: np.ndarray


def split_cloud(points: np.ndarray, labels: np.ndarray | None, max_points: int) -> CloudParts:
    """Split a world-frame cloud ``(N, 3)`` (m; ``labels`` ``(N,)``, negative = no object,
    None = none known) into :class:`CloudParts`: at most ``max_points`` object points,
    ``TABLE_SHARE * max_points`` table points and ``BACKGROUND_SHARE * max_points`` background
    points, each an evenly spaced subset (:func:`evenly`), so the few object points are never
    thinned for the sake of the many table points."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    n = len(pts)
    if labels is None:
        segmented = np.zeros(n, dtype=bool)
    else:
        segmented = np.asarray(labels).reshape(-1) >= 0
    on_table = ~segmented & (np.abs(pts[:, 2]) <= TABLE_BAND)
    rest = ~segmented & ~on_table
    return CloudParts(
        objects=evenly(np.flatnonzero(segmented), int(max_points)),
        table=evenly(np.flatnonzero(on_table), int(TABLE_SHARE * max_points)),
        background=evenly(np.flatnonzero(rest), int(BACKGROUND_SHARE * max_points)),
    )


def object_top(vertices: np.ndarray, T_world_obj: np.ndarray, com: np.ndarray) -> np.ndarray:
    """The top of an object (world frame, m, (3,)): above its centre of mass ``com`` ((3,),
    object frame), at the height of the highest vertex of its mesh (``vertices`` ``(V, 3)``,
    object frame) posed at ``T_world_obj`` (4, 4)."""
    T = np.asarray(T_world_obj, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    top = R @ np.asarray(com, dtype=float) + t
    top[2] = float((np.asarray(vertices, dtype=float) @ R.T + t)[:, 2].max())
    return top


def place_labels(tops: np.ndarray, eye: np.ndarray | None = None) -> np.ndarray:
    """Heights (m, world z) ``(n,)`` of the labels of objects whose tops are ``tops``
    ``(n, 3)`` (world frame, m; the point of the top above each centre of mass): each label at
    :data:`LABEL_MARGIN` above its own top, raised (in steps) until it is at least
    :data:`LABEL_STEP` above or below the label of every object closer than
    :data:`LABEL_CLEARANCE` in x-y. From any view but straight down, the labels of neighbours
    then sit apart on screen, not on top of each other.

    Objects are placed lowest top first (tops binned by :data:`LABEL_STEP`); within a bin the
    one nearest ``eye`` (the camera position, world frame, m, when known) first, so a raised
    label is the farther object's, drawn higher on screen by both its height and its distance
    (raising the nearer one would undo its offset); then in the given order. The same input,
    the same heights."""
    tops = np.asarray(tops, dtype=float).reshape(-1, 3)
    z = tops[:, 2] + LABEL_MARGIN
    near_eye = (
        np.zeros(len(tops))
        if eye is None
        else np.linalg.norm(tops - np.asarray(eye, dtype=float), axis=1)
    )
    order = np.lexsort((np.arange(len(tops)), near_eye, np.floor(tops[:, 2] / LABEL_STEP)))
    placed: list[int] = []
    for i in order:
        near = [j for j in placed if np.hypot(*(tops[i, :2] - tops[j, :2])) < LABEL_CLEARANCE]
        for zj in sorted(z[j] for j in near):  # the lowest clear height, from its own up
            if abs(z[i] - zj) < LABEL_STEP:
                z[i] = zj + LABEL_STEP
        placed.append(int(i))
    return z


def depth_millimetres(depth: np.ndarray) -> np.ndarray:
    """A depth image ``(H, W)`` (or ``(H, W, 1)``; m; 0, negative or non-finite = no return)
    as ``(H, W)`` uint16 millimetres (0 = no return, as rerun reads it), rounded; depths
    beyond :data:`MAX_DEPTH_MM` mm are no return."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    mm = np.where(np.isfinite(d) & (d > 0), np.round(d * 1000.0), 0.0)
    mm[mm > MAX_DEPTH_MM] = 0.0
    return mm.astype(np.uint16)
