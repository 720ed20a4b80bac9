"""The scene probability of a simulated world state: every term of every enabled object.

``log Pr(s | C, D) = sum_objects (log P_B + log P_C + log P_S + log P_D + log P_T)``: the
paper's Eq. 4 with Eq. 5, 6 and the terms of Eq. 9-12 (DESIGN section 4), read from the
physics world after a simulation window:

* stability ``P_B``: the acceleration from rest under gravity and contacts alone (data forces
  are cleared first: a hovering object held by its data force is still unstable);
* collision ``P_C``: the deepest penetration of each object (contacts, table included) times
  the fraction of its volume inside other objects or the table (:mod:`ssp.overlap`), computed
  only for penetrations deeper than ``collision.min_depth`` (solver residue reads as 0);
* support ``P_S``: the fractions of other objects' weight each object carries (Alg. 2);
* data ``P_D``: the fraction of model surface samples within ``r_c`` of the object's segment;
* transition ``P_T``: motion from the previous frame's best pose (0 for new objects).

Scores are only compared between states with the same enabled objects (DESIGN section 4).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from scipy.spatial import cKDTree

from ssp.config import SSPConfig
from ssp.geometry import transform_points
from ssp.overlap import overlap_fractions
from ssp.physics import World
from ssp.probability import (
    ObjectTerms,
    collision_severity,
    data_fit_fraction,
    log_collision,
    log_data,
    log_stability,
    log_support,
    log_transition_from_poses,
)
from ssp.segments import SegmentTrees
from ssp.support import SupportGraph, build_support_graph
from ssp.timing import StageTimer

__all__ = ["TERM_NAMES", "SceneScore", "SceneScorer", "Term", "contact_overlaps"]


class Term(IntEnum):
    """The columns of :attr:`SceneScore.terms`: the log-probability terms of the paper's Eq. 4."""

    STABILITY = 0
    COLLISION = 1
    SUPPORT = 2
    DATA = 3
    TRANSITION = 4


#: Column order of :attr:`SceneScore.terms`.
TERM_NAMES = tuple(t.name.lower() for t in Term)


def contact_overlaps(
    models, contacts, poses: np.ndarray, deep: np.ndarray, min_depth: float
) -> np.ndarray:
    """(n,) volume fraction ``v_c / v_t`` (Eq. 10) of each object flagged in ``deep`` ((n,)
    bool) inside the objects it penetrates by more than ``min_depth`` (m), or below the table
    (:func:`ssp.overlap.overlap_fractions`); 0 for the others. ``models`` and ``poses``
    ((n, 4, 4)) are in the contacts' id order."""
    sel = np.asarray(contacts.depth) > min_depth
    a = np.asarray(contacts.obj_a)[sel]
    b = np.asarray(contacts.obj_b)[sel]
    out = np.zeros(len(models))
    members = sorted({int(i) for i in a} | {int(j) for j in b if j >= 0})
    if not members:
        return out
    local = {k: m for m, k in enumerate(members)}
    pairs = sorted({(local[int(i)], local[int(j)]) for i, j in zip(a, b, strict=True) if j >= 0})
    out[members] = overlap_fractions(
        [models[k] for k in members], poses[members], table=True, pairs=pairs
    )
    return np.where(deep, out, 0.0)


@dataclass(frozen=True, eq=False)
class SceneScore:
    """Terms of one world state.

    Attributes:
        ids: object ids (world order).
        enabled: (n,) bool, objects in the (partial) scene.
        terms: (n, 5) natural-log terms in :data:`TERM_NAMES` order; 0 for disabled objects.
        fit: (n,) data fit fraction c of each object (0 when disabled).
        graph: the support graph of the state.
        poses: (n, 4, 4) poses of the state.
    """

    ids: tuple[str, ...]
    enabled: np.ndarray
    terms: np.ndarray
    fit: np.ndarray
    graph: SupportGraph
    poses: np.ndarray

    @property
    def total(self) -> float:
        """``log Pr(s | C, D)`` of the enabled objects."""
        return float(self.terms[self.enabled].sum())

    def object_terms(self, i: int) -> ObjectTerms:
        """The five terms of object ``i``."""
        return ObjectTerms(*(float(v) for v in self.terms[i]))


