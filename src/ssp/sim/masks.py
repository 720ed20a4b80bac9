"""Real-mask defects on a rendered instance mask: edge bleeding and flying pixels.

An instance segmenter on a real RGB-D frame hands over masks whose borders are wrong by a pixel
or two, and a time-of-flight or structured-light sensor returns *flying pixels* at depth
discontinuities, with depths between the foreground and the background. Both put stray points
into an object's segment: 0.5-2 % of a segment's pixels on real masks (issue 15), which makes
the segment's max-min extent larger than any model and pulls data forces off the object.

:func:`add_mask_defects` adds them to a clean ``(depth, instance)`` pair. For each object
segment (instance >= 0) with ``n`` pixels, a fraction ``f ~ U(fraction)`` of ``n`` defect
pixels is chosen among the pixels just outside the segment (within ``reach`` pixels of it);
each is, with probability ``bleed_share``,

* **bled**: labelled as the object, its depth unchanged (a point of the table or of the object
  behind, up to several centimetres from the object), or else
* **flying**: labelled as the object, its depth replaced by ``a d_fg + (1 - a) d_bg`` with
  ``a ~ U(0.1, 0.9)``, ``d_fg`` the depth of the nearest segment pixel and ``d_bg`` its own
  depth (``d_fg`` times ``U(1.02, 1.3)`` where it had none): a point floating between the
  object and what lies behind it.

Deterministic for a given ``rng``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["DEFECT_FRACTION", "add_mask_defects"]

#: Defect pixels per segment, as a fraction of its pixels (issue 17: 0.5-3 %).
DEFECT_FRACTION = (0.005, 0.03)


def add_mask_defects(
    depth: np.ndarray,
    instance: np.ndarray,
    rng: np.random.Generator,
    *,
    fraction: tuple[float, float] = DEFECT_FRACTION,
    bleed_share: float = 0.5,
    reach: int = 2,
) -> tuple[np.ndarray, np.ndarray, dict[int, int]]:
    """Copies of ``depth`` ``(H, W)`` (m, 0 = none) and ``instance`` ``(H, W)`` (object index
    >= 0, negative = table / nothing) with defects (module docstring), and the number of defect
    pixels given to each object index."""
    depth = np.asarray(depth, dtype=float)
    inst = np.asarray(instance)
    out_d = depth.copy()
    out_i = inst.copy()
    counts: dict[int, int] = {}
    labels = np.unique(inst[inst >= 0])
    structure = ndimage.generate_binary_structure(2, 2)
    taken = np.zeros(inst.shape, dtype=bool)
    for k in labels:
        mask = inst == k
        n = int(mask.sum())
        f = rng.uniform(*fraction)
        n_def = int(round(f * n))
        ring = ndimage.binary_dilation(mask, structure, iterations=reach) & ~mask & ~taken
        cand = np.flatnonzero(ring)
        if n_def == 0 or not len(cand):
            continue
        pick = rng.choice(cand, size=min(n_def, len(cand)), replace=False)
        # depth of the nearest segment pixel, for flying pixels
        _, (iy, ix) = ndimage.distance_transform_edt(~mask, return_indices=True)
        rows, cols = np.unravel_index(pick, inst.shape)
        d_fg = depth[iy[rows, cols], ix[rows, cols]]
        d_bg = depth[rows, cols]
        flying = rng.random(len(pick)) >= bleed_share
        a = rng.uniform(0.1, 0.9, size=len(pick))
        behind = np.where(d_bg > d_fg, d_bg, d_fg * rng.uniform(1.02, 1.3, size=len(pick)))
        new_d = np.where(flying, a * d_fg + (1.0 - a) * behind, d_bg)
        ok = (new_d > 0) & (d_fg > 0)
        rows, cols, new_d = rows[ok], cols[ok], new_d[ok]
        out_d[rows, cols] = new_d
        out_i[rows, cols] = k
        taken[rows, cols] = True
        counts[int(k)] = int(len(rows))
    return out_d, out_i, counts
