"""Why an estimate failed: the estimator stream's condition behind each gross error or false
object, for the per-class tables of the realistic protocol (:mod:`ssp.sim.realistic`).

Per ground-truth object and frame, from the generator's record of every hypothesis's source and
kind (``SimSequence.info["hypothesis_sources"]`` and ``["hypothesis_kinds"]``), the
*condition* of the stream for that object (:func:`object_conditions`), first that applies:

* ``hidden``: less than 10 % visible;
* ``dropout``: visible, but no hypothesis of it in this frame;
* ``top1_<kind>``: its best-scored hypothesis is a ``gross`` outlier, a ``flip`` or a
  ``confusion`` (another class);
* ``nominal``: its best-scored hypothesis is good.

A false object of a method (an estimate matched to no ground-truth object) is attributed
(:func:`false_object_cause`) to the nearest of, within the matching gate: a ``distractor``, a
``false_positive`` hypothesis, a ground-truth object of another class (``class_confusion``), a
ground-truth object of the same class (``duplicate``: an object output twice, or one placed
beyond the gate), else ``elsewhere``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ssp.eval.metrics import DEFAULT_GATE

__all__ = ["VISIBLE", "false_object_cause", "object_conditions"]

#: Objects less visible than this are ``hidden``.
VISIBLE = 0.1


def object_conditions(
    gt: Mapping[str, tuple[str, np.ndarray]],
    visib_fract: Mapping[str, float],
    hypotheses: Sequence,
    sources: Sequence[str | None],
    kinds: Sequence[str],
) -> dict[str, str]:
    """Ground-truth id -> the stream's condition for it in this frame (module docstring);
    ``hypotheses`` best score first, aligned with ``sources`` and ``kinds``."""
    best: dict[str, str] = {}
    for _h, src, kind in zip(hypotheses, sources, kinds, strict=True):
        if src is not None and src not in best:
            best[src] = kind
    out = {}
    for gid in gt:
        if float(visib_fract.get(gid, 0.0)) < VISIBLE:
            out[gid] = "hidden"
        elif gid not in best:
            out[gid] = "dropout"
        elif best[gid] != "nominal":
            out[gid] = f"top1_{best[gid]}"
        else:
            out[gid] = "nominal"
    return out


def false_object_cause(
    T_world_obj: np.ndarray,
    class_name: str,
    gt: Mapping[str, tuple[str, np.ndarray]],
    distractors: Mapping[str, tuple[str, np.ndarray]],
    hypotheses: Sequence,
    kinds: Sequence[str] | None,
    gate: float = DEFAULT_GATE,
) -> str:
    """What a false object of a method most likely came from (module docstring)."""
    p = np.asarray(T_world_obj, dtype=float)[:3, 3]
    cands: list[tuple[float, str]] = []
    for _, T in distractors.values():
        cands.append((float(np.linalg.norm(np.asarray(T)[:3, 3] - p)), "distractor"))
    if kinds is not None:
        for h, kind in zip(hypotheses, kinds, strict=True):
            if kind == "false_positive":
                d = float(np.linalg.norm(np.asarray(h.T_world_obj)[:3, 3] - p))
                cands.append((d, "false_positive"))
    for cls, T in gt.values():
        d = float(np.linalg.norm(np.asarray(T)[:3, 3] - p))
        cands.append((d, "duplicate" if cls == class_name else "class_confusion"))
    near = [c for c in cands if c[0] <= gate]
    return min(near)[1] if near else "elsewhere"