class SceneScorer:
    """Scores states of one world during one frame.

    Args:
        world: the frame's world (its id order defines the arrays).
        config: the method's constants.
        segments: ``id -> (K, 3)`` the object's segment (missing or empty: fit 0).
        previous: ``id -> (4, 4)`` previous frame's best pose, or None for new objects.
        camera_position: (3,) camera position in the world, m, or None. When given, the data
            fit c counts only the model samples facing the camera (the far side was never
            observed), so c is the fraction of the *seeable* surface explained.
        trees: the frame's segment trees to use for the ids in ``segments`` (shared with
            verification); None: built here.
    """

    def __init__(
        self,
        world: World,
        config: SSPConfig,
        segments: Mapping[str, np.ndarray],
        previous: Mapping[str, np.ndarray | None],
        camera_position: np.ndarray | None = None,
        trees: SegmentTrees | None = None,
    ) -> None:
        self.config = config
        self.camera_position = (
            None if camera_position is None else np.asarray(camera_position, float).reshape(3)
        )
        self.ids = world.ids
        self.models = [world.model_of(i) for i in self.ids]
        self.masses = world.masses
        self.g = float(config.physics.gravity)
        self.alpha_max = np.array([m.max_angular_acceleration(self.g) for m in self.models])
        self.diameters = np.array([m.diameter for m in self.models])
        self.previous = [previous.get(i) for i in self.ids]
        self.trees: list[cKDTree | None] = []
        for oid in self.ids:
            seg = segments.get(oid)
            if seg is None or not len(seg):
                self.trees.append(None)
            else:
                self.trees.append(cKDTree(seg) if trees is None else trees.tree(oid))
        self._fits: dict[tuple[int, bytes], float] = {}
        n_fit = int(config.search.fit_samples)
        self.fit_samples, self.fit_normals = [], []
        for m in self.models:
            p = np.asarray(m.surface_points, dtype=float)
            nrm = np.asarray(m.surface_normals, dtype=float)
            if len(p) > n_fit:
                sel = np.linspace(0, len(p) - 1, n_fit).astype(int)
                p, nrm = p[sel], nrm[sel]
            self.fit_samples.append(p)
            self.fit_normals.append(nrm)

    def _overlaps(self, contacts, poses: np.ndarray, deep: np.ndarray) -> np.ndarray:
        return contact_overlaps(self.models, contacts, poses, deep, self.config.collision.min_depth)

    def fit_fraction(self, i: int, T_world_obj: np.ndarray) -> float:
        """Data fit c of object ``i`` at a pose (0 without a segment). Remembered per exact
        pose: the hypotheses are scored by the first guess, the unchanged test and the data
        fallbacks alike."""
        tree = self.trees[i]
        if tree is None:
            return 0.0
        T = np.asarray(T_world_obj, dtype=float)
        key = (i, T.tobytes())
        c = self._fits.get(key)
        if c is None:
            pts = transform_points(T, self.fit_samples[i])
            if self.camera_position is not None:
                nrm = self.fit_normals[i] @ T[:3, :3].T
                pts = pts[((self.camera_position - pts) * nrm).sum(axis=1) > 0.0]
            c = self._fits[key] = data_fit_fraction(pts, tree, self.config.data.inlier_radius)
        return c

    def unsimulated(self, i: int, T_world_obj: np.ndarray) -> float:
        """``log P_D + log P_T`` of object ``i`` at a pose: its terms that need no simulation
        (Eq. 6 and 12). Used to pick the first-guess pose among an object's candidates."""
        cfg = self.config
        log_d = float(log_data(np.array([self.fit_fraction(i, T_world_obj)]), cfg.data)[0])
        return log_d + log_transition_from_poses(
            self.previous[i],
            T_world_obj,
            cfg.transition,
            self.models[i].symmetry,
            self.models[i].center_of_mass,
        )

    def evaluate(self, world: World, timer: StageTimer | None = None) -> SceneScore:
        """Score the world's current state (its applied wrenches are cleared).

        ``timer`` (optional) accumulates the time of the ``contacts`` stage (accelerations,
        contacts, support graph) and of the ``scoring`` stage (the terms).
        """
        timer = timer if timer is not None else StageTimer()
        with timer("contacts"):
            world.clear_wrenches()
            on = world.enabled
            poses = world.pose_array()
            lin, ang = world.acceleration_from_rest()
            contacts = world.contacts()
            graph = build_support_graph(contacts, self.masses, self.g)
        with timer("scoring"):
            return self._terms(on, poses, lin, ang, contacts, graph)

    def _terms(self, on, poses, lin, ang, contacts, graph) -> SceneScore:
        cfg = self.config
        n = len(self.ids)
        terms = np.zeros((n, 5))
        fit = np.zeros(n)
        idx = np.flatnonzero(on)
        if len(idx) == 0:
            return SceneScore(self.ids, on, terms, fit, graph, poses)

        terms[idx, Term.STABILITY] = log_stability(
            lin[idx], ang[idx], self.alpha_max[idx], self.g, cfg.stability
        )

        depth = np.asarray(graph.penetration, dtype=float)
        frac = np.zeros(n)
        deep = (depth > cfg.collision.min_depth) & on
        if deep.any():
            frac = self._overlaps(contacts, poses, deep)
        e_c = collision_severity(depth[idx], frac[idx], self.diameters[idx])
        terms[idx, Term.COLLISION] = log_collision(e_c, cfg.collision)

        terms[idx, Term.SUPPORT] = log_support(graph.support_sums()[idx], cfg.support)

        for i in idx:
            fit[i] = self.fit_fraction(int(i), poses[i])
        terms[idx, Term.DATA] = log_data(fit[idx], cfg.data)

        for i in idx:
            terms[i, Term.TRANSITION] = log_transition_from_poses(
                self.previous[i],
                poses[i],
                cfg.transition,
                self.models[i].symmetry,
                self.models[i].center_of_mass,
            )
        return SceneScore(self.ids, on, terms, fit, graph, poses)
