"""ssp's MSSD, MSPD and their AR against the official BOP toolkit's own functions (issue 30).

On LM-O scene 2 (published models, ground truth and targets) with MegaPose's submitted results
CSV: per target pair, ssp's :func:`ssp.eval.bop_metrics.mssd` / :func:`mspd` against the
toolkit's ``pose_error.mssd`` / ``mspd`` (with the toolkit's own symmetries from the published
``models_info.json``, which ssp snaps to exact half turns); and the recall of ssp's
:class:`~ssp.eval.bop_metrics.BopEvaluator` (the evaluator ``ssp evaluate`` runs) against the
toolkit's ``pose_matching.match_poses_scene`` and ``score.calc_localization_scores`` as
``scripts/eval_calc_scores.py`` calls them for BOP19 (``n_top = -1``, ``visib_gt_min = -1``:
the ``inst_count`` most visible instances of each target are valid). VSD is not compared: the
depth images are not available.

The toolkit is imported from ``../shared/tools/bop_toolkit`` (MSSD, MSPD, matching and scoring
need only numpy and scipy); the test is skipped only when that folder or the data is absent.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from ssp.camera import Camera
from ssp.eval.bop_metrics import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    BopEvaluator,
    bop_symmetries,
    mspd,
    mssd,
)
from ssp.io.bop import open_bop, read_targets
from ssp.io.results import read_bop_csv
from ssp.library.symmetry import Symmetry

SHARED = Path(__file__).parents[1] / ".." / "shared"
TOOLKIT = SHARED / "tools" / "bop_toolkit"
LMO = SHARED / "data" / "lmo-megapose"
CSV = LMO / "cnos-fastsammegapose_lmo-test.csv"
SCENE = 2

pytestmark = pytest.mark.skipif(
    not (TOOLKIT / "bop_toolkit_lib").is_dir() or not CSV.is_file(),
    reason="needs ../shared/tools/bop_toolkit and ../shared/data/lmo-megapose",
)


@pytest.fixture(scope="module")
def toolkit():
    sys.path.insert(0, str(TOOLKIT.resolve()))
    try:
        from bop_toolkit_lib import misc, pose_error, pose_matching, score
    finally:
        sys.path.remove(str(TOOLKIT.resolve()))
    return SimpleNamespace(misc=misc, pose_error=pose_error, matching=pose_matching, score=score)


@pytest.fixture(scope="module")
def lmo(toolkit):
    """Everything both sides need, read once: models (vertices mm), ssp's and the toolkit's
    symmetries, ground truth, targets, the CSV's estimates of scene 2 (cut to the targets'
    ``inst_count`` per image and object, best score first, as eval_calc_errors does)."""
    info = {int(k): v for k, v in json.loads((LMO / "models/models_info.json").read_text()).items()}
    verts = {
        i: np.asarray(trimesh.load(LMO / f"models/obj_{i:06d}.ply", process=False).vertices)
        for i in info
    }
    sym_ssp = {i: Symmetry.from_bop(info[i], 1e-3, name=f"obj_id {i}") for i in info}
    sym_tk = {i: toolkit.misc.get_symmetry_transformations(info[i], 0.01) for i in info}
    scene_dir = LMO / "test" / f"{SCENE:06d}"
    gt = {int(k): v for k, v in json.loads((scene_dir / "scene_gt.json").read_text()).items()}
    gt_info = {
        int(k): v for k, v in json.loads((scene_dir / "scene_gt_info.json").read_text()).items()
    }
    cams = {int(k): v for k, v in json.loads((scene_dir / "scene_camera.json").read_text()).items()}
    targets: dict[int, dict[int, int]] = {}
    for t in json.loads((LMO / "test_targets_bop19.json").read_text()):
        if t["scene_id"] == SCENE:
            targets.setdefault(t["im_id"], {})[t["obj_id"]] = t["inst_count"]
    rows: dict[tuple[int, int], list] = {}
    for r in read_bop_csv(CSV):
        if r["scene_id"] == SCENE:
            rows.setdefault((r["im_id"], r["obj_id"]), []).append(r)
    ests = {}
    for im, objs in targets.items():
        for obj, count in objs.items():
            got = sorted(rows.get((im, obj), []), key=lambda r: -r["score"])[:count]
            if got:
                ests[(im, obj)] = got
    return SimpleNamespace(info=info, verts=verts, sym_ssp=sym_ssp, sym_tk=sym_tk, gt=gt,
                           gt_info=gt_info, cams=cams, targets=targets, ests=ests)  # fmt: skip


def _pose(R, t_mm) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float).reshape(3, 3)
    T[:3, 3] = np.asarray(t_mm, dtype=float).reshape(3) / 1000.0
    return T


def _pairs(lmo):
    """(im, obj, est rank, est row, gt id, gt entry) of every estimate and same-class gt."""
    for (im, obj), got in sorted(lmo.ests.items()):
        for e, row in enumerate(got):
            for g, entry in enumerate(lmo.gt[im]):
                if entry["obj_id"] == obj:
                    yield im, obj, e, row, g, entry


def test_mssd_and_mspd_per_pair_agree_with_the_toolkit(toolkit, lmo):
    d_mssd: dict[bool, list[float]] = {True: [], False: []}
    d_mspd: dict[bool, list[float]] = {True: [], False: []}
    n = 0
    for im, obj, _, row, _, entry in _pairs(lmo):
        R_g = np.asarray(entry["cam_R_m2c"], dtype=float).reshape(3, 3)
        t_g = np.asarray(entry["cam_t_m2c"], dtype=float).reshape(3, 1)
        K = np.asarray(lmo.cams[im]["cam_K"], dtype=float).reshape(3, 3)
        pts = lmo.verts[obj]
        tk_mssd = toolkit.pose_error.mssd(row["R"], row["t"].reshape(3, 1), R_g, t_g, pts,
                                          lmo.sym_tk[obj])  # fmt: skip
        tk_mspd = toolkit.pose_error.mspd(row["R"], row["t"].reshape(3, 1), R_g, t_g, K, pts,
                                          lmo.sym_tk[obj])  # fmt: skip
        syms = bop_symmetries(lmo.sym_ssp[obj])
        T_e, T_g = _pose(row["R"], row["t"]), _pose(R_g, t_g)
        cam = Camera(640, 480, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        ours_mssd = 1000.0 * mssd(T_e, T_g, pts / 1000.0, syms)
        ours_mspd = mspd(T_e, T_g, pts / 1000.0, syms, cam, np.eye(4))
        snapped = len(lmo.info[obj].get("symmetries_discrete", [])) > 0
        d_mssd[snapped].append(abs(ours_mssd - tk_mssd) / lmo.info[obj]["diameter"])
        d_mspd[snapped].append(abs(ours_mspd - tk_mspd))
        n += 1
    assert n > 1000 and d_mssd[True] and d_mssd[False]
    # the same formula: measured 5e-13 mm and 2e-13 px on the six objects without symmetries
    assert max(d_mssd[False]) < 1e-9 and max(d_mspd[False]) < 1e-9
    # ssp snaps the eggbox's 179.81 and the glue's 178.47 deg turns to half turns: measured
    # 0.80 mm (0.45 % of the glue's diameter; thresholds step by 5 %) and 0.27 px (steps: 5 px)
    assert max(d_mssd[True]) < 0.01
    assert max(d_mspd[True]) < 1.0


def _toolkit_recalls(toolkit, lmo, error: str, thresholds) -> list[float]:
    """Recall per threshold by the toolkit's matching and scoring (eval_calc_scores)."""
    errs = []
    for im, obj, e, row, g, entry in _pairs(lmo):
        R_g = np.asarray(entry["cam_R_m2c"], dtype=float).reshape(3, 3)
        t_g = np.asarray(entry["cam_t_m2c"], dtype=float).reshape(3, 1)
        t_e = row["t"].reshape(3, 1)
        if error == "mssd":
            v = toolkit.pose_error.mssd(row["R"], t_e, R_g, t_g, lmo.verts[obj], lmo.sym_tk[obj])
            v /= lmo.info[obj]["diameter"]
        else:
            K = np.asarray(lmo.cams[im]["cam_K"], dtype=float).reshape(3, 3)
            v = toolkit.pose_error.mspd(row["R"], t_e, R_g, t_g, K, lmo.verts[obj],
                                        lmo.sym_tk[obj])  # fmt: skip
        if not errs or (errs[-1]["im_id"], errs[-1]["obj_id"], errs[-1]["est_id"]) != (im, obj, e):
            errs.append({"im_id": im, "obj_id": obj, "est_id": e, "score": row["score"],
                         "errors": {}, "gt_visib_fracts": {}})  # fmt: skip
        errs[-1]["errors"][g] = [v]
        errs[-1]["gt_visib_fracts"][g] = lmo.gt_info[im][g]["visib_fract"]
    gts = {im: lmo.gt[im] for im in lmo.targets}
    valid = {}
    for im, objs in lmo.targets.items():  # visib_gt_min = -1: the inst_count most visible
        left = dict(objs)
        order = sorted(range(len(gts[im])), key=lambda g: -lmo.gt_info[im][g]["visib_fract"])
        valid[im] = [False] * len(gts[im])
        for g in order:
            o = gts[im][g]["obj_id"]
            if left.get(o, 0) > 0:
                valid[im][g], left[o] = True, left[o] - 1
    infos = {im: lmo.gt_info[im] for im in lmo.targets}
    recalls = []
    for th in thresholds:
        matches = toolkit.matching.match_poses_scene(SCENE, gts, infos, valid, errs, [th], -1)
        scores = toolkit.score.calc_localization_scores(
            [SCENE], sorted(lmo.info), matches, -1, do_print=False
        )
        recalls.append(scores["recall"])
    return recalls


