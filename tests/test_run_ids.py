"""``ssp run``'s BOP ids: the ``scene_id`` and ``obj_id`` of its CSV rows, so that the results
of a BOP scene, a folder of clouds or a bag can be scored against the dataset they came from."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from ssp.cli import app
from ssp.errors import ArgumentError, InputError
from ssp.io.bop import open_bop
from ssp.io.clouds import write_cloud
from ssp.io.hypotheses import write_hypotheses
from ssp.io.results import ObjectIds, read_bop_csv
from ssp.perception.depth import cloud_from_depth
from ssp.pipeline.refine import evaluate
from ssp.pipeline.run import run
from ssp.scene import Hypothesis
from ssp.sim.bop import simulate_to_disk

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset(lib, tmp_path_factory):
    """A BOP dataset of two scenes (000000, 000001) as ``ssp simulate`` writes it."""
    tmp = tmp_path_factory.mktemp("ids")
    scenes = simulate_to_disk("structure", 2, 4, out_dir=tmp, library=lib, stages=2,
                              frames_per_stage=1, stride=4, n_objects=4)  # fmt: skip
    return scenes[0].parent.parent, scenes


def _cloud_folder(scene, lib, dest, rename=None):
    """The images of a BOP scene as a folder of camera-frame clouds (instance labels, 0 =
    background) with their ground truth as given hypotheses (camera frame), classes renamed
    by ``rename``."""
    dest.mkdir()
    bop = open_bop(scene, lib)
    T_wc = None
    for k in range(len(bop)):
        f = bop.load(k)
        cloud = cloud_from_depth(f.depth, f.camera, mask=f.instance)
        labels = np.where(cloud.labels >= 0, cloud.labels + 1, 0)
        write_cloud(dest / f"{f.im_id:06d}.ply", cloud.points, labels=labels)
        hyps = [Hypothesis((rename or {}).get(c, c), T) for c, T in f.gt.values()]
        write_hypotheses(dest / f"{f.im_id:06d}.hypotheses.json", hyps, frame="camera")
        T_wc = f.T_world_cam
    (dest / "scene.json").write_text(json.dumps({"T_world_cam": T_wc.tolist()}))
    return dest


def _ar(root, lib, csv):
    return evaluate(root, lib, [csv], vsd=False)[csv.name]["AR"]


def test_a_bop_scene_is_scored_against_itself(lib, dataset, tmp_path):
    """Scene 000000's rows carry scene_id 0 (they carried 1: scored against scene 1's ground
    truth, AR 0.02) and the dataset's obj_ids; run.json records both."""
    root, (scene0, _) = dataset
    run(scene0, lib, tmp_path / "out")
    csv = tmp_path / "out" / "ssp_000000-test.csv"
    rows = read_bop_csv(csv)
    assert rows and {r["scene_id"] for r in rows} == {0}
    table = json.loads((root / "models.json").read_text())["obj_ids"]
    assert json.loads((tmp_path / "out" / "obj_ids.json").read_text())["obj_ids"] == table
    manifest = json.loads((tmp_path / "out" / "run.json").read_text())
    assert manifest["options"]["scene_id"] == 0 and manifest["obj_ids"] == table
    assert _ar(root, lib, csv) > 0.9
    # a scene id that contradicts the scene's own is refused before anything is written
    with pytest.raises(ArgumentError, match="contradicts the BOP scene"):
        run(scene0, lib, tmp_path / "o2", scene_id=3)
    assert not (tmp_path / "o2").exists()


def test_cli_folder_of_clouds_scored_with_scene_id_and_obj_ids(lib, dataset, tmp_path):
    """The clouds of scene 000001 run as a plain folder: --scene-id and --obj-ids make its CSV
    one the dataset scores; without them it holds scene 1 and the sorted-name ids."""
    root, (_, scene1) = dataset
    src = _cloud_folder(scene1, lib, tmp_path / "clouds")
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(src), "--out", str(out), "--scene-id", "1",
                            "--obj-ids", str(root / "models.json")])  # fmt: skip
    assert r.exit_code == 0, r.output
    csv = out / "ssp_clouds-test.csv"
    rows = read_bop_csv(csv)
    table = json.loads((root / "models.json").read_text())["obj_ids"]
    assert rows and {r["scene_id"] for r in rows} == {1}
    assert json.loads((out / "obj_ids.json").read_text())["obj_ids"] == table
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["obj_ids_file"] == str((root / "models.json").resolve())
    assert _ar(root, lib, csv) > 0.4
    # the same rows under the ids of the sorted class names (cube 5: the dataset's mallet)
    sorted_ids = ObjectIds.from_classes(lib)
    lines = csv.read_text().splitlines()
    for k, line in enumerate(lines[1:], start=1):
        parts = line.split(",")
        parts[2] = str(sorted_ids[table[parts[2]]])
        lines[k] = ",".join(parts)
    control = tmp_path / "ctl_clouds-test.csv"
    control.write_text("\n".join(lines) + "\n")
    assert _ar(root, lib, control) < 0.1
    # a resume takes the recorded --scene-id and --obj-ids
    r = runner.invoke(app, ["run", "--resume", str(out)])
    assert r.exit_code == 0, r.output
    # --scene-id names one input's scene
    r = runner.invoke(app, ["run", str(src), str(scene1), "--out", str(tmp_path / "many"),
                            "--scene-id", "1"])  # fmt: skip
    assert r.exit_code != 0 and "--scene-id names the scene of one input" in r.output


