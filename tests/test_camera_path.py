"""Moving cameras in the simulated protocols (ssp.sim.camera_path; issue 32)."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.errors import ArgumentError
from ssp.eval.tracking import ReportedMoves
from ssp.probability import pose_change
from ssp.sim.bop import read_bop, write_bop
from ssp.sim.camera_path import (
    CAMERA_PATHS,
    KEYFRAME_STEP_DEG,
    ORBIT_DEG,
    ORBIT_DRIFT,
    camera_path,
)
from ssp.sim.generate import default_camera_pose, generate_sequence

SMALL = dict(stride=8, frames_per_stage=2, stages=2, n_objects=6)


def _azimuth(T: np.ndarray) -> float:
    """Azimuth of the camera's viewing direction about world z, degrees."""
    z = T[:3, 2]
    return float(np.degrees(np.arctan2(z[0], z[1])))


@pytest.mark.parametrize("kind", CAMERA_PATHS)
def test_every_path_starts_at_the_static_camera_and_is_deterministic(kind):
    a = camera_path(kind, 6, 7, distance=1.0, elevation_deg=45.0)
    b = camera_path(kind, 6, 7, distance=1.0, elevation_deg=45.0)
    assert len(a) == 6
    np.testing.assert_allclose(a[0], default_camera_pose(), atol=1e-12)
    for Ta, Tb in zip(a, b, strict=True):
        np.testing.assert_array_equal(Ta, Tb)
        np.testing.assert_allclose(Ta[:3, :3] @ Ta[:3, :3].T, np.eye(3), atol=1e-12)
    moved = [pose_change(a[0], T)[0] for T in a[1:]]
    assert (max(moved) == 0.0) == (kind == "static")


def test_orbit_turns_about_the_vertical_and_drifts():
    P = camera_path("orbit", 5, 0, distance=1.0, elevation_deg=45.0)
    turns = np.diff([_azimuth(T) for T in P])
    np.testing.assert_allclose(np.abs(turns), ORBIT_DEG, atol=1e-9)
    eye0, eye4 = P[0][:3, 3], P[4][:3, 3]
    assert eye4[2] > 0.5 and abs(np.linalg.norm(eye4[:2]) - np.linalg.norm(eye0[:2])) < 0.1
    for i, T in enumerate(P):  # the point looked at, on the table, drifts sideways
        eye, axis = T[:3, 3], T[:3, 2]
        seen = eye - eye[2] / axis[2] * axis
        np.testing.assert_allclose(seen, [ORBIT_DRIFT * i, 0.0, 0.0], atol=1e-12)


def test_keyframes_are_bop_style_sparse_views_and_handheld_shakes():
    P = camera_path("keyframes", 8, 3, distance=1.0, elevation_deg=45.0)
    steps = np.abs(np.diff([_azimuth(T) for T in P]))
    steps = np.minimum(steps, 360.0 - steps)
    assert np.all(steps >= KEYFRAME_STEP_DEG[0] - 1e-9) and np.all(steps <= KEYFRAME_STEP_DEG[1])
    H = camera_path("handheld", 30, 3, distance=1.0, elevation_deg=45.0)
    dt = [pose_change(H[0], T)[0] for T in H[1:]]
    dr = [np.degrees(pose_change(H[0], T)[1]) for T in H[1:]]
    assert 0.002 < np.mean(dt) < 0.03 and 0.3 < np.mean(dr) < 4.0


def test_unknown_path():
    with pytest.raises(ArgumentError, match="unknown camera path"):
        camera_path("drone", 3, 0, distance=1.0, elevation_deg=45.0)


@pytest.fixture(scope="module")
def orbiting(lib):
    return generate_sequence("structure", 2, lib, camera_path="orbit", **SMALL)


def test_a_moving_camera_sees_the_same_scene_from_its_own_poses(lib, orbiting):
    """The path changes the views, never the scene: the same ground truth as the static
    camera's sequence, frame 0 identical; each later frame is ray cast from its own pose
    (its table points lie at z = 0 in the world through that pose, not through the first)."""
    static = generate_sequence("structure", 2, lib, **SMALL)
    assert orbiting.camera_moves and not static.camera_moves
    assert orbiting.info["camera_path"] == "orbit"
    for fs, fo in zip(static.frames, orbiting.frames, strict=True):
        assert list(fs.gt) == list(fo.gt)
        for iid in fs.gt:
            np.testing.assert_array_equal(fs.gt[iid][1], fo.gt[iid][1])
    np.testing.assert_array_equal(static.frames[0].depth, orbiting.frames[0].depth)
    last = len(orbiting) - 1
    assert not np.array_equal(static.frames[last].depth, orbiting.frames[last].depth)
    f = orbiting.frame(last)
    table = f.points[np.asarray(f.labels) == -1]
    assert abs(float(np.median(table[:, 2]))) < 0.003
    np.testing.assert_array_equal(f.T_world_cam, orbiting.camera_pose(last))
    with pytest.raises(ArgumentError, match="starts at the static camera"):
        generate_sequence("structure", 2, lib, camera_path="orbit",
                          T_world_cam=default_camera_pose(), **SMALL)  # fmt: skip