def _ssp_result(lmo, use_targets: bool = True) -> dict:
    """``ssp evaluate``'s evaluator on the same frames (ground truth through ssp's reader),
    with the dataset's test targets (:func:`ssp.io.bop.read_targets`) or without."""
    targets = read_targets(LMO)
    library = {}
    for i, v in lmo.verts.items():
        mesh = trimesh.Trimesh(v / 1000.0, process=False)
        library[f"obj_{i:06d}"] = SimpleNamespace(
            mesh=mesh, hull_vertices=mesh.vertices, diameter=lmo.info[i]["diameter"] / 1000.0,
            symmetry=lmo.sym_ssp[i])  # fmt: skip
    scene = open_bop(LMO / "test" / f"{SCENE:06d}")
    ev = BopEvaluator(library, vsd=False)
    rows: dict[int, list] = {}
    for r in read_bop_csv(CSV):
        if r["scene_id"] == SCENE:
            rows.setdefault(r["im_id"], []).append(r)
    for k, im in enumerate(scene.im_ids):
        f = scene.load(k, masks=None, depth=False)
        ests = [(f"obj_{r['obj_id']:06d}", _pose(r["R"], r["t"]), r["score"])
                for r in rows.get(im, [])]  # fmt: skip
        tg = None
        if use_targets:
            tg = {f"obj_{o:06d}": c for o, c in (targets or {}).get((SCENE, im), {}).items()}
        ev.add_frame(f.gt, f.visib_fract, ests, f.camera, np.eye(4), targets=tg)
    return ev.result()


