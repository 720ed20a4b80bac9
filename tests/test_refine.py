"""ssp after a pose estimator on a BOP dataset: ssp estimate, ssp refine, ssp evaluate."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from ssp.cli import app
from ssp.errors import InputError
from ssp.io.results import read_bop_csv
from ssp.pipeline.refine import estimate, evaluate, refine, refined_method
from ssp.pipeline.run import REJECTED_SCORE_SCALE
from ssp.sim.bop import simulate_to_disk

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset(lib, tmp_path_factory):
    """A small structure dataset as ssp simulate writes it, and the built-in estimator's
    hypotheses of it as a BOP19 CSV."""
    tmp = tmp_path_factory.mktemp("refine")
    (scene,) = simulate_to_disk("structure", 1, 7, out_dir=tmp, library=lib, stages=2,
                                frames_per_stage=2, stride=4)  # fmt: skip
    root = scene.parent.parent
    est = tmp / "est_structure-test.csv"
    report = estimate(root, lib, est)
    assert report["images"] == 4 and report["rows"] > 0 and not report["failed"]
    return root, est


def _published(root, dest):
    """A copy of the dataset with only the BOP toolkit's files: no ssp extras, no world frame."""
    shutil.copytree(root, dest)
    (dest / "models.json").unlink()
    for scene in (dest / "test").iterdir():
        for extra in ("sequence.json", "hypotheses.json", "hypotheses_gt.json", "models.json",
                      "camera.json"):  # fmt: skip
            (scene / extra).unlink()
        shutil.rmtree(scene / "instance")
        cams = json.loads((scene / "scene_camera.json").read_text())
        for v in cams.values():
            del v["cam_R_w2c"], v["cam_t_w2c"]
        (scene / "scene_camera.json").write_text(json.dumps(cams))
    return dest


def test_estimate_perceives_each_image_in_its_own_table_frame(lib, dataset, tmp_path, monkeypatch):
    """ssp estimate's rows are in the camera frame: images without camera poses are each
    perceived in their own table's world, no camera located across images (a registration
    each), and the first image's rows are those of a located run (the same world there)."""
    from ssp.pipeline.world import CameraLocator

    root, _ = dataset
    pub = _published(root, tmp_path / "pub")
    lib_pub = lib_with_bop_names(lib, pub)
    located = estimate(pub, lib_pub, tmp_path / "located" / "est_structure-test.csv",
                       masks="gt")  # fmt: skip
    monkeypatch.setattr(CameraLocator, "locate", lambda *a, **k: pytest.fail("located"))
    own = estimate(pub, lib_pub, tmp_path / "own" / "est_structure-test.csv", masks="gt")
    assert own["images"] == located["images"] == 4 and not own["failed"]
    rows = [read_bop_csv(tmp_path / d / "est_structure-test.csv") for d in ("located", "own")]
    first = [[(r["obj_id"], r["score"], r["R"].tolist(), r["t"].tolist()) for r in rs
              if r["im_id"] == 0] for rs in rows]  # fmt: skip
    assert first[0] and first[0] == first[1]


def test_refine_writes_a_bop19_csv_that_beats_the_estimator(lib, dataset, tmp_path):
    root, est = dataset
    assert refined_method(est) == "est-ssp"
    summary = refine(root, est, lib, tmp_path / "out")
    assert summary.done and summary.csv == tmp_path / "out" / "est-ssp_structure-test.csv"
    rows = read_bop_csv(summary.csv)
    assert {(r["scene_id"], r["im_id"]) for r in rows} == {(0, k) for k in range(4)}
    ids = json.loads((root / "models.json").read_text())["obj_ids"]
    assert {r["obj_id"] for r in rows} <= {int(k) for k in ids}
    # the rows are the per-frame results, kept and rejected objects, moved into the camera
    # frame (t in mm); a rejected object's row scores below every kept one
    frame = json.loads((tmp_path / "out" / "scenes" / "000000" / "frames" / "000003.json")
                       .read_text())  # fmt: skip
    T_cw = np.linalg.inv(np.asarray(frame["T_world_cam"]))

    def t_cam(objs):
        return sorted(tuple(np.round((T_cw @ np.asarray(o["T_world_obj"]))[:3, 3] * 1000, 3))
                      for o in objs)  # fmt: skip

    rows3 = [r for r in rows if r["im_id"] == 3]
    assert sorted(tuple(np.round(r["t"], 3)) for r in rows3) == t_cam(
        frame["objects"] + frame["rejected"]
    )
    kept = [r for r in rows3 if r["score"] > REJECTED_SCORE_SCALE]
    assert sorted(tuple(np.round(r["t"], 3)) for r in kept) == t_cam(frame["objects"])
    assert (tmp_path / "out" / "scenes" / "000000" / "tum").is_dir()
    res = evaluate(root, lib, [est, summary.csv], vsd=False)
    before, after = res[est.name], res[summary.csv.name]
    assert before["targets"] == after["targets"] > 0
    assert after["AR"] > before["AR"] + 0.05, (before["AR"], after["AR"])


