"""One object per volume: a hypothesis without an instance segment that fills a known object's
volume is about that object's data (paper IV-C; two objects cannot share a volume).

With instance masks, the segment a hypothesis came from says which object it describes
(:func:`ssp.temporal.one_object_per_segment`, :func:`ssp.temporal.duplicates_of_undetected`,
and the segments' votes for hypotheses without one). Without them (a cloud's Euclidean
clusters, a bare cloud; the parser applies this rule only then)
association has only positions: an estimator's gross or class-confused hypothesis of a known
object whose centre lies beyond the association gate became a *new* object inside the known
one. The search then pushed the known object off its data to make room, or turned it to a
wrong pose that clears the intruder, and the intruder was rejected at its final pose, too late:
on Table I's realistic stream without masks (``ssp bench table1 --masks none``) this was most
of the nominal object-frames the parser with memory got grossly wrong and the memoryless one
did not.

:func:`resolve_shared_volumes` settles these before anything else sees them. A hypothesis of a
new group (no known object took it) without an instance segment *claims* a known object when
it fills at least ``temporal.claim_overlap`` of the object's volume at its previous pose or at
its best hypothesis this frame, or the object fills that much of it (:func:`ssp.overlap.
overlap_fractions`; correct hypotheses of different objects share no volume: measured on the
realistic stream, the largest overlap of a correct hypothesis with another object is 0):

* **same class**: it is a pose of that object (an outlier of its estimator): it joins the
  object's group, where the search weighs it with the others (with masks its segment would have
  put it there);
* **another class**: the two compete for the data there, as classes compete for an instance
  segment (:func:`data_rank`: the F1 of each one's visible surface explained, the camera's
  view of free space counting against it, and of the points near either surface that it
  explains); the known object keeps its class unless the newcomer explains the data better by
  :data:`ssp.temporal.CLASS_MARGIN`. A losing hypothesis leaves its group; a newcomer whose best
  remaining hypothesis wins *contests* the known object: the object's own group, if any, is
  dropped, and its triage tests replacement before visibility (:mod:`ssp.retention`).

A new group left without hypotheses is rejected with the reason (nothing is dropped silently);
its hypotheses gave the evidence only about another object's volume.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from ssp.config import SSPConfig
from ssp.estimate import Rejected
from ssp.geometry import in_box, squared_distances
from ssp.library.model import ObjectModel
from ssp.overlap import overlap_fractions
from ssp.scene import Hypothesis
from ssp.segments import surface_grid
from ssp.verification import evidence
from ssp.visibility import CameraView

__all__ = [
    "SharedVolumes",
    "data_rank",
    "local_points",
    "near_surface",
    "resolve_shared_volumes",
    "thin",
]

log = logging.getLogger(__name__)


@dataclass
class SharedVolumes:
    """What :func:`resolve_shared_volumes` decided.

    Attributes:
        groups: the groups after it (``id -> hypotheses``, best score first).
        rejected: new groups left without a hypothesis, by id, with the reason.
        contested: known id -> why another class's newcomer is taken to hold its volume
            (its triage tests replacement first).
        joined: known id -> the new groups whose hypotheses joined it.
    """

    groups: dict[str, list[Hypothesis]]
    rejected: dict[str, Rejected] = field(default_factory=dict)
    contested: dict[str, str] = field(default_factory=dict)
    joined: dict[str, list[str]] = field(default_factory=dict)


def local_points(
    points: np.ndarray,
    models: list[ObjectModel],
    poses: list[np.ndarray],
    margin: float,
) -> np.ndarray:
    """The points ``(N, 3)`` (world, m) inside the box around the bounding spheres of
    ``models`` at ``poses`` grown by ``margin`` (m)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for model, T in zip(models, poses, strict=True):
        c = T[:3, :3] @ np.asarray(model.center_of_mass, dtype=float) + T[:3, 3]
        r = model.d_max + margin
        lo, hi = np.minimum(lo, c - r), np.maximum(hi, c + r)
    return points[in_box(points, lo, hi)]


def thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices (ascending) of one point of ``points`` ``(K, 3)`` per occupied voxel of side
    ``voxel`` (m): the first in order."""
    if not len(points):
        return np.zeros(0, dtype=np.int64)
    ijk = np.floor(np.asarray(points) / voxel).astype(np.int64)
    ijk -= ijk.min(axis=0)
    span = ijk.max(axis=0) + 1
    keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
    _, first = np.unique(keys, return_index=True)
    return np.sort(first)


def near_surface(
    points: np.ndarray, model: ObjectModel, T: np.ndarray, radius: float
) -> np.ndarray:
    """Mask of ``points`` ``(K, 3)`` (world, m) within ``radius`` (m) of ``model``'s surface
    samples at ``T`` (only the points in its bounding sphere grown by ``radius`` are looked
    up)."""
    points = np.asarray(points, dtype=float)
    out = np.zeros(len(points), dtype=bool)
    if not len(points):
        return out
    c = T[:3, :3] @ np.asarray(model.center_of_mass, dtype=float) + T[:3, 3]
    near = np.flatnonzero(squared_distances(points, c) <= (model.d_max + radius) ** 2)
    if not len(near):
        return out
    local = (points[near] - T[:3, 3]) @ T[:3, :3]  # R^T (p - t)
    dist, _ = surface_grid(model, radius).nearest_within(local, radius)
    out[near] = np.isfinite(dist)
    return out


def data_rank(
    objects: Sequence[tuple[ObjectModel, np.ndarray]],
    fits: Sequence[float],
    points: np.ndarray,
    shared: np.ndarray,
    radius: float,
) -> float:
    """How well ``objects`` (``(model, T_world_obj)`` pairs: one newcomer, or the known
    objects whose volume it claims) explain the data where they and a competitor are: the F1
    of their visible surface explained (the mean of their ``fits``,
    :func:`ssp.verification.evidence`'s ``fit``: the samples the camera could see with a
    point near; a face the camera sees through counts against it) and the fraction of the
    ``shared`` points (mask of ``points`` ``(K, 3)``, world, m: those near any competitor's
    surface) within ``radius`` (m) of any of their surfaces. 0 without shared points."""
    if not shared.any() or not objects:
        return 0.0
    return _f1(fits, [near_surface(points[shared], m, T, radius) for m, T in objects])


def _f1(fits: Sequence[float], near: Sequence[np.ndarray]) -> float:
    """:func:`data_rank` from the objects' ``fits`` and, for each, the mask of the shared
    points within the radius of its surface (at least one object and one shared point)."""
    fit = float(np.mean(fits))
    cover = float(np.logical_or.reduce(near).mean())
    return 0.0 if fit + cover == 0 else 2 * fit * cover / (fit + cover)


def resolve_shared_volumes(
    groups: Mapping[str, list[Hypothesis]],
    known: Mapping[str, tuple[str, np.ndarray]],
    library: Mapping[str, ObjectModel],
    points: np.ndarray,
    *,
    view: CameraView | None,
    config: SSPConfig,
    class_margin: float,
    floor: float | None,
) -> SharedVolumes:
    """Hypotheses without an instance segment in a known object's volume (module docstring).

    Args:
        groups: this frame's groups (``id -> hypotheses``, best first); known ids are
            ``known``'s keys.
        known: the previous objects, ``id -> (class, T_world_obj)``.
        library: class name -> model.
        points: the frame's cloud ``(N, 3)``, world, m.
        view: the frame's camera view (None without a camera pose).
        config: ``temporal.claim_overlap`` (1 or more disables the rule); the inlier
            radius and surface spacing of :func:`data_rank`; ``forces.max_distance``, the
            crop margin of :func:`local_points`.
        class_margin: a known object keeps its class unless a newcomer's rank is higher by
            more than this.
        floor: points below this height (m) are the table's (None: no table).
    """
    out = SharedVolumes({oid: list(h) for oid, h in groups.items()})
    if config.temporal.claim_overlap >= 1 or not known:
        return out
    new = [
        oid for oid, hyps in groups.items()
        if oid not in known and hyps and all(h.segment is None for h in hyps)
    ]  # fmt: skip
    if not new:
        return out
    # where each known object may be: its previous pose, and its best hypothesis this frame
    where: dict[str, list[np.ndarray]] = {}
    for k, (_, T) in known.items():
        where[k] = [np.asarray(T, dtype=float)]
        if groups.get(k):
            where[k].append(np.asarray(groups[k][0].T_world_obj, dtype=float))
    rules = _Rules(known, where, library, points, view, config, class_margin, floor)
    for oid in sorted(new):
        rules.settle(oid, out)
    for k, oids in out.joined.items():
        if k in out.contested:  # its volume went to a newcomer: the poses of it with it
            for oid in oids:
                if oid in out.rejected:
                    rej = out.rejected[oid]
                    why = f"{rej.reason} (contested: {out.contested[k]})"
                    out.rejected[oid] = replace(rej, reason=why)
            continue
        out.groups[k].sort(key=lambda h: -float(h.score))  # stable: earlier first on ties
    return out


@dataclass
class _Rules:
    """The claims and competitions of :func:`resolve_shared_volumes` (its arguments, and
    ``where``: each known object's poses, its previous one first)."""

    known: Mapping[str, tuple[str, np.ndarray]]
    where: Mapping[str, list[np.ndarray]]
    library: Mapping[str, ObjectModel]
    points: np.ndarray
    view: CameraView | None
    config: SSPConfig
    class_margin: float
    floor: float | None
    _cloud: tuple[np.ndarray, cKDTree] | None = None
    _fits: dict[tuple[str, bytes], float] = field(default_factory=dict)

    def settle(self, oid: str, out: SharedVolumes) -> None:
        """New group ``oid``'s hypotheses that claim a known object join it (same class) or
        compete for its data (another class); ``out`` is updated in place."""
        kept: list[Hypothesis] = []
        beaten: list[tuple[str, str]] = []  # (known id, why) its best kept hypothesis beat
        lost: list[tuple[str, dict]] = []  # (reason, evidence) of each losing hypothesis
        for h in out.groups[oid]:
            claims = self.claims(h)
            same = [c for c in claims if self.known[c[1]][0] == h.class_name]
            if same:  # a pose of that object: it joins its group
                k = max(same)[1]
                if k not in out.contested:  # else its volume is a newcomer's: dropped with it
                    out.groups.setdefault(k, []).append(replace(h, instance_id=k))
                if oid not in out.joined.setdefault(k, []):
                    out.joined[k].append(oid)
                continue
            if claims:
                ks = [k for _, k in claims]
                wins, why, mine, theirs = self.compete(h, ks)
                if not wins:
                    ev = {"claims": ks, "overlap": [o for o, _ in claims], "data_rank": mine,
                          "data_rank_other": theirs}  # fmt: skip
                    lost.append((why, ev))
                    continue
                if not kept:
                    beaten = [(k, why) for k in ks]
            kept.append(h)
        if kept:
            out.groups[oid] = kept
            for k, why in beaten:  # its best hypothesis holds that volume
                out.contested[k] = f"{oid} ({kept[0].class_name}) {why}"
                out.groups.pop(k, None)
            return
        h = out.groups.pop(oid)[0]
        if lost:
            reason, ev = lost[0]
        else:
            joined = [k for k, v in out.joined.items() if oid in v]
            reason = f"its hypotheses lie in the volume of {', '.join(joined)}: poses of it"
            ev = {"joined": joined}
        T = np.asarray(h.T_world_obj).copy()
        out.rejected[oid] = Rejected(oid, h.class_name, T, reason, ev)
        log.info("%s (%s) dropped: %s", oid, h.class_name, reason)

    def cloud(self) -> tuple[np.ndarray, cKDTree]:
        """The frame's points above the floor, one per voxel of the inlier radius (the ranks
        are fractions of surface, not of point density; a real capture's crop around a tool
        holds tens of thousands of points), and their KD-tree; made once, when a competition
        needs them."""
        if self._cloud is None:
            pts = self.points
            if self.floor is not None:
                pts = pts[pts[:, 2] >= self.floor]
            pts = pts[thin(pts, self.radius)]
            self._cloud = (pts, cKDTree(pts if len(pts) else np.zeros((1, 3)) + np.inf))
        return self._cloud

    def fit(self, model: ObjectModel, T: np.ndarray) -> float:
        """:func:`ssp.verification.evidence`'s ``fit`` of ``model`` at ``T`` on the thinned
        cloud (cached for the frame)."""
        key = (model.name, np.asarray(T, dtype=float).tobytes())
        if key not in self._fits:
            pts, tree = self.cloud()
            ev = evidence(model, T, tree if len(pts) else None, self.view, self.config)
            self._fits[key] = ev.fit
        return self._fits[key]

    @property
    def radius(self) -> float:
        """The inlier radius of the ranks, m: the data term's plus the surface spacing."""
        return self.config.data.inlier_radius + self.config.library.surface_spacing

    def claims(self, h: Hypothesis) -> list[tuple[float, str]]:
        """``[(overlap, known id)]`` of the known objects whose volume ``h`` shares (at least
        ``fraction`` of either's, at any of the object's poses)."""
        model = self.library[h.class_name]
        T = np.asarray(h.T_world_obj, dtype=float)
        c = T[:3, :3] @ np.asarray(model.center_of_mass, dtype=float) + T[:3, 3]
        out = []
        for k in sorted(self.known):
            other = self.library[self.known[k][0]]
            c_other = np.asarray(other.center_of_mass, dtype=float)
            best = 0.0
            for U in self.where[k]:
                # bounding spheres about the centres of mass apart: no shared volume
                if np.linalg.norm(U[:3, :3] @ c_other + U[:3, 3] - c) > model.d_max + other.d_max:
                    continue
                pair = overlap_fractions(
                    [model, other], np.stack([T, U]), table=False, pairs=[(0, 1)]
                )
                best = max(best, float(pair.max()))
            if best >= self.config.temporal.claim_overlap:
                out.append((best, k))
        return out

    def compete(self, h: Hypothesis, ks: list[str]) -> tuple[bool, str, float, float]:
        """Does ``h`` (another class) explain the points around it and the known objects
        ``ks`` whose volume it claims better than they do together (each at its better pose),
        by more than ``class_margin``? ``(wins, why, h's rank, theirs)`` (:func:`data_rank`:
        a block proposed over two cubes is compared with both, not with each)."""
        cfg, radius = self.config, self.radius
        model = self.library[h.class_name]
        T = np.asarray(h.T_world_obj, dtype=float)
        surfaces = [(model, T)]  # h's, then each pose of each known object
        of: dict[str, list[int]] = {}  # known object -> the indices of its poses
        for k in ks:
            m = self.library[self.known[k][0]]
            for U in self.where[k]:
                of.setdefault(k, []).append(len(surfaces))
                surfaces.append((m, U))
        local = local_points(
            self.cloud()[0], [m for m, _ in surfaces], [U for _, U in surfaces],
            cfg.forces.max_distance,
        )  # fmt: skip
        # each surface's near points are found once (data_rank of the shared ones, the same)
        near = [near_surface(local, m, U, radius) for m, U in surfaces]
        shared = np.logical_or.reduce(near)

        def rank(i: list[int]) -> float:  # data_rank of these surfaces
            if not shared.any():
                return 0.0
            return _f1([self.fit(*surfaces[j]) for j in i], [near[j][shared] for j in i])

        mine = rank([0])
        best = [max(of[k], key=lambda j: rank([j])) for k in ks]  # each at its better pose
        theirs = rank(best)
        names = ", ".join(ks)
        if mine > theirs + self.class_margin:
            why = (
                f"explains the data in the volume it shares with {names} better ({mine:.2f} "
                f"against {theirs:.2f})"
            )
            return True, why, mine, theirs
        what = ", ".join(f"{k} ({self.known[k][0]})" for k in ks)
        why = (
            f"lies in the volume of {what}, which explain{'s' if len(ks) == 1 else ''} the data "
            f"there as well or better ({theirs:.2f} against {mine:.2f})"
        )
        return False, why, mine, theirs
