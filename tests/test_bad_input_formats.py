"""Bad input of the estimator formats, refine, bags and TUM output (issue 35): each case a
typed error naming the file and problem, a warning naming what was passed over, or a skipped
frame; never a silent misread, a traceback or an exit status 0 when no frame succeeded."""

from __future__ import annotations

import inspect
import json
import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from ssp.cli import app
from ssp.errors import InputError
from ssp.geometry import invert
from ssp.io.bop import open_bop
from ssp.io.estimators import read_estimates
from ssp.pipeline.refine import evaluate, refine
from ssp.sim.bop import simulate_to_disk

runner = CliRunner()


# ------------------------------------------------------------------------------ the dataset
@pytest.fixture(scope="module")
def dataset(lib, tmp_path_factory):
    """A two-frame structure dataset as ssp simulate writes it (``models.json``: obj_id ->
    built-in class), and its simulated estimator's hypotheses per image, camera frame."""
    tmp = tmp_path_factory.mktemp("formats")
    (scene_dir,) = simulate_to_disk("structure", 1, 7, out_dir=tmp, library=lib, stages=1,
                                    frames_per_stage=2, stride=4)  # fmt: skip
    scene = open_bop(scene_dir, lib)
    ids = {c: i for i, c in scene.classes.items()}
    images = {}
    for k, im in enumerate(scene.im_ids):
        sf = scene.load(k, masks=None)
        T_cw = invert(np.asarray(sf.T_world_cam))
        images[im] = [(ids[h.class_name], h.score, T_cw @ h.T_world_obj) for h in sf.hypotheses]
    return scene_dir.parent.parent, scene.scene_id, images


def _bop_row(scene_id, im, obj, score, T, t_scale=1000.0):
    R = " ".join(f"{v:.17g}" for v in T[:3, :3].ravel())
    t = " ".join(f"{v:.17g}" for v in T[:3, 3] * t_scale)
    return f"{scene_id},{im},{obj},{score:.17g},{R},{t},0.5"


def _bop_csv(path, rows):
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + "\n".join(rows) + "\n")
    return path


def _write_megapose(folder, images, label):
    folder.mkdir()
    for im, hyps in images.items():
        doc = [{"label": label(obj), "score": score,
                "TWO": [Rotation.from_matrix(T[:3, :3]).as_quat().tolist(), T[:3, 3].tolist()]}
               for obj, score, T in hyps]  # fmt: skip
        (folder / f"{im:06d}.json").write_text(json.dumps(doc))
    return folder


def _write_foundationpose(folder, images, label):
    """One folder per object, the best hypothesis of each object per frame."""
    for im, hyps in images.items():
        best = {}
        for obj, score, T in hyps:
            if obj not in best or score > best[obj][0]:
                best[obj] = (score, T)
        for obj, (_, T) in best.items():
            d = folder / label(obj) / "ob_in_cam"
            d.mkdir(parents=True, exist_ok=True)
            np.savetxt(d / f"{im:06d}.txt", T)
    return folder


def _write_cosypose(path, scene_id, images, label):
    lines = ["scene_id,view_id,label,score,TCO"]
    for im, hyps in images.items():
        for obj, score, T in hyps:
            tco = " ".join(f"{v:.17g}" for v in T.ravel())
            lines.append(f"{scene_id},{im},{label(obj)},{score:.17g},{tco}")
    path.write_text("\n".join(lines) + "\n")
    return path


def _frames(summary):
    """(done, failed) frames over the scenes of a refine summary."""
    return (sum(s.get("done", 0) for s in summary.scenes),
            sum(s.get("failed", 0) for s in summary.scenes))  # fmt: skip