def test_recall_and_ar_agree_with_the_toolkit(toolkit, lmo):
    ours = _ssp_result(lmo)
    tk_mssd = _toolkit_recalls(toolkit, lmo, "mssd", MSSD_THRESHOLDS)
    tk_mspd = _toolkit_recalls(toolkit, lmo, "mspd", MSPD_THRESHOLDS)
    assert ours["targets"] == sum(c for objs in lmo.targets.values() for c in objs.values())
    # measured (1,445 targets): AR_MSSD 0.4914 (ssp) / 0.4911 (toolkit), AR_MSPD 0.6028 /
    # 0.6027; per threshold at most 3 targets apart (pairs of the snapped eggbox and glue that
    # sit on a threshold)
    few = 4.0 / ours["targets"]
    assert np.abs(np.subtract(ours["recall_MSSD"], tk_mssd)).max() <= few
    assert np.abs(np.subtract(ours["recall_MSPD"], tk_mspd)).max() <= few
    assert math.isclose(ours["AR_MSSD"], float(np.mean(tk_mssd)), abs_tol=1e-3)
    assert math.isclose(ours["AR_MSPD"], float(np.mean(tk_mspd)), abs_tol=1e-3)
    # without the targets file ssp takes every instance at least 10 % visible: 29 more
    assert _ssp_result(lmo, use_targets=False)["targets"] == ours["targets"] + 29