def test_moving_camera_round_trips_through_bop(lib, orbiting, tmp_path):
    out = write_bop(orbiting, tmp_path / "scene")
    back = read_bop(out, lib)
    assert back.camera_moves
    for i, (fa, fb) in enumerate(zip(orbiting.frames, back.frames, strict=True)):
        np.testing.assert_allclose(back.camera_pose(i), orbiting.camera_pose(i), atol=1e-6)
        for iid in fa.gt:
            np.testing.assert_allclose(fb.gt[iid][1], fa.gt[iid][1], atol=1e-6)


def test_reported_moves_count_only_objects_that_did_not_move():
    T = np.eye(4)
    moved = T.copy()
    moved[0, 3] = 0.05
    r = ReportedMoves()
    r.update({"a": ("cube", T), "b": ("cube", T)}, {"a": "added", "b": "added"})
    r.update({"a": ("cube", T), "b": ("cube", moved)}, {"a": "perturbed", "b": "perturbed"})
    r.update({"a": ("cube", T), "b": ("cube", moved)}, {"a": "static"})
    assert (r.static, r.moved) == (2, 1)  # a twice (once perturbed); b moved, then unmatched
    assert (r.moving, r.unreported) == (1, 0)  # b moved, reported so


def test_moved_objects_reported_static_count_only_moves_beyond_the_static_thresholds():
    r = ReportedMoves(0.0075, 5.0)
    T = np.eye(4)
    r.update({"a": ("cube", T), "b": ("cube", T)}, {"a": "added", "b": "added"})
    near, far = T.copy(), T.copy()
    near[0, 3], far[0, 3] = 0.005, 0.015  # 5 mm: within the parser's static threshold
    r.update({"a": ("cube", near), "b": ("cube", far)}, {"a": "static", "b": "static"})
    assert (r.moving, r.unreported) == (1, 1)  # b: moved 15 mm, reported static
    back = far.copy()
    back[0, 3] = 0.0
    r.update({"a": ("cube", near), "b": ("cube", back)}, {"a": "static", "b": "perturbed"})
    assert (r.moving, r.unreported, r.static, r.moved) == (2, 1, 1, 0)


def test_table1_locates_the_camera_when_its_pose_is_not_given(lib):
    """``ssp bench table1 --camera-pose estimated``: the methods see each frame in the world
    frame ssp locates (the camera's error is in their results); a static camera's frames
    keep one world frame and give the results of the pose given."""
    from ssp.eval.table1 import SequenceSpec, merge_table1, run_table1_parts

    small = dict(stages=2, frames_per_stage=4, stride=2)
    specs = [SequenceSpec("structure", 7, camera="orbit", locate=True, **small)]
    result = merge_table1(run_table1_parts(specs, lib, methods=("ssp",), vsd=False), ["ssp"])
    cam = result["camera"]
    assert cam["frames"] == result["frames"] == len(cam["rows"])
    assert cam["how"]["table"] == 1 and cam["restarts"] == cam["how"].get("restarted", 0)
    located = sum(cam["how"].get(how, 0) for how in ("tracked", "kept", "searched"))
    assert located >= cam["frames"] // 2
    assert cam["error_mm_max"] < 5.0  # located right (a wrong turn: centimetres), or restarted
    assert result["methods"]["ssp"]["bop"]["AR"] > 0.8

    def ssp_ar(locate: bool) -> tuple[float, dict]:
        spec = SequenceSpec("structure", 7, locate=locate, **small)
        r = merge_table1(run_table1_parts([spec], lib, methods=("ssp",), vsd=False), ["ssp"])
        return r["methods"]["ssp"]["bop"]["AR"], r.get("camera", {})

    (given, none), (located, static) = ssp_ar(False), ssp_ar(True)
    assert not none and set(static["how"]) == {"table", "kept"} and static["error_mm_max"] < 1e-9
    assert abs(located - given) < 0.01
