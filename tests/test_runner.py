"""``ssp run``: BOP scenes and cloud folders in, per-frame JSON, BOP19 CSV and a summary out."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ssp.eval.metrics import pose_error
from ssp.geometry import invert
from ssp.io.clouds import write_cloud
from ssp.io.hypotheses import write_hypotheses
from ssp.io.results import read_bop_csv
from ssp.pipeline.run import run
from ssp.scene import Hypothesis
from ssp.sim.bop import simulate_to_disk
from ssp.sim.generate import generate_sequence


@pytest.fixture(scope="module")
def seq(lib):
    return generate_sequence(
        "structure", 3, lib, stages=2, frames_per_stage=2, stride=2, n_objects=5
    )


def test_bop_scene_with_given_hypotheses(lib, tmp_path):
    (scene,) = simulate_to_disk(
        "structure",
        1,
        4,
        out_dir=tmp_path,
        library=lib,
        stages=2,
        frames_per_stage=1,
        stride=4,
        n_objects=4,
    )
    seen = []
    summary = run(scene, lib, tmp_path / "out", progress=lambda d, t, m: seen.append((d, t)))
    assert summary.kind == "bop" and summary.frames == 2
    assert len(summary.done) == 2 and not summary.failed
    assert seen == [(1, 2), (2, 2)]
    out = tmp_path / "out"
    rows = read_bop_csv(out / "ssp_000000-test.csv")
    assert len(rows) == sum(d["objects"] for d in summary.done) > 0
    ids = json.loads((out / "obj_ids.json").read_text())
    classes = {ids["obj_ids"][str(r["obj_id"])] for r in rows}
    assert classes <= {"cube", "block"}
    rec = json.loads((out / "frames" / "000001.json").read_text())
    assert rec["objects"] and {"R", "t", "quat_xyzw", "mode", "terms"} <= set(rec["objects"][0])
    assert json.loads((out / "summary.json").read_text())["done"] == 2


def _camera_cloud(seq, i):
    """Frame ``i`` as a camera-frame cloud with instance labels (0 = background)."""
    f = seq.frames[i]
    depth = np.asarray(f.depth, dtype=float)
    ok = depth.reshape(-1) > 0
    pts = seq.camera.backproject(depth).reshape(-1, 3)[ok]
    inst = np.asarray(f.instance).reshape(-1)[ok].astype(np.int64)
    return pts, np.where(inst >= 0, inst + 1, 0)


def test_cloud_folder_estimated_with_bad_frames(lib, seq, tmp_path):
    """Clouds in the camera frame, no camera pose (the table gives it), labels; a truncated and
    a millimetre cloud are reported and skipped, an unlabelled cloud is clustered, and the good
    frames still come out right."""
    src = tmp_path / "in"
    src.mkdir()
    for i in range(len(seq)):
        pts, lab = _camera_cloud(seq, i)
        write_cloud(src / f"frame{i}.ply", pts, labels=lab)
    (src / "frame10.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9")
    write_cloud(src / "frame11.pcd", *_camera_cloud(seq, 0)[:1], labels=None)
    pts, lab = _camera_cloud(seq, 0)
    write_cloud(src / "frame12.ply", pts * 1000.0, labels=lab)  # millimetres
    (src / "scene.json").write_text(json.dumps({"frame": "camera", "period": 0.5}))
    summary = run(src, lib, tmp_path / "out", classes=list(seq.models))
    done = [d["frame"] for d in summary.done]
    failed = {f["frame"]: f["error"] for f in summary.failed}
    assert done[: len(seq)] == [f"frame{i}" for i in range(len(seq))]
    assert "frame10" in failed and "frame12" in failed
    assert "frame11" in done  # no labels: plane removal and clustering
    assert "millimetres" in failed["frame12"] or "mm" in failed["frame12"]
    # the last good frame: every visible object found within 5 mm (camera frame)
    rec = json.loads((tmp_path / "out" / "frames" / f"frame{len(seq) - 1}.json").read_text())
    T_cw = invert(np.asarray(rec["T_world_cam"]))
    sf = seq.frames[-1]
    for gid, (cls, T) in sf.gt.items():
        if sf.visib_fract[gid] < 0.3:
            continue
        T_cam_gt = invert(seq.T_world_cam) @ T
        errs = [
            pose_error(T_cam_gt, T_cw @ np.asarray(o["T_world_obj"]), lib[cls].symmetry)[0]
            for o in rec["objects"]
            if o["class"] == cls
        ]
        assert errs and min(errs) < 5.0, (gid, errs)


def test_cloud_folder_given_hypotheses(lib, seq, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    pts, lab = _camera_cloud(seq, 0)
    write_cloud(src / "a.pcd", pts, labels=lab)
    T_cw = invert(seq.T_world_cam)
    hyps = [Hypothesis(c, T_cw @ T) for c, T in seq.frames[0].gt.values()]
    write_hypotheses(src / "a.hypotheses.json", hyps, frame="camera")
    (src / "scene.json").write_text(json.dumps({"T_world_cam": seq.T_world_cam.tolist()}))
    summary = run(src, lib, tmp_path / "out", hypotheses="given")
    assert len(summary.done) == 1 and summary.done[0]["hypotheses"] == len(hyps)
    # without a hypotheses file, "given" fails that frame and says why
    write_cloud(src / "b.pcd", pts, labels=lab)
    summary = run(src, lib, tmp_path / "out2", hypotheses="given")
    assert [f["frame"] for f in summary.failed] == ["b"]
    assert "hypotheses" in summary.failed[0]["error"]
