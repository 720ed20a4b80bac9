"""Between frames: data association, transition modes, symmetry snapping (paper section IV-C).

* :func:`associate` gives every hypothesis of a frame an object instance id: the id it carries,
  else the id of the previous object it matches (Hungarian assignment), else a fresh one.
* :func:`classify` names an object's transition mode (added / removed / static / perturbed /
  support-retained) from its previous and current poses (DESIGN section 4, "Temporal");
  whether a changed estimate is motion in the world or a correction, and the mean of an
  object's estimates while it is at rest, are :mod:`ssp.motion`'s.
* :func:`snap_symmetric` picks, among the symmetric equivalents of a pose, the one closest to
  the previous frame's, so a symmetric object never flips between frames (DESIGN "Symmetry").

Ephemeral objects and the support test behind ``retained`` need the physics and the camera;
they belong to the scene parser, which passes its verdict to :func:`classify`.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from ssp.config import TemporalConfig
from ssp.errors import DuplicateObjectError, SSPError
from ssp.estimate import Rejected
from ssp.first_guess import first_guess
from ssp.library.symmetry import Symmetry
from ssp.overlap import same_volume
from ssp.probability import pose_change
from ssp.retention import TriageState
from ssp.scene import FrameError, Hypothesis, TransitionMode
from ssp.segments import (
    TABLE_CLEARANCE,
    explained_fraction,
)
from ssp.shared_volume import resolve_shared_volumes

if TYPE_CHECKING:
    from ssp.frame_context import FrameContext

__all__ = [
    "CLASS_MARGIN",
    "Association",
    "associate",
    "associate_frame",
    "association_gates",
    "classify",
    "counted_id_factory",
    "default_id_factory",
    "duplicates_of_undetected",
    "one_object_per_segment",
    "reidentify",
    "reidentify_moved",
    "same_volume_test",
    "snap_symmetric",
]

log = logging.getLogger(__name__)

#: Cost of a forbidden (gated-out) pair in the assignment matrix.
_FORBIDDEN = 1e6


def association_gates(library: Mapping, cfg: TemporalConfig) -> dict[str, float]:
    """Per-class association radius, m: ``min(association_distance, association_size_fraction
    x the model's median extent)``. The median extent is the centre distance of two objects
    of the class lying side by side (a thin wrench's thickness would give a gate smaller than
    the hypotheses' own noise, so one wrench would split into several objects)."""
    return {
        name: min(
            cfg.association_distance,
            cfg.association_size_fraction * float(np.median(np.asarray(m.extents, float))),
        )
        for name, m in library.items()
    }


def default_id_factory(taken: Iterable[str] = ()) -> Callable[[str], str]:
    """A deterministic ``new_id(class_name)``: ``f"{class_name}_{k}"``, k = 0, 1, ... per class,
    skipping every id in ``taken`` and every id it has already returned."""
    used = set(taken)
    counters: dict[str, itertools.count] = {}

    def new_id(class_name: str) -> str:
        counter = counters.setdefault(class_name, itertools.count())
        while True:
            candidate = f"{class_name}_{next(counter)}"
            if candidate not in used:
                used.add(candidate)
                return candidate

    return new_id


class _Cluster:
    """Hypotheses of one class taken to describe one physical object."""

    def __init__(self, first: Hypothesis, order: int, instance_id: str | None = None) -> None:
        self.members = [first]
        self.indices = [order]  # input positions of the members
        self.order = order  # position of its first (best) hypothesis, for stable ordering
        self.first_index = order  # smallest input position among its members
        self.instance_id = instance_id
        self.segment = first.segment  # instance segment of its members, None: unknown

    def add(self, h: Hypothesis, index: int) -> None:
        self.members.append(h)
        self.indices.append(index)
        self.first_index = min(self.first_index, index)
        if self.segment is None:
            self.segment = h.segment

    def accepts(self, segment: int | None) -> bool:
        """Can a hypothesis (or cluster) of instance segment ``segment`` describe this object?
        Not when both segments are known and differ: one instance segment is one object."""
        return segment is None or self.segment is None or segment == self.segment

    @property
    def best(self) -> Hypothesis:
        return self.members[0]


def same_volume_test(library: Mapping, fraction: float) -> Callable[[Hypothesis, Hypothesis], bool]:
    """The ``same_volume`` test of :func:`associate`: do two hypotheses (one class) share
    ``fraction`` of their model's volume in ``library``? (:func:`ssp.overlap.same_volume`)"""

    def test(a: Hypothesis, b: Hypothesis) -> bool:
        return same_volume(library[a.class_name], a.T_world_obj, b.T_world_obj, fraction)

    return test


def associate(
    hypotheses: list[Hypothesis],
    previous: Mapping[str, tuple[str, np.ndarray]],
    symmetries: Mapping[str, Symmetry],
    *,
    max_distance: float | Mapping[str, float] = 0.05,
    rotation_weight: float = 0.05,
    new_id: Callable[[str], str] | None = None,
    same_volume: Callable[[Hypothesis, Hypothesis], bool] | None = None,
    centres: Mapping[str, np.ndarray] | None = None,
) -> dict[str, list[Hypothesis]]:
    """Group a frame's hypotheses by object instance id.

    1. **Given ids.** A hypothesis with ``instance_id`` keeps it; its group is fixed.
    2. **Clustering.** The other hypotheses are visited by decreasing score (ties: input
       order). Each joins the group of its class whose *best* (first) hypothesis is nearest in
       translation, if that is within ``max_distance``; groups with a given id are candidates
       too. Otherwise it starts a new cluster. Only the translation counts here: hypotheses at
       one place with different orientations are alternative poses of one object (two objects
       cannot share a volume), and they are what the search compares. Note that two touching
       objects of one class closer than ``max_distance`` (centre to centre) would merge: keep
       ``max_distance`` below the smallest object's size. Hypotheses from different instance
       segments (:attr:`Hypothesis.segment`, both known) never share a group: a half-hidden
       object's hypotheses can reach into the object on top of it. Hypotheses of one class
       from the same instance segment always do, however far apart: an estimator's gross
       outliers on a segment are wrong poses of that segment's object, not other objects.
    2b. **Merging** (with ``same_volume``): a cluster whose best hypothesis occupies the same
       volume as the best of an earlier (better-scored) cluster of its class joins it, unless
       their instance segments differ: two objects cannot share a volume, so widely spread
       hypotheses of one half-hidden object do not become two objects.
    3. **Matching.** Clusters without an id are matched, class by class, to the previous
       objects of that class not claimed by a given id, with
       :func:`scipy.optimize.linear_sum_assignment` (globally optimal) on
       ``cost = dt + rotation_weight * dtheta`` (:func:`ssp.probability.pose_change`,
       symmetry-aware), minimised over the cluster's members. A pair is allowed only when some
       member is within ``max_distance`` in translation of the previous pose; the rotation is
       left out of the gate so that an object which toppled (rotated by 90 degrees in place)
       keeps its id, and only ranks nearby candidates.
    4. **New ids.** Unmatched clusters get ``new_id(class_name)`` in a stable order (class name,
       then decreasing best score, then input order).

    Args:
        hypotheses: the frame's hypotheses (validated: rigid poses, known classes).
        previous: previous objects, ``instance_id -> (class_name, T_world_obj)``.
        symmetries: class name -> model symmetry (missing classes: asymmetric).
        max_distance: clustering radius and matching gate, m; a mapping gives one per class
            (classes missing from it use 0.05 m).
        rotation_weight: metres of cost per radian of symmetric rotation angle.
        same_volume: ``f(h1, h2) -> bool``, do two hypotheses of one class overlap so much
            that they must be one object (see step 2b); None: no merging.
        new_id: fresh-id factory; default :func:`default_id_factory` over the previous ids and
            the given ids (``f"{class}_{k}"``).
        centres: class name -> model point (model frame, m; the centre of mass) at which
            distances are measured; classes missing from it, or None: the model origin (a mesh
            whose origin lies far from its body would otherwise split into several objects
            when its hypotheses' orientations differ).

    Returns:
        ``instance_id -> hypotheses`` (each with ``instance_id`` set, best score first), in the
        order of each group's best hypothesis in the input.

    Raises:
        DuplicateObjectError: ``new_id`` returned an id already in use.
    """
    given_ids = {h.instance_id for h in hypotheses if h.instance_id is not None}
    gate = _gate(max_distance)
    if new_id is None:
        new_id = default_id_factory([*previous, *given_ids])
    at = _centre_at(centres)
    # each hypothesis's centre, once (a cluster's best is its first member: centre[c.order])
    centre = [tuple(at(h.class_name, h.T_world_obj).tolist()) for h in hypotheses]
    clusters, by_id = _cluster(hypotheses, centre, gate)
    if same_volume is not None:  # two objects cannot share a volume: merge such clusters
        clusters = _merge_same_volume(clusters, same_volume)
    matching = _Matching(previous, symmetries, centres, centre, at, gate, rotation_weight)
    matching.name(clusters, given_ids, by_id, new_id)
    return _groups(clusters)


def _gate(max_distance: float | Mapping[str, float]) -> Callable[[str], float]:
    """``gate(class_name)``: the clustering radius and matching gate of a class, m."""
    if isinstance(max_distance, Mapping):
        gates = dict(max_distance)

        def gate(class_name: str) -> float:
            return float(gates.get(class_name, 0.05))

        return gate
    radius = float(max_distance)

    def fixed(class_name: str) -> float:
        return radius

    return fixed


def _centre_at(
    centres: Mapping[str, np.ndarray] | None,
) -> Callable[[str, np.ndarray], np.ndarray]:
    """``at(class_name, T)``: the world position (3,) of the class's centre at pose ``T``."""
    points = dict(centres or {})

    def at(class_name: str, T: np.ndarray) -> np.ndarray:
        T = np.asarray(T, dtype=float)
        c = points.get(class_name)
        return T[:3, 3] if c is None else T[:3, :3] @ np.asarray(c, dtype=float) + T[:3, 3]

    return at


def _cluster(
    hypotheses: list[Hypothesis], centre: list[tuple], gate: Callable[[str], float]
) -> tuple[list[_Cluster], dict[str, _Cluster]]:
    """Steps 1-2 of :func:`associate`: the given ids' groups, then every other hypothesis (best
    score first) joins the nearest cluster of its class within the gate (or its instance
    segment's), or starts one. Returns the clusters and those with a given id, by id."""
    order = sorted(range(len(hypotheses)), key=lambda i: (-float(hypotheses[i].score), i))
    clusters: list[_Cluster] = []
    by_id: dict[str, _Cluster] = {}
    for i in order:  # given ids first: their groups seed the clustering
        h = hypotheses[i]
        if h.instance_id is None:
            continue
        if h.instance_id in by_id:
            by_id[h.instance_id].add(h, i)
        else:
            by_id[h.instance_id] = _Cluster(h, i, h.instance_id)
            clusters.append(by_id[h.instance_id])
    for i in order:
        h = hypotheses[i]
        if h.instance_id is not None:
            continue
        t = centre[i]
        best, best_d = None, np.inf
        if h.segment is not None:  # one instance segment is one object, however spread
            best = next(
                (
                    c
                    for c in clusters
                    if c.best.class_name == h.class_name and c.segment == h.segment
                ),
                None,
            )
        for c in clusters if best is None else ():
            if c.best.class_name != h.class_name or not c.accepts(h.segment):
                continue
            d = math.dist(centre[c.order], t)
            if d <= gate(h.class_name) and d < best_d:
                best, best_d = c, d
        if best is None:
            clusters.append(_Cluster(h, i))
        else:
            best.add(h, i)
    return clusters, by_id


def _merge_same_volume(
    clusters: list[_Cluster], same_volume: Callable[[Hypothesis, Hypothesis], bool]
) -> list[_Cluster]:
    """Step 2b of :func:`associate`: a cluster without a given id whose best hypothesis shares
    the volume of an earlier cluster's best (same class, segments not different) joins it."""
    kept: list[_Cluster] = []
    for c in clusters:
        target = None
        if c.instance_id is None:
            target = next(
                (
                    k
                    for k in kept
                    if k.best.class_name == c.best.class_name
                    and k.accepts(c.segment)
                    and same_volume(k.best, c.best)
                ),
                None,
            )
        if target is None:
            kept.append(c)
        else:
            for h, index in zip(c.members, c.indices, strict=True):
                target.add(h, index)
    return kept


class _Matching:
    """Steps 3-4 of :func:`associate`: clusters to previous objects, then new ids."""

    def __init__(
        self, previous, symmetries, centres, centre, at, gate, rotation_weight: float
    ) -> None:
        self.previous, self.symmetries, self.centre, self.at = previous, symmetries, centre, at
        self.centres, self.gate = dict(centres or {}), gate
        self.rotation_weight = rotation_weight

    def name(
        self,
        clusters: list[_Cluster],
        given_ids: set[str],
        by_id: dict[str, _Cluster],
        new_id: Callable[[str], str],
    ) -> None:
        """Give every cluster without an id one: a previous object's (:meth:`assign`, class by
        class), else ``new_id(class_name)`` (class name, then decreasing best score, then
        input order). DuplicateObjectError when ``new_id`` returns an id in use."""
        previous = self.previous
        free = [c for c in clusters if c.instance_id is None]
        for class_name in sorted({c.best.class_name for c in free}):
            rows = [c for c in free if c.best.class_name == class_name]
            rows.sort(key=lambda c: (-float(c.best.score), c.order))
            cols = sorted(
                k for k, (cls, _) in previous.items() if cls == class_name and k not in given_ids
            )
            if cols:
                self.assign(class_name, rows, cols)
            for c in rows:
                if c.instance_id is None:
                    ident = new_id(class_name)
                    if ident in previous or ident in given_ids or ident in by_id:
                        raise DuplicateObjectError(f"new_id returned {ident!r}, which is in use")
                    c.instance_id = ident
                    by_id[ident] = c

    def assign(self, class_name: str, rows: list[_Cluster], cols: list[str]) -> None:
        """Give each cluster of ``rows`` the id of the previous object of ``cols`` it is
        assigned to (globally optimal on ``dt + rotation_weight * dtheta``, gated)."""
        sym = self.symmetries.get(class_name)
        c_model = self.centres.get(class_name)
        radius_c = self.gate(class_name)
        p_prev = {k: self.at(class_name, self.previous[k][1]) for k in cols}
        cost = np.full((len(rows), len(cols)), _FORBIDDEN)
        for r, c in enumerate(rows):
            at_members = np.array([self.centre[i] for i in c.indices])
            for j, k in enumerate(cols):
                T_prev = self.previous[k][1]
                near = np.linalg.norm(at_members - p_prev[k], axis=1) <= radius_c
                # the gated-out members skip the (costlier) symmetric rotation
                for m in np.flatnonzero(near):
                    h = c.members[m]
                    dt, dth = pose_change(T_prev, h.T_world_obj, sym, c_model)
                    if dt <= radius_c:
                        cost[r, j] = min(cost[r, j], dt + self.rotation_weight * dth)
        for r, j in zip(*linear_sum_assignment(cost), strict=True):
            if cost[r, j] < _FORBIDDEN:
                rows[r].instance_id = cols[j]


def _groups(clusters: list[_Cluster]) -> dict[str, list[Hypothesis]]:
    """The clusters as ``id -> hypotheses`` (best score first; input order on ties), in the
    order of each cluster's first hypothesis in the input."""
    clusters = sorted(clusters, key=lambda c: c.first_index)
    out: dict[str, list[Hypothesis]] = {}
    for c in clusters:
        ident = c.instance_id
        assert ident is not None, "every cluster has an id by now"
        members = sorted(c.members, key=lambda h: -float(h.score))  # stable: input order on ties
        out[ident] = [replace(h, instance_id=ident) for h in members]
    return out


def one_object_per_segment(
    groups: Mapping[str, list[Hypothesis]],
    rank: Callable[[str, list[Hypothesis]], float | tuple],
) -> tuple[dict[str, list[Hypothesis]], dict[str, str]]:
    """One object per instance segment: among the groups whose hypotheses came from the same
    segment (:attr:`Hypothesis.segment` of their best; of different classes, since
    :func:`associate` already joins one class's), the one with the highest ``rank(id, group)``
    stays (ties: the first in ``groups``); the others are an estimator's class confusions.

    Returns:
        the groups kept (in their order) and ``dropped id -> the id that kept the segment``.
    """
    by_segment: dict[int, list[str]] = {}
    for oid, hyps in groups.items():
        seg = hyps[0].segment if hyps else None
        if seg is not None:
            by_segment.setdefault(int(seg), []).append(oid)
    dropped: dict[str, str] = {}
    for oids in by_segment.values():
        if len(oids) < 2:
            continue
        keep = max(oids, key=lambda o: (rank(o, groups[o]), -oids.index(o)))
        dropped.update({o: keep for o in oids if o != keep})
    kept = {oid: hyps for oid, hyps in groups.items() if oid not in dropped}
    return kept, dropped


def duplicates_of_undetected(
    groups: Mapping[str, list[Hypothesis]],
    known: Mapping[str, tuple[object, np.ndarray]],
    points_of: Callable[[int], np.ndarray],
    explained: Callable[[str, np.ndarray], float],
    fraction: float,
) -> tuple[dict[str, list[Hypothesis]], dict[str, int], dict[str, str]]:
    """New objects whose segment an undetected known object explains where it was.

    A new group (no known object took it) estimated from instance segment ``s`` is the same
    object as an undetected known one when ``explained(known id, points of s)`` (the fraction
    of the segment's points its previous pose accounts for) is at least ``fraction``:
    typically a mostly hidden object for which the estimator proposed only a wrong class. The
    group is dropped and the known object takes the segment (it counts as still visible, so
    its data forces hold it where it is seen).

    Args:
        groups: this frame's groups; known ids are ``known``'s keys.
        known: the previous objects, ``id -> (class, T_world_obj)``.
        points_of: instance label -> its points ``(K, 3)``.
        explained: ``(known id, points) -> fraction``.
        fraction: the threshold; 1 or more disables the rule.

    Returns:
        the remaining groups, ``undetected id -> label`` of the segments they take, and
        ``dropped group id -> the known id it duplicates``.
    """
    undetected = sorted(set(known) - set(groups))
    if fraction >= 1 or not undetected:
        return dict(groups), {}, {}
    kept = dict(groups)
    claimed: dict[str, int] = {}
    dropped: dict[str, str] = {}
    for oid in sorted(groups):
        seg = groups[oid][0].segment
        if oid in known or seg is None:
            continue
        points = points_of(int(seg))
        best, best_fraction = None, fraction
        for u in undetected:
            if claimed.get(u, seg) != seg:
                continue
            f = explained(u, points)
            if f >= best_fraction:
                best, best_fraction = u, f
        if best is not None:
            del kept[oid]
            claimed[best] = int(seg)
            dropped[oid] = best
    return kept, claimed, dropped


def reidentify(
    gone: Mapping[str, tuple[str, np.ndarray]],
    new: Mapping[str, tuple[str, np.ndarray]],
    max_distance: Mapping[str, float] | None = None,
) -> dict[str, str]:
    """A new object where a known one of its class just vanished is that object, moved.

    ``gone``: objects removed this frame because their place is seen empty or taken (or whose
    pose the depth contradicts), ``id -> (class, last pose)``; ``new``: objects added this
    frame, ``id -> (class, pose)``; ``max_distance``: per gone id, the farthest a new object may
    be to be it (m; missing: any distance). Per class, the pairs of a globally optimal
    assignment on the distance between positions (:func:`scipy.optimize.linear_sum_assignment`)
    are matched. Returns ``new id -> old id``.
    """
    limit = dict(max_distance or {})
    out: dict[str, str] = {}
    for cls in sorted({c for c, _ in gone.values()} & {c for c, _ in new.values()}):
        a = sorted(k for k, (c, _) in gone.items() if c == cls)
        b = sorted(k for k, (c, _) in new.items() if c == cls)
        dist = np.array(
            [[float(np.linalg.norm(gone[i][1][:3, 3] - new[j][1][:3, 3])) for j in b] for i in a]
        )
        allowed = dist <= np.array([limit.get(i, np.inf) for i in a])[:, None]
        cost = np.where(allowed, dist, _FORBIDDEN)
        for r, c in zip(*linear_sum_assignment(cost), strict=True):
            if allowed[r, c]:
                out[b[c]] = a[r]
    return out


def classify(
    prev_pose: np.ndarray | None,
    cur_pose: np.ndarray | None,
    symmetry: Symmetry | None,
    cfg: TemporalConfig,
    retained: bool = False,
    centre: np.ndarray | None = None,
) -> TransitionMode:
    """Transition mode of one object between the previous and the current frame.

    * no previous pose: ``ADDED``;
    * ``retained`` (the object was not detected but kept because objects it supports would be
      unstable without it; its current pose, if any, is the one the search kept):
      ``SUPPORT_RETAINED``;
    * no current pose: ``REMOVED``;
    * moved less than ``cfg.static_translation`` (at the model point ``centre``, the centre of
      mass; None: the origin) *and* rotated (symmetry-aware) less than ``cfg.static_rotation``,
      both strictly: ``STATIC``; else ``PERTURBED``.

    Raises:
        SSPError: both poses are None, or ``retained`` for an object with no previous pose.
    """
    if prev_pose is None:
        if cur_pose is None:
            raise SSPError("classify: an object needs a previous or a current pose")
        if retained:
            raise SSPError("classify: an object new in this frame cannot be support-retained")
        return TransitionMode.ADDED
    if retained:
        return TransitionMode.SUPPORT_RETAINED
    if cur_pose is None:
        return TransitionMode.REMOVED
    dt, dtheta = pose_change(prev_pose, cur_pose, symmetry, centre)
    if dt < cfg.static_translation and dtheta < cfg.static_rotation:
        return TransitionMode.STATIC
    return TransitionMode.PERTURBED


def _quat_angle(R: np.ndarray) -> float:
    q = Rotation.from_matrix(R).as_quat()
    return float(2.0 * np.arctan2(np.linalg.norm(q[:3]), abs(q[3])))


def snap_symmetric(T_prev: np.ndarray, T_cur: np.ndarray, symmetry: Symmetry | None) -> np.ndarray:
    """The symmetric equivalent ``T_cur @ S`` of ``T_cur`` closest in rotation to ``T_prev``.

    Every discrete symmetry is tried; a continuous axis is handled exactly, in closed form
    (the rotation ``phi`` about the axis after ``S`` that maximises the scalar part of the
    quaternion of ``R_prev^T R_cur R_S R_phi``: ``phi = 2 atan2(-(v.a), w)``); two non-parallel
    continuous axes (a sphere) make every orientation equivalent, so the result takes
    ``T_prev``'s rotation about the symmetry centre. Ties (within 1e-9 rad) go to the first
    symmetry, the identity, so a pose that is already closest is returned unchanged (a copy).
    The result is the same physical pose as ``T_cur`` (only its parametrisation changes).
    """
    T_prev = np.asarray(T_prev, dtype=float)
    T_cur = np.asarray(T_cur, dtype=float)
    if symmetry is None or not symmetry.is_symmetric:
        return T_cur.copy()
    axes = [c.axis for c in symmetry.continuous]
    if len(axes) > 1 and any(np.linalg.norm(np.cross(axes[0], a)) > 1e-6 for a in axes[1:]):
        R = T_cur[:3, :3].T @ T_prev[:3, :3]
        o = symmetry.continuous[0].offset
        S = np.eye(4)
        S[:3, :3] = R
        S[:3, 3] = o - R @ o
        return T_cur @ S
    R_base = T_prev[:3, :3].T @ T_cur[:3, :3]
    if not symmetry.continuous:  # all discrete candidates at once
        q = Rotation.from_matrix(R_base[None] @ symmetry.discrete[:, :3, :3]).as_quat()
        angles = 2.0 * np.arctan2(np.linalg.norm(q[:, :3], axis=1), np.abs(q[:, 3]))
        # ties within 1e-9 rad go to the first (the identity)
        best = int(np.flatnonzero(angles <= angles.min() + 1e-9)[0])
        return T_cur @ symmetry.discrete[best]
    best_T, best_angle = T_cur.copy(), np.inf
    for S in symmetry.discrete:
        T = T_cur @ S
        if symmetry.continuous:
            cont = symmetry.continuous[0]
            q = Rotation.from_matrix(R_base @ S[:3, :3]).as_quat()
            phi = 2.0 * np.arctan2(-float(q[:3] @ cont.axis), q[3])
            if abs(phi) > 1e-12:
                T = T @ cont.transform(phi)
        angle = _quat_angle(T_prev[:3, :3].T @ T[:3, :3])
        if angle < best_angle - 1e-9:
            best_T, best_angle = T, angle
    return best_T


# ------------------------------------------------------------------ the association stage
#: A known object keeps its class on its segment unless another class accounts for this much
#: more of the segment's points (a fraction).
CLASS_MARGIN = 0.05


@dataclass
class Association:
    """What the association stage found: the groups per object id, the id counters after it,
    the segments undetected objects took, and the groups dropped (class confusions,
    duplicates)."""

    groups: dict[str, list[Hypothesis]]
    counters: dict[str, int]
    #: undetected known object -> the instance label whose points lie on it
    claimed: dict[str, int]
    #: dropped group -> the object whose segment it is
    confused: dict[str, str]
    #: dropped new group -> the undetected object it duplicates
    duplicates: dict[str, str]
    #: new groups without segments dropped for lying in a known object's volume
    #: (:mod:`ssp.shared_volume`), with the reason
    shared: dict[str, Rejected] = field(default_factory=dict)
    #: known object -> why a newcomer of another class holds its volume (triage tests
    #: replacement first)
    contested: dict[str, str] = field(default_factory=dict)


def counted_id_factory(counters: dict[str, int], taken: set[str]) -> Callable[[str], str]:
    """``new_id(class_name)``: ``f"{class_name}_{k}"`` with ``k`` from ``counters`` (advanced in
    place, so ids are never reused across frames), skipping the ids in ``taken`` (extended)."""

    def new_id(class_name: str) -> str:
        while True:
            k = counters.get(class_name, 0)
            counters[class_name] = k + 1
            candidate = f"{class_name}_{k}"
            if candidate not in taken:
                taken.add(candidate)
                return candidate

    return new_id


def associate_frame(ctx: FrameContext) -> None:
    """Stage *association*: the frame's hypotheses grouped per object (:func:`associate`,
    :func:`one_object_per_segment`, :func:`duplicates_of_undetected`; paper section IV-C), the
    best ``search.hypotheses_per_object`` kept per object; every object's class and model,
    the known objects' previous poses and each detected object's provisional pose
    (:func:`ssp.first_guess.first_guess`).

    Sets ``association``, ``groups``, ``classes``, ``models``, ``prev_pose``, ``first``.

    Raises:
        FrameError: an instance id given to a hypothesis of another class than its object's.
    """
    assoc = _associate(ctx)
    cfg, known = ctx.config, ctx.known
    groups = assoc.groups
    classes = {oid: hyps[0].class_name for oid, hyps in groups.items()}
    classes.update({oid: k.class_name for oid, k in known.items() if oid not in groups})
    models = {oid: ctx.library[c] for oid, c in classes.items()}
    prev_pose = {oid: known[oid].T_world_obj for oid in known}
    # Provisional pose per detected object (segment vote, triage of undetected objects);
    # replaced by the first guess once the scorer can weigh the candidates.
    first = {
        oid: first_guess(
            hyps,
            prev_pose.get(oid),
            models[oid].symmetry,
            cfg.temporal,
            models[oid].center_of_mass,
        )  # fmt: skip
        for oid, hyps in groups.items()
    }
    ctx.association, ctx.groups, ctx.classes = assoc, groups, classes
    ctx.models, ctx.prev_pose, ctx.first = models, prev_pose, first


def _associate(ctx: FrameContext) -> Association:
    """The groups per object (:func:`associate_frame`)."""
    cfg, frame, library, known = ctx.config, ctx.frame, ctx.library, ctx.known
    previous = {oid: (k.class_name, k.T_world_obj) for oid, k in known.items()}
    counters = dict(ctx.counters)
    hypotheses = frame.hypotheses if ctx.hypotheses is None else ctx.hypotheses
    taken = set(previous) | {h.instance_id for h in hypotheses if h.instance_id}
    groups = associate(
        hypotheses,
        previous,
        {n: m.symmetry for n, m in library.items()},
        max_distance=association_gates(library, cfg.temporal),
        same_volume=same_volume_test(library, cfg.temporal.merge_overlap),
        new_id=counted_id_factory(counters, taken),
        centres={n: m.center_of_mass for n, m in library.items()},
    )
    for oid, hyps in groups.items():
        k = known.get(oid)
        if k is not None and k.class_name != hyps[0].class_name:
            raise FrameError(
                f"instance id {oid!r} is a {k.class_name!r} but this frame's "
                f"hypothesis calls it a {hyps[0].class_name!r}"
            )
    k_max = cfg.search.hypotheses_per_object
    labels = None if frame.labels is None else np.asarray(frame.labels)
    # a scene point on the surface lies up to about one sample spacing from a sample
    radius = cfg.data.inlier_radius + cfg.library.surface_spacing

    def rank(oid: str, hyps: list[Hypothesis]) -> tuple:
        """Which class a segment is: the group that accounts for most of its points (a
        known object's with a margin: its class is not given up for a near tie)."""
        if labels is None or hyps[0].segment is None:
            return (oid in known, float(hyps[0].score))
        points = frame.points[labels == hyps[0].segment]
        model = library[hyps[0].class_name]
        best = max(explained_fraction(points, model, h.T_world_obj, radius) for h in hyps[:k_max])
        return (best + (CLASS_MARGIN if oid in known else 0.0), float(hyps[0].score))

    groups, confused = one_object_per_segment(groups, rank)
    # without instance masks, the volume says which object a hypothesis is about
    shared = resolve_shared_volumes(
        groups, {} if frame.instance_masks else previous, library, frame.points,
        view=ctx.view, config=cfg, class_margin=CLASS_MARGIN,
        floor=TABLE_CLEARANCE if ctx.table else None,
    )  # fmt: skip
    groups = shared.groups
    groups = {oid: hyps[:k_max] for oid, hyps in groups.items()}
    claimed: dict[str, int] = {}
    duplicates: dict[str, str] = {}
    if labels is not None:

        def explained(u: str, points: np.ndarray) -> float:
            k = known[u]
            return explained_fraction(points, library[k.class_name], k.T_world_obj, radius)

        groups, claimed, duplicates = duplicates_of_undetected(
            groups,
            previous,
            lambda seg: frame.points[labels == seg],
            explained,
            cfg.temporal.explained_fraction,
        )
        for oid, u in duplicates.items():
            log.info("new %s: its segment lies on %s where it was; a duplicate", oid, u)
    for oid, winner in confused.items():
        log.info("%s dropped: its segment is %s's (one object per segment)", oid, winner)
    return Association(
        groups, counters, claimed, confused, duplicates, shared.rejected, shared.contested
    )


def reidentify_moved(ctx: FrameContext) -> None:
    """Stage *re-identification*: a new object where a known one of its class just vanished
    (replaced or seen empty) is that object, moved; so is one beside a known object that the
    depth contradicts (seen through): the known object's pose was wrong, and the new one is
    where it really is (:func:`reidentify`). The contradicted objects found again leave the
    output (``superseded``); the scene is scored again without what leaves it.

    Sets ``old_of``, ``moved_away`` and ``superseded``; updates ``gone`` and ``score``.
    """
    cfg, score, models, prev_pose = ctx.config, ctx.scene_score, ctx.models, ctx.prev_pose
    ids, gone = score.ids, ctx.gone
    left = (TriageState.REPLACED, TriageState.SEEN_EMPTY)
    vanished = {
        oid: (models[oid].name, prev_pose[oid])
        for oid in ctx.removed
        if oid in ctx.verdicts and ctx.verdicts[oid].state in left
    }
    contradicted = {
        oid: (models[oid].name, score.poses[ids.index(oid)])
        for oid in ids
        if oid in prev_pose and oid not in gone and ctx.evidence[oid].seen_empty(cfg)
    }
    added = {
        oid: (models[oid].name, ctx.placed.get(oid, score.poses[ids.index(oid)]))
        for oid in ids
        if oid not in gone and oid not in prev_pose
    }
    renamed = reidentify(
        {**vanished, **contradicted},
        added,
        {oid: models[oid].diameter for oid in contradicted},  # beside it, not elsewhere
    )
    ctx.old_of = dict(renamed)  # new id -> old id
    ctx.moved_away = set(renamed.values())
    ctx.superseded = ctx.moved_away & set(contradicted)  # their new pose replaces them
    gone |= ctx.superseded
    dropped = [oid for oid in ids if oid in gone and oid not in ctx.removed]
    if dropped:  # the output's terms and support without what is not in it
        ctx.score = ctx.rescore_without(dropped)
