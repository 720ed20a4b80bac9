"""The tower case study: the idealised robot (``ssp.sim.robot``) and ``ssp bench tower``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.config import SSPConfig
from ssp.eval import tower
from ssp.eval.baselines import Detection
from ssp.library import ObjectLibrary
from ssp.library.build import build_model
from ssp.library.builtin import builtin_spec
from ssp.library.model import ObjectInstance
from ssp.physics.world import World
from ssp.sim.hypotheses import HypothesisNoise
from ssp.sim.robot import grasp, gripper_pose, place, release, tilt_deg, upright, upright_yaw

EDGE = 0.0508


@pytest.fixture(scope="module")
def lib() -> ObjectLibrary:
    """The built-in 2-inch cube alone (with its 24 symmetries)."""
    spec = builtin_spec("cube")
    return ObjectLibrary(
        [
            build_model(
                spec.name,
                spec.mesh,
                config=SSPConfig().library,
                density=spec.density,
                friction=spec.friction,
                symmetry=spec.symmetry,
                convex_parts=spec.parts,
            )
        ]
    )


def pose(x=0.0, y=0.0, z=EDGE / 2, rotvec_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


def world_of(lib, poses: dict) -> World:
    w = World([ObjectInstance(k, lib["cube"]) for k in poses], table=True)
    w.set_poses(poses)
    return w


# ------------------------------------------------------------------------------ robot
def test_upright_picks_the_face_pointing_up(lib):
    cube = lib["cube"]
    T = pose(rotvec_deg=(0.0, 0.0, 30.0)) @ pose(z=0.0, rotvec_deg=(90.0, 0.0, 0.0))  # y up
    U = upright(cube, T)
    assert U[2, 2] == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(U[:3, 3], T[:3, 3])
    assert tilt_deg(cube, T) == pytest.approx(0.0, abs=1e-6)
    assert tilt_deg(cube, pose(rotvec_deg=(7.0, 0.0, 0.0))) == pytest.approx(7.0, abs=1e-6)
    yaw = math.degrees(upright_yaw(cube, pose(rotvec_deg=(0.0, 0.0, 20.0))))
    assert yaw % 90.0 == pytest.approx(20.0, abs=1e-6)


def test_perception_error_becomes_the_offset_in_the_hand(lib):
    cube = lib["cube"]
    true = pose(0.2, 0.1, rotvec_deg=(0.0, 0.0, 10.0))
    w = world_of(lib, {"a": true})
    err = pose(0.004, -0.003, 0.0, rotvec_deg=(0.0, 0.0, 6.0))
    perceived = true @ err
    held = grasp(w, cube, perceived)
    assert held is not None and held.oid == "a"
    assert np.allclose(held.T_world_grip, gripper_pose(cube, perceived))
    # the true block seen from the gripper is the inverse of the error
    assert np.allclose(held.T_grip_obj, np.linalg.inv(err), atol=1e-9)
    # placed so that the perceived pose sits at the target: the true block is off by the error
    target = pose(0.0, 0.0, EDGE / 2)
    stop = place(w, held, target)
    assert stop <= 0.001
    got = w.get_pose("a")
    assert np.allclose(got, target @ np.linalg.inv(err), atol=2e-4)


def test_grasp_misses_when_nothing_is_near_the_perceived_pose(lib):
    w = world_of(lib, {"a": pose(0.2, 0.1)})
    assert grasp(w, lib["cube"], pose(0.2, 0.13), tolerance=0.02) is None
    assert grasp(w, lib["cube"], pose(0.2, 0.1), candidates=()) is None


def test_guarded_place_stops_at_first_contact_and_release_settles(lib):
    cube = lib["cube"]
    w = world_of(lib, {"base": pose(), "a": pose(0.2, 0.0)})
    held = grasp(w, cube, w.get_pose("a"))
    # the perceived top of the tower is 4 mm too low: the descent stops on the base
    target = pose(0.0, 0.0, 1.5 * EDGE - 0.004)
    stop = place(w, held, target)
    assert stop == pytest.approx(0.004, abs=3e-4)
    assert w.contacts().max_depth < 2e-4
    assert release(w) is not None
    T = w.get_pose("a")
    assert T[2, 3] == pytest.approx(1.5 * EDGE, abs=5e-4)
    assert np.linalg.norm(w.get_pose("base")[:3, 3] - pose()[:3, 3]) < 5e-4


def test_release_of_a_tilted_block_settles_flat(lib):
    cube = lib["cube"]
    w = world_of(lib, {"base": pose(), "a": pose(0.2, 0.0)})
    true = w.get_pose("a")
    held = grasp(w, cube, true @ pose(0, 0, 0, rotvec_deg=(8.0, 0.0, 0.0)))  # perceived tilted
    place(w, held, pose(0.0, 0.0, 1.5 * EDGE))
    assert tilt_deg(cube, w.get_pose("a")) == pytest.approx(8.0, abs=0.1)
    release(w)
    assert tilt_deg(cube, w.get_pose("a")) < 0.5


# ------------------------------------------------------------------------------ measures
def test_straightness_divides_by_the_level(lib):
    tr = tower.TowerTrial(
        stacks=3,
        tower=["a", "b", "c"],
        tower_poses={
            "a": pose(),
            "b": pose(0.002, 0.0, 1.5 * EDGE, rotvec_deg=(0, 0, 4.0)),
            "c": pose(0.003, 0.004, 2.5 * EDGE, rotvec_deg=(0, 0, 3.0)),
        },
    )
    mm, deg = tower.straightness(tr, lib["cube"])
    assert mm == pytest.approx([2.0, 2.5])
    assert deg == pytest.approx([4.0, 1.5])
    assert tower.straightness(tower.TowerTrial(tower=["a"], tower_poses={"a": pose()}),
                              lib["cube"]) == ([], [])  # fmt: skip


def test_consistency_restarts_when_the_block_moves(lib):
    a0, a1 = pose(), pose(0.1, 0.0)
    est = [pose(0.001), pose(-0.001), pose(0.1 + 0.002), pose(0.1 - 0.002)]
    frames = [
        ({"a": a0}, [Detection("cube", est[0])]),
        ({"a": a0}, [Detection("cube", est[1])]),
        ({"a": a1}, [Detection("cube", est[2])]),
        ({"a": a1}, [Detection("cube", est[3])]),
    ]
    mm, deg = tower.consistency(tower.TowerTrial(frames=frames), lib)
    assert sorted(mm) == pytest.approx([1.0, 1.0, 2.0, 2.0])
    assert max(deg) < 1e-6


# ------------------------------------------------------------------------------ trials
def test_perfect_perception_builds_a_straight_tower(lib):
    tr = tower.run_trial(
        "estimator", 0, 3, lib, SSPConfig(), noise=HypothesisNoise.structure().replace(
            sigma_t=0.0, sigma_r_deg=0.0, score_jitter=0.0), frames_per_step=1, stride=2,
    )  # fmt: skip
    assert tr.stacks == tower.BLOCKS and tr.failure is None
    mm, deg = tower.straightness(tr, lib["cube"])
    assert len(mm) == tower.BLOCKS - 1
    assert max(mm) < 0.5 and max(deg) < 0.5
    heights = [tr.tower_poses[o][2, 3] for o in tr.tower]
    assert np.allclose(np.diff(heights), EDGE, atol=1e-3)
    assert len(tr.frames) == tower.BLOCKS + 1  # one per step and the final look


def test_gross_perception_error_ends_the_trial_with_a_reason(lib):
    noise = HypothesisNoise.structure().replace(sigma_t=0.03, sigma_r_deg=20.0)
    tr = tower.run_trial("estimator", 0, 3, lib, SSPConfig(), noise=noise,
                         frames_per_step=1, stride=2)  # fmt: skip
    assert tr.stacks < tower.BLOCKS
    assert tr.failure in {
        "tower fell", "cube not resting flat", "cube not on the table", "cube not on the one "
        "below", "grasp missed", "tower not perceived", "no cube perceived to pick",
    }  # fmt: skip


def test_run_tower_is_deterministic_and_writes_the_report(lib, tmp_path):
    kw = dict(methods=("estimator",), frames_per_step=1, blocks=3, stride=2)
    r1 = tower.run_tower(2, 5, lib, SSPConfig(), **kw)
    r2 = tower.run_tower(2, 5, lib, SSPConfig(), **kw)
    for r in (r1, r2):  # wall times differ
        assert r["methods"]["estimator"].pop("sec_per_frame") > 0 and r.pop("wall_s") > 0
    assert r1 == r2
    m = r1["methods"]["estimator"]
    for key in ("stacks_mean", "stacks_std", "straightness_mm", "straightness_deg",
                "consistency_mm", "consistency_deg"):  # fmt: skip
        assert isinstance(m[key], float), key
    assert r1["protocol"] == "tower" and r1["trials"] == 2
    assert [row["trial"] for row in r1["trials_detail"]["estimator"]] == [0, 1]
    files = tower.write_tower(r1, tmp_path, {"estimator": np.zeros((8, 8, 3), np.uint8)})
    assert json.loads((tmp_path / "results.json").read_text())["protocol"] == "tower"
    assert "Successful stacks" in (tmp_path / "results.md").read_text()
    assert (tmp_path / "tower_estimator.png").exists() and len(files) == 3


def test_ssp_stacks_a_short_tower(lib):
    tr = tower.run_trial("ssp", 0, 4, lib, SSPConfig(), frames_per_step=2, blocks=3, stride=2)
    assert tr.stacks == 3, tr.failure
    mm, _ = tower.consistency(tr, lib)
    assert len(mm) > 0 and np.mean(mm) < 3.0


def test_a_wrist_camera_looks_from_a_new_view_before_each_pick_and_ssp_stacks(lib, monkeypatch):
    """The wrist camera (eye in hand): each look a new view of the table (turned or tilted by
    degrees), its frames a few millimetres apart (the arm's shake); the frames the method sees
    carry those poses, and ssp stacks a short tower from them."""
    from ssp.probability import pose_change

    looks = [tower.wrist_camera_pose(4, 0, k, 0) for k in range(4)]
    for a, b in zip(looks, looks[1:], strict=False):
        assert np.degrees(pose_change(a, b)[1]) > 3.0
    shaken = tower.wrist_camera_pose(4, 0, 0, 1)
    dt, dr = pose_change(looks[0], shaken)
    assert 0.0 < dt < 0.02 and np.degrees(dr) < 1.5
    seen = []
    real_frame = tower._Camera.frame

    def frame(self, *args, **kwargs):
        out = real_frame(self, *args, **kwargs)
        seen.append(out.T_world_cam.copy())
        return out

    monkeypatch.setattr(tower._Camera, "frame", frame)
    tr = tower.run_trial("ssp", 0, 4, lib, SSPConfig(), frames_per_step=2, blocks=3, stride=2,
                         camera_path="wrist")  # fmt: skip
    assert tr.stacks == 3, tr.failure
    np.testing.assert_allclose(seen[0], looks[0])
    np.testing.assert_allclose(seen[2], looks[1])  # the second look's first frame
    with pytest.raises(ValueError, match="camera"):
        tower.run_trial("ssp", 0, 4, lib, SSPConfig(), camera_path="drone")


def test_noise_presets():
    base = HypothesisNoise.structure()
    assert tower.noise_preset("structure") == base
    loud = tower.noise_preset("case-study")
    assert loud.sigma_r_deg == pytest.approx(4.3 * base.sigma_r_deg)
    assert loud.sigma_t == pytest.approx(1.2 * base.sigma_t) and loud.k == base.k
    with pytest.raises(ValueError, match="case-study"):
        tower.noise_preset("loud")


def test_bad_arguments_are_rejected(lib):
    with pytest.raises(ValueError, match="hypotheses"):
        tower.run_tower(1, 0, lib, hypotheses="perfect")
    with pytest.raises(ValueError, match=">= 1"):
        tower.run_tower(0, 0, lib)


def test_bench_tower_command(tmp_path):
    from typer.testing import CliRunner

    from ssp.cli import app

    runner = CliRunner()
    args = ["bench", "tower", "--trials", "1", "--methods", "estimator", "--frames-per-step", "1"]
    r = runner.invoke(app, [*args, "--seed", "7", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    result = json.loads((tmp_path / "results.json").read_text())
    assert result["protocol"] == "tower" and result["command"]["noise"] == "structure"
    assert set(result["methods"]) == {"estimator"}
    assert (tmp_path / "tower_estimator.png").stat().st_size > 1000
    assert "Tower case study" in r.output and "estimator" in r.output
    r = runner.invoke(app, [*args, "--noise", "loud", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "structure" in r.output
    r = runner.invoke(app, [*args, "--methods", "oracle", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "oracle" in r.output


def test_realistic_trial_has_distractors_and_explains_a_missed_grasp(lib):
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    noise = RealisticNoise(distractor_rate=1.0, mode_persistence=1.0)
    realism = SceneRealism(events=(), mask_defects=(0.01, 0.01))
    tr = tower.run_trial(
        "estimator", 0, 11, lib, SSPConfig(), noise=noise, realism=realism,
        frames_per_step=1, blocks=3, stride=2,
    )  # fmt: skip
    assert all(set(poses) == {"b0", "b1", "b2"} for poses, _ in tr.frames)  # cubes only
    if tr.failure == "grasp missed":
        d = tr.failure_detail
        assert d["pick"] >= 1 and d["nearest_cube_mm"] > 0
        assert d["reached_for"] in ("cube", "distractor", "nothing (a ghost)")
    else:
        assert tr.failure is None or tr.failure_detail is not None
    # the stream named cubes on the distractors: more detections than cubes at some frame
    assert max(len(dets) for _, dets in tr.frames) > 3


def test_ghost_cubes_are_counted(lib):
    T = pose(0.0, 0.0)
    tr = tower.TowerTrial(
        frames=[
            ({"b0": T}, [Detection("cube", T)]),
            ({"b0": T}, [Detection("cube", T), Detection("cube", pose(0.2, 0.0))]),  # a ghost
        ]
    )
    assert tower.ghosts(tr, lib) == (1, 1)


def test_the_cli_default_methods_are_the_library_default():
    import inspect

    from ssp.cli.experiments import bench_tower
    from ssp.eval.tower import DEFAULT_METHODS

    option = inspect.signature(bench_tower).parameters["methods"].default
    assert option.default.split(",") == list(DEFAULT_METHODS)


def test_bench_tower_refuses_an_unknown_camera():
    from typer.testing import CliRunner

    from ssp.cli import app

    r = CliRunner().invoke(app, ["bench", "tower", "--camera", "drone", "--trials", "1"])
    assert r.exit_code != 0 and "--camera must be one of static, wrist" in r.output
