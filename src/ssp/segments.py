"""Each object's own part of the scene cloud (its "segment"), prepared once per frame.

The data forces (paper Eq. 13-14) and the data-fit term (Eq. 12) compare an
object's model with the scene points that belong to it. Where those come from, in order:

1. ``frame.segments[instance_id]``: the caller segmented the cloud per object;
2. ``frame.labels`` and the instance segment the object's hypotheses were estimated from
   (:attr:`ssp.scene.Hypothesis.segment`): the points of that label;
3. ``frame.labels``: the label that covers most of the object's best candidate pose (the label
   of the nearest scene point of each model sample, voted over samples within ``radius``;
   negative labels mark the table and background and never vote). Objects already in the scene
   take an instance label each: of those voting for one label, the one it covers most of its
   samples takes it, the others the next label they touch that none of them took, or none (a
   known object hidden under another then has its own few points or no data, not the other
   object's segment, which would pull it off). A new object takes the label it covers most,
   another's too: it must earn its place with its data, and a false object on an unknown one
   would pass on the unknown object's points (a label an object's hypotheses came from, 2,
   is never voted away either: those may be a false object on a known one);
4. otherwise a local crop: the scene points within the object's bounding sphere (plus ``radius``)
   of any of its candidate poses, leaving out the table (``z < table_clearance``) when the world
   has one. Neighbouring objects can leak into a crop; labels or segments are better.

All points are world frame, metres.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Collection, Mapping, Sequence
from functools import cache
from typing import TYPE_CHECKING
from weakref import WeakKeyDictionary

import numpy as np
from scipy.spatial import cKDTree

from ssp.cells import PointCells
from ssp.correction import camera_view
from ssp.geometry import in_box, squared_distances, transform_points
from ssp.library.model import ObjectModel
from ssp.sample_grid import SampleGrid
from ssp.scene import Frame

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "SegmentTrees",
    "explained_fraction",
    "indices_by_label",
    "object_segments",
    "point_spacing",
    "segment_frame",
    "segment_verdicts",
    "surface_grid",
]

log = logging.getLogger(__name__)

#: Crops leave out points less than this high (m) above the table: they are the table's.
TABLE_CLEARANCE = 0.002

#: Model samples used to vote for an object's label.
_VOTE_SAMPLES = 200


def point_spacing(tree: cKDTree, n: int = 256) -> float:
    """Median distance (m) from a segment's points to their nearest other point (an evenly
    strided subset of at most ``n``): the cloud's sampling on that object. A downsampled or
    low-resolution cloud explains fewer model samples within a fixed radius; the fit counts
    samples within a few spacings, so it does not depend on the density."""
    pts = tree.data
    if len(pts) < 2:
        return 0.0
    q = pts[:: max(1, len(pts) // n)]
    d, _ = tree.query(q, k=2)
    return float(np.median(d[:, 1]))


class SegmentTrees:
    """The KD-tree and :func:`point_spacing` of each object's segment, built on first use and
    shared by the frame's scorer and verification (one tree per segment and frame).

    Args:
        segments: ``id -> (K, 3)`` segment points (world, m); missing or empty: no tree.
    """

    def __init__(self, segments: Mapping[str, np.ndarray]) -> None:
        self._segments = segments
        self._trees: dict[str, cKDTree | None] = {}
        self._spacings: dict[str, float | None] = {}

    def tree(self, oid: str) -> cKDTree | None:
        """The segment's tree, or None when the object has no points."""
        if oid not in self._trees:
            seg = self._segments.get(oid)
            ok = seg is not None and len(seg)
            self._trees[oid] = cKDTree(np.asarray(seg, dtype=float)) if ok else None
        return self._trees[oid]

    def spacing(self, oid: str) -> float | None:
        """The segment's point spacing (m), or None when the object has no points."""
        if oid not in self._spacings:
            tree = self.tree(oid)
            self._spacings[oid] = None if tree is None else point_spacing(tree)
        return self._spacings[oid]


def _bounding_sphere(model: ObjectModel) -> tuple[np.ndarray, float]:
    """(centre (3,) in the model frame, radius m) of the model's hull vertices about its COM."""
    c = np.asarray(model.center_of_mass, dtype=float)
    return c, model.d_max


