"""``ssp run`` on a camera with no pose given (ssp.pipeline.world; issue 32): the camera is
located frame by frame in the first frame's table frame, a static one keeps that frame
exactly, a camera it cannot locate starts the world frame again (said, the scene forgotten),
and a stopped run resumes to the uninterrupted run's results."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ssp.io.bop import open_bop
from ssp.perception.egomotion import CameraNotLocatedError, CameraTracker
from ssp.pipeline.run import run
from ssp.pipeline.summary import without_timings
from ssp.pipeline.world import RESTARTED
from ssp.sim.bop import simulate_to_disk

SCENE = dict(stages=1, frames_per_stage=8, stride=2, n_objects=6)


def _scene(lib, root: Path, camera_path: str, camera_pose: bool) -> Path:
    (path,) = simulate_to_disk("structure", 1, 7, out_dir=root, library=lib,
                               camera_path=camera_path, camera_pose=camera_pose,
                               **SCENE)  # fmt: skip
    return path


@pytest.fixture(scope="module")
def orbit(lib, tmp_path_factory):
    """The same orbit written without and with its camera poses (the truth)."""
    root = tmp_path_factory.mktemp("orbit")
    return _scene(lib, root / "bare", "orbit", False), _scene(lib, root / "posed", "orbit", True)


@pytest.fixture(scope="module")
def orbit_run(lib, orbit, tmp_path_factory):
    out = tmp_path_factory.mktemp("orbit-run") / "out"
    summary = run(orbit[0], lib, out)
    assert len(summary.done) == summary.frames == 8
    return out


def _frames(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / "frames").iterdir())]


def _truth(posed: Path) -> list[np.ndarray]:
    scene = open_bop(posed)
    return [scene.load(k, depth=False, masks=None).T_world_cam for k in range(len(scene))]


def test_a_scene_without_camera_poses_is_written_as_published(orbit):
    bare, posed = orbit
    cams = json.loads((bare / "scene_camera.json").read_text())
    assert all("cam_R_w2c" not in c and "cam_t_w2c" not in c for c in cams.values())
    assert not open_bop(bare).has_world and open_bop(posed).has_world
    assert open_bop(bare).hypotheses_frame == "camera"
    assert open_bop(posed).hypotheses_frame == "world"
    # the same hypotheses, in the camera frame
    b = open_bop(bare).load(4, depth=False, masks=None)
    p = open_bop(posed).load(4, depth=False, masks=None)
    T_cw = np.linalg.inv(p.T_world_cam)
    for hb, hp in zip(b.hypotheses, p.hypotheses, strict=True):
        np.testing.assert_allclose(hb.T_world_obj, T_cw @ hp.T_world_obj, atol=1e-9)


def test_an_orbiting_camera_is_followed_not_taken_for_moving_objects(orbit, orbit_run):
    """Each frame's camera in the run's world frame agrees with the truth within 3 mm at the
    objects; the objects' world poses stay put (no object reported moved by the camera)."""
    frames = _frames(orbit_run)
    truth = _truth(orbit[1])
    assert frames[0]["camera"]["how"] == "table"
    assert {f["camera"]["how"] for f in frames[1:]} <= {"tracked", "searched"}
    align = truth[0] @ np.linalg.inv(np.asarray(frames[0]["T_world_cam"]))
    for f, T_true in zip(frames, truth, strict=True):
        D = align @ np.asarray(f["T_world_cam"]) @ np.linalg.inv(T_true)
        c = np.array([align @ np.asarray(o["T_world_obj"]) for o in f["objects"]])[:, :3, 3]
        err = np.linalg.norm(c @ D[:3, :3].T + D[:3, 3] - c, axis=1).max()
        assert err < 0.003, (f["name"], err)
        assert f["camera"]["how"] == "table" or f["camera"]["points"] > 0
    # objects seen in several frames stay within a few mm in the world
    where: dict[str, list] = {}
    for f in frames:
        for o in f["objects"]:
            where.setdefault(o["id"], []).append(np.asarray(o["T_world_obj"])[:3, 3])
    spread = [
        np.linalg.norm(np.array(v) - np.median(v, axis=0), axis=1).max() for v in where.values()
    ]
    assert max(spread) < 0.01, spread


def test_a_static_camera_without_pose_keeps_one_world_frame(lib, tmp_path):
    scene = _scene(lib, tmp_path / "sim", "static", False)
    out = tmp_path / "out"
    run(scene, lib, out)
    frames = _frames(out)
    assert [f["camera"]["how"] for f in frames] == ["table"] + ["kept"] * (len(frames) - 1)
    assert len({json.dumps(f["T_world_cam"]) for f in frames}) == 1


def test_a_stopped_run_resumes_to_the_same_camera_and_results(lib, orbit, orbit_run, tmp_path):
    out = tmp_path / "out"

    def stop_after_five(done, total, message):
        if done == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(orbit[0], lib, out, progress=stop_after_five)
    run(orbit[0], lib, out, resume=True)
    for a, b in zip(_frames(out), _frames(orbit_run), strict=True):
        assert without_timings(a, ("files",)) == without_timings(b, ("files",)), a["name"]


def test_a_camera_not_located_starts_the_world_frame_again(lib, orbit, monkeypatch, tmp_path):
    """The frame is not guessed: its world frame is its own table's, it says so, and the
    scene before is forgotten (its objects are added again, none reported moved)."""
    update = CameraTracker.update
    calls = {"n": 0}

    def lost_at_the_fourth(self, points):
        calls["n"] += 1
        if calls["n"] == 4:
            raise CameraNotLocatedError("lost (test)")
        return update(self, points)

    monkeypatch.setattr(CameraTracker, "update", lost_at_the_fourth)
    out = tmp_path / "out"
    summary = run(orbit[0], lib, out)
    assert len(summary.done) == summary.frames
    frames = _frames(out)
    lost = frames[3]
    assert lost["camera"]["how"] == RESTARTED
    assert any("camera not located (lost (test))" in w for w in lost["warnings"])
    assert lost["objects"] and {o["mode"] for o in lost["objects"]} == {"added"}
    before = {o["id"] for o in frames[2]["objects"]}
    assert not before & {o["id"] for o in lost["objects"]}  # new tracks, none carried over
    assert "tracked" in {f["camera"]["how"] for f in frames[4:]}  # it goes on in the new world


def test_a_given_camera_pose_is_checked_against_the_static_scene(lib, orbit, tmp_path):
    """A given pose that the static points contradict (2 cm off in one image) or that does not
    put the table at z = 0 is said in that frame's warnings; it is used all the same."""
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(orbit[1], scene)
    cams = json.loads((scene / "scene_camera.json").read_text())
    cams["5"]["cam_t_w2c"][0] += 20.0  # mm: the world 2 cm off in the camera's x
    cams["6"]["cam_t_w2c"][2] += 30.0  # 3 cm farther: the table 3 cm from z = 0 (and off)
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    out = tmp_path / "out"
    run(scene, lib, out)
    frames = _frames(out)
    said = {f["name"]: [w for w in f["warnings"] if "given camera pose" in w] for f in frames}
    assert all(f["camera"]["how"] == "given" for f in frames)
    assert any("disagrees with the static scene" in w for w in said["000005"]), said["000005"]
    assert frames[5]["camera"]["shift_mm"] > 10.0
    assert any("from z = 0" in w for w in said["000006"]), said["000006"]
    assert not [n for n, w in said.items() if w and n not in ("000005", "000006")], said
    assert frames[5]["T_world_cam"] != frames[4]["T_world_cam"]  # used as given
