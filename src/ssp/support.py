"""Support graph (paper Alg. 2 ``GenSupportGraph``; DESIGN section 4 "Support graph").

Built from a :class:`~ssp.physics.Contacts` snapshot (normal from a to b, gravity along -z).
For every touching pair the vertical push on b, ``V = sum_contacts normal_force * n_z``, decides
the direction: ``V > 0`` (b is pushed up, a lies below) means a supports b, otherwise b supports
a. Contacts with the table always mean the ground (index -1) supports the object. Pairs whose
net vertical push is below ``min_force`` (side-by-side objects, contacts within the margin that
carry no load) get no edge.

Support fractions F_S (used by the support term P_S, the paper's Eq. 11). The raw vertical
force between a supporter and an object also carries the weight of everything stacked on that
object (in a 3-cube tower the table pushes with 3 m g, the bottom cube with 2 m g on the middle
one). So the fraction of b's *own* weight carried by supporter a is its share of b's upward
support times b's net supported weight (the paper says only "the percentage of object i weight
supported by an object"):

    F_S(a -> b) = V_ab / U_b * (U_b - D_b) / (m_b g),

with U_b the total upward push on b from its supporters and D_b the total downward push b
exerts on the objects it supports. At rest ``U_b - D_b = m_b g``, so the fractions of b sum to 1
and a tower gives F_S = 1 on every edge; a block bridging two cubes gives 0.5 to each. An object
that is not in equilibrium (sliding, falling, pressed down) gets a sum below or above 1. The raw
vertical forces are kept in :attr:`SupportGraph.edge_vertical`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ssp.physics.contacts import Contacts

__all__ = ["GROUND", "SupportGraph", "build_support_graph"]

#: Index of the ground (the table) in the graph's edges.
GROUND = -1


@dataclass(frozen=True, eq=False)
class SupportGraph:
    """Who supports whom, from the contact forces of one world state.

    Attributes:
        ids: object ids (the world's order); indices below refer to it.
        supporter: (E,) int, supporting object index, or -1 for the ground (table).
        supported: (E,) int, supported object index.
        edge_force: (E,) summed contact normal force of the pair, N (all directions).
        edge_vertical: (E,) net upward push of the supporter on the supported object, N (> 0).
        edge_fraction: (E,) F_S: fraction of the supported object's own weight carried by the
            supporter (see the module docstring).
        penetration: (n,) deepest penetration of each object over all its contacts, m
            (0 when it has none or only gaps): the ``d`` of Eq. 10 (Alg. 2 sums the contacts'
            depths; DESIGN section 4 takes the deepest).
        masses: (n,) kg, as given.
        gravity: m/s^2, as given.

    Edges are sorted by (supporter, supported), ground edges first.
    """

    ids: tuple[str, ...]
    supporter: np.ndarray
    supported: np.ndarray
    edge_force: np.ndarray
    edge_vertical: np.ndarray
    edge_fraction: np.ndarray
    penetration: np.ndarray
    masses: np.ndarray
    gravity: float

    @property
    def n(self) -> int:
        return len(self.ids)

    def __len__(self) -> int:
        """Number of edges."""
        return len(self.supporter)

    def __repr__(self) -> str:
        return f"SupportGraph({self.n} objects, {len(self)} edges, layers={self.layers()})"

    def edges(self) -> list[tuple[int, int]]:
        """``[(supporter, supported), ...]`` (supporter -1 = ground)."""
        return list(zip(self.supporter.tolist(), self.supported.tolist(), strict=True))

    def supported_by(self, i: int) -> list[int]:
        """Supporters of object ``i`` (-1 = ground), ascending."""
        return self.supporter[self.supported == i].tolist()

    def children(self, i: int) -> list[int]:
        """Objects supported by ``i`` (``i = -1``: objects on the table), ascending."""
        return self.supported[self.supporter == i].tolist()

    def fraction(self, supporter: int, supported: int) -> float:
        """F_S of the edge ``supporter -> supported`` (0.0 if there is none)."""
        sel = (self.supporter == supporter) & (self.supported == supported)
        return float(self.edge_fraction[sel].sum())

    def support_sum(self, i: int) -> float:
        """Sum of F_S over the objects ``i`` carries (the input of P_S, Eq. 11)."""
        return float(self.edge_fraction[self.supporter == i].sum())

    def support_sums(self) -> np.ndarray:
        """(n,) :meth:`support_sum` of every object."""
        out = np.zeros(self.n)
        obj = self.supporter >= 0
        np.add.at(out, self.supporter[obj], self.edge_fraction[obj])
        return out

    def supported_fraction(self, i: int) -> float:
        """Sum of F_S over the supporters of ``i`` (about 1 for an object at rest)."""
        return float(self.edge_fraction[self.supported == i].sum())

    def depths(self) -> np.ndarray:
        """(n,) BFS distance of each object from the ground (0: on the table), -1 if no
        support path reaches it."""
        n = self.n
        depth = np.full(n, -1, dtype=int)
        children: list[list[int]] = [[] for _ in range(n + 1)]  # slot n: ground
        for a, b in self.edges():
            children[n if a < 0 else a].append(b)
        queue: deque[int] = deque()
        for b in children[n]:
            if depth[b] < 0:
                depth[b] = 0
                queue.append(b)
        while queue:
            a = queue.popleft()
            for b in children[a]:
                if depth[b] < 0:
                    depth[b] = depth[a] + 1
                    queue.append(b)
        return depth

    def layers(self) -> list[list[int]]:
        """Object indices grouped by BFS distance from the ground (layer 0: on the table; the
        ``VerticesByDistance`` of Alg. 3), each group ascending; objects with no support path
        from the ground come last, as one extra group (absent when every object is reachable:
        DESIGN section 4)."""
        depth = self.depths()
        top = int(depth.max()) if self.n else -1
        out = [np.flatnonzero(depth == d).tolist() for d in range(top + 1)]
        rest = np.flatnonzero(depth < 0).tolist()
        if rest:
            out.append(rest)
        return out

    def unsupported(self) -> list[int]:
        """Objects with no support path from the ground, ascending."""
        return np.flatnonzero(self.depths() < 0).tolist()


def build_support_graph(
    contacts: Contacts,
    masses,
    g: float = 9.81,
    *,
    min_force: float = 1e-3,
) -> SupportGraph:
    """Support graph (Alg. 2) from ``contacts`` (e.g. ``world.contacts()``).

    Args:
        contacts: the contact snapshot; its ``ids`` define the objects.
        masses: (n,) object masses, kg, in id order (``world.masses``).
        g: gravity magnitude, m/s^2.
        min_force: a pair (or table contact set) whose net vertical push is below this (N)
            gets no edge (lateral or load-free touching).

    Disabled objects have no contacts, so they end up in the unsupported group.
    """
    ids = tuple(contacts.ids)
    n = len(ids)
    masses = np.asarray(masses, dtype=float).reshape(-1)
    if masses.shape != (n,):
        raise ValueError(f"masses must have shape ({n},), got {masses.shape}")
    g = float(g)
    if not g > 0:
        raise ValueError(f"g must be > 0, got {g}")

    a = np.asarray(contacts.obj_a, dtype=int)
    b = np.asarray(contacts.obj_b, dtype=int)
    nf = np.asarray(contacts.normal_force, dtype=float)
    vz = nf * np.asarray(contacts.normal, dtype=float).reshape(-1, 3)[:, 2]  # push on b, up +
    depth = np.asarray(contacts.depth, dtype=float)

    penetration = _penetration(a, b, depth, n)
    sup, sud, force, up = _support_edges(a, b, nf, vz, n, float(min_force))
    fraction = _edge_fractions(sup, sud, up, masses, g, n)
    return SupportGraph(
        ids=ids,
        supporter=_frozen(sup, int),
        supported=_frozen(sud, int),
        edge_force=_frozen(force),
        edge_vertical=_frozen(up),
        edge_fraction=_frozen(fraction),
        penetration=_frozen(penetration),
        masses=_frozen(masses),
        gravity=g,
    )


def _penetration(a: np.ndarray, b: np.ndarray, depth: np.ndarray, n: int) -> np.ndarray:
    """(n,) deepest penetration of each object over its contacts (``a``, ``b``: the contacts'
    objects, ``b = -1`` the table; ``depth``: their penetration depths), m."""
    penetration = np.zeros(n)
    if len(depth):
        d = np.maximum(depth, 0.0)
        np.maximum.at(penetration, a, d)
        obj_b = b >= 0
        np.maximum.at(penetration, b[obj_b], d[obj_b])
    return penetration


def _support_edges(
    a: np.ndarray, b: np.ndarray, nf: np.ndarray, vz: np.ndarray, n: int, min_force: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(supporter, supported, force, vertical push)`` of the support edges, sorted by
    supporter then supported: the contacts (objects ``a``, ``b``, normal forces ``nf``,
    vertical pushes ``vz`` on ``b``) summed per pair, the pairs pushing up by ``min_force`` or
    more kept."""
    # Sum per unordered pair (a < b, or b = -1 for the table; Contacts guarantees the order).
    key = (a + 1) * (n + 1) + (b + 1)
    uniq, inv = np.unique(key, return_inverse=True)
    pair_a = uniq // (n + 1) - 1
    pair_b = uniq % (n + 1) - 1
    force = np.bincount(inv, weights=nf, minlength=len(uniq))
    vert = np.bincount(inv, weights=vz, minlength=len(uniq))

    table = pair_b < 0
    # Table: the normal points from the object into the table, so the push on the object is -vz.
    up = np.where(table, -vert, np.abs(vert))
    a_supports_b = vert > 0
    sup = np.where(table, GROUND, np.where(a_supports_b, pair_a, pair_b))
    sud = np.where(table, pair_a, np.where(a_supports_b, pair_b, pair_a))
    keep = up >= min_force
    sup, sud, force, up = sup[keep], sud[keep], force[keep], up[keep]
    order = np.lexsort((sud, sup))
    return sup[order], sud[order], force[order], up[order]


def _edge_fractions(
    sup: np.ndarray, sud: np.ndarray, up: np.ndarray, masses: np.ndarray, g: float, n: int
) -> np.ndarray:
    """Fraction of the supported object's weight each edge carries (its share of the net
    upward push, U_b - D_b, over the weight)."""
    upward = np.bincount(sud, weights=up, minlength=n)  # U_b
    obj = sup >= 0
    downward = np.bincount(sup[obj], weights=up[obj], minlength=n)  # D_b
    net = np.maximum(upward - downward, 0.0)
    weight = masses * g
    with np.errstate(divide="ignore", invalid="ignore"):
        per_b = np.where(upward > 0, net / (upward * weight), 0.0)
    return up * per_b[sud] if len(sud) else np.zeros(0)


def _frozen(x, dtype=float) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=dtype)
    x.flags.writeable = False
    return x