def object_segments(
    frame: Frame,
    objects: Mapping[str, tuple[ObjectModel, Sequence[np.ndarray]]],
    *,
    radius: float,
    table: bool = True,
    table_clearance: float = TABLE_CLEARANCE,
    labels: Mapping[str, int] | None = None,
    members: dict[str, int] | None = None,
    known: Collection[str] = (),
) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Segment points ``(K, 3)`` per object id (possibly empty), and the label each object's
    segment was taken from (only for objects segmented by instance ``frame.labels``).

    With ``frame.label_kind == "cluster"`` a label may hold several objects: each object's
    points are those near it (the crop), and no object owns a label. ``members`` (filled when
    given): ``id -> label`` the object lies in, for instance and cluster labels alike.

    Args:
        frame: the validated frame.
        objects: ``id -> (model, candidate poses)``; the first pose is the best guess.
        labels: ``id -> label`` of ``frame.labels`` known to be the object's (the instance
            segment its hypotheses came from); the others vote.
        known: the objects already in the scene (verified in an earlier frame): their votes
            take an instance label each (module docstring, 3).
        radius: vote distance (labels) and crop margin, m (use the data-force cut-off d_t).
        table: the world has a table at z = 0; crops leave out points below ``table_clearance``.
    """
    points = frame.points

    by_label = indices_by_label(frame.labels) if frame.labels is not None else {}
    voters = [
        (model, poses[0])
        for oid, (model, poses) in objects.items()
        if (frame.segments is None or oid not in frame.segments)
        and len(points)
        and len(poses)
        and frame.labels is not None
        and (labels or {}).get(oid) not in by_label
    ]
    vote_cells = cache(lambda: _vote_cells(points, voters, radius))
    crop_points = cache(lambda: _crop_tree(points, table, table_clearance))

    out: dict[str, np.ndarray] = {}
    owner: dict[str, int] = {}
    chosen: dict[str, int | None] = {}  # id -> label (known or voted), None: crop
    votes: dict[str, dict[int, float]] = {}  # voters: id -> label -> fraction of samples
    for oid, (model, poses) in objects.items():
        if frame.segments is not None and oid in frame.segments:
            out[oid] = frame.segments[oid]
        elif not len(points) or not len(poses):
            out[oid] = np.zeros((0, 3))
        elif frame.labels is None:
            chosen[oid] = None
        else:
            label = (labels or {}).get(oid)
            if label is not None and label not in by_label:
                log.warning("object %s: its segment label %d is not in the cloud", oid, label)
                label = None
            if label is None:
                votes[oid] = _label_votes(frame, vote_cells(), model, poses[0], radius)
                label = _top_label(votes[oid])
            chosen[oid] = label
    known_votes = {oid: v for oid, v in votes.items() if oid in known}
    if frame.label_kind == "instance" and known_votes:
        chosen.update(_one_object_per_label(known_votes))
    for oid, label in chosen.items():
        model, poses = objects[oid]
        if label is not None and members is not None:
            members[oid] = label
        if label is not None and frame.label_kind == "instance":
            out[oid] = points[by_label[label]]
            owner[oid] = label
        elif label is None and oid in votes and votes[oid]:
            out[oid] = np.zeros((0, 3))  # every label it touches is another object's
        else:
            out[oid] = _crop(*crop_points(), model, poses, radius, table, table_clearance)
    return {oid: out[oid] for oid in objects}, owner


def _one_object_per_label(votes: Mapping[str, Mapping[int, float]]) -> dict[str, int | None]:
    """Instance labels for the voters (``votes``: id -> label -> fraction of its samples
    nearest a point of that label), one voter per label: best fraction first (ties: id, then
    label), each voter takes a label it touches that no other voter has taken. A hidden object
    thus gets its own few points, not the segment of the object on it; one that touches only
    taken labels gets no segment (its data are another object's)."""
    taken: set[int] = set()
    pairs = sorted((-f, oid, label) for oid, vs in votes.items() for label, f in vs.items())
    out: dict[str, int | None] = {oid: None for oid in votes}
    done: set[str] = set()
    for _, oid, label in pairs:
        if oid in done or label in taken:
            continue
        out[oid] = label
        done.add(oid)
        taken.add(label)
    for oid in sorted(votes):
        if votes[oid] and out[oid] != _top_label(votes[oid]):
            how = "none of them" if out[oid] is None else f"segment {out[oid]}"
            log.info(
                "object %s: the labels it touches are other objects' segments; it takes %s",
                oid,
                how,
            )
    return out


def _top_label(votes: Mapping[int, float]) -> int | None:
    """The label with the largest share of the votes (ties: the smallest label), or None."""
    return max(votes, key=lambda k: (votes[k], -k), default=None)


def indices_by_label(labels: np.ndarray) -> dict[int, np.ndarray]:
    """``label -> indices (ascending)`` of the points that carry it."""
    labels = np.asarray(labels).reshape(-1)
    if not len(labels):
        return {}
    keys = labels
    if labels.dtype.kind in "iu" and -(2**15) <= labels.min() and labels.max() < 2**15:
        keys = labels.astype(np.int16)  # the same stable order, by radix sort (4x faster)
    order = np.argsort(keys, kind="stable")
    ordered = labels[order]
    starts = np.concatenate(([0], np.flatnonzero(ordered[1:] != ordered[:-1]) + 1))
    ends = np.append(starts[1:], len(order))
    return {int(ordered[a]): order[a:b] for a, b in zip(starts, ends, strict=True)}


def _vote_cells(
    points: np.ndarray, voters: Sequence[tuple[ObjectModel, np.ndarray]], radius: float
) -> PointCells | None:
    """The points ``(N, 3)`` a vote may reach sorted into cells (:class:`ssp.cells.PointCells`,
    a sample's nearest point closer than ``radius`` m, exact): those within ``radius`` of a
    voter's samples lie inside the box around every voter's bounding sphere (at its pose)
    grown by ``radius``, so a sample's nearest point within ``radius`` is the same among them
    as among all; None when the box holds no point. (A KD-tree of them took 10-20 ms a frame
    on 640 x 480 clouds, most of it building; the cells take a few.)"""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for model, T in voters:
        c_local, r = _bounding_sphere(model)
        c = T[:3, :3] @ c_local + T[:3, 3]
        lo, hi = np.minimum(lo, c - r - radius), np.maximum(hi, c + r + radius)
    near = np.flatnonzero(in_box(points, lo, hi))
    if not len(near):
        return None
    return PointCells(points, radius, live=near)


def _crop_tree(points: np.ndarray, table: bool, clearance: float) -> tuple[np.ndarray, cKDTree]:
    """The points ``(N, 3)`` a crop may take (with a table, those at least ``clearance`` m
    above it: the table and what lies below never are; they are most of a frame's points) and
    their tree, for ball queries (sliding-midpoint splits build faster)."""
    pts = points[points[:, 2] >= clearance] if table else points
    return pts, cKDTree(pts, balanced_tree=False, compact_nodes=False)


def _label_votes(
    frame: Frame,
    cells: PointCells | None,
    model: ObjectModel,
    T: np.ndarray,
    radius: float,
) -> dict[int, float]:
    """``label -> fraction`` of the model's vote samples at ``T`` whose nearest scene point
    (closer than ``radius``, m) carries that label (negative labels: table, background,
    unlabelled, never vote); empty when no sample has a labelled point near. ``cells``: the
    frame's points, at least all those within ``radius`` of a sample (None: no point is)."""
    if cells is None:
        return {}
    samples = np.asarray(model.surface_points, dtype=float)
    if len(samples) > _VOTE_SAMPLES:
        samples = samples[:: int(np.ceil(len(samples) / _VOTE_SAMPLES))]
    idx = cells.nearest(transform_points(T, samples), radius)
    hit = idx >= 0
    if not hit.any():
        return {}
    votes = np.asarray(frame.labels)[idx[hit]]
    votes = votes[votes >= 0]
    values, counts = np.unique(votes, return_counts=True)
    return {int(v): int(c) / len(samples) for v, c in zip(values, counts, strict=True)}


def _crop(
    points: np.ndarray,
    tree: cKDTree,
    model: ObjectModel,
    poses: Sequence[np.ndarray],
    radius: float,
    table: bool,
    table_clearance: float,
) -> np.ndarray:
    c_local, r = _bounding_sphere(model)
    centres = np.array([T[:3, :3] @ c_local + T[:3, 3] for T in poses])
    hits = tree.query_ball_point(centres, r + radius)
    idx = np.unique(np.concatenate([np.asarray(h, dtype=int) for h in hits]))
    seg = points[idx]
    if table:
        seg = seg[seg[:, 2] >= table_clearance]
    return seg


#: Each model's surface samples in :class:`~ssp.sample_grid.SampleGrid` s by reach (m), per
#: process (a grid does not pickle, so it stays off the model): the lookups of
#: :func:`_near_surface` and the shared volumes, the same nearest samples and distances as
#: :attr:`ObjectModel.surface_tree`'s (tests/test_segments.py) in less than half pykdtree's
#: time (docs/benchmarks.md, "Whole-frame latency": static fusion and the transition modes).
_SURFACE_GRIDS: WeakKeyDictionary[ObjectModel, dict[float, SampleGrid]] = WeakKeyDictionary()

#: The reach of a model's first surface grid (m): the radii of the frame's lookups (the
#: inlier radius and the surface spacing, 7.4 mm by default; the residual cap, 6.75 mm) fit.
SURFACE_GRID_REACH = 0.0075
#: Its voxel (m): some 15 samples listed per voxel (a finer one lists fewer and takes longer
#: to build).
SURFACE_GRID_VOXEL = 0.003
#: A lookup farther than :data:`SURFACE_GRID_REACH` gets a grid whose reach is its radius
#: rounded up to a multiple of this (m), so that a few grids serve any radii.
SURFACE_GRID_STEP = 0.0025


def _near_surface(
    points: np.ndarray, model: ObjectModel, T_world_obj: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``points`` ``(K, 3)`` (world, m) within the model's bounding sphere at
    ``T_world_obj`` grown by ``radius`` (m), in the model frame ``(L, 3)``, with each one's
    distance to its nearest surface sample within ``radius`` (inf: none) and that sample's
    index."""
    c_local, r = _bounding_sphere(model)
    R, t = T_world_obj[:3, :3], T_world_obj[:3, 3]
    near = np.sqrt(squared_distances(points, R @ c_local + t)) <= r + radius  # = the norms
    local = np.ascontiguousarray((points[near] - t) @ R)  # R^T (p - t)
    if not len(local):
        return local, np.zeros(0), np.zeros(0, dtype=np.int64)
    return (local, *surface_grid(model, radius).nearest_within(local, radius))


def surface_grid(model: ObjectModel, radius: float) -> SampleGrid:
    """``model``'s surface samples (model frame) in a :class:`~ssp.sample_grid.SampleGrid`
    that reaches ``radius`` (m), made once per process and reach (:data:`_SURFACE_GRIDS`):
    :data:`SURFACE_GRID_REACH`, or ``radius`` rounded up to :data:`SURFACE_GRID_STEP` when
    farther."""
    reach = SURFACE_GRID_REACH
    if radius > reach:
        reach = max(SURFACE_GRID_STEP * math.ceil(float(radius) / SURFACE_GRID_STEP), radius)
    grids = _SURFACE_GRIDS.setdefault(model, {})
    if reach not in grids:
        samples = np.ascontiguousarray(model.surface_points, dtype=float)
        grids[reach] = SampleGrid(samples, reach, SURFACE_GRID_VOXEL)
    return grids[reach]


def explained_fraction(
    points: np.ndarray, model: ObjectModel, T_world_obj: np.ndarray, radius: float
) -> float:
    """Fraction of ``points`` ``(K, 3)`` (world, m) within ``radius`` (m) of the model's surface
    samples at ``T_world_obj``: how much of a segment the object at that pose accounts for
    (the data-to-model direction; the data fit c of Eq. 12 is model-to-data). 0 for no points.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if not len(points):
        return 0.0
    _, dist, _ = _near_surface(points, model, T_world_obj, radius)
    return float(np.count_nonzero(np.isfinite(dist))) / len(points)


def surface_residual(
    points: np.ndarray, model: ObjectModel, T_world_obj: np.ndarray, cap: float
) -> float:
    """Mean point-to-plane distance (m) of the ``points`` ``(K, 3)`` (world, m) within the
    model's bounding sphere grown by ``cap`` to the model's surface at ``T_world_obj``
    (:func:`surface_distances`). Noise-level where the pose is right, whatever part of it the
    camera sees; it grows with a pose error smaller than the inlier radius that the data
    fit's counts do not see (a turn of a few degrees). NaN without such points."""
    d = surface_distances(points, model, T_world_obj, cap)
    return float(np.mean(d)) if len(d) else float("nan")


def surface_distances(
    points: np.ndarray, model: ObjectModel, T_world_obj: np.ndarray, cap: float
) -> np.ndarray:
    """(L,) the distance (m) of each of the ``points`` ``(K, 3)`` (world, m) within the model's
    bounding sphere at ``T_world_obj`` grown by ``cap`` (m) to the tangent plane of its
    nearest surface sample, capped at ``cap`` (a point with no sample within ``cap`` counts
    ``cap``)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    local, dist, j = _near_surface(points, model, T_world_obj, cap)
    out = np.full(len(local), cap)
    hit = np.isfinite(dist)
    samples = np.asarray(model.surface_points, dtype=float)[j[hit]]
    normals = np.asarray(model.surface_normals, dtype=float)[j[hit]]
    plane = np.abs(np.einsum("ij,ij->i", local[hit] - samples, normals))
    out[hit] = np.minimum(plane, cap)
    return out


def segment_frame(ctx: FrameContext) -> None:
    """Stage *segments*: each object's segment (:func:`object_segments`, gathered around its
    provisional pose and its hypotheses, or its previous pose when undetected; the instance
    segment its hypotheses came from, or the one an undetected object took, is its own), the
    camera's view of the frame (:class:`ssp.visibility.CameraView`, when the frame has a camera
    pose) and the segments' KD-trees.

    Sets ``cand_poses``, ``segments``, ``owner``, ``members``, ``view`` and ``trees``.
    """
    cfg, frame, groups, models = ctx.config, ctx.frame, ctx.groups, ctx.models
    cand_poses = {oid: [ctx.first[oid], *(h.T_world_obj for h in groups[oid])] for oid in groups}
    cand_poses.update({oid: [T] for oid, T in ctx.prev_pose.items() if oid not in groups})
    # the segment each object's hypotheses came from, and those undetected objects took
    segment_labels = {oid: hyps[0].segment for oid, hyps in groups.items()}
    own_labels = {oid: s for oid, s in segment_labels.items() if s is not None}
    own_labels.update(ctx.assoc.claimed)
    members: dict[str, int] = {}
    segments, owner = object_segments(
        frame,
        {oid: (models[oid], cand_poses[oid]) for oid in cand_poses},
        radius=cfg.forces.max_distance,
        table=ctx.table,
        labels=own_labels,
        members=members,
        known=set(ctx.known),
    )
    if ctx.view is None:  # built by the depth correction, unless the stages run by hand
        ctx.view = camera_view(frame, cfg)
    ctx.cand_poses, ctx.segments, ctx.owner, ctx.members = cand_poses, segments, owner, members
    ctx.trees = SegmentTrees(segments)


def segment_verdicts(ctx: FrameContext, kept: set[str]) -> dict[int, str]:
    """Label -> what became of it: the object it is (``ctx.members``: the label each object
    lies in; ``kept``: the output's ids), or why none, for every label of the cloud that is not
    the table or background."""
    frame, old_of = ctx.frame, ctx.old_of
    if frame.labels is None:
        return {}
    held: dict[int, set[str]] = {}
    for oid, label in ctx.members.items():
        out_id = old_of.get(oid, oid)
        if out_id in kept:
            held.setdefault(int(label), set()).add(out_id)
    out: dict[int, str] = {
        label: ("object " if len(ids) == 1 else "objects ") + ", ".join(sorted(ids))
        for label, ids in held.items()
    }
    said: dict[int, list[str]] = {}
    for r in sorted(ctx.rejected.values(), key=lambda r: r.id):
        # the segment its hypotheses came from, else the one it took (a cluster, a class mask)
        its = r.segment if r.segment is not None else ctx.members.get(r.id)
        if its is not None and int(its) not in out:
            said.setdefault(int(its), []).append(f"rejected {r.class_name} {r.id}: {r.reason}")
    out.update({label: "; ".join(texts) for label, texts in said.items()})
    for label in _labels_present(np.asarray(frame.labels)):
        if int(label) not in out:
            out[int(label)] = "no object: no hypothesis was given for it"
    return dict(sorted(out.items()))


def _labels_present(labels: np.ndarray) -> np.ndarray:
    """The distinct instance labels ``>= 0`` of ``labels`` (integers), ascending: counted, as
    ``np.unique`` finds them by sorting every point's label (5 ms for a 640 x 480 frame)."""
    labels = labels[labels >= 0]
    if not len(labels) or labels.max() > len(labels) + (1 << 16):  # sparse: sorting is cheaper
        return np.unique(labels)
    return np.flatnonzero(np.bincount(labels))
