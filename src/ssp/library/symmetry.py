"""Object symmetries in the BOP ``models_info`` convention, in metres.

A symmetry is a transform ``T_sym`` in the model frame that leaves the object's shape unchanged:
``T_world_obj @ T_sym`` is the same physical pose as ``T_world_obj``. Discrete symmetries are a
finite set (identity included); continuous ones are rotation axes (through ``offset``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.errors import ModelError


@dataclass(frozen=True)
class ContinuousSymmetry:
    """Rotation by any angle about ``axis`` (unit, model frame) through ``offset`` (m)."""

    axis: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def transform(self, angle: float) -> np.ndarray:
        """4x4 model-frame transform of the rotation by ``angle`` (rad)."""
        R = Rotation.from_rotvec(self.axis * angle).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = self.offset - R @ self.offset
        return T


@dataclass(frozen=True)
class Symmetry:
    """Discrete transforms ``(S, 4, 4)`` (first one the identity) and continuous axes."""

    discrete: np.ndarray = field(default_factory=lambda: np.eye(4)[None])
    continuous: tuple[ContinuousSymmetry, ...] = ()

    def __post_init__(self) -> None:
        d = np.asarray(self.discrete, dtype=float).reshape(-1, 4, 4)
        if not np.allclose(d[0], np.eye(4), atol=1e-9):
            ident = np.all(np.isclose(d, np.eye(4), atol=1e-9), axis=(1, 2))
            d = np.concatenate([np.eye(4)[None], d[~ident]])
        R = d[:, :3, :3]
        if not np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-5):
            raise ModelError("discrete symmetries must be rigid transforms")
        object.__setattr__(self, "discrete", d)
        cont = []
        for c in self.continuous:
            axis = np.asarray(c.axis, dtype=float)
            n = np.linalg.norm(axis)
            if not np.isfinite(n) or n < 1e-9:
                raise ModelError(f"continuous symmetry axis must be non-zero, got {axis}")
            cont.append(ContinuousSymmetry(axis / n, np.asarray(c.offset, dtype=float)))
        object.__setattr__(self, "continuous", tuple(cont))

    @property
    def is_symmetric(self) -> bool:
        return len(self.discrete) > 1 or bool(self.continuous)

    def transforms(self, continuous_step: float = np.radians(5.0)) -> np.ndarray:
        """All symmetry transforms ``(n, 4, 4)``: discrete x sampled continuous rotations.

        Continuous axes are sampled every ``continuous_step`` rad (BOP samples likewise); with
        several continuous axes (a sphere) only the first is sampled, as in bop_toolkit.
        """
        if not self.continuous:
            return self.discrete.copy()
        n = max(1, int(np.ceil(2 * np.pi / continuous_step)))
        rots = np.stack([self.continuous[0].transform(2 * np.pi * i / n) for i in range(n)])
        return np.einsum("aij,bjk->abik", self.discrete, rots).reshape(-1, 4, 4)

    @classmethod
    def from_bop(cls, info: dict, scale: float = 1.0) -> Symmetry:
        """From a BOP ``models_info`` entry; ``scale`` converts its units to metres (mm: 1e-3)."""
        try:
            discrete = [
                np.asarray(s, dtype=float).reshape(4, 4)
                for s in info.get("symmetries_discrete", [])
            ]
            for T in discrete:
                T[:3, 3] *= scale
            continuous = tuple(
                ContinuousSymmetry(
                    np.asarray(c["axis"], dtype=float),
                    np.asarray(c.get("offset", [0, 0, 0]), dtype=float) * scale,
                )
                for c in info.get("symmetries_continuous", [])
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"malformed symmetry description {info!r}: {exc}") from exc
        d = np.stack([np.eye(4), *discrete]) if discrete else np.eye(4)[None]
        return cls(d, continuous)

    def to_bop(self, scale: float = 1.0) -> dict:
        """BOP ``models_info`` keys; ``scale`` converts metres to the file's units."""
        out: dict = {}
        if len(self.discrete) > 1:
            ds = self.discrete[1:].copy()
            ds[:, :3, 3] *= scale
            out["symmetries_discrete"] = [d.reshape(-1).tolist() for d in ds]
        if self.continuous:
            out["symmetries_continuous"] = [
                {"axis": c.axis.tolist(), "offset": (c.offset * scale).tolist()}
                for c in self.continuous
            ]
        return out
