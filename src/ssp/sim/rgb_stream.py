"""The RGB estimator's errors (MegaPose-like) for :class:`ssp.sim.realistic.RealisticStream`:
measured tables (:class:`RgbErrors`) and the per-object draw (:class:`RgbObjects`).

An RGB estimator errs mostly in depth, along the viewing ray. Per object and frame (the
object's visible fraction ``v`` picks the row of every per-visibility table, bins
:attr:`RgbErrors.visib_edges`):

* **missed** with probability ``miss[v]`` (no hypothesis at all);
* else its first hypothesis is **far** (a wrong detection, > 10 cm off) with probability
  ``far[v]``: along-ray error, lateral error and rotation from the ``far_*`` tables, the turn
  about a random axis through the centre of mass;
* else **near**: along-ray error (signed, + farther from the camera) from ``along_mm[v]``,
  lateral error (magnitude) from ``lateral_mm[v]`` in a random direction across the ray, a
  small turn from ``rotation_deg[v]`` about a random axis; and with probability ``flip[v]`` a
  **flip** on top: a turn by ``flip_deg`` about one of the model's bounding-box axes through
  its centre of mass (measured flips turn about a model axis: 78 % within 18 deg of one, 15 %
  for random axes; 60 % are half turns);
* ``rows`` gives the number of hypotheses (1-5); the extra ones are other detections, errors
  from the ``far_*`` tables;
* scores: the first hypothesis from ``score_right`` (near, no flip) or ``score_wrong``, the
  extra ones from ``score_extra``, capped below the first's (so the best-scored hypothesis is
  the object's first, as the tables were measured on the best-scored row).

Tables are inverse CDFs at ``levels`` (linear in between). Every random quantity is a standard
normal latent ``z`` turned into a uniform ``Phi(z)`` or a direction: the latent of a
hypothesis is ``sqrt(persistence) z_view + sqrt(1 - persistence) n`` with ``z_view`` an AR(1)
per object (coefficient ``rho``) redrawn when the view changes, ``n`` fresh: an RGB estimator
errs the same way on frames of a static scene, while each hypothesis' marginal distribution is
exactly the measured one.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import ndtr

from ssp.probability import pose_change

__all__ = ["LATENT", "MEGAPOSE_LMO", "RgbErrors", "RgbObjects"]

#: Latent dimensions per object: along 0, lateral 1-2, rotation 3-5, miss 6, far 7, flip 8,
#: far along 9, far lateral 10-11, far turn axis 12-14 and angle 15, flip axis 16 and angle 17,
#: rows 18.
LATENT = 19
_LEVELS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.98, 1.0)
_BINS = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0)
#: Near tables of the bins with too few near rows (< 50) are those of the next bin up.
MIN_NEAR = 50

Table = tuple[float, ...]

#: :class:`RgbErrors` of MegaPose on LM-O scene 2 (``ssp bench rgb-calibration --data
#: ../shared/data/lmo-megapose``, then :meth:`RgbErrors.from_calibration`; mm, deg).
# fmt: off
MEGAPOSE_LMO: dict[str, Any] = {
    "visib_edges": (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0),
    "levels": (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.98, 1.0),
    "miss": (0.907, 0.8571, 0.5352, 0.2642, 0.0958, 0.0578),
    "far": (1.0, 1.0, 0.6667, 0.3662, 0.0935, 0.0644),
    "flip": (0.0, 0.0, 0.1364, 0.1333, 0.1065, 0.0721),
    "along_mm": (  # below 0.7 visible: the 0.5-0.7 table (MIN_NEAR)
        *((
            -72.305, -46.474, -36.681, -22.982, -17.412, -7.485, -3.433, 2.095, 7.162, 13.647,
            21.417, 28.448, 61.45, 77.222, 86.558
        ),) * 4,
        (
            -82.486, -49.7, -40.194, -31.004, -20.843, -12.397, -8.22, -2.321, 1.09, 5.025, 10.015,
            19.944, 26.734, 46.812, 91.645
        ),
        (
            -71.707, -54.741, -45.695, -36.095, -24.982, -15.011, -8.621, -3.445, 0.261, 3.493,
            7.07, 12.018, 17.783, 25.329, 83.577
        ),
    ),
    "lateral_mm": (  # below 0.7 visible: the 0.5-0.7 table (MIN_NEAR)
        *((
            1.011, 1.329, 2.12, 2.936, 3.621, 4.184, 5.486, 6.195, 7.334, 8.562, 11.304, 17.274,
            36.693, 55.284, 80.444
        ),) * 4,
        (
            0.519, 0.975, 1.381, 1.985, 2.601, 3.426, 4.082, 4.654, 5.753, 6.903, 8.874, 10.518,
            15.967, 22.688, 66.543
        ),
        (
            0.241, 0.94, 1.266, 1.659, 2.358, 2.901, 3.381, 4.026, 4.652, 5.531, 6.506, 8.238,
            11.178, 13.512, 19.191
        ),
    ),
    "rotation_deg": (  # below 0.7 visible: the 0.5-0.7 table (MIN_NEAR)
        *((
            1.099, 1.565, 1.964, 2.579, 3.166, 3.919, 4.236, 4.778, 5.726, 6.303, 7.645, 9.885,
            13.19, 19.284, 24.446
        ),) * 4,
        (
            0.397, 0.663, 1.125, 1.506, 2.157, 2.631, 3.013, 3.596, 4.266, 5.25, 6.081, 8.293,
            11.146, 16.202, 20.657
        ),
        (
            0.103, 1.032, 1.43, 2.041, 2.791, 3.331, 3.947, 4.639, 5.406, 6.27, 7.594, 9.105,
            11.071, 14.313, 29.439
        ),
    ),
    "flip_deg": (
        30.58, 30.622, 31.396, 34.749, 74.595, 93.654, 155.28, 170.601, 174.034, 175.889, 177.732,
        178.681, 179.324, 179.586, 179.863
    ),
    "far_along_mm": (
        -697.962, -506.483, -301.236, -112.428, 85.911, 149.435, 231.519, 310.215, 414.73, 559.136,
        780.75, 1206.832, 1498.017, 1648.142, 1805.544
    ),
    "far_lateral_mm": (
        2.725, 7.617, 13.39, 23.85, 44.306, 61.868, 84.457, 190.666, 351.737, 477.633, 632.049,
        923.399, 1093.134, 1293.264, 1334.82
    ),
    "far_rotation_deg": (
        11.041, 16.051, 22.72, 34.852, 59.793, 76.515, 96.223, 113.119, 136.335, 145.748, 161.712,
        171.485, 176.922, 178.819, 179.975
    ),
    "rows": (0.7192, 0.2121, 0.0545, 0.0126, 0.0017),
    "score_right": (
        0.144, 0.991, 0.997, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0
    ),
    "score_wrong": (
        0.003, 0.014, 0.036, 0.118, 0.299, 0.654, 0.865, 0.97, 0.993, 0.998, 1.0, 1.0, 1.0, 1.0,
        1.0
    ),
    "score_extra": (
        0.0, 0.006, 0.013, 0.026, 0.056, 0.109, 0.189, 0.32, 0.502, 0.725, 0.92, 0.975, 0.995,
        0.999, 1.0
    ),
}
# fmt: on


@dataclass(frozen=True)
class RgbErrors:
    """Measured error tables of an RGB estimator (module docstring). Units: mm, deg.

    :meth:`megapose_lmo`: MegaPose (CNOS + FastSAM detections, BOP19 submission) on LM-O test
    scene 2, by
    ``ssp bench rgb-calibration --data ../shared/data/lmo-megapose`` (LM-O ground truth and
    the published CSV; :mod:`ssp.eval.rgb_calibration`): 1,466 targets >= 10 % visible (the
    images the CSV has rows for), 273 (18.6 %) without a row; of the best-scored rows, 15.1 %
    are far (> 10 cm off); along-ray |error| median 14.1 mm, p75 34.7 mm, 60 % > 10 mm,
    40 % > 20 mm; not far, the signed along-ray error has median -3.0 mm (estimates slightly
    too close), 42 % positive, tails a little heavier than Gaussian ((q95-q05)/(q75-q25) 2.78,
    Gaussian 2.44); lateral median 5.1 mm; rotation (up to the symmetries) median 5.5 deg,
    p75 13.2 deg, 21.5 % > 30 deg; flips (not far, > 30 deg) 8.9 %, 60 % of them > 150 deg,
    about a model axis; rows per detected target 1: 858, 2: 253, 3: 65, 4: 15, 5: 2 (96 % of
    extra rows are far); scores: right best rows ~1.0 (p2 0.991), wrong best rows median 0.97,
    extra rows median 0.32. Per visible fraction 0-0.1 / 0.1-0.3 / 0.3-0.5 / 0.5-0.7 /
    0.7-0.9 / 0.9-1: missed 0.91 / 0.86 / 0.54 / 0.26 / 0.10 / 0.06; far 1.0 / 1.0 / 0.67 /
    0.37 / 0.09 / 0.06. Near tables of bins below 0.5 (< 50 near rows) are the 0.5-0.7 bin's.

    ``persistence`` (share of each latent that persists over a static view) is chosen: the
    CSV has one image per view.
    """

    visib_edges: Table
    levels: Table
    miss: Table
    far: Table
    flip: Table
    along_mm: tuple[Table, ...]
    lateral_mm: tuple[Table, ...]
    rotation_deg: tuple[Table, ...]
    flip_deg: Table
    far_along_mm: Table
    far_lateral_mm: Table
    far_rotation_deg: Table
    rows: Table
    score_right: Table
    score_wrong: Table
    score_extra: Table
    persistence: float = 0.9

    def __post_init__(self) -> None:
        nb = len(self.visib_edges) - 1
        for name in ("miss", "far", "flip", "along_mm", "lateral_mm", "rotation_deg"):
            if len(getattr(self, name)) != nb:
                raise ValueError(f"{name} needs one entry per visibility bin ({nb})")
        tables = [*self.along_mm, *self.lateral_mm, *self.rotation_deg, self.flip_deg,
                  self.far_along_mm, self.far_lateral_mm, self.far_rotation_deg,
                  self.score_right, self.score_wrong, self.score_extra]  # fmt: skip
        for t in tables:
            if len(t) != len(self.levels) or any(b < a for a, b in zip(t, t[1:], strict=False)):
                raise ValueError("every table needs one non-decreasing value per level")
        if not 0.0 <= self.persistence < 1.0:
            raise ValueError(f"persistence must be in [0, 1), got {self.persistence}")
        if abs(sum(self.rows) - 1.0) > 1e-3:
            raise ValueError("rows must be probabilities summing to 1")

    @classmethod
    def from_calibration(cls, result: Mapping[str, Any], persistence: float = 0.9) -> RgbErrors:
        """The tables of a :func:`ssp.eval.rgb_calibration.calibrate_rgb` result. A bin without
        targets takes the next bin up's rates (the top bin the next one down), a bin with
        fewer than :data:`MIN_NEAR` near rows the next bin up's near tables; a table with no
        sample at all is constant (0; flips 180 deg; scores 0.5)."""
        bins = result["per_bin"]
        nb = len(bins)
        levels = tuple(float(v) for v in result["settings"]["quantile_levels"])
        rates: list = [None] * nb
        near: list = [None] * nb
        for k in reversed(range(nb)):
            up = k + 1 if k < nb - 1 else None
            rates[k] = bins[k] if bins[k]["targets"] or up is None else rates[up]
            ok = bins[k].get("near_n", 0) >= MIN_NEAR
            near[k] = bins[k]["near"] if ok or up is None else near[up]
        for k in range(nb):  # the top bin without targets: the next one down
            if not rates[k]["targets"] and k > 0:
                rates[k] = rates[k - 1]
        o, r = result["overall"], result["rows"]
        hist = [r["rows_per_detected_target"][str(k)] for k in range(1, 6)]

        def t(x, default: float = 0.0) -> Table:
            if x is None:
                return (default,) * len(levels)
            return tuple(float(default if v is None else v) for v in x)

        def pick(i: int, key: str) -> Table:
            n = near[i]
            return t(n[key] if n is not None else None)

        return cls(
            visib_edges=t(result["settings"]["visibility_bins"]),
            levels=levels,
            miss=t(b["miss_rate"] for b in rates),
            far=t((b["far_rate"] if b["n"] else 1.0) for b in rates),
            flip=t(b["flip_rate"] for b in rates),
            along_mm=tuple(pick(i, "along_mm_q") for i in range(nb)),
            lateral_mm=tuple(pick(i, "lateral_mm_q") for i in range(nb)),
            rotation_deg=tuple(pick(i, "rotation_small_deg_q") for i in range(nb)),
            flip_deg=t(o["near"]["flip_deg_q"], 180.0),
            far_along_mm=t(o["far"]["along_mm_q"]),
            far_lateral_mm=t(o["far"]["lateral_mm_q"]),
            far_rotation_deg=t(o["far"]["rotation_deg_q"]),
            rows=t(round(h / sum(hist), 4) for h in hist),
            score_right=t(r["score_best_right_q"], 0.5),
            score_wrong=t(r["score_best_wrong_q"], 0.5),
            score_extra=t(r["score_extra_q"], 0.5),
            persistence=persistence,
        )

    @classmethod
    def megapose_lmo(cls, persistence: float = 0.9) -> RgbErrors:
        """MegaPose on LM-O scene 2 (:data:`MEGAPOSE_LMO`; the class docstring)."""
        return cls(**MEGAPOSE_LMO, persistence=persistence)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def bin(self, v: float) -> int:
        """The visibility bin of ``v``."""
        k = int(np.searchsorted(self.visib_edges, float(v), side="right")) - 1
        return int(np.clip(k, 0, len(self.visib_edges) - 2))

    def quantile(self, table: Table, u: float) -> float:
        """The table's inverse CDF at ``u`` in [0, 1]."""
        return float(np.interp(u, self.levels, table))