def test_refine_on_a_published_scene_fits_the_world_to_the_table(lib, dataset, tmp_path):
    """No cam_R_w2c, no ssp files: the world frame comes from the depth (one frame for the
    static camera), the classes from models_info.json ids, the segments from clustering."""
    root, est = dataset
    ids = json.loads((root / "models.json").read_text())["obj_ids"]
    assert ids == {str(i): c for i, c in enumerate(lib, 1)}  # what lib_with_bop_names assumes
    pub = _published(root, tmp_path / "pub")
    summary = refine(pub, est, lib_with_bop_names(lib, pub), tmp_path / "out")
    assert summary.done
    frames = sorted((tmp_path / "out" / "scenes" / "000000" / "frames").glob("*.json"))
    docs = [json.loads(p.read_text()) for p in frames]
    T = [np.asarray(d["T_world_cam"]) for d in docs]
    assert all(np.array_equal(T[0], t) for t in T[1:])  # the static camera keeps its world
    truth = json.loads((root / "test" / "000000" / "scene_camera.json").read_text())["0"]
    up_true = np.asarray(truth["cam_R_w2c"]).reshape(3, 3)[:, 2]  # world z in the camera
    up_fit = T[0][2, :3]
    assert np.degrees(np.arccos(np.clip(up_true @ up_fit, -1, 1))) < 1.0
    res = evaluate(pub, lib_with_bop_names(lib, pub), [est, summary.csv], vsd=False)
    assert res[summary.csv.name]["AR"] >= res[est.name]["AR"]


def lib_with_bop_names(lib, pub):
    """The library under the dataset's ``obj_XXXXXX`` names (``ssp simulate`` numbers the
    library's classes from 1 and writes these meshes to ``models/``): the same models without
    CoACD on every mesh of ``pub/models``."""
    from dataclasses import replace

    from ssp.library import ObjectLibrary

    return ObjectLibrary(replace(lib[c], name=f"obj_{i:06d}") for i, c in enumerate(lib, 1))


def test_a_bad_row_fails_its_frame_only(lib, dataset, tmp_path):
    root, est = dataset
    lines = est.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines[1:], start=1) if ln.split(",")[1] == "2")
    parts = lines[i].split(",")
    parts[5] = "nan 0 900"
    lines[i] = ",".join(parts)
    bad = tmp_path / "bad_structure-test.csv"
    bad.write_text("\n".join(lines) + "\n")
    summary = refine(root, bad, lib, tmp_path / "out")
    (scene,) = summary.scenes
    assert scene["failed"] == 1 and scene["done"] == 3
    doc = json.loads((tmp_path / "out" / "scenes" / "000000" / "frames" / "000002.json")
                     .read_text())  # fmt: skip
    assert doc["status"] == "failed" and bad.name in doc["error"] and f":{i + 1}" in doc["error"]
    assert {r["im_id"] for r in read_bop_csv(summary.csv)} == {0, 1, 3}


def test_unknown_obj_ids_and_missing_scenes_are_clear_errors(lib, dataset, tmp_path):
    root, est = dataset
    with pytest.raises(InputError, match="no scene with id"):
        refine(root, est, lib, tmp_path / "out", scene_ids=[5])
    other = tmp_path / "x_structure-test.csv"
    other.write_text(est.read_text().replace("\n0,", "\n9,", 1))
    with pytest.raises(InputError, match="scenes \\[9\\]"):
        evaluate(root, lib, [other], vsd=False)


def test_cli_refine_and_evaluate(dataset, tmp_path):
    root, est = dataset
    r = runner.invoke(app, ["refine", str(root), "--hypotheses", str(est), "--out",
                            str(tmp_path / "out")])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "est-ssp_structure-test.csv" in "".join(r.output.split())  # rich wraps long paths
    r = runner.invoke(app, ["evaluate", str(root), str(est),
                            str(tmp_path / "out" / "est-ssp_structure-test.csv"), "--no-vsd",
                            "--out", str(tmp_path / "ar.json")])  # fmt: skip
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "ar.json").read_text())
    assert list(res) == [est.name, "est-ssp_structure-test.csv"]


def test_bop_options_are_refused_on_other_inputs(lib, tmp_path):
    from ssp.errors import ArgumentError
    from ssp.pipeline.run import run

    (tmp_path / "in").mkdir()
    with pytest.raises(ArgumentError, match="options of a BOP scene input"):
        run(tmp_path / "in", lib, tmp_path / "out", masks="gt")