def test_bop_model_names_are_their_obj_ids(lib, dataset, tmp_path):
    """Models named as a BOP models folder names them (obj_000005.ply) keep their obj_id, not
    their position among the sorted names (obj_000002 -> 1, obj_000005 -> 2 before)."""
    _, (scene0, _) = dataset
    names = {"cube": "obj_000005", "block": "obj_000002"}
    bop_lib = {new: replace(lib[old], name=new) for old, new in names.items()}
    src = _cloud_folder(scene0, lib, tmp_path / "clouds", rename=names)
    summary = run(src, bop_lib, tmp_path / "out", hypotheses="given")
    assert summary.done and not summary.failed
    ids = json.loads((tmp_path / "out" / "obj_ids.json").read_text())["obj_ids"]
    assert ids == {"2": "obj_000002", "5": "obj_000005"}
    rows = read_bop_csv(tmp_path / "out" / "ssp_clouds-test.csv")
    assert rows and {r["obj_id"] for r in rows} <= {2, 5}


def test_obj_ids_missing_a_class_fail_before_any_frame(lib, dataset, tmp_path):
    root, (scene0, _) = dataset
    table = tmp_path / "ids.json"
    table.write_text(json.dumps({"obj_ids": {"1": "cube", "2": "block"}}))
    with pytest.raises(InputError, match=r"no obj_id for the classes .*'claw_hammer'"):
        run(scene0, lib, tmp_path / "out", obj_ids=table)
    assert not (tmp_path / "out").exists()
    with pytest.raises(InputError, match="no such file"):
        run(scene0, lib, tmp_path / "out", obj_ids=tmp_path / "nope.json")
    r = runner.invoke(app, ["run", str(scene0), "--out", str(tmp_path / "o"), "--obj-ids",
                            str(table)])  # fmt: skip
    assert r.exit_code != 0 and "'wrench'" in r.output
    assert not (tmp_path / "o" / "frames").exists()


def test_resume_refuses_other_obj_ids(lib, dataset, tmp_path):
    root, (_, scene1) = dataset
    src = _cloud_folder(scene1, lib, tmp_path / "clouds")
    out = tmp_path / "out"
    run(src, lib, out, obj_ids=root / "models.json", scene_id=1)
    other = json.loads((root / "models.json").read_text())
    other["obj_ids"]["1"], other["obj_ids"]["2"] = "block", "cube"
    swapped = tmp_path / "swapped.json"
    swapped.write_text(json.dumps(other))
    with pytest.raises(ArgumentError, match=r"object ids \(obj_ids.json\) block 2 -> 1, cube 1"):
        run(src, lib, out, resume=True, obj_ids=swapped, scene_id=1)
    with pytest.raises(ArgumentError, match="option scene_id 1 -> 4"):
        run(src, lib, out, resume=True, obj_ids=root / "models.json", scene_id=4)
    # the same ids (from an equal table elsewhere) resume
    same = tmp_path / "same.json"
    same.write_text((root / "models.json").read_text())
    assert run(src, lib, out, resume=True, obj_ids=same, scene_id=1).status == "finished"
    # a run.json that records no ids (an older ssp): its obj_ids.json is what was used
    manifest = json.loads((out / "run.json").read_text())
    del manifest["obj_ids"]
    (out / "run.json").write_text(json.dumps(manifest))
    (out / "obj_ids.json").write_text(json.dumps(other))
    with pytest.raises(ArgumentError, match="object ids"):
        run(src, lib, out, resume=True, obj_ids=root / "models.json", scene_id=1)


def test_id_tables_of_bop_files(dataset, tmp_path):
    root, _ = dataset
    models = root / "models"
    by_info = ObjectIds.from_file(models / "models_info.json")
    assert by_info["obj_000001"] == 1 and len(by_info) == len(list(models.glob("obj_*.ply")))
    assert ObjectIds.from_file(models).as_dict() == by_info.as_dict()
    assert ObjectIds.from_file(root / "models.json")["cube"] == 1
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name in ("obj_000007.ply", "obj_000012.obj", "readme.txt"):
        (meshes / name).write_text("")
    assert ObjectIds.from_file(meshes).as_dict() == {"obj_000007": 7, "obj_000012": 12}
    assert ObjectIds.from_bop_names(["obj_000003", "obj_000010"]).as_dict() == {
        "obj_000003": 3,
        "obj_000010": 10,
    }
    assert ObjectIds.from_bop_names(["obj_000003", "cube"]) is None
    bad = tmp_path / "bad.json"
    for text, needle in (
        ("[1, 2]", "not an id table"),
        ('{"x": {"diameter": 1}}', "obj_id 'x' is not an integer"),
        ('{"obj_ids": {"1": "cube", "2": "cube"}}', "two obj_ids"),
        ("{", "cannot read"),
    ):
        bad.write_text(text)
        with pytest.raises(InputError, match=needle):
            ObjectIds.from_file(bad)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a BOP models folder"):
        ObjectIds.from_file(tmp_path / "empty")
