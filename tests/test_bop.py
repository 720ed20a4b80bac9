"""BOP-layout reader/writer of synthetic sequences (ssp.sim.bop)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ssp.errors import InputError
from ssp.io.bop import bop_scenes, open_bop, published_rotation, rotation_deviation
from ssp.library import ObjectLibrary
from ssp.library.properties import read_bop_models
from ssp.sim.bop import DEPTH_SCALE, read_bop, simulate_to_disk, write_bop
from ssp.sim.generate import generate_sequence


@pytest.fixture(scope="module")
def seq(lib):
    return generate_sequence(
        "structure", 2, lib, stages=2, frames_per_stage=2, stride=8, n_objects=6
    )


def test_round_trip(lib, seq, tmp_path):
    out = write_bop(seq, tmp_path / "scene", scene_id=7)
    for name in (
        "scene_gt.json",
        "scene_camera.json",
        "scene_gt_info.json",
        "camera.json",
        "hypotheses.json",
        "hypotheses_gt.json",
        "models.json",
        "sequence.json",
        "depth/000000.png",
        "mask_visib/000003_000005.png",
    ):
        assert (out / name).exists(), name
    back = read_bop(out, lib)
    assert back.experiment == seq.experiment and back.seed == seq.seed
    assert back.camera == seq.camera
    np.testing.assert_allclose(back.T_world_cam, seq.T_world_cam, atol=1e-12)
    assert back.models == seq.models
    assert len(back) == len(seq)
    for a, b in zip(seq.frames, back.frames, strict=True):
        assert (a.index, a.stamp, a.static_group) == (b.index, b.stamp, b.static_group)
        assert list(a.gt) == list(b.gt)
        for iid, (cls, T) in a.gt.items():
            assert b.gt[iid][0] == cls
            np.testing.assert_allclose(b.gt[iid][1], T, atol=1e-9)
        assert b.visib_fract == a.visib_fract
        np.testing.assert_array_equal(b.instance, a.instance)
        assert b.depth.dtype == np.float32
        assert np.abs(b.depth - a.depth).max() <= DEPTH_SCALE / 2000 + 1e-6
        np.testing.assert_array_equal(b.depth > 0, a.depth > 0)
        assert len(b.hypotheses) == len(a.hypotheses)
        for ha, hb in zip(a.hypotheses, b.hypotheses, strict=True):
            assert (ha.class_name, ha.score) == (hb.class_name, hb.score)
            assert hb.instance_id is None
            np.testing.assert_allclose(hb.T_world_obj, ha.T_world_obj, atol=1e-12)
    # the frames of one static scene share their ground truth exactly after reading too
    for iid in back.frames[0].gt:
        np.testing.assert_array_equal(back.frames[0].gt[iid][1], back.frames[1].gt[iid][1])
    assert back.info["hypothesis_sources"] == seq.info["hypothesis_sources"]
    assert back.info["stage_objects"] == seq.info["stage_objects"]


def test_bop_files(seq, tmp_path):
    out = write_bop(seq, tmp_path / "scene")
    gt = json.loads((out / "scene_gt.json").read_text())
    cam = json.loads((out / "scene_camera.json").read_text())
    info = json.loads((out / "scene_gt_info.json").read_text())
    models = json.loads((out / "models.json").read_text())
    hyps = json.loads((out / "hypotheses.json").read_text())
    last = str(len(seq) - 1)
    assert len(gt[last]) == len(seq.frames[-1].gt)
    e = gt[last][0]
    assert len(e["cam_R_m2c"]) == 9 and len(e["cam_t_m2c"]) == 3
    assert 500 < np.linalg.norm(e["cam_t_m2c"]) < 2000  # mm, ~1 m from the camera
    assert models["obj_ids"][str(e["obj_id"])] in ("cube", "block")
    assert cam["0"]["depth_scale"] == DEPTH_SCALE and len(cam["0"]["cam_K"]) == 9
    # world -> camera -> model composes to the world pose
    R_w2c = np.reshape(cam["0"]["cam_R_w2c"], (3, 3))
    np.testing.assert_allclose(R_w2c.T, seq.T_world_cam[:3, :3], atol=1e-12)
    row = info[last][0]
    assert {"visib_fract", "px_count_visib", "px_count_all", "bbox_visib"} <= set(row)
    assert row["px_count_visib"] <= row["px_count_all"]
    assert all("inst_id" not in h and set(h) == {"class", "obj_id", "score", "R", "t"}
               for h in hyps[last])  # fmt: skip


def test_read_plain_bop_masks(lib, seq, tmp_path):
    out = write_bop(seq, tmp_path / "scene")
    shutil.rmtree(out / "instance")
    back = read_bop(out, lib)
    for a, b in zip(seq.frames, back.frames, strict=True):
        np.testing.assert_array_equal(b.instance >= 0, a.instance >= 0)
        np.testing.assert_array_equal(b.instance[a.instance >= 0], a.instance[a.instance >= 0])


def test_read_needs_the_classes(lib, seq, tmp_path):
    out = write_bop(seq, tmp_path / "scene")
    with pytest.raises(ValueError, match="not in the library"):
        read_bop(out, ObjectLibrary([lib["mallet"]]))


def test_simulate_to_disk(lib, tmp_path):
    calls = []
    paths = simulate_to_disk(
        "isolated",
        2,
        5,
        None,
        tmp_path,
        library=lib,
        stages=1,
        frames_per_stage=1,
        stride=8,
        objects_per_stage=2,
        progress=lambda done, total, path: calls.append((done, total, path)),
    )
    root = tmp_path / "isolated"
    assert paths == [root / "test" / "000000", root / "test" / "000001"]
    assert [c[:2] for c in calls] == [(1, 2), (2, 2)]
    seqs = [read_bop(p, lib) for p in paths]
    assert [s.seed for s in seqs] == [5, 6]
    assert all(len(s) == 1 and len(s.frames[0].gt) == 2 for s in seqs)
    # the dataset as the BOP toolkit publishes it: camera, models in mm with their symmetries
    cam = json.loads((root / "camera.json").read_text())
    assert {"width", "height", "fx", "fy", "cx", "cy", "depth_scale"} <= set(cam)
    assert bop_scenes(root) == paths
    obj_ids = json.loads((root / "models.json").read_text())["obj_ids"]
    entries = {e.name: e for e in read_bop_models(root / "models")}
    assert sorted(entries) == [f"obj_{int(i):06d}" for i in sorted(obj_ids, key=int)]
    info = json.loads((root / "models" / "models_info.json").read_text())
    for oid, cls in obj_ids.items():
        e = entries[f"obj_{int(oid):06d}"]
        assert e.problem is None and e.scale == 1e-3
        mesh = trimesh.load(e.mesh_path, force="mesh")
        np.testing.assert_allclose(mesh.bounds * 1e-3, lib[cls].mesh.bounds, atol=1e-6)
        assert info[oid]["diameter"] == pytest.approx(lib[cls].diameter * 1000.0)
        assert len(e.symmetry.discrete) == len(lib[cls].symmetry.discrete)
        for a, b in zip(e.symmetry.discrete, lib[cls].symmetry.discrete, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-9)
        assert len(e.symmetry.continuous) == len(lib[cls].symmetry.continuous)


def test_a_simulated_dataset_read_with_its_own_models_folder(lib, tmp_path):
    """``ssp simulate`` names its objects in ``models.json`` (mug, tin, ...) and writes their
    BOP models (obj_000001, ...): read with a library of that ``models/`` folder, the scene's
    classes, its hypotheses and the results' obj_ids are the BOP models' (they were refused:
    "classes not in the library")."""
    from ssp.pipeline.bop import bop_object_ids

    (path,) = simulate_to_disk("isolated", 1, 3, None, tmp_path, library=lib, stages=1,
                               frames_per_stage=1, stride=8, objects_per_stage=2)  # fmt: skip
    root = tmp_path / "isolated"
    names = {
        int(k): v for k, v in json.loads((root / "models.json").read_text())["obj_ids"].items()
    }
    own = ObjectLibrary.from_folder(root / "models")
    scene = open_bop(path, own)
    assert scene.classes == {i: f"obj_{i:06d}" for i in names}
    frame = scene.load(0)
    used = {h.class_name for h in frame.hypotheses} | {c for c, _ in frame.gt.values()}
    assert used and used <= set(own)
    ids = bop_object_ids(path, own)
    assert all(ids[f"obj_{i:06d}"] == i for i in names)
    # with the library the dataset names, as before; a library that lacks some names the folder
    assert open_bop(path, lib).classes == names
    with pytest.raises(InputError, match=r"give the dataset's models with --models \(.*models\)"):
        open_bop(path, ObjectLibrary([lib["cube"]]))


def test_published_scene_without_ssp_files(lib, seq, tmp_path):
    """A scene with only the toolkit's files: stamps from im_id, classes obj_XXXXXX, no world
    frame unless cam_R_w2c is given, segmentation from mask_visib (ground truth)."""
    (path,) = simulate_to_disk("isolated", 1, 5, None, tmp_path, library=lib, stages=1,
                               frames_per_stage=2, stride=8, objects_per_stage=2)  # fmt: skip
    root = path.parent.parent
    for extra in ("sequence.json", "hypotheses.json", "hypotheses_gt.json", "models.json",
                  "camera.json"):  # fmt: skip
        (path / extra).unlink()
    shutil.rmtree(path / "instance")
    (root / "models.json").unlink()
    cams = json.loads((path / "scene_camera.json").read_text())
    for v in cams.values():
        del v["cam_R_w2c"], v["cam_t_w2c"]
    (path / "scene_camera.json").write_text(json.dumps(cams))
    scene = open_bop(path, period=0.5)
    assert not scene.simulated and not scene.has_world and not scene.has_hypotheses
    assert scene.stamps == [0.0, 0.5]
    assert all(c.startswith("obj_") for c in scene.models)
    f = scene.load(1)
    assert f.T_world_cam is None and f.instance_is_gt and f.hypotheses == []
    assert set(np.unique(f.instance)) <= {-2, -1, 0, 1}
    assert all(cls.startswith("obj_") for cls, _ in f.gt.values())
    with pytest.raises(InputError, match="not in the library"):
        open_bop(path, lib)


SHARED = Path(__file__).parents[1] / ".." / "shared"
LMO = SHARED / "data" / "lmo-megapose"


def _perturbed_scene(lib, tmp_path, bend):
    """A one-stage simulated scene whose first ground-truth rotation is ``bend(R)``."""
    (path,) = simulate_to_disk("isolated", 1, 5, None, tmp_path, library=lib, stages=1,
                               frames_per_stage=1, stride=8, objects_per_stage=2)  # fmt: skip
    gt = json.loads((path / "scene_gt.json").read_text())
    first = sorted(gt, key=int)[0]
    R = np.asarray(gt[first][0]["cam_R_m2c"], dtype=float).reshape(3, 3)
    gt[first][0]["cam_R_m2c"] = bend(R).ravel().tolist()
    (path / "scene_gt.json").write_text(json.dumps(gt))
    return path, first, R


def test_ground_truth_rotations_orthonormal_to_1e3_are_read_as_rotations(lib, tmp_path, caplog):
    """LM-O's published rotations are orthonormal only to about 1e-3: read as the nearest
    rotation with one warning for the file (the renderer refused them: issue 30)."""
    path, first, R = _perturbed_scene(lib, tmp_path, lambda R: np.round(R, 3) * 1.0005)
    with caplog.at_level("WARNING", logger="ssp.io.bop"):
        scene = open_bop(path)
        open_bop(path)  # a command opens a scene more than once: still one warning
    said = [r.getMessage() for r in caplog.records if "orthonormal only" in r.getMessage()]
    assert len(said) == 1 and "scene_gt.json: 1 of" in said[0]
    (cls, T), *_ = scene.load(0).gt.values()
    R_read = T[:3, :3]
    assert np.abs(R_read @ R_read.T - np.eye(3)).max() < 1e-12
    assert np.linalg.det(R_read) == pytest.approx(1.0)
    assert np.abs(R_read - R).max() < 2e-3  # the nearest rotation: what was published


@pytest.mark.parametrize(
    "bend", [lambda R: R @ np.diag([1.0, 1.0, -1.0]), lambda R: 1.2 * R], ids=["mirror", "scale"]
)
def test_ground_truth_far_from_a_rotation_is_an_error_naming_file_and_row(lib, tmp_path, bend):
    path, first, _ = _perturbed_scene(lib, tmp_path, bend)
    scene = open_bop(path)
    with pytest.raises(
        InputError, match=rf"scene_gt.json: im_id {first}, entry 0: cam_R_m2c is not a rotation"
    ):
        scene.load(0)


def test_published_rotation_by_hand():
    R = published_rotation(np.round(np.eye(3) * 1.0, 3).ravel() + 1e-3, "x.json: row 3")
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    with pytest.raises(InputError, match=r"x.json: row 3 is not a rotation .*det -1"):
        published_rotation(np.diag([1.0, -1.0, 1.0]).ravel(), "x.json: row 3")
    with pytest.raises(InputError, match=r"x.json: row 3 must be 9 numbers"):
        published_rotation([1, 0, 0], "x.json: row 3")


@pytest.mark.skipif(not LMO.is_dir(), reason="needs ../shared/data/lmo-megapose")
def test_published_lmo_ground_truth_is_read_as_rotations(caplog, monkeypatch):
    """Every published rotation of LM-O scene 2 is accepted and made orthonormal."""
    import ssp.io.bop

    monkeypatch.setattr(ssp.io.bop, "_WARNED_ROTATIONS", set())  # another test may have warned
    scene_dir = LMO / "test" / "000002"
    with caplog.at_level("WARNING", logger="ssp.io.bop"):
        open_bop(scene_dir)
    assert any("orthonormal only to" in r.getMessage() for r in caplog.records)
    gt = json.loads((scene_dir / "scene_gt.json").read_text())
    devs = []
    for im, entries in gt.items():
        for j, g in enumerate(entries):
            devs.append(float(rotation_deviation(np.reshape(g["cam_R_m2c"], (3, 3)))))
            R = published_rotation(g["cam_R_m2c"], f"im_id {im}, entry {j}")
            assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12
    assert max(devs) > 1e-4  # as published: the renderer's 1e-5 refused them