def test_run_on_a_published_scene_with_gt_masks(lib, dataset, tmp_path):
    from ssp.pipeline.run import run

    root, est = dataset
    pub = _published(root, tmp_path / "pub")
    run(pub / "test" / "000000", lib_with_bop_names(lib, pub), tmp_path / "out", masks="gt",
        period=0.5, hypotheses="estimated")  # fmt: skip
    doc = json.loads((tmp_path / "out" / "frames" / "000001.json").read_text())
    assert doc["stamp"] == 0.5 and any("ground-truth masks" in w for w in doc["warnings"])
    assert doc["objects"] and all(o["class"].startswith("obj_") for o in doc["objects"])


def test_cli_run_masks_option(dataset, tmp_path):
    root, _ = dataset
    r = runner.invoke(app, ["run", str(root / "test" / "000000"), "--out", str(tmp_path / "out"),
                            "--masks", "gt"])  # fmt: skip
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "out" / "frames" / "000000.json").read_text())
    assert any("ground-truth masks" in w for w in doc["warnings"])
    r = runner.invoke(app, ["run", str(root / "test" / "000000"), "--out", str(tmp_path / "o2"),
                            "--masks", "maybe"])  # fmt: skip
    assert r.exit_code != 0 and "masks must be one of" in r.output


def test_refine_output_folder_rules(lib, dataset, tmp_path):
    from ssp.errors import ArgumentError

    root, est = dataset
    out = tmp_path / "out"
    first = refine(root, est, lib, out, scene_ids=[0]).csv.read_text()
    with pytest.raises(ArgumentError, match="holds an ssp refine: continue it with --resume"):
        refine(root, est, lib, out)
    again = refine(root, est, lib, out, resume=True)  # finished scenes are kept
    assert again.done and again.csv.read_text() == first
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.txt").write_text("mine")
    with pytest.raises(ArgumentError, match="holds no ssp refine"):
        refine(root, est, lib, tmp_path / "other")


def test_bad_scene_files_fail_their_frames_only(lib, dataset, tmp_path):
    """A published scene with an image without cam_K, a negative depth_scale and a truncated
    depth PNG: those three frames fail, each naming its file; the fourth is refined."""
    root, est = dataset
    pub = _published(root, tmp_path / "pub")
    scene = pub / "test" / "000000"
    cams = json.loads((scene / "scene_camera.json").read_text())
    del cams["1"]["cam_K"]
    cams["2"]["depth_scale"] = -1
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (scene / "depth" / "000003.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    summary = refine(pub, est, lib_with_bop_names(lib, pub), tmp_path / "out")
    (s,) = summary.scenes
    assert (s["done"], s["failed"]) == (1, 3)
    frames = tmp_path / "out" / "scenes" / "000000" / "frames"
    errors = {p.stem: json.loads(p.read_text()).get("error", "") for p in frames.glob("*.json")}
    assert errors["000001"].startswith(f"{scene / 'scene_camera.json'}: im_id 1: no valid cam_K")
    assert "depth_scale -1" in errors["000002"] and "scene_camera.json" in errors["000002"]
    assert errors["000003"].startswith(f"{scene / 'depth' / '000003.png'}: cannot read the image")
    assert {r["im_id"] for r in read_bop_csv(summary.csv)} == {0}


def test_refine_keeps_every_object_the_estimator_reported(lib, dataset, tmp_path):
    """Never lower AR: an object ssp rejects (here one floating in the camera's view, where the
    camera sees through it) is still in the CSV, at its pose, scored below every kept object;
    the frame JSON says why it is doubted."""
    root, est = dataset
    rows = est.read_text().splitlines()
    scene_id, im_id, obj_id, *_ = rows[1].split(",")
    R = " ".join(f"{v:g}" for v in np.eye(3).ravel())
    rows.append(f"{scene_id},{im_id},{obj_id},0.99,{R},0 0 250,-1")  # 25 cm from the camera
    bad = tmp_path / "bad_structure-test.csv"
    bad.write_text("\n".join(rows) + "\n")
    summary = refine(root, bad, lib, tmp_path / "out")
    out = read_bop_csv(summary.csv)
    near = [r for r in out if r["im_id"] == int(im_id) and r["t"][2] < 300]
    assert len(near) == 1 and near[0]["obj_id"] == int(obj_id)
    kept = [r["score"] for r in out if r["im_id"] == int(im_id) and r["t"][2] >= 300]
    assert kept and near[0]["score"] < min(kept)
    frame = json.loads(
        (tmp_path / "out" / "scenes" / f"{int(scene_id):06d}" / "frames" / f"{int(im_id):06d}.json")
        .read_text()
    )  # fmt: skip
    assert any(r["reason"] for r in frame["rejected"])
