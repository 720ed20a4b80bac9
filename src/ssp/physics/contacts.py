"""Contact read-out: a frozen, array-based snapshot of the contacts of a world."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


class ContactRecord(NamedTuple):
    """One contact point as plain values. ``b`` is ``None`` for the table."""

    a: str
    b: str | None
    position: np.ndarray
    normal: np.ndarray
    depth: float
    normal_force: float


def _frozen(x: np.ndarray) -> np.ndarray:
    x = np.ascontiguousarray(x)
    x.flags.writeable = False
    return x


@dataclass(frozen=True, eq=False)
class Contacts:
    """Contact points of a world at one state, as arrays of length ``n`` (one row per point).

    Attributes:
        ids: the world's object ids; ``obj_a`` / ``obj_b`` index into it.
        obj_a: (n,) int, index of the first object.
        obj_b: (n,) int, index of the second object, or -1 for the table. The table is always
            ``obj_b``; for two objects ``obj_a < obj_b``.
        position: (n, 3) contact point, world frame, m (midway between the two surfaces).
        normal: (n, 3) unit contact normal, world frame, pointing from a to b (for a table
            contact: downward into the table).
        depth: (n,) penetration depth, m; positive when the surfaces interpenetrate, negative for
            a gap within the contact margin.
        normal_force: (n,) normal contact force, N (>= 0), from the last constraint solve.
    """

    ids: tuple[str, ...]
    obj_a: np.ndarray
    obj_b: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    normal_force: np.ndarray

    TABLE = -1

    def __post_init__(self) -> None:
        for name in ("obj_a", "obj_b", "position", "normal", "depth", "normal_force"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))

    @classmethod
    def empty(cls, ids: tuple[str, ...]) -> Contacts:
        z = np.zeros(0)
        return cls(
            ids, np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), z, z.copy()
        )

    def __len__(self) -> int:
        return len(self.depth)

    def __iter__(self) -> Iterator[ContactRecord]:
        return iter(self.records())

    def records(self) -> list[ContactRecord]:
        """The contacts as :class:`ContactRecord` tuples (object ids instead of indices)."""
        return [
            ContactRecord(
                self.ids[a],
                None if b < 0 else self.ids[b],
                self.position[k],
                self.normal[k],
                float(self.depth[k]),
                float(self.normal_force[k]),
            )
            for k, (a, b) in enumerate(zip(self.obj_a.tolist(), self.obj_b.tolist(), strict=True))
        ]

    def select(self, mask: np.ndarray) -> Contacts:
        """The subset of contacts where the boolean ``mask`` (n,) is true."""
        mask = np.asarray(mask, dtype=bool)
        return Contacts(
            self.ids,
            self.obj_a[mask],
            self.obj_b[mask],
            self.position[mask],
            self.normal[mask],
            self.depth[mask],
            self.normal_force[mask],
        )

    def involving(self, index: int) -> Contacts:
        """Contacts of object ``index`` (as a or b); ``-1`` gives the table's contacts."""
        return self.select((self.obj_a == index) | (self.obj_b == index))

    def between(self, a: int, b: int) -> Contacts:
        """Contacts between objects ``a`` and ``b`` (either order; ``-1`` = table)."""
        return self.select(
            ((self.obj_a == a) & (self.obj_b == b)) | ((self.obj_a == b) & (self.obj_b == a))
        )

    @property
    def max_depth(self) -> float:
        """Deepest penetration, m (0.0 when there are no contacts)."""
        return float(self.depth.max()) if len(self) else 0.0

    def __repr__(self) -> str:
        return f"Contacts(n={len(self)}, max_depth={self.max_depth:.3g} m)"
