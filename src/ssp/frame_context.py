"""One frame's walk through :meth:`ssp.parser.SceneParser.update`: the stages and their context.

:meth:`SceneParser.update` runs an ordered list of :class:`Stage` s over one
:class:`FrameContext`. Each stage is a function ``stage(ctx) -> None`` in the module of its
concept (``ssp.temporal.associate_frame``, ``ssp.search.search_scene``, ...); it reads what the
stages before it wrote and fills its own fields (each field below names the stage that sets
it). A stage never touches the parser: what the next frame remembers is
:attr:`FrameContext.next_known`, committed by the parser once every stage has run, so a frame
that fails leaves the parser's state as it was.

Poses are 4x4 ``T_world_obj`` arrays in metres; ids are object ids (``"cube_0"``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # annotations only: the stage modules import this module, not the reverse
    from ssp.config import SSPConfig
    from ssp.correction import Correction
    from ssp.estimate import ObjectEstimate, Rejected, SceneEstimate
    from ssp.library.library import ObjectLibrary
    from ssp.library.model import ObjectModel
    from ssp.orientation import Orientation, Ranking
    from ssp.physics import World
    from ssp.retention import Triage
    from ssp.scene import Frame, Hypothesis
    from ssp.scoring import SceneScore, SceneScorer
    from ssp.search import Simulator
    from ssp.segments import SegmentTrees
    from ssp.temporal import Association
    from ssp.timing import StageTimer
    from ssp.verification import Evidence, Verdict
    from ssp.visibility import CameraView

__all__ = ["FrameContext", "Known", "Simulation", "Stage"]


@dataclass
class Known:
    """What the parser remembers of an object between frames."""

    class_name: str
    T_world_obj: np.ndarray
    ephemeral: bool = False
    #: data fit c (paper eq. 12) at ``T_world_obj`` in the frame that set it
    fit: float = 0.0
    #: its data holds it where nothing in the scene does (a data fallback)
    held: bool = False
    #: why the data did not support it in the frame that set it (a frame without instance
    #: masks, :func:`ssp.verification.doubt_known`); None: it did, or it was not checked
    doubt: str | None = None
    #: the orientations its data allowed as well as ``T_world_obj`` (poses, 4x4, m;
    #: :mod:`ssp.orientation`): the candidates a later view may decide between
    alternatives: tuple[np.ndarray, ...] = ()
    #: its decided orientation ranking and the view it was ranked from (None: none decided
    #: yet; :func:`ssp.orientation.same_view`)
    ranking: Ranking | None = None
    #: the fraction of its visible surface its data explained at ``T_world_obj`` in the frame
    #: that set it (:class:`ssp.verification.Evidence`'s ``fit``; None: too little of it was
    #: visible to say): what :func:`ssp.motion.moved_in_world` compares the next frame with,
    #: with the residual below
    seen_fit: float | None = None
    #: its segment's mean point-to-plane distance to it there (m,
    #: :func:`ssp.motion.object_residual`; NaN: not known)
    seen_residual: float = float("nan")
    #: frames it has been static in the world, its data where it was as they were
    #: (:func:`ssp.motion.fuse_static`)
    still: int = 0
    #: some of its segment's points in the frame that set it ((K, 3), world, m;
    #: :func:`ssp.motion.seen_points`; None: none known): a later estimate that explains
    #: them as well is a correction, not a motion (:func:`ssp.motion.explains_before`)
    seen_points: np.ndarray | None = None


@dataclass(frozen=True)
class Stage:
    """A named step of :meth:`SceneParser.update`.

    Attributes:
        name: the stage's name (logs, errors, :data:`ssp.parser.STAGES`).
        run: ``run(ctx)``, filling the stage's fields of the :class:`FrameContext`.
        timer: the :class:`~ssp.timing.StageTimer` entry its wall time is added to (None: its
            name); the steps timed inside it (stepping, forces, contacts, scoring, icp) keep
            their own entries, and its entry their exclusive rest.
        when: run only when ``when(ctx)`` is true (None: always).
    """

    name: str
    run: Callable[[FrameContext], None]
    timer: str | None = None
    when: Callable[[FrameContext], bool] | None = None


def _dict() -> Any:
    return field(default_factory=dict)


@dataclass
class Simulation:
    """The frame's physics world with its data forces and scorer (``ssp.search.prepare_world``)."""

    world: World
    simulator: Simulator
    scorer: SceneScorer
    #: objects with data forces and a data term (detected, or undetected and still visible)
    with_data: set[str]
    #: camera position (3,) for the visible-surface terms, None without a camera
    camera_position: np.ndarray | None


