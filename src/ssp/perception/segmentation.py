"""Object segments of a scene cloud: Euclidean clustering and label handling.

:func:`euclidean_clusters` joins points closer than ``tolerance`` (a kd-tree radius graph from
scipy's ``cKDTree.query_pairs`` and its connected components). Its cost is bounded: identical
points are merged first (a sensor that writes invalid pixels as one point gives thousands), and
a cloud so dense that the radius graph would exceed :data:`MAX_PAIRS` edges is clustered on a
voxel grid instead (see the function). :func:`segment_cloud` turns a
world-frame cloud, with or without per-point labels, into instance segments (:class:`Segmentation`).
Labels are deterministic: clusters are numbered by descending size, ties by their lowest point
index.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ssp.components import connected_components
from ssp.errors import PerceptionError

__all__ = ["MAX_PAIRS", "Segmentation", "euclidean_clusters", "segment_cloud"]

log = logging.getLogger(__name__)

#: Most point pairs the clustering's radius graph may hold (about 16 bytes each, so ~130 MB,
#: plus the sparse matrix built from them); denser clouds are clustered on a voxel grid.
MAX_PAIRS = 8_000_000


@dataclass
class Segmentation:
    """Instance segments of a cloud.

    Attributes:
        labels: ``(N,)`` int64 segment label per point; -1 for table, background and noise.
        classes: segment label -> object class name, or None when the class is unknown.
    """

    labels: np.ndarray
    classes: dict[int, str | None] = field(default_factory=dict)

    @property
    def segment_ids(self) -> list[int]:
        """The segment labels, ascending."""
        return sorted(self.classes)

    def points(self, points: np.ndarray, label: int) -> np.ndarray:
        """The rows of ``points`` ``(N, 3)`` in segment ``label``."""
        return np.asarray(points)[self.labels == label]


def euclidean_clusters(
    points: np.ndarray, *, tolerance: float = 0.006, min_points: int = 30
) -> np.ndarray:
    """Euclidean clusters of a cloud: labels ``(N,)`` int64.

    Two points are in one cluster when a chain of points links them with steps of at most
    ``tolerance`` (m). Clusters are numbered 0, 1, ... by descending size, ties by their lowest
    point index; points of clusters smaller than ``min_points``, and non-finite points, get -1.

    Time and memory are bounded (O(N log N), at most :data:`MAX_PAIRS` pairs): identical
    points are merged before the radius graph is built (they still count in the cluster
    sizes), which changes nothing else. If the
    distinct points would still give more than :data:`MAX_PAIRS` pairs (a cloud with very
    many points within ``tolerance`` of each other), the points are binned on a grid of cell
    ``tolerance / 2`` (each cell's points lie within ``tolerance`` of each other, so a cell is
    one cluster anyway), and cells are linked when their first points lie within
    ``tolerance``; the grid is coarsened to ``tolerance`` if that is still too many. Both are
    logged.
    """
    p = _check_points(points, "points")
    if not tolerance > 0:
        raise ValueError(f"tolerance must be > 0, got {tolerance}")
    labels = np.full(len(p), -1, dtype=np.int64)
    finite = np.flatnonzero(np.isfinite(p).all(axis=1))
    if len(finite) == 0:
        return labels
    q = p[finite]
    _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    uniq, inverse = q[first], np.asarray(inverse).reshape(-1)
    if len(uniq) < len(q):
        log.info(
            "euclidean_clusters: %d of %d points are copies of others (%d distinct)",
            len(q) - len(uniq),
            len(q),
            len(uniq),
        )
    comp = _radius_components(uniq, float(tolerance))
    labels[finite] = _renumber(comp[inverse], min_points)  # sizes and order over all points
    return labels


def pair_bound(points: np.ndarray, tolerance: float) -> int:
    """An upper bound on the pairs of ``points`` ``(N, 3)`` within ``tolerance`` (m), without
    a tree: ``N (N - 1) / 2``, or, binned on a grid of cell ``tolerance`` (two such points lie
    in the same or adjacent cells), the pairs within each cell plus those between each cell
    and its 13 neighbours of one half-space (each adjacent pair of cells once)."""
    n = len(points)
    if n * (n - 1) // 2 <= MAX_PAIRS:
        return n * (n - 1) // 2
    keys = np.floor(np.asarray(points, dtype=float) / tolerance).astype(np.int64)
    keys -= keys.min(axis=0) - 1  # >= 1: the neighbours' keys stay >= 0
    span = keys.max(axis=0) + 2
    if float(np.prod(span.astype(float))) >= 2.0**62:  # too far apart to pack: no bound
        return n * (n - 1) // 2
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    cells, counts = np.unique(flat, return_counts=True)
    bound = int(np.dot(counts, counts - 1)) // 2
    for dx, dy, dz in _HALF_NEIGHBOURS:
        other = cells + (dx * span[1] + dy) * span[2] + dz
        at = np.searchsorted(cells, other)
        hit = at < len(cells)
        hit[hit] = cells[at[hit]] == other[hit]
        bound += int(np.dot(counts[hit], counts[at[hit]]))
    return bound


#: The 13 neighbours of a grid cell on one side (the other 13 are their opposites).
_HALF_NEIGHBOURS = [
    (dx, dy, dz)
    for dx in (-1, 0, 1)
    for dy in (-1, 0, 1)
    for dz in (-1, 0, 1)
    if (dx, dy, dz) > (0, 0, 0)
]


def _radius_components(q: np.ndarray, tolerance: float) -> np.ndarray:
    """Connected components ``(M,)`` of the ``tolerance`` radius graph of distinct points
    ``q``, within the :data:`MAX_PAIRS` budget (voxel grid fallback: :func:`euclidean_clusters`)."""
    for cell in (None, tolerance / 2.0, tolerance):
        if cell is None:
            nodes, of_point = q, None
        else:
            keys = np.floor(q / cell).astype(np.int64)
            _, first, inv = np.unique(keys, axis=0, return_index=True, return_inverse=True)
            nodes, of_point = q[first], np.asarray(inv).reshape(-1)
        # sliding-midpoint tree: ~2x faster to build than the balanced one, queries as fast
        tree = cKDTree(nodes, balanced_tree=False)
        if cell is None and pair_bound(nodes, tolerance) <= MAX_PAIRS:
            break  # within the budget for sure: the exact count (twice the query) not needed
        pairs_needed = (int(tree.count_neighbors(tree, tolerance)) - len(nodes)) // 2
        if pairs_needed <= MAX_PAIRS or cell == tolerance:
            break
    if cell is not None:
        log.warning(
            "euclidean_clusters: %d distinct points would give more than %d pairs within "
            "%.4f m; clustered on a %.4f m grid (%d cells)",
            len(q),
            MAX_PAIRS,
            tolerance,
            cell,
            len(nodes),
        )
    pairs = tree.query_pairs(tolerance, output_type="ndarray")
    n = len(nodes)
    _, comp = connected_components(n, pairs[:, 0], pairs[:, 1])
    return comp if of_point is None else comp[of_point]


def segment_cloud(
    points_world: np.ndarray,
    labels: np.ndarray | None = None,
    label_classes: Mapping[int, str] | None = None,
    *,
    table_height: float = 0.004,
    tolerance: float = 0.006,
    min_points: int = 30,
) -> Segmentation:
    """Instance segments of a world-frame cloud (z up, table top at z = 0).

    Three modes:

    * ``labels`` given, no ``label_classes``: the labels are instance segments and keep their
      values (negative = background, becomes -1); class unknown (None).
    * ``labels`` and ``label_classes`` given: the labels are *class* regions (one label may
      cover several touching or separate objects, e.g. a colour class). Each region is split
      into Euclidean clusters, each cluster a new segment of that class
      (``label_classes[label]``, None for a label missing from it). New labels are numbered by
      descending size, ties by lowest point index.
    * no ``labels``: points less than ``table_height`` (m) above the table (``z <
      table_height``) are background; the rest is split into Euclidean clusters.

    In every mode segments of fewer than ``min_points`` points become -1.

    Args:
        points_world: ``(N, 3)`` points, world frame, m.
        labels: ``(N,)`` integer label per point, or None.
        label_classes: class label -> class name.
        table_height: height (m) below which points are table (mode without labels).
        tolerance: clustering distance (m).
        min_points: smallest segment kept.
    """
    p = _check_points(points_world, "points_world")
    if labels is None:
        if label_classes is not None:
            raise PerceptionError("label_classes given without labels")
        return _segment_unlabelled(p, table_height, tolerance, min_points)
    lab = _check_labels(labels, len(p))
    if label_classes is None:
        return _segment_instances(lab, min_points)
    return _segment_classes(p, lab, label_classes, tolerance, min_points)


# ------------------------------------------------------------------------------------------
# helpers


def _check_points(points: np.ndarray, what: str) -> np.ndarray:
    """``points`` as float64 ``(N, 3)``; PerceptionError otherwise."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise PerceptionError(f"{what} must have shape (N, 3), got {p.shape}")
    return p