# ------------------------------------------------------------------------------ 1: labels
@pytest.mark.parametrize(
    ("fmt", "label"),
    [
        ("megapose", "id"),  # label "2": the dataset's obj_id as a string
        ("foundationpose", "id"),
        ("cosypose", "id"),
        ("cosypose", "bop"),  # "obj_000002": CosyPose's label of a BOP object
        ("megapose", "class"),  # the library's class name
    ],
)
def test_label_formats_refine_on_a_dataset_with_models_json(lib, dataset, tmp_path, fmt, label):
    """obj_ids are integers in the dataset's models.json, labels strings in the files: they
    match (item 1: every frame failed with "label '2' is not in the label -> class mapping")."""
    root, scene_id, images = dataset
    classes = open_bop(next((root / "test").iterdir())).classes
    name = {"id": str, "bop": lambda o: f"obj_{o:06d}", "class": lambda o: classes[o]}[label]
    if fmt == "megapose":
        path = _write_megapose(tmp_path / "mp", images, name)
    elif fmt == "foundationpose":
        path = _write_foundationpose(tmp_path / "fp", images, name)
    else:
        path = _write_cosypose(tmp_path / "cosy.csv", scene_id, images, name)
    summary = refine(root, path, lib, tmp_path / "out", fmt=fmt)
    assert _frames(summary) == (len(images), 0), summary.scenes


# ------------------------------------------------------------------------------ 2: exit codes
def test_cli_refine_exits_nonzero_when_no_frame_succeeded(dataset, tmp_path):
    """Every row names an obj_id the dataset lacks: every frame fails, the command says so in
    its last line and exits non-zero (it printed "finished (0 of N frames)" and exited 0)."""
    root, scene_id, images = dataset
    rows = [_bop_row(scene_id, im, 99, s, T) for im, hyps in images.items() for _, s, T in hyps]
    csv = _bop_csv(tmp_path / "est_structure-test.csv", rows)
    res = runner.invoke(app, ["refine", str(root), "--hypotheses", str(csv),
                              "--out", str(tmp_path / "out")])  # fmt: skip
    assert res.exit_code == 1, res.output
    assert "no frame succeeded" in res.output.strip().splitlines()[-1]


