"""``ssp bench table1``: the paper's Table I on synthetic sequences, ssp beside its baselines.

:func:`run_table1` feeds every frame of every sequence to every method (a fresh method per
sequence; :mod:`ssp.eval.baselines`) and measures, per method:

* ``accuracy``: error to the ground truth of every matched object in every frame, occluded
  objects included; ``precision``: spread about the object's mean estimate over the repeated
  frames of one static scene (:mod:`ssp.eval.metrics` has the exact definitions, the matching
  and its gate). Both as mean and std of translation (mm) and rotation (deg), symmetry-aware.
  ``matched`` / ``missed`` / ``false_positives`` count the object-frames behind them.
* ``max_penetration_mm``: the method's output objects placed in a physics world
  (:class:`ssp.physics.World`, table at z = 0) as they are, no simulation; the deepest contact
  penetration (``world.contacts().depth``, table contacts included), maximum over all frames.
* ``unsupported_objects``: **mean number per frame** of output objects that are not physically
  supported, in the same world: an object is unsupported when no support path leads to it from
  the table (:meth:`ssp.support.SupportGraph.unsupported` of
  :func:`ssp.support.build_support_graph` on the contacts: a floating object, or one resting
  only on floating ones) *or* its centre of mass, at rest, would accelerate downwards faster
  than ``0.1 g`` (:meth:`World.acceleration_from_rest`: tipping or sliding off its support).
  An object pushed up or sideways out of a penetration is not counted here (that is the
  penetration column). ``unsupported_total`` is the sum over frames.
* ``sec_per_frame``: mean wall time of ``method.update(frame)``, one frame.

``induced_noise`` is the error of every hypothesis against its source object
(:func:`ssp.eval.metrics.hypothesis_errors`, with ``SimSequence.info["hypothesis_sources"]``
when the generator recorded them).
Per-object and per-frame records for plots are kept under ``result["records"]``, column-wise.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from ssp.config import SSPConfig
from ssp.errors import ArgumentError
from ssp.eval.baselines import METHODS, Detection, make_method
from ssp.eval.bop_metrics import BopEvaluator
from ssp.eval.failures import (
    VISIBLE,
    DetectionHistory,
    false_object_cause,
    object_conditions,
)
from ssp.eval.metrics import (
    DEFAULT_GATE,
    FrameMatch,
    hypothesis_errors,
    match_frame,
    plus_minus,
    precision_deviations,
    summarize,
)
from ssp.eval.tracking import Flips, IdSwitches, ReportedMoves
from ssp.library.model import ObjectInstance
from ssp.physics import World
from ssp.pipeline.executor import Parallel, done_messages, map_items
from ssp.scene import Frame
from ssp.sim.sequence import SimSequence
from ssp.support import build_support_graph

__all__ = [
    "DEFAULT_METHODS",
    "PAPER_TABLE1",
    "PhysicsCheck",
    "SequencePart",
    "SequenceSpec",
    "merge_table1",
    "per_class",
    "per_class_markdown",
    "run_table1",
    "run_table1_parts",
    "table1_report",
    "write_table1",
]

DEFAULT_METHODS = (
    "ssp", "estimator", "icp", "ray_slide", "bestfit", "temporal_filter", "icp_filter",
    "ssp_single",
)  # fmt: skip

#: The paper's Table I: experiment -> row -> ((trans mm mean, std), (rot deg mean, std)).
PAPER_TABLE1 = {
    "isolated": {
        "induced": ((3.05, 1.11), (3.35, 1.2)),
        "accuracy": ((5.25, 0.96), (2.79, 2.92)),
        "precision": ((1.57, 1.27), (0.72, 1.2)),
    },
    "structure": {
        "induced": ((5.19, 2.81), (5.7, 3.02)),
        "accuracy": ((3.65, 3.41), (2.23, 1.94)),
        "precision": ((2.49, 3.34), (1.23, 1.25)),
    },
}

#: Downward acceleration from rest (fraction of g) above which an object is unsupported.
UNSUPPORTED_ACCELERATION = 0.1

_COUNT_KEYS = ("matched", "missed", "false_positives")
_OBJECT_COLUMNS = ("sequence", "frame", "object", "class", "visib_fract", "trans_mm", "rot_deg")
_FRAME_COLUMNS = (
    "sequence",
    "frame",
    "objects",
    "matched",
    "missed",
    "false_positives",
    "penetration_mm",
    "unsupported",
    "sec",
)


class PhysicsCheck:
    """Penetration and support of a set of output objects, in a MuJoCo world with a table.

    Worlds are cached by the multiset of classes (reset before each use, so results do not
    depend on the cache).
    """

    def __init__(self, library, config: SSPConfig, max_worlds: int = 32) -> None:
        self.library = library
        self.config = config
        self.max_worlds = int(max_worlds)
        self._worlds: dict[tuple[str, ...], World] = {}

    def __call__(self, detections: Sequence[Detection]) -> tuple[float, int]:
        """``(deepest penetration m (>= 0), number of unsupported objects)``."""
        if not detections:
            return 0.0, 0
        order = sorted(range(len(detections)), key=lambda i: (detections[i][0], i))
        key = tuple(detections[i][0] for i in order)
        world = self._worlds.get(key)
        if world is None:
            if len(self._worlds) >= self.max_worlds:
                self._worlds.clear()
            world = World(
                [ObjectInstance(f"o{j}", self.library[c]) for j, c in enumerate(key)],
                table=True,
                config=self.config.physics,
            )
            self._worlds[key] = world
        world.reset()
        world.set_poses({f"o{j}": detections[i][1] for j, i in enumerate(order)})
        contacts = world.contacts()
        g = float(self.config.physics.gravity)
        lin, _ = world.acceleration_from_rest()
        graph = build_support_graph(contacts, world.masses, g)
        bad = set(graph.unsupported())
        bad |= {int(k) for k in np.flatnonzero(lin[:, 2] < -UNSUPPORTED_ACCELERATION * g)}
        return max(contacts.max_depth, 0.0), len(bad)


#: An estimate more than this far (mm, deg) from its object, or none, is a gross error.
GROSS_MM = 10.0
GROSS_DEG = 10.0


def is_gross(trans_mm: float, rot_deg: float) -> bool:
    """A matched estimate more than :data:`GROSS_MM` or :data:`GROSS_DEG` off."""
    return trans_mm > GROSS_MM or rot_deg > GROSS_DEG


class _Tails:
    """Per method: gross errors, false objects and id switches, and their causes."""

    def __init__(self) -> None:
        self.object_frames = 0
        self.gross = 0
        self.visible = 0
        self.gross_visible = 0
        self.by_condition: dict[str, list[int]] = {}  # condition -> [object-frames, gross]
        self.fp_causes: dict[str, int] = {}
        self.switches = 0
        self.static_switches = 0
        self.tracked = False
        self.switch_events: list[dict] = []
        self.flips = 0
        self.flips_from_right = 0
        self.static_modes = 0  # object-frames of objects that did not move, with a mode
        self.reported_moved = 0  # ... reported perturbed
        self.moving_modes = 0  # object-frames of objects that moved, with a mode
        self.unreported_moves = 0  # ... reported static

    def add(self, sf, fm: FrameMatch, dets, conditions, kinds, gate: float) -> None:
        by_gt = fm.by_gt()
        for gid in sf.gt:
            mt = by_gt.get(gid)
            bad = mt is None or is_gross(mt.trans_mm, mt.rot_deg)
            self.object_frames += 1
            self.gross += int(bad)
            if sf.visib_fract.get(gid, 0.0) >= VISIBLE:
                self.visible += 1
                self.gross_visible += int(bad)
            if conditions is not None:
                row = self.by_condition.setdefault(conditions[gid], [0, 0])
                row[0] += 1
                row[1] += int(bad)
        for j in fm.false_positives:
            d = dets[j]
            cause = false_object_cause(
                d.T_world_obj, d.class_name, sf.gt, sf.distractors, sf.hypotheses, kinds, gate
            )
            self.fp_causes[cause] = self.fp_causes.get(cause, 0) + 1

    def add_ids(
        self, ids: IdSwitches, tracked: bool, sequence: int, flips: Flips, moves: ReportedMoves
    ) -> None:
        self.static_modes += moves.static
        self.reported_moved += moves.moved
        self.moving_modes += moves.moving
        self.unreported_moves += moves.unreported
        self.flips += flips.flips
        self.flips_from_right += flips.from_right
        self.tracked |= tracked
        self.switches += ids.switches
        self.static_switches += ids.static_switches
        self.switch_events += [{"sequence": sequence, **e} for e in ids.events[:20]]

    def merge(self, other: _Tails) -> None:
        """Add ``other``'s counts and examples after this one's (sequence order)."""
        self.object_frames += other.object_frames
        self.gross += other.gross
        self.visible += other.visible
        self.gross_visible += other.gross_visible
        for k, (n, g) in other.by_condition.items():
            row = self.by_condition.setdefault(k, [0, 0])
            row[0] += n
            row[1] += g
        for k, v in other.fp_causes.items():
            self.fp_causes[k] = self.fp_causes.get(k, 0) + v
        self.switches += other.switches
        self.static_switches += other.static_switches
        self.flips += other.flips
        self.flips_from_right += other.flips_from_right
        self.static_modes += other.static_modes
        self.reported_moved += other.reported_moved
        self.moving_modes += other.moving_modes
        self.unreported_moves += other.unreported_moves
        self.tracked |= other.tracked
        self.switch_events += other.switch_events

    def result(self) -> dict:
        n = max(self.object_frames, 1)
        out = {
            "gross_rate": self.gross / n,
            "gross_rate_visible": self.gross_visible / max(self.visible, 1),
            "gross": self.gross,
            "id_switches": self.switches if self.tracked else None,
            "id_switches_static": self.static_switches if self.tracked else None,
            "flips": self.flips,
            "flips_from_right": self.flips_from_right,
            "static_reported_moved": self.reported_moved if self.static_modes else None,
            "moved_reported_static": self.unreported_moves if self.moving_modes else None,
            "moved_with_mode": self.moving_modes,
            "false_object_causes": dict(sorted(self.fp_causes.items())),
        }
        if self.by_condition:
            out["gross_by_condition"] = {
                k: {"object_frames": v[0], "gross": v[1], "rate": v[1] / max(v[0], 1)}
                for k, v in sorted(self.by_condition.items())
            }
        if self.tracked:
            out["id_switch_examples"] = self.switch_events[:20]
        return out


def _modes(fm: FrameMatch, dets, estimate) -> dict[str, str]:
    """Ground-truth id -> the transition mode of its matched estimate (``estimate``: the
    method's last :class:`~ssp.estimate.SceneEstimate`, None for methods without modes)."""
    if estimate is None:
        return {}
    mode = {o.id: str(o.mode) for o in estimate.objects}
    out = {}
    for mt in fm.matches:
        eid = dets[mt.est_index].id
        if eid in mode:
            out[mt.gt_id] = mode[eid]
    return out


def _sources(seq: SimSequence) -> list | None:
    """The generator's per-frame source ids of the hypotheses, if recorded and consistent."""
    src = (seq.info or {}).get("hypothesis_sources")
    if not isinstance(src, list | tuple) or len(src) != len(seq.frames):
        return None
    if any(len(s) != len(f.hypotheses) for s, f in zip(src, seq.frames, strict=True)):
        return None
    return list(src)


def _common(values: list):
    """The value if all agree, else the list."""
    return values[0] if values and all(v == values[0] for v in values) else values


@dataclass(frozen=True)
class SequenceSpec:
    """A synthetic sequence to generate where it is run (in a worker, so the images are never
    pickled): :func:`ssp.sim.generate.generate_sequence` with these settings (``realistic``:
    the realistic estimator stream and scene; with ``rgb`` also, the RGB-estimator stream,
    :meth:`RealisticNoise.rgb <ssp.sim.realistic.RealisticNoise.rgb>`), then, with
    ``estimated``, its hypotheses replaced by the perception front end's
    (:func:`ssp.eval.estimated.estimate_sequence`; ``masks`` False: on the cloud's clusters, as
    ``ssp run --masks none`` does it); ``camera``: the camera's path
    (:data:`ssp.sim.camera_path.CAMERA_PATHS`); ``locate``: its pose is not given, each
    frame's camera is located as ``ssp run`` does it (:class:`ssp.pipeline.world.CameraLocator`)
    and the methods see the frames in that world frame (:func:`_located`)."""

    experiment: str
    seed: int
    stages: int | None = None
    frames_per_stage: int = 4
    stride: int = 1
    realistic: bool = False
    estimated: bool = False
    rgb: bool = False
    masks: bool = True
    camera: str = "static"
    locate: bool = False

    def build(self, library, config: SSPConfig) -> tuple[SimSequence, list[dict]]:
        """The sequence and the estimator's records (empty unless ``estimated``)."""
        from ssp.sim.generate import generate_sequence
        from ssp.sim.realistic import RealisticNoise, SceneRealism

        seq = generate_sequence(
            self.experiment,
            self.seed,
            library,
            stages=self.stages,
            frames_per_stage=self.frames_per_stage,
            stride=self.stride,
            hypotheses=(RealisticNoise.rgb() if self.rgb else RealisticNoise())
            if self.realistic
            else None,
            realism=SceneRealism() if self.realistic else None,
            camera_path=self.camera,
        )
        if not self.estimated:
            return seq, []
        from ssp.eval.estimated import estimate_sequence

        return estimate_sequence(seq, library, config, masks=self.masks)


@dataclass
class SequencePart:
    """What one sequence adds to Table I (:func:`run_table1_parts`); :func:`merge_table1`
    joins the parts in sequence order.

    Per method: ``errors`` (translation mm, rotation deg of every match), ``counts``,
    ``precision`` (deviations over the sequence's static scenes, mm and deg), ``records``
    (the columns of ``result["records"]``), ``bop`` (:meth:`BopEvaluator.counts`) and
    ``tails``. ``info``: the sequence's ``info`` without the per-frame hypothesis sources;
    ``estimator_records``: :func:`ssp.eval.estimated.estimate_sequence`'s, for a
    :class:`SequenceSpec` with ``estimated``.
    """

    index: int
    experiment: str
    seed: int
    frames: int
    hyp_t: list[float]
    hyp_r: list[float]
    hyp_outliers: int
    errors: dict[str, tuple[list[float], list[float]]]
    counts: dict[str, dict[str, int]]
    precision: dict[str, tuple[list[float], list[float]]]
    records: dict[str, dict[str, dict[str, list]]]
    bop: dict[str, tuple]
    tails: dict[str, _Tails]
    info: dict = field(default_factory=dict)
    estimator_records: list[dict] = field(default_factory=list)
    #: per method, each object's spread over each static scene it was matched in: its
    #: largest deviation from its mean estimate there (mm, deg)
    spreads: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    camera: list[dict] = field(default_factory=list)


def _bare(frame: Frame, config: SSPConfig) -> Frame:
    """``frame`` (no labels) as ``ssp run --masks none`` gives it to the parser: its cloud
    clustered above the table as the front end does it
    (:func:`ssp.perception.segmentation.segment_cloud`, labels of kind ``cluster``), and its
    hypotheses without segments (they come from no mask)."""
    from ssp.perception.segmentation import segment_cloud

    pc = config.perception
    seg = segment_cloud(
        frame.points,
        None,
        table_height=pc.table_height,
        tolerance=pc.cluster_tolerance,
        min_points=pc.min_segment_points,
    )
    return replace(
        frame,
        labels=seg.labels,
        label_kind="cluster",
        hypotheses=[replace(h, segment=None) for h in frame.hypotheses],
    )


def _check_methods(methods: Sequence[str]) -> tuple[str, ...]:
    methods = tuple(methods)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; known: {', '.join(METHODS)}")
    return methods


def run_table1(
    sequences: Sequence[SimSequence | SequenceSpec],
    library,
    config: SSPConfig | None = None,
    methods: Sequence[str] = DEFAULT_METHODS,
    progress: Callable[[str], None] | None = None,
    *,
    gate: float = DEFAULT_GATE,
    on_output: Callable[[int, int, str, list[Detection]], None] | None = None,
    vsd: bool = True,
    on_estimate: Callable[..., None] | None = None,
    parallel: Parallel | None = None,
    masks: bool = True,
) -> dict:
    """Run every method on every frame of ``sequences``; a JSON-ready dict (module docstring).

    Args:
        sequences: the synthetic sequences (:class:`SimSequence`, or :class:`SequenceSpec` to
            generate them where they are run), usually of one experiment.
        library: the object library (every class of the sequences).
        config: ssp's constants (also used by the baselines: association gates, segments, data
            fit radius); default ``SSPConfig()``.
        methods: names from :data:`ssp.eval.baselines.METHODS`, in report order.
        progress: called with a short message before each frame (serial), or after each
            sequence (in parallel).
        gate: matching gate, m (:func:`ssp.eval.metrics.match_frame`).
        on_output: called as ``on_output(sequence index, frame index, method, detections)``
            after each method's update (e.g. to draw estimate-vs-truth images); serial only.
        vsd: include VSD in the BOP metrics (one render per estimate-object pair that
            overlaps in the image).
        on_estimate: called as ``on_estimate(sequence index, frame index, frame, estimate)``
            after the ``ssp`` method's update, with the parser's input and its last
            :class:`ssp.estimate.SceneEstimate` (that of an earlier frame when this one failed;
            e.g. to record the run, :mod:`ssp.viz.record`); serial only.
        parallel: how the sequences are run (:mod:`ssp.pipeline.executor`; default serial).
            The result is the serial one but for the wall times (``sec`` and
            ``sec_per_frame``).
        masks: the methods get the instance masks (each point's object, each hypothesis's
            segment); False: the cloud's Euclidean clusters as ``ssp run --masks none`` makes
            them (:func:`_bare`: touching objects, and an object touching a distractor, are
            one segment).
    """
    methods = _check_methods(methods)
    parts = run_table1_parts(
        sequences,
        library,
        config,
        methods,
        progress,
        gate=gate,
        on_output=on_output,
        vsd=vsd,
        parallel=parallel,
        on_estimate=on_estimate,
        masks=masks,
    )
    return merge_table1(parts, methods, gate)


def run_table1_parts(
    sequences: Sequence[SimSequence | SequenceSpec],
    library,
    config: SSPConfig | None = None,
    methods: Sequence[str] = DEFAULT_METHODS,
    progress: Callable[[str], None] | None = None,
    *,
    gate: float = DEFAULT_GATE,
    on_output: Callable[[int, int, str, list[Detection]], None] | None = None,
    vsd: bool = True,
    parallel: Parallel | None = None,
    on_sequence: Callable[[int, int], None] | None = None,
    on_estimate: Callable[..., None] | None = None,
    masks: bool = True,
) -> list[SequencePart]:
    """One :class:`SequencePart` per sequence, in order (arguments as :func:`run_table1`;
    ``on_sequence(done, total)`` after each sequence).

    Raises:
        ItemError: a sequence failed (:mod:`ssp.pipeline.executor`; named by its index and seed).
    """
    config = config if config is not None else SSPConfig()
    methods = _check_methods(methods)
    parallel = parallel if parallel is not None else Parallel()
    if (on_output is not None or on_estimate is not None) and not parallel.serial:
        raise ArgumentError("on_output and on_estimate need the serial executor")
    n = len(sequences)
    serial = parallel.serial
    work = partial(
        _sequence_part,
        n=n,
        config=config,
        methods=methods,
        gate=gate,
        vsd=vsd,
        progress=progress if serial else None,
        on_output=on_output,
        on_estimate=on_estimate,
        masks=masks,
    )
    names = [
        f"sequence {s + 1}/{n} (seed {seq.seed}, {seq.experiment})"
        for s, seq in enumerate(sequences)
    ]

    tell = done_messages(progress, parallel)

    def done(k: int, total: int, name: str) -> None:
        if tell is not None:
            tell(k, total, name)
        if on_sequence is not None:
            on_sequence(k, total)

    return map_items(
        work,
        list(enumerate(sequences)),
        shared=library,
        parallel=parallel,
        names=names,
        progress=done,
    )


def _sequence_part(
    item: tuple[int, SimSequence | SequenceSpec],
    library,
    *,
    n: int,
    config: SSPConfig,
    methods: tuple[str, ...],
    gate: float,
    vsd: bool,
    progress: Callable[[str], None] | None = None,
    on_output: Callable[[int, int, str, list[Detection]], None] | None = None,
    on_estimate: Callable[..., None] | None = None,
    masks: bool = True,
) -> SequencePart:
    """Every method on every frame of one sequence (``item``: its index and the sequence;
    ``masks`` as for :func:`run_table1`)."""
    s, seq = item
    estimator_records: list[dict] = []
    located = _Located(config) if isinstance(seq, SequenceSpec) and seq.locate else _Given()
    if isinstance(seq, SequenceSpec):
        seq, estimator_records = seq.build(library, config)
    physics = PhysicsCheck(library, config)
    hyp_t: list[float] = []
    hyp_r: list[float] = []
    hyp_outliers = 0
    err = {m: ([], []) for m in methods}
    counts = {m: dict.fromkeys(_COUNT_KEYS, 0) for m in methods}
    stacks: dict[str, dict[tuple, list[np.ndarray]]] = {m: {} for m in methods}
    stack_class: dict[tuple, str] = {}
    records = {
        m: {
            "objects": {c: [] for c in _OBJECT_COLUMNS},
            "frames": {c: [] for c in _FRAME_COLUMNS},
        }
        for m in methods
    }
    bop = {m: BopEvaluator(library, vsd=vsd) for m in methods}
    tails = {m: _Tails() for m in methods}

    runners = {m: make_method(m, library, config) for m in methods}
    ids = {m: IdSwitches() for m in methods}
    flips = {m: Flips() for m in methods}
    t = (config or SSPConfig()).temporal
    tilt = float(np.degrees(t.static_rotation))
    moves = {m: ReportedMoves(t.static_translation, tilt) for m in methods}
    sources = _sources(seq)
    kinds = (seq.info or {}).get("hypothesis_kinds") if sources is not None else None
    history = DetectionHistory()
    for i, sf in enumerate(seq.frames):
        if progress is not None:
            progress(f"sequence {s + 1}/{n}, frame {i + 1}/{len(seq)}")
        frame = seq.frame(i) if masks else _bare(seq.frame(i, labels=False), config)
        frame = located.frame(seq, i, frame, runners.values())
        errs, outliers = hypothesis_errors(
            sf.gt, sf.hypotheses, library, gate, None if sources is None else sources[i]
        )
        hyp_outliers += outliers
        hyp_t.extend(e[0] for e in errs)
        hyp_r.extend(e[1] for e in errs)
        conditions = None
        if kinds is not None:
            seen = history.update(sf.gt, {g for g in sources[i] if g is not None})
            conditions = object_conditions(
                sf.gt, sf.visib_fract, sf.hypotheses, sources[i], kinds[i], seen
            )
        for m, runner in runners.items():
            t0 = time.perf_counter()
            dets = runner.update(frame)
            wall = time.perf_counter() - t0
            dets = located.output(dets)
            if on_output is not None:
                on_output(s, i, m, dets)
            if on_estimate is not None and m == "ssp":
                on_estimate(s, i, frame, runner.last_estimate)
            fm = match_frame(sf.gt, dets, library, gate)
            bop[m].add_frame(
                sf.gt,
                sf.visib_fract,
                [(d.class_name, d.T_world_obj, d.score) for d in dets],
                seq.camera,
                seq.camera_pose(i),
                sf.depth,
            )
            ids[m].update(sf.index, sf.gt, {mt.gt_id: dets[mt.est_index].id for mt in fm.matches})
            flips[m].update(
                sf.gt, {mt.gt_id: dets[mt.est_index].T_world_obj for mt in fm.matches}, library
            )
            moves[m].update(sf.gt, _modes(fm, dets, getattr(runner, "last_estimate", None)))
            tails[m].add(sf, fm, dets, conditions, kinds[i] if kinds else None, gate)
            depth, n_unsup = physics(dets)
            c = counts[m]
            c["matched"] += len(fm.matches)
            c["missed"] += len(fm.missed)
            c["false_positives"] += len(fm.false_positives)
            by_gt = fm.by_gt()
            obj = records[m]["objects"]
            for gid, (cls, _) in sf.gt.items():
                mt = by_gt.get(gid)
                vis = sf.visib_fract.get(gid)
                obj["sequence"].append(s)
                obj["frame"].append(sf.index)
                obj["object"].append(gid)
                obj["class"].append(cls)
                obj["visib_fract"].append(None if vis is None else float(vis))
                obj["trans_mm"].append(None if mt is None else mt.trans_mm)
                obj["rot_deg"].append(None if mt is None else mt.rot_deg)
                if mt is not None:
                    err[m][0].append(mt.trans_mm)
                    err[m][1].append(mt.rot_deg)
                    key = (s, gid, sf.static_group)
                    stacks[m].setdefault(key, []).append(np.array(dets[mt.est_index][1]))
                    stack_class[key] = cls
            fr = records[m]["frames"]
            for name, value in (
                ("sequence", s),
                ("frame", sf.index),
                ("objects", len(dets)),
                ("matched", len(fm.matches)),
                ("missed", len(fm.missed)),
                ("false_positives", len(fm.false_positives)),
                ("penetration_mm", 1000.0 * depth),
                ("unsupported", n_unsup),
                ("sec", wall),
            ):
                fr[name].append(value)
    for m in methods:
        tails[m].add_ids(ids[m], getattr(runners[m], "tracks_ids", False), s, flips[m], moves[m])
    precision, spreads = {}, {}
    for m in methods:
        pt, pr, spreads[m] = [], [], []
        for key, poses in stacks[m].items():
            dt, dr = precision_deviations(poses, library[stack_class[key]].symmetry)
            pt.extend(dt)
            pr.extend(dr)
            if dt:
                spreads[m].append((max(dt), max(dr)))
        precision[m] = (pt, pr)
    info = {k: v for k, v in (seq.info or {}).items() if k != "hypothesis_sources"}
    return SequencePart(
        index=s,
        experiment=seq.experiment,
        seed=seq.seed,
        frames=len(seq.frames),
        hyp_t=hyp_t,
        hyp_r=hyp_r,
        hyp_outliers=hyp_outliers,
        errors=err,
        counts=counts,
        precision=precision,
        records=records,
        bop={m: bop[m].counts() for m in methods},
        tails=tails,
        info=info,
        estimator_records=estimator_records,
        camera=located.rows,
        spreads=spreads,
    )


class _Given:
    """A sequence's frames with their camera poses given: as they are."""

    def __init__(self) -> None:
        self.rows: list[dict] = []

    def frame(self, seq: SimSequence, i: int, frame: Frame, runners) -> Frame:
        return frame

    def output(self, dets: list[Detection]) -> list[Detection]:
        return dets


class _Located:
    """A sequence's frames as ``ssp run`` sees a camera with no pose given (a
    :class:`SequenceSpec` with ``locate``): each frame's camera located in the first frame's
    table frame (:class:`ssp.pipeline.world.CameraLocator`, from the frame's depth), the frame
    moved into that world frame; the methods' outputs come back to the truth's world frame by
    :attr:`align`, the one transform that makes the first located frame's camera the true one
    (a camera error moves a method's objects). A camera not located restarts the world frame:
    the methods forget their objects (the ssp parser keeps counting ids) and :attr:`align` is
    set again. :attr:`rows`: per frame, how the camera was found and its error at the
    objects (the largest displacement of the true objects' centres, mm)."""

    def __init__(self, config: SSPConfig) -> None:
        from ssp.pipeline.world import CameraLocator

        self.locator = CameraLocator(config.perception.table_distance)
        self.align = np.eye(4)
        self.rows: list[dict] = []

    def frame(self, seq: SimSequence, i: int, frame: Frame, runners) -> Frame:
        from ssp.perception.depth import cloud_from_depth
        from ssp.pipeline.world import RESTARTED

        sf = seq.frames[i]
        T_true = np.asarray(seq.camera_pose(i), dtype=float)
        T_est, fix = self.locator.locate(cloud_from_depth(sf.depth, seq.camera).points, [])
        if not self.rows or fix["how"] == RESTARTED:
            if self.rows:
                for runner in runners:
                    parser = getattr(runner, "parser", None)
                    if parser is not None:
                        parser.reset(keep_ids=True)  # ssp: new tracks, ids go on counting
                    else:
                        runner.reset()
            self.align = T_true @ np.linalg.inv(T_est)
        D = self.align @ T_est @ np.linalg.inv(T_true)  # true world -> where the run puts it
        c = np.array([np.asarray(T, dtype=float)[:3, 3] for _, T in sf.gt.values()])
        err = np.linalg.norm(c @ D[:3, :3].T + D[:3, 3] - c, axis=1).max() if len(c) else 0.0
        self.rows.append({"frame": sf.index, "how": fix["how"], "error_mm": 1000.0 * float(err)})
        return frame.moved_by(T_est @ np.linalg.inv(T_true))

    def output(self, dets: list[Detection]) -> list[Detection]:
        """A method's detections in the truth's world frame."""
        return [d._replace(T_world_obj=self.align @ d.T_world_obj) for d in dets]


def merge_table1(
    parts: Sequence[SequencePart], methods: Sequence[str], gate: float = DEFAULT_GATE
) -> dict:
    """The Table I result (module docstring) of the sequences' parts, joined in their order."""
    methods = tuple(methods)
    hyp_t = [v for p in parts for v in p.hyp_t]
    hyp_r = [v for p in parts for v in p.hyp_r]
    hyp_outliers = sum(p.hyp_outliers for p in parts)
    records = {
        m: {
            kind: {c: [v for p in parts for v in p.records[m][kind][c]] for c in cols}
            for kind, cols in (("objects", _OBJECT_COLUMNS), ("frames", _FRAME_COLUMNS))
        }
        for m in methods
    }
    out_methods = {}
    for m in methods:
        errs_t = [v for p in parts for v in p.errors[m][0]]
        errs_r = [v for p in parts for v in p.errors[m][1]]
        pt = [v for p in parts for v in p.precision[m][0]]
        pr = [v for p in parts for v in p.precision[m][1]]
        counts = {
            k: sum(p.counts[m][k] for p in parts) for k in ("matched", "missed", "false_positives")
        }
        bop = BopEvaluator({}, vsd=parts[0].bop[m][0] if parts else True)
        tails = _Tails()
        for p in parts:
            bop.add_counts(p.bop[m])
            tails.merge(p.tails[m])
        fr = records[m]["frames"]
        n = max(len(fr["sec"]), 1)
        out_methods[m] = {
            "accuracy": summarize(errs_t, errs_r),
            "precision": summarize(pt, pr),
            "static_spread": _spread([v for p in parts for v in p.spreads.get(m, [])]),
            "max_penetration_mm": float(max(fr["penetration_mm"], default=0.0)),
            "unsupported_objects": float(sum(fr["unsupported"]) / n),
            "unsupported_total": int(sum(fr["unsupported"])),
            "sec_per_frame": float(sum(fr["sec"]) / n),
            **counts,
            "missed_per_frame": counts["missed"] / n,
            "false_positives_per_frame": counts["false_positives"] / n,
            "bop": bop.result(),
            **tails.result(),
        }

    # accuracy over the object-frames every method matched (methods that keep hard, occluded
    # objects are otherwise judged on more difficult cases than methods that drop them)
    trans = [records[m]["objects"]["trans_mm"] for m in methods]
    common = [
        i for i in range(len(trans[0]) if trans else 0) if all(t[i] is not None for t in trans)
    ]
    for m in methods:
        o = records[m]["objects"]
        out_methods[m]["accuracy_common"] = summarize(
            [o["trans_mm"][i] for i in common], [o["rot_deg"][i] for i in common]
        )
        out_methods[m]["common_objects"] = len(common)
        out_methods[m]["per_class"] = per_class(o, out_methods[m]["bop"].get("per_class", {}))

    noise = summarize(hyp_t, hyp_r)
    return {
        "protocol": "table1",
        "experiment": _common([p.experiment for p in parts]),
        "seed": _common([p.seed for p in parts]),
        "sequences": len(parts),
        "frames": sum(p.frames for p in parts),
        "induced_noise": {
            "trans_mm_mean": noise["trans_mm_mean"],
            "rot_deg_mean": noise["rot_deg_mean"],
            "trans_mm_std": noise["trans_mm_std"],
            "rot_deg_std": noise["rot_deg_std"],
            "hypotheses": len(hyp_t),
            "outliers": hyp_outliers,
        },
        "methods": out_methods,
        "match_gate_mm": 1000.0 * gate,
        "records": records,
        **_camera_summary(parts),
    }


#: A static object's estimate should stay within this of its mean over a static scene, mm
#: (issue 32's acceptance for moving cameras).
SPREAD_MM = 2.0


def _spread(spreads: Sequence[tuple[float, float]]) -> dict | None:
    """The static objects' spreads (:attr:`SequencePart.spreads`): how many object-scenes, the
    share within :data:`SPREAD_MM`, and the worst (None: none)."""
    if not spreads:
        return None
    mm = np.array([a for a, _ in spreads])
    return {
        "object_scenes": len(spreads),
        "within_2mm": float(np.mean(mm < SPREAD_MM)),
        "worst_mm": float(mm.max()),
        "worst_deg": float(max(b for _, b in spreads)),
    }


def _camera_summary(parts: Sequence[SequencePart]) -> dict:
    """``{"camera": ...}`` when the camera was located (:class:`_Located`): frames, how each
    was found, restarts, and the error at the objects (mm: median, p95, max); else empty."""
    rows = [r for p in parts for r in p.camera]
    if not rows:
        return {}
    err = np.array([r["error_mm"] for r in rows])
    hows: dict[str, int] = {}
    for r in rows:
        hows[r["how"]] = hows.get(r["how"], 0) + 1
    return {
        "camera": {
            "frames": len(rows),
            "how": hows,
            "restarts": hows.get("restarted", 0),
            "error_mm_median": float(np.median(err)),
            "error_mm_p95": float(np.percentile(err, 95)),
            "error_mm_max": float(err.max()),
            "rows": [{"sequence": p.index, **r} for p in parts for r in p.camera],
        }
    }


def table1_report(
    parts: Sequence[SequencePart],
    methods: Sequence[str],
    *,
    hypotheses: str,
    noise: str,
    command: dict | None = None,
) -> dict:
    """The result ``ssp bench table1`` writes: :func:`merge_table1` of the parts, with the
    hypotheses (``noisy`` or ``estimated``) and noise (``paper``, ``realistic`` or ``rgb``)
    settings; for ``realistic`` and ``rgb``, the realistic protocol's settings and each
    sequence's events; for estimated hypotheses, the estimator's summary and records
    (:func:`ssp.eval.estimated.summarize_estimator`); and the ``command`` that ran it."""
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    result = merge_table1(parts, methods)
    records = [{"sequence": p.index, **r} for p in parts for r in p.estimator_records]
    result["hypotheses"] = hypotheses
    result["noise"] = noise
    result["masks"] = (command or {}).get("masks", "instance")
    if noise in ("realistic", "rgb"):
        result["protocol_settings"] = {
            "estimator": (RealisticNoise.rgb() if noise == "rgb" else RealisticNoise()).to_dict(),
            "scene": SceneRealism().to_dict(),
            "events": [p.info.get("events") for p in parts],
            "events_skipped": [p.info.get("events_skipped") for p in parts],
        }
    if records:
        from ssp.eval.estimated import summarize_estimator

        result["estimator"] = summarize_estimator(records)
        result["estimator_records"] = records
    result["command"] = command
    return result


# ------------------------------------------------------------------------------ report
def _markdown(result: dict) -> str:
    exp = result["experiment"]
    lines = [
        f"# Table I: {exp} ({result['sequences']} sequences, {result['frames']} frames)",
        "",
        *(
            ["Without masks: the methods got bare clouds (`--masks none`).", ""]
            if result.get("masks") == "none"
            else []
        ),
        "Translation and rotation errors are mean ± std (symmetry-aware). Accuracy: error to "
        "the ground truth of every matched object in every frame (occluded included); "
        "precision: spread about the object's mean estimate over each static scene; accuracy, "
        "common: over the object-frames that every method matched. "
        "Penetration: deepest contact of the output objects, maximum over frames; unsupported: "
        "mean number per frame of output objects with no support path from the table or "
        f"falling faster than {UNSUPPORTED_ACCELERATION:g} g; matches within "
        f"{result.get('match_gate_mm', 50):.0f} mm.",
        "",
        "| Method | Category | Translation (mm) | Rotation (deg) | max penetration (mm) "
        "| unsupported / frame | s / frame | matched / missed / false pos. |",
        "|---|---|---|---|---|---|---|---|",
    ]
    n = result["induced_noise"]
    if "camera" in result:
        cam = result["camera"]
        lines[2:2] = [
            f"Camera pose not given: located by ssp (`--camera-pose estimated`) in "
            f"{cam['frames'] - cam['restarts']} of {cam['frames']} frames "
            f"({', '.join(f'{k} {v}' for k, v in sorted(cam['how'].items()))}; a restart "
            "forgets the scene); its error at the objects median / p95 / max "
            f"{cam['error_mm_median']:.2f} / {cam['error_mm_p95']:.2f} / "
            f"{cam['error_mm_max']:.2f} mm, in every method's errors below.",
            "",
        ]
    if result.get("hypotheses") == "estimated":
        lines[2:2] = [
            "Hypotheses: estimated by the perception front end (`ssp.perception`) on the "
            "rendered depth, segmented by the instance mask (without masks: on the cloud's "
            "clusters); the Induced Noise row is the error of those hypotheses to the nearest "
            "object of their class.",
            "",
        ]
    lines.append(
        f"| hypotheses | Induced Noise | {plus_minus(n['trans_mm_mean'], n['trans_mm_std'])} | "
        f"{plus_minus(n['rot_deg_mean'], n['rot_deg_std'])} | | | | "
        f"{n.get('hypotheses', '')} hyp., {n.get('outliers', 0)} outliers |"
    )
    for name, d in result["methods"].items():
        a, p = d["accuracy"], d["precision"]
        lines.append(
            f"| {name} | Accuracy | {plus_minus(a['trans_mm_mean'], a['trans_mm_std'])} | "
            f"{plus_minus(a['rot_deg_mean'], a['rot_deg_std'])} | {d['max_penetration_mm']:.2f} | "
            f"{d['unsupported_objects']:.2f} | {d['sec_per_frame']:.3f} | "
            f"{d.get('matched', '')} / {d.get('missed', '')} / {d.get('false_positives', '')} |"
        )
        lines.append(
            f"| {name} | Precision | {plus_minus(p['trans_mm_mean'], p['trans_mm_std'])} | "
            f"{plus_minus(p['rot_deg_mean'], p['rot_deg_std'])} | | | | |"
        )
        c = d.get("accuracy_common")
        if c:
            lines.append(
                f"| {name} | Accuracy, common | "
                f"{plus_minus(c['trans_mm_mean'], c['trans_mm_std'])} | "
                f"{plus_minus(c['rot_deg_mean'], c['rot_deg_std'])} | | | | "
                f"{d['common_objects']} matched by all |"
            )
    lines += _tails_markdown(result)
    e = result.get("estimator")
    if e:
        lines += [
            "",
            f"Pose estimator: {e['sec_per_segment_mean']:.3f} s per segment on average (median "
            f"{e['sec_per_segment_median']:.3f}, p95 {e['sec_per_segment_p95']:.3f}; "
            f"{e['segments']} segments). Recall (a hypothesis of the object's class within "
            f"{e['recall_mm']:.0f} mm and {e['recall_deg']:.0f} deg): {e['recall']:.2f} of "
            f"all {e['objects']} object-frames, {e['recall_visible']:.2f} of the "
            f"{e['visible_objects']} at least {100 * e['visible_fraction']:.0f} % visible"
            + ("" if e["top1_recall_visible"] is None else
               f" (best-scored hypothesis: {e['top1_recall_visible']:.2f})")
            + ("." if "clusters" not in e else
               f"; without masks, {e['objects_per_cluster_mean']:.2f} objects found per cluster, "
               f"{e['objects_per_frame_mean']:.1f} per frame."),
        ]  # fmt: skip
    lines += [
        "",
        "The paper's Table I, for reference (ssp on Gazebo data):",
        "",
        "| Test | Category | Translation (mm) | Rotation (deg) |",
        "|---|---|---|---|",
    ]
    labels = {"induced": "Induced Noise", "accuracy": "Accuracy", "precision": "Precision"}
    tests = {"isolated": "Isolated Object", "structure": "Complex Structure"}
    for key, rows in PAPER_TABLE1.items():
        for row, ((tm, ts), (rm, rs)) in rows.items():
            lines.append(f"| {tests[key]} | {labels[row]} | {tm} ± {ts} | {rm} ± {rs} |")
    lines += [
        "",
        "Plots: `error_vs_visibility.png` (mean error per visible-fraction bin), "
        "`error_over_frames.png` (mean error per frame index over objects and sequences).",
    ]
    return "\n".join(lines) + "\n"


def _tails_markdown(result: dict) -> list[str]:
    """The tails tables: BOP AR, gross errors, false objects, id switches; on the realistic
    stream, gross errors by the stream's condition and false objects by cause."""
    methods = result["methods"]
    lines = [
        "",
        "Tails. AR: BOP19 average recall (mean of VSD, MSSD, MSPD, as the BOP toolkit defines "
        "them, symmetry-aware; targets: objects at least 10 % visible). Gross: ground-truth "
        f"object-frames whose estimate is more than {GROSS_MM:.0f} mm or {GROSS_DEG:.0f} deg "
        "off (at the centre of mass) or missing; visible: of those at least 10 % visible. "
        "False objects: estimates matched to no object. Id switches: CLEAR-MOT, in brackets "
        "those of objects that had not moved (methods without ids: -).",
        "",
        "| Method | AR | AR VSD / MSSD / MSPD | gross | gross, visible | missed / frame "
        "| false objects / frame | id switches (static) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, d in methods.items():
        b = d.get("bop")
        if b is None:
            continue
        sw = d.get("id_switches")
        vsd = f"{b['AR_VSD']:.3f} / " if "AR_VSD" in b else ""
        lines.append(
            f"| {name} | {b['AR']:.3f} | {vsd}{b['AR_MSSD']:.3f} / {b['AR_MSPD']:.3f} | "
            f"{d['gross_rate']:.3f} | {d['gross_rate_visible']:.3f} | "
            f"{d['missed_per_frame']:.2f} | {d['false_positives_per_frame']:.2f} | "
            + ("-" if sw is None else f"{sw} ({d['id_switches_static']})")
            + " |"
        )
    lines += _column_table(
        methods,
        "gross_by_condition",
        "Gross object-frames by the stream's condition for the object in that frame "
        "(`ssp.eval.failures`): gross / object-frames.",
        lambda v: f"{v['gross']} / {v['object_frames']}",
    )
    lines += _column_table(
        methods,
        "false_object_causes",
        "False objects (object-frames) by what they lie on.",
        str,
        missing="0",
    )
    moved = [f"{name} {d['static_reported_moved']}" for name, d in methods.items()
             if d.get("static_reported_moved") is not None]  # fmt: skip
    if moved:
        lines += ["", "Objects reported moved (transition mode perturbed) that did not move "
                  "(object-frames): " + ", ".join(moved) + "."]  # fmt: skip
    still = [f"{name} {d['moved_reported_static']} of {d['moved_with_mode']}"
             for name, d in methods.items()
             if d.get("moved_reported_static") is not None]  # fmt: skip
    if still:
        lines += ["", "Objects that moved (beyond the static thresholds, 7.5 mm or 5 deg, "
                  "since their last match) reported static (object-frames): "
                  + ", ".join(still) + "."]  # fmt: skip
    spread = [f"{name} {100 * d['static_spread']['within_2mm']:.1f} % of "
              f"{d['static_spread']['object_scenes']} within 2 mm, the worst "
              f"{d['static_spread']['worst_mm']:.1f} mm / {d['static_spread']['worst_deg']:.1f} deg"
              for name, d in methods.items() if d.get("static_spread")]  # fmt: skip
    if spread:
        lines += ["", "Spread of each object's estimate over each static scene (its largest "
                  "deviation from its mean estimate there): "
                  + "; ".join(spread) + "."]  # fmt: skip
    flips = [f"{name} {d['flips']} ({d['flips_from_right']})" for name, d in methods.items()
             if d.get("flips") is not None]  # fmt: skip
    if flips:
        lines += ["", "Orientation flips of objects that did not move (an estimate turned by "
                  "over 15 deg since the object's last match; in brackets, from an orientation "
                  "within 10 deg of the truth): " + ", ".join(flips) + "."]  # fmt: skip
    lines += per_class_markdown(methods)
    return lines


def per_class(objects: dict, bop_per_class: dict) -> dict[str, dict]:
    """Per class of the object records ``objects`` (the columns of ``result["records"][m]
    ["objects"]``): ``object_frames``, ``matched``, ``gross`` (more than :data:`GROSS_MM` or
    :data:`GROSS_DEG` off, or missing), the mean and median translation (mm) and rotation
    (deg) error of the matched ones (None without), and the class's BOP ``AR`` from
    ``bop_per_class`` (None when it had no target). A class whose orientation the view cannot
    always decide (a mug's hidden handle) shows here, not in the means over all classes."""
    out: dict[str, dict] = {}
    for cls in sorted(set(objects["class"])):
        rows = [i for i, c in enumerate(objects["class"]) if c == cls]
        t = [objects["trans_mm"][i] for i in rows if objects["trans_mm"][i] is not None]
        r = [objects["rot_deg"][i] for i in rows if objects["rot_deg"][i] is not None]
        gross = sum(
            1 for i in rows
            if objects["trans_mm"][i] is None
            or is_gross(objects["trans_mm"][i], objects["rot_deg"][i])
        )  # fmt: skip
        ar = bop_per_class.get(cls, {}).get("AR")
        out[cls] = {
            "object_frames": len(rows),
            "matched": len(t),
            "gross": gross,
            "trans_mm_mean": float(np.mean(t)) if t else None,
            "trans_mm_median": float(np.median(t)) if t else None,
            "rot_deg_mean": float(np.mean(r)) if r else None,
            "rot_deg_median": float(np.median(r)) if r else None,
            "AR": None if ar is None else float(ar),
        }
    return out


def per_class_markdown(methods: dict) -> list[str]:
    """A row per class, a column per method: BOP AR, mean rotation error (deg) and gross
    object-frames."""
    classes = sorted({c for d in methods.values() for c in d.get("per_class", {})})
    if len(classes) < 2:
        return []
    names = list(methods)

    def cell(v: dict | None) -> str:
        if v is None:
            return ""
        ar = "-" if v["AR"] is None else f"{v['AR']:.3f}"
        rot = "-" if v["rot_deg_mean"] is None else f"{v['rot_deg_mean']:.1f}"
        return f"{ar} / {rot} / {v['gross']}"

    lines = [
        "",
        "Per class: AR / mean rotation error of the matched object-frames (deg) / gross "
        "object-frames.",
        "",
        "| Class | object-frames | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for cls in classes:
        rows = [methods[m].get("per_class", {}).get(cls) for m in names]
        n = next((r["object_frames"] for r in rows if r is not None), 0)
        lines.append(f"| {cls} | {n} | " + " | ".join(cell(r) for r in rows) + " |")
    return lines


def _column_table(methods: dict, key: str, title: str, cell, missing: str = "") -> list[str]:
    """Markdown lines of a table with a row per method and a column per key of the methods'
    ``key`` dicts (none when no method has one); ``cell(value)`` formats an entry, ``missing``
    stands where a method lacks a column."""
    cols = sorted({c for d in methods.values() for c in d.get(key, {})})
    if not cols:
        return []
    lines = ["", title, "", "| Method | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for name, d in methods.items():
        row = d.get(key, {})
        cells = [cell(row[c]) if c in row else missing for c in cols]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _object_arrays(rec: dict) -> tuple[np.ndarray, ...]:
    o = rec["objects"]
    ok = np.array([t is not None for t in o["trans_mm"]], dtype=bool)
    t = np.array([v if v is not None else np.nan for v in o["trans_mm"]], dtype=float)
    r = np.array([v if v is not None else np.nan for v in o["rot_deg"]], dtype=float)
    vis = np.array([v if v is not None else np.nan for v in o["visib_fract"]], dtype=float)
    frame = np.array(o["frame"], dtype=int)
    return ok, t, r, vis, frame


def _plots(result: dict, out: Path) -> list[Path]:
    from matplotlib.figure import Figure  # Agg through savefig; no pyplot, no global backend
    from matplotlib.ticker import MaxNLocator

    records = result.get("records", {})
    edges = np.linspace(0.0, 1.0, 11)
    centres = 0.5 * (edges[:-1] + edges[1:])

    fig = Figure(figsize=(10, 4), layout="constrained")
    axes = fig.subplots(1, 2)
    for name, rec in records.items():
        ok, t, r, vis, _ = _object_arrays(rec)
        sel = ok & np.isfinite(vis)
        b = np.clip(np.digitize(vis[sel], edges) - 1, 0, len(centres) - 1)
        for ax, v in zip(axes, (t[sel], r[sel]), strict=True):
            means = np.array([v[b == k].mean() if np.any(b == k) else np.nan for k in range(10)])
            ax.plot(centres, means, marker="o", label=name)
    for ax, what in zip(axes, ("translation error (mm)", "rotation error (deg)"), strict=True):
        ax.set_xlabel("visible fraction")
        ax.set_ylabel(what)
        ax.set_xlim(0, 1)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"Error vs visibility ({result.get('experiment')})")
    p1 = out / "error_vs_visibility.png"
    fig.savefig(p1, dpi=110)

    fig = Figure(figsize=(10, 4), layout="constrained")
    axes = fig.subplots(1, 2)
    for name, rec in records.items():
        ok, t, r, _, frame = _object_arrays(rec)
        if not ok.any():
            continue
        idx = np.unique(frame[ok])
        for ax, v in zip(axes, (t, r), strict=True):
            ax.plot(idx, [v[ok & (frame == k)].mean() for k in idx], marker=".", label=name)
    for ax, what in zip(axes, ("translation error (mm)", "rotation error (deg)"), strict=True):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("frame")
        ax.set_ylabel(what)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"Error over frames ({result.get('experiment')}, mean over objects)")
    p2 = out / "error_over_frames.png"
    fig.savefig(p2, dpi=110)
    return [p1, p2]


def write_table1(result: dict, out_dir: str | Path) -> list[Path]:
    """``results.json``, ``results.md`` (Table I layout with the paper's numbers) and the plots
    ``error_vs_visibility.png`` and ``error_over_frames.png`` in ``out_dir`` (created)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    j = out / "results.json"
    rest = {k: v for k, v in result.items() if k != "records"}
    text = json.dumps(rest, indent=2)
    if "records" in result:  # column lists on one line each: the file stays readable
        recs = ",\n".join(
            f"    {json.dumps(name)}: " + json.dumps(rec, separators=(",", ":"))
            for name, rec in result["records"].items()
        )
        text = text[: text.rindex("}")].rstrip() + ',\n  "records": {\n' + recs + "\n  }\n}"
    j.write_text(text + "\n")
    m = out / "results.md"
    m.write_text(_markdown(result))
    return [j, m, *_plots(result, out)]
