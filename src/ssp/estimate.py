"""What the scene parser returns for one frame: objects, support, and a verdict for everything.

Nothing appears or disappears without a reason (DESIGN section 6): every object in the scene
carries why it is there (``reason``), every object removed or rejected carries why it went, every
instance segment of the frame gets a verdict (the object it became, or why it became none), and
scene-level doubts (an output that physics or the data contradict) are ``warnings``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ssp.probability import ObjectTerms
from ssp.scene import TransitionMode

if TYPE_CHECKING:
    from ssp.orientation import Orientation

__all__ = ["ObjectEstimate", "Rejected", "SceneEstimate", "SupportEdge"]


@dataclass(frozen=True, eq=False)
class ObjectEstimate:
    """One object of a :class:`SceneEstimate`.

    Attributes:
        id: instance id (stable across frames).
        class_name: model name in the library.
        T_world_obj: (4, 4) pose, m (for removed objects: the last known pose).
        mode: transition mode since the previous frame.
        ephemeral: kept although undetected, because the camera could not see it.
        terms: the five log-probability terms (None for removed objects).
        source: which candidate the search kept (``hypothesis``, ``previous``, ``current``,
            ``unchanged``, ``retained``), or ``removed``.
        fit: data fit fraction c at the output pose (0..1).
        reason: why the object is in the scene (or why it was removed), in words.
        evidence: for an object new in this frame, the figures verification judged it by at
            its output pose (``Evidence.as_dict``: ``fit`` of its visible surface,
            ``explained``, ...); None otherwise.
        orientation: whether its orientation is decided and the orientations its data allow
            as well (:class:`ssp.orientation.Orientation`); None for an object without points
            of its own (:class:`ssp.orientation.OwnPoints`: without masks, one that shares its
            cluster), and for removed objects.
    """

    id: str
    class_name: str
    T_world_obj: np.ndarray
    mode: TransitionMode
    ephemeral: bool = False
    terms: ObjectTerms | None = None
    source: str = ""
    fit: float = 0.0
    reason: str = ""
    evidence: dict | None = None
    orientation: Orientation | None = None

    @property
    def log_prob(self) -> float:
        """Sum of the terms (``-inf`` for a removed object)."""
        return self.terms.total if self.terms is not None else -math.inf

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (pose as a nested list)."""
        return {
            "id": self.id,
            "class": self.class_name,
            "T_world_obj": np.asarray(self.T_world_obj).tolist(),
            "mode": str(self.mode),
            "ephemeral": self.ephemeral,
            "terms": self.terms.as_dict() if self.terms is not None else None,
            "log_prob": self.log_prob if self.terms is not None else None,
            "source": self.source,
            "fit": self.fit,
            "reason": self.reason,
            "evidence": None if self.evidence is None else dict(self.evidence),
            "orientation": None if self.orientation is None else self.orientation.as_dict(),
        }


@dataclass(frozen=True, eq=False)
class Rejected:
    """An object the estimator proposed and verification turned down (``ssp.verification``).

    Attributes:
        id: the id it would have had; class_name, T_world_obj (4, 4): its best pose, m.
        reason: why, in words; evidence: the verification figures (``Evidence.as_dict``).
        segment: the instance segment its hypotheses came from, if any.
        unheld: when it was rejected because it would fall where its data puts it and nothing
            was shown to hold it up (weak data, or data that rules a holder out:
            :func:`ssp.holders.nothing_holds`), why; the next frame remembers it where its
            view cannot see under the object.
    """

    id: str
    class_name: str
    T_world_obj: np.ndarray
    reason: str
    evidence: dict = field(default_factory=dict)
    segment: int | None = None
    unheld: str | None = None

    def state(self) -> dict[str, Any]:
        """What the next frame remembers of it (:meth:`ssp.parser.SceneParser.state`)."""
        return {
            "class": self.class_name,
            "T_world_obj": np.asarray(self.T_world_obj).tolist(),
            "reason": self.reason,
            "unheld": self.unheld,
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "class": self.class_name,
            "T_world_obj": np.asarray(self.T_world_obj).tolist(),
            "reason": self.reason,
            "evidence": dict(self.evidence),
            "segment": self.segment,
            "unheld": self.unheld,
        }


@dataclass(frozen=True)
class SupportEdge:
    """``supporter`` (an id, or ``"table"``) carries ``fraction`` of ``supported``'s weight."""

    supporter: str
    supported: str
    fraction: float


@dataclass(frozen=True, eq=False)
class SceneEstimate:
    """The parser's answer for one frame.

    Attributes:
        stamp: the frame's time stamp, s.
        frame_index: 0-based count of frames this parser accepted.
        objects: the objects in the scene, by id.
        removed: objects removed in this frame (mode ``REMOVED``, last known pose, reason).
        rejected: objects proposed this frame that verification turned down.
        segments: instance label of the frame -> its verdict (the id of the object it is, or
            why it is none), for every instance segment of the cloud.
        warnings: doubts about the whole scene (physics or data contradict the output).
        support: support edges with the fraction of the supported object's weight.
        log_prob: ``log Pr(s | C, D)``, the sum of every object's terms.
        timings: exclusive wall seconds per stage (``validation``, ``correction``,
            ``association``, ``segments``, ``verification``, ``world``, ... each stage of
            :data:`ssp.parser.STAGES` under its timer name, and the steps timed inside them:
            ``forces``, ``stepping``, ``contacts``, ``scoring``, ``icp``) and ``total``, the
            whole update; the stages add up to ``total`` (:func:`ssp.timing.stage_sum`). With
            ``search.processes`` > 1 the stages include the lane processes' seconds, and
            ``lanes`` is what those processes worked in all (``total + lanes``: CPU seconds).
        hypotheses_tested: candidate simulations run by the search.
        unchanged: the frame took the unchanged-scene shortcut.
    """

    stamp: float
    frame_index: int
    objects: tuple[ObjectEstimate, ...]
    removed: tuple[ObjectEstimate, ...] = ()
    rejected: tuple[Rejected, ...] = ()
    segments: dict[int, str] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    support: tuple[SupportEdge, ...] = ()
    log_prob: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    hypotheses_tested: int = 0
    unchanged: bool = False

    def __getitem__(self, oid: str) -> ObjectEstimate:
        for o in self.objects:
            if o.id == oid:
                return o
        raise KeyError(oid)

    def __contains__(self, oid: object) -> bool:
        return any(o.id == oid for o in self.objects)

    def __len__(self) -> int:
        return len(self.objects)

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(o.id for o in self.objects)

    def poses(self) -> dict[str, np.ndarray]:
        """``id -> T_world_obj`` of the objects in the scene."""
        return {o.id: o.T_world_obj for o in self.objects}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of the whole estimate."""
        return {
            "stamp": self.stamp,
            "frame_index": self.frame_index,
            "log_prob": self.log_prob,
            "objects": [o.to_dict() for o in self.objects],
            "removed": [o.to_dict() for o in self.removed],
            "rejected": [r.to_dict() for r in self.rejected],
            "segments": {str(k): v for k, v in sorted(self.segments.items())},
            "warnings": list(self.warnings),
            "support": [
                {"supporter": e.supporter, "supported": e.supported, "fraction": e.fraction}
                for e in self.support
            ],
            "timings": dict(self.timings),
            "hypotheses_tested": self.hypotheses_tested,
            "unchanged": self.unchanged,
        }
