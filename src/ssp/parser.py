"""The scene parser: ``SceneParser.update(frame) -> SceneEstimate`` (paper sections IV-V).

:meth:`SceneParser.update` validates the frame (a bad frame raises :class:`FrameError` and leaves
the parser's state untouched), takes :attr:`Frame.moved` into the remembered scene, and runs
:data:`STAGES` in order over one :class:`~ssp.frame_context.FrameContext`; each stage lives in
the module of its concept (docs/algorithm.md maps them to the paper):

1. **depth correction** (:func:`ssp.correction.correct_frame`): the camera's view; each
   hypothesis whose silhouette covers observed surface at another depth slid along its
   viewing ray to it and aligned (an RGB estimator's error), before anything judges it;
2. **association** (:func:`ssp.temporal.associate_frame`): hypotheses grouped per object
   (instance ids, else an optimal assignment on class and pose), one object per instance
   segment, duplicates of undetected objects dropped; each detected object's provisional
   pose (:func:`ssp.first_guess.first_guess`);
3. **segments** (:func:`ssp.segments.segment_frame`): each object's points;
4. **verification of the new** (:func:`ssp.verification.verify_new_objects`): a new object the
   data supports at none of its hypotheses is rejected before the search;
5. **triage of the undetected** (:func:`ssp.retention.triage_undetected`): replaced, still
   visible, seen empty, hidden (ephemeral) or unseen;
6. **world** (:func:`ssp.search.prepare_world`): the physics world, data forces, scorer;
7. **static objects** (:func:`ssp.static.find_static`): which known objects are unchanged, and
   whether the whole frame is; then either
8. the **unchanged shortcut** (:func:`ssp.static.keep_unchanged`: the previous scene,
   settled), or 9-11:
9. **first guess** (:func:`ssp.first_guess.first_guess_scene`): every object at its best
   candidate by the terms that need no simulation, settled; its support graph (Alg. 2);
10. **support-retained** (:func:`ssp.retention.retain_or_remove`): an unseen object that holds
   up objects which would fall without it stays; it and the objects seen empty otherwise go;
11. **search** (:func:`ssp.search.search_scene`): the layered search (Alg. 3);
12. **polish** (:func:`ssp.polish.polish_scene`): ICP springs inside the simulation;
13. **fallbacks** (:func:`ssp.verification.fall_back_to_data`): data wins over physics for new
    objects the search moved off their data;
14. **placement** (:func:`ssp.verification.place_new`): new objects verified at their final
    poses, or put where their data puts them;
15. **orientations** (:func:`ssp.orientation.decide_orientations`): view ambiguity;
16. **final verdicts** (:func:`ssp.verification.judge_final`): an unverified object stays only
    when it holds others up;
17. **re-verification** (:func:`ssp.verification.doubt_known`): without instance masks, a
    known object its data contradicts two frames running leaves;
18. **re-identification** (:func:`ssp.temporal.reidentify_moved`): a new object where a known
    one of its class vanished is that object, moved;
19. **static fusion** (:func:`ssp.outcome.fuse_at_rest`): an object at rest is output at
    the mean of its estimates since it came to rest;
20. **transition modes** (:func:`ssp.outcome.transition_modes`): output poses (symmetric
    snapping), modes (motion in the world), reasons, warnings;
21. **outcome** (:func:`ssp.outcome.scene_estimate`): the :class:`SceneEstimate`.

The parser then commits what the next frame remembers; a frame that raises leaves it as it was.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ssp.config import SSPConfig
from ssp.correction import correct_frame
from ssp.errors import InvalidPoseError, SSPError, UnknownObjectError
from ssp.estimate import ObjectEstimate, Rejected, SceneEstimate, SupportEdge
from ssp.first_guess import first_guess_scene
from ssp.forces import load_kernels as load_force_kernels
from ssp.frame_context import FrameContext, Known, Stage
from ssp.geometry import validate_pose
from ssp.library.library import ObjectLibrary
from ssp.library.model import ObjectInstance
from ssp.motion import seen_from_state, seen_state
from ssp.orientation import decide_orientations, orientations_from_state, orientations_state
from ssp.outcome import fuse_at_rest, report_moved, scene_estimate, transition_modes
from ssp.overlap import load_kernels as load_overlap_kernels
from ssp.physics import World
from ssp.polish import polish_scene
from ssp.registration import load_kernels as load_icp_kernels
from ssp.retention import retain_or_remove, triage_undetected
from ssp.scene import Frame, FrameError
from ssp.search import prepare_world, search_scene
from ssp.segments import segment_frame
from ssp.static import find_static, keep_unchanged
from ssp.temporal import associate_frame, reidentify_moved
from ssp.timing import StageTimer
from ssp.verification import (
    doubt_known,
    fall_back_to_data,
    judge_final,
    place_new,
    verify_new_objects,
)

__all__ = [
    "STAGES",
    "ObjectEstimate",
    "Rejected",
    "SceneEstimate",
    "SceneParser",
    "SupportEdge",
    "parse_sequence",
    "run_stages",
]

log = logging.getLogger(__name__)

STATE_FORMAT = "ssp-scene-state"
STATE_VERSION = 1


# ------------------------------------------------------------------------------ the parser
class SceneParser:
    """Sequential scene parsing: feed frames in time order to :meth:`update`.

    Args:
        library: the object models (every hypothesis class must be in it).
        config: the method's constants (default ``SSPConfig()``).
        table: the world has a table plane at z = 0 (DESIGN section 3).
    """

    def __init__(
        self, library: ObjectLibrary, config: SSPConfig | None = None, *, table: bool = True
    ) -> None:
        self.library = library
        self.config = config if config is not None else SSPConfig()
        self.table = bool(table)
        self._known: dict[str, Known] = {}
        #: the previous frame's rejected objects (ssp.static.repeated_rejections)
        self._rejected: list[Rejected] = []
        self._counters: dict[str, int] = {}
        self._frame_index = 0
        self._last_stamp: float | None = None
        self._world: World | None = None
        self._world_key: tuple[tuple[str, str], ...] | None = None
        # the data forces', the polish's ICP's and the volume test's kernels, not in a frame
        load_force_kernels()
        load_icp_kernels()
        load_overlap_kernels()

    def __repr__(self) -> str:
        return f"SceneParser({len(self._known)} objects, {self._frame_index} frames)"

    @property
    def objects(self) -> dict[str, tuple[str, np.ndarray]]:
        """Current scene: ``id -> (class_name, T_world_obj)`` (copies)."""
        return {k: (v.class_name, v.T_world_obj.copy()) for k, v in self._known.items()}

    def reset(self, keep_ids: bool = False) -> None:
        """Forget every object; ids and frames count from 0 unless ``keep_ids`` (world lost)."""
        self._known.clear()
        self._rejected = []
        if not keep_ids:
            self._counters.clear()
            self._frame_index, self._last_stamp = 0, None

    # -------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """JSON-ready snapshot of everything the next :meth:`update` depends on."""
        return {
            "format": STATE_FORMAT,
            "version": STATE_VERSION,
            "frame_index": self._frame_index,
            "last_stamp": self._last_stamp,
            "id_counters": dict(sorted(self._counters.items())),
            "objects": [
                {
                    "id": oid,
                    "class": k.class_name,
                    "T_world_obj": k.T_world_obj.tolist(),
                    "ephemeral": k.ephemeral,
                    "fit": k.fit,
                    "held": k.held,
                    "doubt": k.doubt,
                    **orientations_state(k.alternatives, k.ranking),
                    **seen_state(k.seen_fit, k.seen_residual, k.still, k.seen_points),
                }
                for oid, k in sorted(self._known.items())
            ],
            "rejected": [r.state() for r in self._rejected],
        }

    @classmethod
    def from_state(
        cls,
        library: ObjectLibrary,
        state: Mapping[str, Any],
        config: SSPConfig | None = None,
        *,
        table: bool = True,
    ) -> SceneParser:
        """A parser that continues from :meth:`state` (same library and config expected).

        Raises:
            SSPError: not a scene state, or an unsupported version.
            UnknownObjectError: a class missing from ``library``.
            InvalidPoseError: a pose that is not rigid.
        """
        if not isinstance(state, Mapping) or state.get("format") != STATE_FORMAT:
            raise SSPError(f"not an ssp scene state (expected format {STATE_FORMAT!r})")
        if state.get("version") != STATE_VERSION:
            raise SSPError(
                f"scene state version {state.get('version')!r} is not supported "
                f"(this ssp reads version {STATE_VERSION})"
            )
        parser = cls(library, config, table=table)
        try:
            parser._frame_index = int(state["frame_index"])
            stamp = state.get("last_stamp")
            parser._last_stamp = None if stamp is None else float(stamp)
            parser._counters = {str(k): int(v) for k, v in state.get("id_counters", {}).items()}
            for o in state["objects"]:
                cls_name, T = _state_entry(library, o, f"object {o['id']!r}")
                doubt = None if o.get("doubt") is None else str(o["doubt"])
                parser._known[str(o["id"])] = Known(
                    cls_name, T, bool(o.get("ephemeral")), float(o.get("fit", 0.0)),
                    bool(o.get("held", False)), doubt, *orientations_from_state(o),
                    **seen_from_state(o),
                )  # fmt: skip
            for k, r in enumerate(state.get("rejected", [])):
                cls_name, T = _state_entry(library, r, f"rejected object {k}")
                held = r.get("unheld") and str(r["unheld"])  # none in older states
                parser._rejected.append(Rejected(f"rejected_{k}", cls_name, T, str(r["reason"]),
                                                 unheld=held))  # fmt: skip
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InvalidPoseError | UnknownObjectError):
                raise
            raise SSPError(f"malformed scene state: {exc!r}") from exc
        return parser

    # -------------------------------------------------------------- update
    def update(self, frame: Frame) -> SceneEstimate:
        """Parse one frame; returns the scene estimate and advances the parser's state.

        Runs :data:`STAGES` in order over one :class:`~ssp.frame_context.FrameContext`, then
        commits what the next frame remembers.

        Raises:
            FrameError: the frame is invalid (the state is unchanged).
            PhysicsError: the simulation failed beyond recovery (the state is unchanged).
        """
        timer = StageTimer()
        with timer("total"):
            with timer("validation"):
                frame = frame.validate(self.library)
                if self._last_stamp is not None and frame.stamp < self._last_stamp:
                    raise FrameError(
                        f"frame stamp {frame.stamp} is earlier than the previous frame's "
                        f"({self._last_stamp}); frames must come in time order"
                    )
                known_before = dict(self._known)
                gone = self._apply_moved(frame.moved or {})
                ctx = self.frame_context(frame, timer)
            try:
                run_stages(ctx, STAGES)
            except BaseException:
                self._known = known_before  # the state is that of the last good frame
                self._world, self._world_key = None, None  # never reuse a half-used world
                raise
        assert ctx.estimate is not None, "the outcome stage sets the estimate"
        self._known = ctx.next_known
        self._rejected = list(ctx.estimate.rejected)
        self._counters = ctx.assoc.counters
        self._frame_index += 1
        self._last_stamp = frame.stamp
        estimate = ctx.estimate
        if frame.moved:
            estimate = report_moved(estimate, frame.moved, gone)
        # exclusive seconds per stage (they add up to ``total`` but for what no stage holds)
        timings = {k: v for k, v in timer.own.items() if k != "total"}
        timings["total"] = timer.seconds["total"]
        return replace(estimate, timings=timings)

    def frame_context(self, frame: Frame, timer: StageTimer | None = None) -> FrameContext:
        """A fresh context for the validated ``frame`` over the parser's remembered scene (what
        :meth:`update` runs :data:`STAGES` on; for running or testing stages by hand)."""
        return FrameContext(
            frame=frame,
            library=self.library,
            config=self.config,
            table=self.table,
            known=dict(self._known),
            remembered=list(self._rejected),
            counters=dict(self._counters),
            frame_index=self._frame_index,
            timer=timer if timer is not None else StageTimer(),
            world_for=self._world_for,
        )

    def _world_for(self, objects: Mapping[str, str]) -> World:
        """The physics world of ``{id: class}``: the last one while the objects stay."""
        key = tuple(sorted(objects.items()))
        if self._world is None or self._world_key != key:
            instances = [ObjectInstance(oid, self.library[c]) for oid, c in key]
            self._world = World(instances, table=self.table, config=self.config.physics)
            self._world_key = key
        return self._world

    def _apply_moved(self, moved: Mapping[str, np.ndarray | None]) -> dict[str, Known]:
        """Take :attr:`Frame.moved` into the remembered scene: a moved object's previous pose
        becomes the one it was put at; one that left the scene is forgotten (returned, for
        the report). FrameError for an id the parser does not know."""
        unknown = sorted(set(moved) - set(self._known))
        if unknown:
            raise FrameError(
                f"moved names objects not in the scene: {', '.join(unknown)} (known: "
                f"{', '.join(sorted(self._known)) or 'none'})"
            )
        gone: dict[str, Known] = {}
        for oid, T in moved.items():
            if T is None:
                gone[oid] = self._known.pop(oid)
            else:
                self._known[oid] = Known(self._known[oid].class_name, np.array(T, dtype=float))
        return gone


def _state_entry(
    library: ObjectLibrary, entry: Mapping[str, Any], what: str
) -> tuple[str, np.ndarray]:
    """``(class, T_world_obj)`` of a scene state's ``entry`` (``what`` names it).

    Raises:
        UnknownObjectError: its class is not in ``library``.
        InvalidPoseError: its pose is not rigid.
    """
    cls_name = str(entry["class"])
    if cls_name not in library:
        raise UnknownObjectError(
            f"scene state {what} has class {cls_name!r}, which is not in the library "
            f"({', '.join(library.names) or 'empty'})"
        )
    return cls_name, validate_pose(np.asarray(entry["T_world_obj"], dtype=float), what)


def _searching(ctx: FrameContext) -> bool:
    return not ctx.unchanged


def _unchanged(ctx: FrameContext) -> bool:
    return ctx.unchanged


#: The stages of :meth:`SceneParser.update`, in order (module docstring; docs/algorithm.md).
STAGES: tuple[Stage, ...] = (
    Stage("depth correction", correct_frame, timer="correction"),
    Stage("association", associate_frame, timer="association"),
    Stage("segments", segment_frame, timer="segments"),
    Stage("verification of the new", verify_new_objects, timer="verification"),
    Stage("triage of the undetected", triage_undetected, timer="verification"),
    Stage("world", prepare_world, timer="world"),
    Stage("static objects", find_static),
    Stage("unchanged shortcut", keep_unchanged, when=_unchanged),
    Stage("first guess", first_guess_scene, when=_searching),
    Stage("support-retained", retain_or_remove, when=_searching),
    Stage("search", search_scene, when=_searching),
    Stage("polish", polish_scene),
    Stage("fallbacks", fall_back_to_data),
    Stage("placement", place_new, timer="verification"),
    Stage("orientations", decide_orientations, timer="verification"),
    Stage("final verdicts", judge_final),
    Stage("re-verification", doubt_known, timer="verification"),
    Stage("re-identification", reidentify_moved),
    Stage("static fusion", fuse_at_rest),
    Stage("transition modes", transition_modes),
    Stage("outcome", scene_estimate),
)


def run_stages(ctx: FrameContext, stages: Sequence[Stage]) -> None:
    """Run ``stages`` in order over ``ctx``, each under its timer entry (its ``timer``, else
    its name); a stage whose ``when`` is false is skipped."""
    for stage in stages:
        if stage.when is not None and not stage.when(ctx):
            continue
        log.debug("frame %d: %s", ctx.frame_index, stage.name)
        with ctx.timer(stage.timer or stage.name):
            stage.run(ctx)


def parse_sequence(
    parser: SceneParser, frames: Iterable[Frame]
) -> Iterator[tuple[int, SceneEstimate | Exception]]:
    """Feed ``frames`` to ``parser``; yields ``(index, estimate)`` or ``(index, error)``.

    A frame that fails is logged and skipped: the parser's state stays that of the last good
    frame, and the sequence goes on. Bad input and physics failures raise :class:`SSPError`
    (logged as a warning); any other exception is a bug, logged with its traceback as an error
    and yielded all the same, so one frame never ends the sequence. ``KeyboardInterrupt`` and
    ``SystemExit`` are not caught.
    """
    for i, frame in enumerate(frames):
        try:
            estimate = parser.update(frame)
        except SSPError as exc:
            log.warning("frame %d skipped: %s", i, exc)
            yield i, exc
        except Exception as exc:  # a bug: count it, keep its traceback, go on
            log.error("frame %d failed with an unexpected error", i, exc_info=exc)
            yield i, exc
        else:
            yield i, estimate
