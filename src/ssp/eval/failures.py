"""Why an estimate failed: the estimator stream's condition behind each gross error or false
object, for the per-class tables of the realistic protocol (:mod:`ssp.sim.realistic`).

Per ground-truth object and frame, from the generator's record of every hypothesis's source and
kind (``SimSequence.info["hypothesis_sources"]`` and ``["hypothesis_kinds"]``), the
*condition* of the stream for that object (:func:`object_conditions`), first that applies:

* ``hidden``: less than 10 % visible;
* ``never_detected``: visible, but no hypothesis of it in this frame nor in any frame since it
  came to this pose (it appeared or moved during a dropout): no method can know where it is;
* ``dropout``: visible, no hypothesis of it in this frame, but some since it came to this
  pose;
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

__all__ = ["VISIBLE", "DetectionHistory", "false_object_cause", "object_conditions"]

#: Objects less visible than this are ``hidden``.
VISIBLE = 0.1


class DetectionHistory:
    """Per ground-truth object of one sequence: has it had a hypothesis since it came to its
    current pose? (moved more than 2 mm or 2 deg: a new pose)"""

    def __init__(self) -> None:
        self._pose: dict[str, np.ndarray] = {}
        self._seen: dict[str, bool] = {}

    def update(self, gt: Mapping[str, tuple[str, np.ndarray]], detected: set[str]) -> set[str]:
        """Record a frame; returns the ids detected at some frame since they came to their
        current pose (this frame included)."""
        for gid, (_, T) in gt.items():
            T = np.asarray(T, dtype=float)
            last = self._pose.get(gid)
            if last is None or _moved(last, T):
                self._pose[gid], self._seen[gid] = T.copy(), False
            self._seen[gid] |= gid in detected
        return {g for g in gt if self._seen.get(g)}


def _moved(a: np.ndarray, b: np.ndarray) -> bool:
    d = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    c = np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return d > 0.002 or np.degrees(np.arccos(c)) > 2.0


def object_conditions(
    gt: Mapping[str, tuple[str, np.ndarray]],
    visib_fract: Mapping[str, float],
    hypotheses: Sequence,
    sources: Sequence[str | None],
    kinds: Sequence[str],
    seen_since_moved: set[str] | None = None,
) -> dict[str, str]:
    """Ground-truth id -> the stream's condition for it in this frame (module docstring);
    ``hypotheses`` best score first, aligned with ``sources`` and ``kinds``;
    ``seen_since_moved`` from :meth:`DetectionHistory.update` (None: every dropout is a
    ``dropout``)."""
    best: dict[str, str] = {}
    for _h, src, kind in zip(hypotheses, sources, kinds, strict=True):
        if src is not None and src not in best:
            best[src] = kind
    out = {}
    for gid in gt:
        if float(visib_fract.get(gid, 0.0)) < VISIBLE:
            out[gid] = "hidden"
        elif gid not in best:
            seen = seen_since_moved is None or gid in seen_since_moved
            out[gid] = "dropout" if seen else "never_detected"
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
