"""Trace the objects a Table I run reports moved that did not move (issue 32).

Runs ``ssp bench table1`` with the given arguments in this process (no ``--workers``: the
tracing wraps functions of this process) and prints, for each matched object-frame whose
object stood still (within the static thresholds since its last match) but whose transition
mode is ``perturbed``, one JSON line: the frame, the ground-truth and output ids, the output's
source and reason, and the motion test's inputs (``ssp.outcome._corrected``: the fit and
visible samples at the previous pose and at the estimate, the residuals, the change) with the
errors of the previous pose, the estimate and the output to the truth.

    .venv/bin/python examples/trace_reported_moves.py --experiment structure --sequences 10 \\
        --seed 1000 --noise realistic --methods ssp --camera keyframes --out bench-out/trace

It reaches into private functions (``ssp.eval.table1._modes``, ``ssp.outcome._corrected``),
so it follows the code it was written with; docs/benchmarks.md cites what it printed.
"""

# ruff: noqa: T201  (a script: it prints what it traces)
from __future__ import annotations

import json
import math
import sys

import numpy as np

import ssp.eval.table1 as table1
import ssp.eval.tracking as tracking
import ssp.outcome as outcome
from ssp.cli import app

_matched: dict[str, object] = {}  # ground-truth id -> this frame's matched ObjectEstimate
_frame = [0]  # the frame index of the last estimate
_tests: dict[tuple[int, str], dict] = {}  # (frame, output id) -> the motion test's inputs
_modes, _corrected, _update = table1._modes, outcome._corrected, tracking.ReportedMoves.update


def _traced_modes(fm, dets, estimate):
    if estimate is not None:
        by_id = {o.id: o for o in estimate.objects}
        _matched.clear()
        _matched.update({m.gt_id: by_id.get(dets[m.est_index].id) for m in fm.matches})
        _frame[0] = estimate.frame_index
    return _modes(fm, dets, estimate)


def _traced_corrected(ctx, oid, prev, T):
    why, fit = _corrected(ctx, oid, prev, T)
    model, known, est = ctx.models[oid], ctx.known.get(oid), ctx.evidence.get(oid)
    trees = ctx.segment_trees
    now = outcome.evidence(
        model, prev, trees.tree(oid), ctx.view, ctx.config, own_label=ctx.owner.get(oid),
        segment_spacing=trees.spacing(oid),
    )  # fmt: skip
    dt, dr = outcome.pose_change(prev, T, model.symmetry, model.center_of_mass)
    _tests[(ctx.frame_index, ctx.old_of.get(oid, oid))] = {
        "seen_fit": None if known is None else known.seen_fit,
        "seen_residual_mm": None if known is None else 1000 * known.seen_residual,
        "still": None if known is None else known.still,
        "prev_fit": now.fit,
        "prev_visible": now.visible,
        "prev_residual_mm": 1000 * outcome.object_residual(ctx, oid, prev),
        "estimate_fit": None if est is None else est.fit,
        "estimate_visible": None if est is None else est.visible,
        "estimate_residual_mm": 1000 * outcome.object_residual(ctx, oid, T),
        "change": f"{1000 * dt:.1f} mm / {math.degrees(dr):.1f} deg",
        "static_because": why,
        "_poses": (np.array(prev), np.array(T), model.symmetry, model.center_of_mass),
    }
    return why, fit


def _traced_update(self, gt, modes):
    for gid, mode in modes.items():
        last = self._last.get(gid)
        if last is None or str(mode) != "perturbed":
            continue
        T_gt = np.asarray(gt[gid][1], dtype=float)
        dt, dr = tracking.pose_change(last, T_gt)
        if dt >= tracking.STATIC_SHIFT or math.degrees(dr) >= tracking.STATIC_TILT_DEG:
            continue
        o = _matched.get(gid)
        test = dict(_tests.get((_frame[0], o.id), {})) if o is not None else {}
        if "_poses" in test:
            prev, T, sym, com = test.pop("_poses")
            for name, pose in (("prev", prev), ("estimate", T), ("output", o.T_world_obj)):
                e_t, e_r = outcome.pose_change(T_gt, pose, sym, com)
                test[f"error_{name}"] = f"{1000 * e_t:.1f} mm / {math.degrees(e_r):.1f} deg"
        line = {"frame": _frame[0], "gt": gid, "id": None if o is None else o.id}
        if o is not None:
            line.update(source=str(o.source), reason=o.reason, test=test)
        print("REPORTED_MOVED", json.dumps(line, default=float), flush=True)
    return _update(self, gt, modes)


def main() -> None:
    table1._modes = _traced_modes
    outcome._corrected = _traced_corrected
    tracking.ReportedMoves.update = _traced_update
    sys.argv = ["ssp", "bench", "table1", *sys.argv[1:]]
    app()


if __name__ == "__main__":
    main()
