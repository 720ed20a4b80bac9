"""TUM trajectories of a run's objects (ssp.io.tum), read back by evo when it is installed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.errors import InputError
from ssp.estimate import ObjectEstimate, SceneEstimate
from ssp.io.results import frame_record, write_json
from ssp.io.tum import TumWriter, read_frame_records, tum_line, write_tum
from ssp.scene import TransitionMode


def _pose(euler, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", euler).as_matrix()
    T[:3, 3] = t
    return T


# frame index -> (stamp, {id: pose}); frame 2 fails
FRAMES = {
    0: (0.0, {"cube_0": _pose((0.1, 0.2, 0.3), (0.1, 0.0, 0.02))}),
    1: (0.1, {"cube_0": _pose((0.1, 0.2, 0.35), (0.11, 0.0, 0.02)),
              "mug/1": _pose((0.0, 0.0, 3.0), (-0.2, 0.1, 0.05))}),
    3: (0.3, {"cube_0": _pose((2.0, -1.0, 0.5), (0.3, -0.1, 0.02)),
              "mug/1": _pose((0.0, 0.0, -2.5), (-0.2, 0.12, 0.05))}),
}  # fmt: skip


def _run_dir(tmp_path):
    out = tmp_path / "out"
    for i, (stamp, poses) in FRAMES.items():
        objs = tuple(
            ObjectEstimate(oid, oid.split("_")[0].split("/")[0], T, TransitionMode.STATIC)
            for oid, T in poses.items()
        )
        gone = ObjectEstimate("old_9", "old", np.eye(4), TransitionMode.REMOVED, source="removed")
        est = SceneEstimate(stamp=stamp, frame_index=i, objects=objs, removed=(gone,))
        rec = frame_record(est, name=f"f{i:02d}", index=i, extra={"status": "done"})
        write_json(out / "frames" / f"f{i:02d}.json", rec)
    failed = {"name": "f02", "index": 2, "status": "failed", "error": "x", "warnings": []}
    write_json(out / "frames" / "f02.json", failed)
    return out


def _expected(oid):
    return [(stamp, poses[oid]) for stamp, poses in FRAMES.values() if oid in poses]


def _parse(path):
    """Our own reading of a TUM file: (stamps, 4x4 poses)."""
    rows = [ln.split() for ln in path.read_text().splitlines() if not ln.startswith("#")]
    mat = np.array(rows, dtype=float)
    assert mat.shape[1] == 8
    poses = []
    for r in mat:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(r[4:8]).as_matrix()  # x, y, z, w
        T[:3, 3] = r[1:4]
        poses.append(T)
    return mat[:, 0], poses


def test_write_tum_one_file_per_object(tmp_path):
    out = _run_dir(tmp_path)
    (out / "tum").mkdir()
    (out / "tum" / "stale.txt").write_text("0 0 0 0 0 0 0 1\n")
    files = write_tum(out)
    assert {k: p.name for k, p in files.items()} == {"cube_0": "cube_0.txt", "mug/1": "mug_1.txt"}
    assert sorted(p.name for p in (out / "tum").iterdir()) == ["cube_0.txt", "mug_1.txt"]
    for oid, p in files.items():
        stamps, poses = _parse(p)
        exp = _expected(oid)
        np.testing.assert_array_equal(stamps, [s for s, _ in exp])  # failed frame 2: no line
        for T, (_, T_exp) in zip(poses, exp, strict=True):
            np.testing.assert_allclose(T, T_exp, atol=1e-12)
    head = files["mug/1"].read_text().splitlines()[0]
    assert head.startswith("# ssp object mug/1 (class mug): timestamp tx ty tz qx qy qz qw")


def test_evo_reads_the_files_back(tmp_path):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    files = write_tum(_run_dir(tmp_path))
    for oid, p in files.items():
        traj = file_interface.read_tum_trajectory_file(str(p))
        exp = _expected(oid)
        np.testing.assert_array_equal(traj.timestamps, [s for s, _ in exp])
        for T, (_, T_exp) in zip(traj.poses_se3, exp, strict=True):
            np.testing.assert_allclose(T, T_exp, atol=1e-12)


def test_tum_writer_appends_per_frame_as_write_tum_writes(tmp_path):
    out = _run_dir(tmp_path)
    whole = {k: p.read_text() for k, p in write_tum(out).items()}
    w = TumWriter(tmp_path / "inc")
    for rec in read_frame_records(out):
        w.add(rec)
    assert {k: w.path(k).read_text() for k in whole} == whole
    # a second writer with fresh=False continues the files
    w2 = TumWriter(tmp_path / "inc", fresh=False)
    rec = read_frame_records(out)[-1]
    rec["stamp"] = 0.4
    w2.add(rec)
    assert w2.path("cube_0").read_text().splitlines()[-1].startswith("0.4 ")
    assert len(w2.path("cube_0").read_text().splitlines()) == 1 + 4


def test_tum_line_and_bad_records(tmp_path):
    T = _pose((0.0, 0.0, np.pi / 2), (1.0, 2.0, 3.0))
    vals = [float(v) for v in tum_line(12.5, T).split()]
    np.testing.assert_allclose(vals, [12.5, 1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    with pytest.raises(InputError, match="no finite 'stamp'"):
        write_tum(tmp_path, [{"name": "a", "index": 0, "stamp": None, "objects": []}])
    with pytest.raises(InputError, match=r"objects\[0\]: no 'id'"):
        write_tum(tmp_path, [{"name": "a", "index": 0, "stamp": 0.0, "objects": [{"id": "x"}]}])
    with pytest.raises(InputError, match="no such folder"):
        read_frame_records(tmp_path / "nothing")
    (tmp_path / "run" / "frames").mkdir(parents=True)
    (tmp_path / "run" / "frames" / "f.json").write_text("{")
    with pytest.raises(InputError, match=r"f.json: cannot read the frame record"):
        write_tum(tmp_path / "run")
