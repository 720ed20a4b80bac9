"""The RGB-estimator stream (ssp.sim.rgb_stream, RealisticNoise.rgb) and its calibration on a
real estimator's results (ssp.eval.rgb_calibration)."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ssp.errors import ArgumentError
from ssp.eval.rgb_calibration import calibrate_rgb, write_rgb_calibration
from ssp.sim.generate import default_camera_pose
from ssp.sim.realistic import RealisticNoise, RealisticStream
from ssp.sim.rgb_stream import MEGAPOSE_LMO, RgbErrors

LMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lmo-megapose"
EDGE = 0.0508


def _grid(n: int, spacing: float = 0.3) -> dict:
    """``n`` cubes far apart (independent objects), resting, turned about z."""
    gt = {}
    for i in range(n):
        T = np.eye(4)
        a = 0.7 * i
        T[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
        T[:3, 3] = [spacing * (i % 40 - 20), spacing * (i // 40), EDGE / 2]
        gt[f"o{i}"] = ("cube", T)
    return gt


def _errors(lib, gt, drawn, T_wc):
    """Per object (first = best-scored hypothesis): along-ray (signed), lateral (mm),
    rotation (deg, up to the cube's symmetries) of its best hypothesis; None when missed."""
    from ssp.probability import pose_change

    best = {}
    for d in drawn:  # best score first
        best.setdefault(d.source, d.hypothesis)
    cam = T_wc[:3, 3]
    model = lib["cube"]
    c = np.asarray(model.center_of_mass)
    out = {}
    for oid, (_, T) in gt.items():
        h = best.get(oid)
        if h is None:
            out[oid] = None
            continue
        p = T[:3, :3] @ c + T[:3, 3]
        u = (p - cam) / np.linalg.norm(p - cam)
        e = 1000.0 * (h.T_world_obj[:3, :3] @ c + h.T_world_obj[:3, 3] - p)
        along = float(e @ u)
        rot = math.degrees(pose_change(T, h.T_world_obj, model.symmetry)[1])
        out[oid] = (along, float(np.linalg.norm(e - along * u)), rot)
    return out


def test_stream_statistics_match_the_calibration(lib):
    """Many independent objects, one frame: miss and far rates, the along-ray error's
    quantiles (relative to the ray from the camera), the lateral and rotation medians are the
    tables' (0.9-1 visible bin)."""
    T_wc = default_camera_pose()
    noise = RealisticNoise.rgb()
    e = noise.rgb_errors
    gt = _grid(2400)
    stream = RealisticStream(lib, noise, 3, classes=["cube"], T_world_cam=T_wc)
    errs = _errors(lib, gt, stream.draw(0, gt, {k: 0.95 for k in gt}), T_wc)
    k = e.bin(0.95)
    got = [v for v in errs.values() if v is not None]
    assert 1 - len(got) / len(errs) == pytest.approx(e.miss[k], abs=0.015)
    far = np.array([math.hypot(a, b) > 100 for a, b, _ in got])
    assert far.mean() == pytest.approx(e.far[k], abs=0.015)
    near = np.array([v for v, f in zip(got, far, strict=True) if not f])
    for q in (0.1, 0.25, 0.5, 0.75, 0.9):
        want = e.quantile(e.along_mm[k], q)
        assert np.quantile(near[:, 0], q) == pytest.approx(want, abs=2.5)
    assert np.median(near[:, 1]) == pytest.approx(e.quantile(e.lateral_mm[k], 0.5), rel=0.1)
    # the cube's symmetries hide part of the flips; the small turns' median stands
    small = near[near[:, 2] < 30, 2]
    assert np.median(small) == pytest.approx(e.quantile(e.rotation_deg[k], 0.5), rel=0.15)
    # the error is along the ray: depth spread much wider than the lateral one
    assert np.median(np.abs(near[:, 0])) > 2.0 * np.median(near[:, 1])


def test_lower_visibility_is_missed_and_far_more_often(lib):
    T_wc = default_camera_pose()
    e = RealisticNoise.rgb().rgb_errors
    gt = _grid(1200)
    stream = RealisticStream(lib, RealisticNoise.rgb(), 5, classes=["cube"], T_world_cam=T_wc)
    errs = _errors(lib, gt, stream.draw(0, gt, {k: 0.6 for k in gt}), T_wc)
    got = [v for v in errs.values() if v is not None]
    k = e.bin(0.6)
    assert 1 - len(got) / len(errs) == pytest.approx(e.miss[k], abs=0.04)
    assert np.mean([math.hypot(a, b) > 100 for a, b, _ in got]) == pytest.approx(e.far[k], abs=0.04)
    assert e.miss[k] > 3 * e.miss[e.bin(0.95)]


def test_rows_per_object_and_scores(lib):
    noise = RealisticNoise.rgb()
    e = noise.rgb_errors
    gt = _grid(1500)
    stream = RealisticStream(lib, noise, 9, classes=["cube"], T_world_cam=default_camera_pose())
    drawn = stream.draw(0, gt, {k: 1.0 for k in gt})
    per = {}
    for d in drawn:
        per.setdefault(d.source, []).append(d)
    counts = np.bincount([len(v) for v in per.values()], minlength=6)[1:6] / len(per)
    assert counts == pytest.approx(np.asarray(e.rows), abs=0.03)
    # the object's first (nominal) hypothesis outscores its extra detections
    for hs in per.values():
        assert all(h.hypothesis.score <= hs[0].hypothesis.score for h in hs)
    right = [hs[0].hypothesis.score for hs in per.values() if hs[0].kind == "nominal"]
    assert np.median(right) > 0.98


def test_error_persists_over_a_static_view_and_is_redrawn_when_the_object_moves(lib):
    T_wc = default_camera_pose()
    gt = _grid(300)
    stream = RealisticStream(lib, RealisticNoise.rgb(), 2, classes=["cube"], T_world_cam=T_wc)
    visib = {k: 1.0 for k in gt}
    frames = [_errors(lib, gt, stream.draw(i, gt, visib), T_wc) for i in range(2)]
    pairs = np.array(
        [
            (a[0], b[0])
            for a, b in zip(frames[0].values(), frames[1].values(), strict=True)
            if a is not None and b is not None and abs(a[0]) < 100 and abs(b[0]) < 100
        ]
    )
    assert np.corrcoef(pairs.T)[0, 1] > 0.7  # consistent between frames
    moved = {k: (c, T @ _shift(0.05)) for k, (c, T) in gt.items()}
    after = _errors(lib, moved, stream.draw(2, moved, visib), T_wc)
    pairs = np.array(
        [
            (a[0], b[0])
            for a, b in zip(frames[1].values(), after.values(), strict=True)
            if a is not None and b is not None and abs(a[0]) < 100 and abs(b[0]) < 100
        ]
    )
    assert abs(np.corrcoef(pairs.T)[0, 1]) < 0.3  # a new view: a new error


def _shift(dx: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = dx
    return T


def test_rgb_stream_is_deterministic_and_needs_the_camera(lib):
    gt = _grid(20)
    visib = {k: 0.8 for k in gt}

    def run(seed):
        s = RealisticStream(
            lib, RealisticNoise.rgb(), seed, classes=["cube"], T_world_cam=default_camera_pose()
        )
        return [
            [
                (d.source, d.kind, d.hypothesis.score, d.hypothesis.T_world_obj)
                for d in s.draw(i, gt, visib)
            ]
            for i in range(3)
        ]

    a, b, c = run(4), run(4), run(5)
    assert len(a[0]) == len(b[0])
    for fa, fb in zip(a, b, strict=True):
        for x, y in zip(fa, fb, strict=True):
            assert x[:3] == y[:3] and np.array_equal(x[3], y[3])
    assert [x[2] for x in a[0]] != [x[2] for x in c[0]]
    with pytest.raises(ArgumentError):
        RealisticStream(lib, RealisticNoise.rgb(), 0, classes=["cube"])


def test_default_stream_is_unchanged(lib):
    """The default stream's draws and settings are those of the code before the RGB stream
    (the digest was computed with it): Table I realistic stays bit-identical."""
    gt = {"a": ("cube", _shift(0.0) @ _up(0.0254)), "b": ("block", _shift(0.1) @ _up(0.0127))}
    s = RealisticStream(lib, RealisticNoise(), 7, classes=["block", "cube"])
    h = hashlib.sha256()
    for i in range(12):
        for d in s.draw(i, gt, {"a": 1.0, "b": 0.6}):
            h.update(np.round(d.hypothesis.T_world_obj, 9).tobytes())
            h.update(f"{d.hypothesis.score:.9f}{d.kind}{d.source}".encode())
    assert h.hexdigest() == "1f142eb67ee075e1b2f9d1948f973e5eda2015cdc7169226821685e37d6c0360"
    assert "rgb_errors" not in RealisticNoise().to_dict()
    assert tuple(RealisticNoise.rgb().to_dict()["rgb_errors"]["miss"]) == MEGAPOSE_LMO["miss"]


def _up(z: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = z
    return T


# ------------------------------------------------------------------------------ calibration
def _rot(axis, deg) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float)).as_matrix()


def _synthetic(tmp_path: Path) -> Path:
    """A 2-object dataset: obj 1 with an inexact published half-turn symmetry about z."""
    root = tmp_path / "data"
    (root / "models").mkdir(parents=True)
    (root / "test" / "000001").mkdir(parents=True)
    S = np.eye(4)
    S[:3, :3] = _rot([0, 0, 1], 179.8)
    info = {"1": {"diameter": 100.0, "symmetries_discrete": [S.ravel().tolist()]},
            "2": {"diameter": 100.0}}  # fmt: skip
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    gt, ginfo, rows = {}, {}, ["scene_id,im_id,obj_id,score,R,t,time"]
    for im in range(4):
        t1, t2 = np.array([0.0, 0.0, 1000.0]), np.array([100.0, 0.0, 1000.0])
        R = _rot([1, 0, 0], 10 * im)
        gt[str(im)] = [
            {"cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": t1.tolist(), "obj_id": 1},
            {"cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": t2.tolist(), "obj_id": 2},
        ]
        ginfo[str(im)] = [{"visib_fract": 0.95}, {"visib_fract": 0.95 if im < 3 else 0.05}]

        def row(obj, Rr, t, score, im=im):
            return (f"1,{im},{obj},{score},{' '.join(map(str, Rr.ravel()))},"
                    f"{' '.join(map(str, t))},-1")  # fmt: skip

        # obj 1: the symmetric equivalent (a half turn about z), 20 mm too far, 3 mm across
        rows.append(row(1, R @ _rot([0, 0, 1], 180.0), t1 + [3.0, 0.0, 20.0], 0.99))
        if im < 3:  # obj 2: 10 mm too close; in image 1 a far extra row; image 3: missed
            rows.append(row(2, R @ _rot([0, 1, 0], 5.0), t2 * (1 - 10 / np.linalg.norm(t2)), 0.9))
        if im == 1:
            rows.append(row(2, R, t2 + [0.0, 0.0, 400.0], 0.2))
    (root / "test" / "000001" / "scene_gt.json").write_text(json.dumps(gt))
    (root / "test" / "000001" / "scene_gt_info.json").write_text(json.dumps(ginfo))
    (root / "est_lmo-test.csv").write_text("\n".join(rows) + "\n")
    return root


def test_calibration_on_a_synthetic_case(tmp_path):
    r = calibrate_rgb(_synthetic(tmp_path))
    assert r["targets"] == 7 and r["missed"] == 0  # image 3's obj 2 is 5 % visible
    o = r["overall"]
    assert o["far_rate"] == 0
    # obj 1: +20 mm along, 3 mm across, no rotation error up to its (inexact) symmetry
    assert r["per_bin"][-1]["near"]["along_mm_q"][-1] == pytest.approx(20.0, abs=1e-3)
    assert r["per_bin"][-1]["near"]["along_mm_q"][0] == pytest.approx(-10.0, abs=1e-3)
    assert o["rotation_over_30deg"] == 0
    assert o["near"]["rotation_small_deg_q"][-1] == pytest.approx(5.0, abs=0.01)
    assert o["near"]["rotation_small_deg_q"][0] < 0.5  # the 179.8 deg symmetry taken as a half turn
    assert r["per_bin"][0]["miss_rate"] == 1.0  # obj 2 in image 3, 5 % visible: no row
    assert r["rows"]["rows_per_detected_target"] == {"1": 6, "2": 1, "3": 0, "4": 0, "5": 0}
    assert r["rows"]["extra_far"] == 1.0
    errs = RgbErrors.from_calibration(r)
    assert errs.miss[-1] == 0.0 and errs.rows[0] == pytest.approx(6 / 7, abs=1e-3)
    files = write_rgb_calibration(r, tmp_path / "out")
    assert json.loads(files[0].read_text())["targets"] == 7
    assert "targets" in files[1].read_text()


@pytest.mark.skipif(not LMO.is_dir(), reason="../shared/data/lmo-megapose is absent")
def test_calibration_on_megapose_lmo_gives_the_preset():
    r = calibrate_rgb(LMO)
    assert r["targets"] == 1466 and r["missed"] == 273
    o = r["overall"]
    assert o["along_abs_median_mm"] == pytest.approx(14.1, abs=0.1)
    assert o["along_abs_p75_mm"] == pytest.approx(34.7, abs=0.1)
    assert o["along_over_10mm"] == pytest.approx(0.60, abs=0.01)
    assert o["lateral_median_mm"] == pytest.approx(5.1, abs=0.1)
    assert r["flips"]["aligned_over_0.95"] > 3 * r["flips"]["random_aligned_over_0.95"]
    assert RgbErrors.from_calibration(r) == RgbErrors.megapose_lmo()


def test_rgb_estimates_csv_of_a_simulated_dataset(tmp_path, lib):
    """``ssp estimate --noise rgb``'s CSV: rows in the camera frame near the ground truth
    (t in mm), scores in [0, 1], the same file for the same seed, another for another."""
    from ssp.io.bop import open_bop
    from ssp.io.results import read_bop_csv
    from ssp.sim.bop import simulate_to_disk
    from ssp.sim.rgb_csv import rgb_estimates

    (scene,) = simulate_to_disk(
        "structure", 1, 5, out_dir=tmp_path, stages=1, frames_per_stage=3, stride=8, library=lib
    )
    a, b, c = (tmp_path / f"rgb{k}_sim-test.csv" for k in "abc")
    rep = rgb_estimates(scene, lib, a, seed=1)
    rgb_estimates(scene, lib, b, seed=1)
    rgb_estimates(scene, lib, c, seed=2)
    assert a.read_bytes() == b.read_bytes() and a.read_bytes() != c.read_bytes()
    rows = read_bop_csv(a)
    assert rep["images"] == 3 and rep["rows"] == len(rows) > 0
    assert all(0.0 <= r["score"] <= 1.0 for r in rows)
    f = open_bop(scene, lib).load(0, masks=None)
    truth = [1000.0 * T[:3, 3] for _, T in f.gt.values()]
    best = [r for r in rows if r["im_id"] == f.im_id]
    near = [min(np.linalg.norm(r["t"] - t) for t in truth) for r in best]
    assert np.median(near) < 100.0  # mm: most rows are at an object, in the camera frame


def test_rgb_estimates_refuse_a_scene_without_ground_truth(tmp_path, lib):
    """No scene_gt.json: an InputError naming the scene, and no CSV written."""
    from ssp.errors import InputError
    from ssp.sim.bop import simulate_to_disk
    from ssp.sim.rgb_csv import rgb_estimates

    (scene,) = simulate_to_disk(
        "structure", 1, 5, out_dir=tmp_path, stages=1, frames_per_stage=1, stride=8, library=lib
    )
    (scene / "scene_gt.json").unlink()
    out = tmp_path / "rgb_sim-test.csv"
    with pytest.raises(InputError, match=r"no scene_gt.json"):
        rgb_estimates(scene, lib, out, seed=0)
    assert not out.exists()


def test_calibration_reads_continuous_symmetries_as_the_toolkit():
    """A cylinder's rotation about its axis is no error (not a flip): the continuous axis is
    sampled every 5 deg, composed with the discrete symmetries."""
    from scipy.spatial.transform import Rotation

    from ssp.eval.rgb_calibration import _row_error, _symmetries

    syms = _symmetries(
        {
            "1": {
                "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
                "symmetries_discrete": [np.diag([1.0, -1.0, -1.0, 1.0]).ravel()],
            }
        }
    )
    assert len(syms[1]) == 2 * 72
    turn = Rotation.from_euler("zx", [37.0, 180.0], degrees=True).as_matrix()
    err = _row_error(np.eye(3), np.array([0.0, 0.0, 800.0]), syms[1], turn, [0.0, 0.0, 800.0])
    assert err["rot"] < 2.6  # within half a 5 deg step