@dataclass
class FrameContext:
    """Everything one frame's stages share; each group of fields is set by the stage it names.

    The inputs are set by the parser; every other field starts empty.
    """

    # ---- inputs (the parser)
    frame: Frame
    library: ObjectLibrary
    config: SSPConfig
    #: the world has a table plane at z = 0
    table: bool
    #: the scene remembered before this frame (after :attr:`Frame.moved`)
    known: Mapping[str, Known]
    #: the objects the previous frame rejected (:func:`ssp.static.repeated_rejections`)
    remembered: list[Rejected]
    #: the object-id counters before this frame (class -> next index)
    counters: Mapping[str, int]
    frame_index: int
    timer: StageTimer
    #: the physics world for ``{id: class}`` (the parser reuses it while the objects stay)
    world_for: Callable[[Mapping[str, str]], World]

    # ---- depth correction (ssp.correction.correct_frame)
    #: the camera's view of the frame (None without a camera pose; also used by segments)
    view: CameraView | None = None
    #: the frame's hypotheses, those the correction moved in their place (None: the frame's)
    hypotheses: list[Hypothesis] | None = None
    #: each corrected hypothesis with what was done
    corrections: list[tuple[Hypothesis, Correction]] = field(default_factory=list)

    # ---- association (ssp.temporal.associate_frame)
    association: Association | None = None
    #: detected object -> its hypotheses, best first (at most ``search.hypotheses_per_object``)
    groups: dict[str, list[Hypothesis]] = _dict()
    #: every object of the frame (detected and known) -> its class
    classes: dict[str, str] = _dict()
    models: dict[str, ObjectModel] = _dict()
    #: known object -> its previous pose
    prev_pose: dict[str, np.ndarray] = _dict()
    #: detected object -> its provisional pose, then its first guess (ssp.first_guess)
    first: dict[str, np.ndarray] = _dict()

    # ---- segments (ssp.segments.segment_frame)
    #: object -> the poses its segment is gathered around
    cand_poses: dict[str, list[np.ndarray]] = _dict()
    #: object -> its segment, (M, 3) world points
    segments: dict[str, np.ndarray] = _dict()
    #: object -> the instance label its segment came from (instance segments only)
    owner: dict[str, int] = _dict()
    #: object -> the label it lies in (instance segments and clusters alike)
    members: dict[str, int] = _dict()
    trees: SegmentTrees | None = None

    # ---- verification of the new (ssp.verification.verify_new_objects)
    rejected: dict[str, Rejected] = _dict()

    # ---- triage of the undetected (ssp.retention.triage_undetected)
    #: known objects without a group, sorted
    missing: list[str] = field(default_factory=list)
    verdicts: dict[str, Triage] = _dict()
    #: objects removed this frame (replaced; then seen empty or unseen, ssp.retention)
    removed: set[str] = field(default_factory=set)

    # ---- the frame's world (ssp.search.prepare_world)
    simulation: Simulation | None = None

    # ---- static objects (ssp.static.find_static)
    static: set[str] = field(default_factory=set)
    #: nothing changed: the search is replaced by a settle of the previous scene
    unchanged: bool = False

    # ---- first guess (ssp.first_guess.first_guess_scene)
    #: objects that keep their previous pose untested (ssp.static.settled_objects)
    settled: set[str] = field(default_factory=set)
    #: the settled first-guess scene's score (its support graph gives the search's layers)
    first_score: SceneScore | None = None

    # ---- support-retained objects (ssp.retention.retain_or_remove)
    #: support-retained object -> the objects it holds up
    retained: dict[str, list[str]] = _dict()

    # ---- the search (ssp.search.search_scene, ssp.static.keep_unchanged, ssp.polish)
    score: SceneScore | None = None
    #: object -> the candidate the search kept ("hypothesis", "previous", "current", ...)
    chosen: dict[str, str] = _dict()
    tested: int = 0

    # ---- data fallbacks (ssp.verification.fall_back_to_data)
    #: object -> (its hypothesis pose, the warning)
    fallbacks: dict[str, tuple[np.ndarray, str]] = _dict()

    # ---- placement (ssp.verification.place_new)
    #: each new object's verdict at its final pose
    final_verdicts: dict[str, Verdict] = _dict()
    #: new objects put where their data puts them (kept with a warning)
    placed: dict[str, np.ndarray] = _dict()
    #: every object's evidence at its final pose
    evidence: dict[str, Evidence] = _dict()

    # ---- static fusion (ssp.outcome.fuse_at_rest)
    #: object at rest -> its output pose, the mean of its estimates since it came to rest
    fused: dict[str, np.ndarray] = _dict()

    # ---- orientations (ssp.orientation.decide_orientations)
    #: object with an instance segment -> whether its orientation is decided, and the tied ones
    orientations: dict[str, Orientation] = _dict()
    #: object -> its decided ranking, remembered (``Known.ranking``)
    rankings: dict[str, Ranking] = _dict()
    # ---- final verdicts (ssp.verification.judge_final)
    warnings: list[str] = field(default_factory=list)
    #: kept object -> why (verified, or unverified but holding others up)
    reasons: dict[str, str] = _dict()
    #: objects not in the output (removed, rejected, superseded)
    gone: set[str] = field(default_factory=set)

    # ---- re-verification (ssp.verification.doubt_known)
    #: known object -> why its data does not support it in this frame (remembered)
    doubts: dict[str, str] = _dict()
    #: known objects removed for it two frames running -> why
    doubted: dict[str, str] = _dict()

    # ---- re-identification (ssp.temporal.reidentify_moved)
    #: new id -> the known id it is (moved)
    old_of: dict[str, str] = _dict()
    #: known ids found again elsewhere
    moved_away: set[str] = field(default_factory=set)
    #: known ids whose pose the camera saw through, found again beside it
    superseded: set[str] = field(default_factory=set)

    # ---- outcome (ssp.outcome)
    objects: list[ObjectEstimate] = field(default_factory=list)
    #: what the next frame remembers (committed by the parser)
    next_known: dict[str, Known] = _dict()
    estimate: SceneEstimate | None = None

    @property
    def sim(self) -> Simulation:
        """The frame's world, simulator and scorer (set by the world stage)."""
        if self.simulation is None:
            raise RuntimeError("the world stage has not run")
        return self.simulation

    @property
    def assoc(self) -> Association:
        """What the association found (set by the association stage)."""
        if self.association is None:
            raise RuntimeError("the association stage has not run")
        return self.association

    @property
    def segment_trees(self) -> SegmentTrees:
        """The segments' KD-trees (set by the segments stage)."""
        if self.trees is None:
            raise RuntimeError("the segments stage has not run")
        return self.trees

    @property
    def scene_score(self) -> SceneScore:
        """The scene's current score (set by the search, or the unchanged shortcut)."""
        if self.score is None:
            raise RuntimeError("no stage has scored the scene yet")
        return self.score

    def rescore_without(self, drop: list[str]) -> SceneScore:
        """The scene's score with the objects ``drop`` disabled (then enabled again)."""
        world, scorer = self.sim.world, self.sim.scorer
        for oid in drop:
            world.set_enabled(oid, False)
        try:
            return scorer.evaluate(world, self.timer)
        finally:
            for oid in drop:
                world.set_enabled(oid, True)