def _check_labels(labels: np.ndarray, n: int) -> np.ndarray:
    """``labels`` as int64 ``(n,)``; PerceptionError otherwise."""
    lab = np.asarray(labels)
    if lab.shape != (n,):
        raise PerceptionError(f"labels must have shape ({n},) (one per point), got {lab.shape}")
    if not np.issubdtype(lab.dtype, np.integer):
        if not (np.issubdtype(lab.dtype, np.number) and np.array_equal(lab, np.round(lab))):
            raise PerceptionError(f"labels must be integers, got dtype {lab.dtype}")
    return lab.astype(np.int64)


def _renumber(comp: np.ndarray, min_points: int) -> np.ndarray:
    """Component ids ``(N,)`` (>= 0) renumbered by descending size, ties by lowest index;
    components smaller than ``min_points`` become -1."""
    ids, first, sizes = np.unique(comp, return_index=True, return_counts=True)
    order = np.lexsort((first, -sizes))  # primary key: size (descending), then first index
    keep = order[sizes[order] >= int(min_points)]
    new = np.full(len(ids), -1, dtype=np.int64)
    new[keep] = np.arange(len(keep))
    return new[np.searchsorted(ids, comp)]


def _segment_unlabelled(
    p: np.ndarray, table_height: float, tolerance: float, min_points: int
) -> Segmentation:
    labels = np.full(len(p), -1, dtype=np.int64)
    above = np.flatnonzero(p[:, 2] >= float(table_height))  # NaN rows fail the test
    labels[above] = euclidean_clusters(p[above], tolerance=tolerance, min_points=min_points)
    n_seg = int(labels.max()) + 1 if len(labels) else 0
    log.debug("segment_cloud: %d points above the table, %d segments", len(above), n_seg)
    return Segmentation(labels, {i: None for i in range(n_seg)})