def test_cli_run_says_no_frame_succeeded(tmp_path):
    """Every cloud of the folder is broken: exit 1 and a final line saying why."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in ("a.ply", "b.ply"):
        (folder / name).write_text("not a ply file\n")
    res = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "out")])
    assert res.exit_code == 1, res.output
    assert "no frame succeeded" in res.output.strip().splitlines()[-1]


def test_estimates_of_another_scene_are_an_error(lib, dataset, tmp_path):
    """A CSV whose rows all name a scene the dataset lacks: not a refine with an empty CSV."""
    root, scene_id, images = dataset
    rows = [_bop_row(scene_id + 7, im, o, s, T) for im, h in images.items() for o, s, T in h]
    csv = _bop_csv(tmp_path / "est_structure-test.csv", rows)
    with pytest.raises(InputError, match=rf"est_structure-test.csv: none of its {len(images)} "
                       rf"images \(scenes \[{scene_id + 7}\]"):  # fmt: skip
        refine(root, csv, lib, tmp_path / "out")
    # per-image files whose names are no image of the scene
    mp = _write_megapose(tmp_path / "mp", {im + 50: h for im, h in images.items()}, str)
    with pytest.raises(InputError, match=r"mp: none of its 2 images"):
        refine(root, mp, lib, tmp_path / "out2")


def test_estimates_naming_absent_images_and_scenes_warn(lib, dataset, tmp_path, caplog):
    root, scene_id, images = dataset
    rows = [_bop_row(scene_id, im, o, s, T) for im, h in images.items() for o, s, T in h]
    o, s, T = images[0][0]
    rows += [_bop_row(scene_id, 99, o, s, T), _bop_row(scene_id + 5, 0, o, s, T)]
    csv = _bop_csv(tmp_path / "est_structure-test.csv", rows)
    with caplog.at_level(logging.WARNING):
        summary = refine(root, csv, lib, tmp_path / "out")
    assert _frames(summary) == (len(images), 0)
    assert f"names scenes the dataset lacks: [{scene_id + 5}]" in caplog.text
    assert f"1 of its images are not in the refined scenes (no such im_id): scene {scene_id} " \
           "image 99" in caplog.text  # fmt: skip


def test_bop19_translations_in_metres_warn(dataset, tmp_path, caplog):
    root, scene_id, images = dataset
    rows = [_bop_row(scene_id, im, o, s, T, t_scale=1.0) for im, h in images.items()
            for o, s, T in h]  # fmt: skip
    csv = _bop_csv(tmp_path / "est_structure-test.csv", rows)
    classes = open_bop(next((root / "test").iterdir())).classes
    with caplog.at_level(logging.WARNING):
        read_estimates(csv, "bop19", classes)
    assert "BOP19's t is in millimetres, these look like metres" in caplog.text
    caplog.clear()
    csv = _bop_csv(tmp_path / "mm.csv", [_bop_row(scene_id, 0, o, s, T) for o, s, T in images[0]])
    with caplog.at_level(logging.WARNING):
        read_estimates(csv, "bop19", classes)
    assert "millimetres" not in caplog.text


# ------------------------------------------------------------------------------ 3: names
@pytest.mark.parametrize("fmt", ["megapose", "foundationpose"])
def test_a_stray_file_shifts_no_image(dataset, tmp_path, caplog, fmt):
    """000000_backup.json beside 000000.json, 000001.json: every image keeps its own file
    (they were matched by position, so 000001 got the backup's hypotheses)."""
    root, scene_id, images = dataset
    o, s, T = images[0][0]
    T2 = T.copy()
    T2[:3, 3] += 0.1
    per_image = {0: [(o, s, T)], 1: [(o, s, T2)]}
    if fmt == "megapose":
        path = _write_megapose(tmp_path / "mp", per_image, str)
        (path / "000000_backup.json").write_text((path / "000000.json").read_text())
        stray = "000000_backup"
    else:
        path = _write_foundationpose(tmp_path / "fp", per_image, str)
        d = path / str(o) / "ob_in_cam"
        (d / "000000 (copy).txt").write_text((d / "000000.txt").read_text())
        stray = "000000 (copy)"
    with caplog.at_level(logging.WARNING):
        est = read_estimates(path, fmt, {o: "cube"})
    assert est.images() == [(0, 0), (0, 1)]
    np.testing.assert_allclose(est.for_image(0, 1)[0].T_world_obj, T2, atol=1e-9)
    np.testing.assert_allclose(est.for_image(0, 0)[0].T_world_obj, T, atol=1e-9)
    assert "1 files name no image" in caplog.text and stray in caplog.text


# ------------------------------------------------------------------------------ 4: bags
def _bag_writer(path):
    pytest.importorskip("rosbags")
    from test_io_rosbag import BagWriter

    return BagWriter(path, "ros1")


def _image_at(bw, topic, header_ns, bag_ns, arr, encoding):
    """An Image stamped ``header_ns`` written at bag time ``bag_ns``."""
    h, w = arr.shape
    msg = bw.T["sensor_msgs/msg/Image"](
        header=bw.header(header_ns), height=h, width=w, encoding=encoding, is_bigendian=0,
        step=w * arr.dtype.itemsize, data=np.ascontiguousarray(arr).view(np.uint8).reshape(-1),
    )  # fmt: skip
    bw.put(topic, "sensor_msgs/msg/Image", bag_ns, msg)


def test_bag_frames_sharing_a_stamp_get_their_own_masks(dataset, tmp_path, caplog):
    """Two depth frames and their two masks all stamped alike: each frame its own mask, in
    bag order (both got the first frame's), and a warning about the shared stamps."""
    from ssp.io.rosbag import open_bag

    root, _, _ = dataset
    scene = open_bop(next((root / "test").iterdir()))
    sf = scene.load(0, masks=None)
    depth = np.asarray(sf.depth, dtype=np.float32)
    bw = _bag_writer(tmp_path / "dup.bag")
    stamp = 1_700_000_000 * 10**9
    for k in range(2):
        bag_ns = stamp + k * 10_000_000
        _image_at(bw, "/camera/depth/image_rect", stamp, bag_ns, depth, "32FC1")
        bw.camera_info("/camera/depth/camera_info", stamp, sf.camera)
        mask = np.full(depth.shape, k + 1, dtype=np.uint16)
        _image_at(bw, "/camera/segmentation_mask", stamp, bag_ns + 1, mask, "mono16")
    bw.close()
    with caplog.at_level(logging.WARNING):
        bag = open_bag(tmp_path / "dup.bag", {})
    f0, f1 = (fs.load() for fs in bag.frames())
    assert np.all(f0.labels == 1) and np.all(f1.labels == 2)
    assert "stamps of /camera/depth/image_rect are each on several messages" in caplog.text


def test_bag_without_masks_says_it_clusters(lib, dataset, tmp_path):
    """No mask topic: the frames are clustered, which the run says once (log and summary)."""
    from ssp.pipeline.run import run

    root, _, _ = dataset
    scene = open_bop(next((root / "test").iterdir()), lib)
    bw = _bag_writer(tmp_path / "nomask.bag")
    base = 1_700_000_000 * 10**9
    for k in range(len(scene)):
        sf = scene.load(k, masks=None)
        ns = base + int(round(sf.stamp * 1e9))
        if k == 0:
            bw.tf("/tf_static", ns, [bw.transform("world", "camera_optical", 0, sf.T_world_cam)])
        bw.image("/camera/depth/image_rect", ns, np.asarray(sf.depth, np.float32), "32FC1")
        bw.camera_info("/camera/depth/camera_info", ns, sf.camera)
        doc = {"frame": "world", "hypotheses": [
            {"class": h.class_name, "score": h.score, "T": np.asarray(h.T_world_obj).tolist()}
            for h in sf.hypotheses]}  # fmt: skip
        bw.string("/ssp/hypotheses", ns, json.dumps(doc))
    bw.close()
    s = run(tmp_path / "nomask.bag", lib, tmp_path / "out", bag={"world_frame": "world"})
    said = [w for w in s.warnings if "no instance mask topic" in w["warning"]]
    assert len(said) == 1 and "clustering" in said[0]["warning"], s.warnings
    assert len(s.done) == len(scene)


# ------------------------------------------------------------------------------ 5: duplicates
def test_duplicated_rows_are_merged_with_a_warning(dataset, tmp_path, caplog):
    """The same row three times is one hypothesis (three would take three of the places kept
    per object and crowd out the others: AR 0.756 -> 0.736)."""
    root, scene_id, images = dataset
    hyps = images[0]
    rows = [_bop_row(scene_id, 0, o, s, T) for o, s, T in hyps]
    rows += rows[:1] * 2
    csv = _bop_csv(tmp_path / "dup.csv", rows)
    classes = open_bop(next((root / "test").iterdir())).classes
    with caplog.at_level(logging.WARNING):
        est = read_estimates(csv, "bop19", classes)
    assert len(est.for_image(scene_id, 0)) == len(hyps)
    assert "2 duplicated rows or entries" in caplog.text


# ------------------------------------------------------------------------------ 6: rotations
def test_evaluate_refuses_rotations_that_are_not_3x3(lib, dataset, tmp_path):
    """A result row or a ground-truth entry whose R is 3x2 (6 numbers) is an error naming the
    file and the row, not a reshape message (nor a score)."""
    import shutil

    root, scene_id, images = dataset
    o, s, T = images[0][0]
    good = _bop_row(scene_id, 0, o, s, T)
    parts = good.split(",")
    parts[4] = " ".join(parts[4].split()[:6])
    csv = _bop_csv(tmp_path / "r_structure-test.csv", [good, ",".join(parts)])
    with pytest.raises(InputError, match=r"r_structure-test.csv:3: R must be 9 numbers "
                       r"\(3x3, row-major\), got 6"):  # fmt: skip
        evaluate(root, lib, [csv], vsd=False)
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    scene = next((copy / "test").iterdir())
    gt = json.loads((scene / "scene_gt.json").read_text())
    first = sorted(gt, key=int)[0]
    gt[first][0]["cam_R_m2c"] = gt[first][0]["cam_R_m2c"][:6]
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    csv = _bop_csv(tmp_path / "ok_structure-test.csv", [good])
    with pytest.raises(InputError, match=rf"scene_gt.json: im_id {first}, entry 0: cam_R_m2c "
                       r"must be 9 numbers"):  # fmt: skip
        evaluate(copy, lib, [csv], vsd=False)


def test_bop_evaluator_refuses_a_pose_that_is_not_4x4(lib):
    from ssp.camera import Camera
    from ssp.eval.bop_metrics import BopEvaluator

    cls = next(iter(lib))
    T = np.eye(4)
    T[2, 3] = 0.5
    cam = Camera(fx=500.0, fy=500.0, cx=80.0, cy=60.0, width=160, height=120)
    ev = BopEvaluator(lib, vsd=False)
    with pytest.raises(ValueError, match=r"estimate 0: a pose must be a finite 4x4 matrix"):
        ev.add_frame({"a": (cls, T)}, {"a": 1.0}, [(cls, T[:3, :2], 1.0)], cam, np.eye(4))


# ------------------------------------------------------------------------------ 7: parsing
def test_a_deeply_nested_json_is_an_input_error(dataset, tmp_path):
    """json recursing past Python's limit killed the whole refine (RecursionError)."""
    root, scene_id, images = dataset
    mp = _write_megapose(tmp_path / "mp", images, str)
    deep = "[" * 200_000 + "]" * 200_000
    (mp / "000000.json").write_text(deep)
    est = read_estimates(mp, "megapose")
    with pytest.raises(InputError, match=r"000000.json: invalid JSON: nested too deeply"):
        est.for_image(0, 0)
    assert est.for_image(0, 1)  # the other image reads
    with pytest.raises(InputError, match=r"000000.json: invalid JSON: nested too deeply"):
        read_estimates(mp / "000000.json", "megapose")
    (tmp_path / "syntax.json").write_text("[{")
    with pytest.raises(InputError, match=r"syntax.json: invalid JSON"):
        read_estimates(tmp_path / "syntax.json", "megapose")


def test_a_deeply_nested_hypotheses_file_is_an_input_error(tmp_path):
    from ssp.io.hypotheses import read_hypotheses

    p = tmp_path / "frame.hypotheses.json"
    p.write_text('{"hypotheses": ' + "[" * 200_000 + "]" * 200_000 + "}")
    with pytest.raises(InputError, match=r"frame.hypotheses.json: invalid JSON: nested too"):
        read_hypotheses(p)


# ------------------------------------------------------------------------------ 8: TUM stamps
@pytest.mark.parametrize(
    ("stamp", "text"),
    [
        (1_700_000_000_100_000_000 * 1e-9, "1700000000.1"),  # was 1700000000.1000001
        (1_700_000_000_033_333_333 * 1e-9, "1700000000.033333"),  # float holds ~0.2 us there
        (1 / 30, "0.033333333"),
        (0.0, "0.0"),
        (2.5, "2.5"),
    ],
)
def test_tum_stamps_print_without_float_noise(stamp, text):
    from ssp.io.tum import tum_line

    line = tum_line(stamp, np.eye(4))
    assert line.split()[0] == text
    assert abs(float(text) - stamp) <= max(0.5e-9, np.spacing(stamp))


# ------------------------------------------------------------------------------ 9: help texts
def test_help_texts_state_the_true_defaults():
    from ssp.cli import datasets, run

    assert "default: detected" not in run.WorldFrameOption.help
    assert "table" in run.WorldFrameOption.help
    assert "default: detected" not in run.ClassMapOption.help
    assert "class names" in run.ClassMapOption.help
    for cmd in (datasets.refine_cmd, datasets.evaluate_cmd, datasets.estimate_cmd):
        help_text = inspect.signature(cmd).parameters["models"].default.help
        assert "the dataset's models/ folder" in help_text, (cmd.__name__, help_text)