@dataclass
class _View:
    T: np.ndarray
    visib: float
    z: np.ndarray  # (LATENT,)


def _across(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to the unit vector ``u`` and to each other."""
    a = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(u, a)


def _unit(g: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(g))
    return g / n if n > 0 else np.array([1.0, 0.0, 0.0])[: len(g)]


@dataclass
class RgbObjects:
    """Per-object RGB-estimator draws over one sequence (module docstring): call
    :meth:`draw` per object and frame, in frame order.

    Args:
        errors: the tables.
        rho: AR(1) coefficient of each object's latent while its view is unchanged.
        redraw: ``(shift m, tilt deg, visibility)``: a larger change is a new view.
    """

    errors: RgbErrors
    rho: float
    redraw: tuple[float, float, float]
    _views: dict[str, _View] = field(default_factory=dict, init=False)

    def _latent(self, oid: str, T: np.ndarray, v: float, rng) -> np.ndarray:
        innovation = rng.standard_normal(LATENT)
        st = self._views.get(oid)
        if st is None:
            self._views[oid] = _View(T.copy(), v, innovation)
            return innovation
        dt, dth = pose_change(st.T, T)
        shift, tilt, dv = self.redraw
        if dt > shift or math.degrees(dth) > tilt or abs(v - st.visib) > dv:
            st.z = innovation
        else:
            st.z = self.rho * st.z + math.sqrt(1.0 - self.rho**2) * innovation
        st.T, st.visib = T.copy(), v
        return st.z

    def draw(
        self,
        oid: str,
        T: np.ndarray,
        v: float,
        centre: np.ndarray,
        axes: np.ndarray,
        T_world_cam: np.ndarray,
        rng: np.random.Generator,
    ) -> list[tuple[np.ndarray, float, str]]:
        """The hypotheses of object ``oid`` at true pose ``T`` (4x4 world, m) with visible
        fraction ``v``: ``(T_world_obj, score, kind)`` each (kind ``nominal``, ``flip`` or
        ``gross``), the first one best scored; ``[]`` when missed.

        Args:
            centre: (3,) the model's centre of mass (model frame, m): turns are about it.
            axes: (3, 3) the model's bounding-box axes (columns, model frame): flip axes.
            T_world_cam: the camera pose (its position sets the viewing ray).
        """
        e = self.errors
        T = np.asarray(T, dtype=float)
        z_view = self._latent(oid, T, v, rng)
        s = e.persistence
        z = math.sqrt(s) * z_view + math.sqrt(1.0 - s) * rng.standard_normal(LATENT)
        u = ndtr(z)  # the uniforms
        k = e.bin(v)
        if u[6] < e.miss[k]:
            return []
        p = T[:3, :3] @ centre + T[:3, 3]
        ray = _unit(p - np.asarray(T_world_cam, dtype=float)[:3, 3])
        a, b = _across(ray)
        if u[7] < e.far[k]:
            first = self._far(T, centre, ray, a, b, z[10:16], u[9])
            kind, score_table = "gross", e.score_wrong
        else:
            d = e.quantile(e.along_mm[k], u[0])
            lat = e.quantile(e.lateral_mm[k], float(1.0 - math.exp(-0.5 * z[1:3] @ z[1:3])))
            shift = 1e-3 * (d * ray + lat * (_unit(z[1:3])[0] * a + _unit(z[1:3])[1] * b))
            chi3 = float(_chi3_cdf(float(np.linalg.norm(z[3:6]))))
            turn = math.radians(e.quantile(e.rotation_deg[k], chi3)) * _unit(z[3:6])
            first = _moved(T, centre, shift, Rotation.from_rotvec(turn).as_matrix())
            kind, score_table = "nominal", e.score_right
            if u[8] < e.flip[k]:
                axis = axes[:, min(int(u[16] * 3), 2)]
                angle = math.radians(e.quantile(e.flip_deg, u[17]))
                F = np.eye(4)
                F[:3, :3] = Rotation.from_rotvec(axis * angle).as_matrix()
                F[:3, 3] = centre - F[:3, :3] @ centre
                first = first @ F
                kind, score_table = "flip", e.score_wrong
        score = e.quantile(score_table, float(rng.random()))
        out = [(first, score, kind)]
        n = 1 + int(np.searchsorted(np.cumsum(e.rows), u[18] * sum(e.rows), side="right"))
        for _ in range(min(n, len(e.rows)) - 1):
            g = rng.standard_normal(7)
            Th = self._far(T, centre, ray, a, b, g[:6], float(ndtr(g[6])))
            s_extra = e.quantile(e.score_extra, float(rng.random()))
            out.append((Th, min(s_extra, 0.999 * score), "gross"))
        return out

    def _far(self, T, centre, ray, a, b, g: np.ndarray, u_along: float) -> np.ndarray:
        """A far hypothesis: along and lateral errors and a turn from the far tables; ``g``
        (6,) standard normals (lateral direction and magnitude 2, turn 3, angle 1)."""
        e = self.errors
        d = e.quantile(e.far_along_mm, u_along)
        lat = e.quantile(e.far_lateral_mm, float(1.0 - math.exp(-0.5 * g[:2] @ g[:2])))
        dir2 = _unit(g[:2])
        shift = 1e-3 * (d * ray + lat * (dir2[0] * a + dir2[1] * b))
        angle = math.radians(e.quantile(e.far_rotation_deg, float(ndtr(g[5]))))
        R = Rotation.from_rotvec(angle * _unit(g[2:5])).as_matrix()
        return _moved(T, centre, shift, R)


def _chi3_cdf(r: float) -> float:
    """CDF of the norm of a 3D standard normal vector (Maxwell law)."""
    return float(math.erf(r / math.sqrt(2.0)) - math.sqrt(2.0 / math.pi) * r * math.exp(-r * r / 2))


def _moved(T: np.ndarray, centre: np.ndarray, shift: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``T`` turned by ``R`` (world-frame rotation) about its centre of mass and shifted by
    ``shift`` (m, world)."""
    out = np.eye(4)
    out[:3, :3] = R @ T[:3, :3]
    p = T[:3, :3] @ centre + T[:3, 3]
    out[:3, 3] = p + shift - out[:3, :3] @ centre
    return out