def _segment_instances(lab: np.ndarray, min_points: int) -> Segmentation:
    labels = np.where(lab < 0, -1, lab)
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    small = ids[counts < int(min_points)]
    if len(small):
        log.debug("segment_cloud: dropped %d segments below %d points", len(small), min_points)
        labels[np.isin(labels, small)] = -1
    kept = ids[counts >= int(min_points)]
    return Segmentation(labels, {int(i): None for i in kept})


def _segment_classes(
    p: np.ndarray,
    lab: np.ndarray,
    label_classes: Mapping[int, str],
    tolerance: float,
    min_points: int,
) -> Segmentation:
    classes = {int(k): v for k, v in label_classes.items()}
    region = np.full(len(p), -1, dtype=np.int64)  # one component id per (class, cluster)
    region_class: list[str | None] = []
    for value in np.unique(lab[lab >= 0]):
        idx = np.flatnonzero(lab == value)
        sub = euclidean_clusters(p[idx], tolerance=tolerance, min_points=min_points)
        ok = sub >= 0
        region[idx[ok]] = sub[ok] + len(region_class)
        region_class.extend([classes.get(int(value))] * (int(sub.max()) + 1 if ok.any() else 0))
        if int(value) not in classes:
            log.warning("segment_cloud: label %d has no class in label_classes", int(value))
    labels = np.full(len(p), -1, dtype=np.int64)
    inside = np.flatnonzero(region >= 0)
    labels[inside] = _renumber(region[inside], 0)
    ids, first = np.unique(region[inside], return_index=True)
    out = {int(labels[inside[f]]): region_class[int(r)] for r, f in zip(ids, first, strict=True)}
    return Segmentation(labels, dict(sorted(out.items())))
