"""Readers of pose estimators' outputs (ssp.io.estimators): files written the way each upstream
library writes them, and bad files whose problems stay with their image."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.errors import ArgumentError, InputError
from ssp.io.estimators import (
    EstimatorHypotheses,
    detect_format,
    read_bop19_csv,
    read_cosypose_csv,
    read_estimates,
    read_foundationpose,
    read_megapose,
)
from ssp.io.hypotheses import to_world
from ssp.io.results import ObjectIds, read_bop_csv

LIBRARY = ["cracker_box", "mug", "mustard_bottle"]


def _pose(euler=(0.4, -0.1, 0.9), t=(0.1, -0.05, 0.7)):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", euler).as_matrix()
    T[:3, 3] = t
    return T


T_A = _pose()
T_B = _pose((1.2, 0.3, -2.0), (-0.12, 0.04, 0.85))
T_C = _pose((-0.7, 2.1, 0.2), (0.02, 0.1, 0.6))


# ------------------------------------------------------------------------------ BOP19
def _bop_toolkit_csv(path, results):
    """What bop_toolkit_lib.inout.save_bop_results writes (header, ' '.join(map(str, ...)),
    lines joined by newlines, no final newline)."""
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for e in results:
        R = " ".join(map(str, e["R"].flatten().tolist()))
        t = " ".join(map(str, e["t"].flatten().tolist()))
        lines.append(f"{e['scene_id']},{e['im_id']},{e['obj_id']},{e['score']},{R},{t},{e['time']}")
    path.write_text("\n".join(lines))
    return path


def _bop_row(scene, im, obj, score, T, time=0.5):
    return {"scene_id": scene, "im_id": im, "obj_id": obj, "score": score, "R": T[:3, :3],
            "t": T[:3, 3] * 1000.0, "time": time}  # fmt: skip


def test_bop19_csv_as_the_toolkit_writes_it(tmp_path):
    path = _bop_toolkit_csv(
        tmp_path / "cosypose_ycbv-test.csv",
        [
            _bop_row(48, 1, 2, 0.4, T_A),
            _bop_row(48, 1, 5, 0.9, T_B),
            _bop_row(48, 1, 2, 0.9, T_C),  # same score as the row before: file order kept
            _bop_row(48, 7, 5, 0.3, T_C),
            _bop_row(50, 0, 2, 0.8, T_A),
        ],
    )
    est = read_bop19_csv(path, {2: "cracker_box", "5": "mustard_bottle"}, library=LIBRARY)
    assert isinstance(est, EstimatorHypotheses) and est.format == "bop19"
    assert est.images() == [(48, 1), (48, 7), (50, 0)] and est.bad_images() == []
    hyps = est.for_image(48, 1)
    assert [(h.class_name, h.score) for h in hyps] == [
        ("mustard_bottle", 0.9),
        ("cracker_box", 0.9),
        ("cracker_box", 0.4),
    ]
    for h, T in zip(hyps, (T_B, T_C, T_A), strict=True):
        np.testing.assert_allclose(h.T_world_obj, T, atol=1e-12)  # mm -> m, camera frame
    assert est.for_image(48, 2) == []  # an image the estimator wrote nothing for
    # ObjectIds (class -> obj_id) works as the mapping; auto detection finds the format
    ids = ObjectIds({"cracker_box": 2, "mustard_bottle": 5})
    again = read_estimates(path, classes=ids)
    assert again.format == "bop19"
    np.testing.assert_array_equal(
        again.for_image(50, 0)[0].T_world_obj, est.for_image(50, 0)[0].T_world_obj
    )
    # the existing reader still reads the same file
    assert len(read_bop_csv(path)) == 5
    # camera frame -> world with the camera pose
    T_wc = _pose((0.1, 0.2, 0.3), (1.0, 2.0, 0.5))
    np.testing.assert_allclose(to_world(hyps, T_wc)[0].T_world_obj, T_wc @ T_B, atol=1e-12)


def test_bop19_bad_rows_fail_only_their_image(tmp_path):
    good = _bop_row(1, 0, 2, 0.9, T_A)
    path = _bop_toolkit_csv(tmp_path / "x_ycbv-test.csv", [good, _bop_row(1, 6, 2, 0.5, T_B)])
    lines = path.read_text().split("\n")
    R_nan = " ".join(["nan"] + ["0.0"] * 8)
    R_bad = "1 0 0 0 1 0 0 0 2"  # not orthonormal
    lines += [
        f"1,1,2,0.5,{R_nan},0 0 500,-1",
        f"1,2,2,0.5,{R_bad},0 0 500,-1",
        "1,3,2,0.5,1 0 0 0 1 0 0 0 1,0 0 500",  # 6 columns, ids readable
        "1,4,7,0.5,1 0 0 0 1 0 0 0 1,0 0 500,-1",  # unknown obj_id
        "1,5,2,nan,1 0 0 0 1 0 0 0 1,0 0 500,-1",  # NaN score
        "1,6,2,0.5,1 0 0 0 1 0 0,0 0 500,-1",  # 7 rotation numbers; image 6 also has a good row
    ]
    path.write_text("\n".join(lines) + "\n")
    est = read_bop19_csv(path, {2: "cracker_box", 5: "mug"})
    assert est.images() == [(1, i) for i in range(7)]
    assert est.bad_images() == [(1, i) for i in range(1, 7)]
    np.testing.assert_allclose(est.for_image(1, 0)[0].T_world_obj, T_A, atol=1e-12)
    expect = {
        1: (4, "NaN"),
        2: (5, "not a rotation"),
        3: (6, "expected 7 columns, got 6"),
        4: (7, r"obj_id 7 has no class; known obj_ids: 2 \(cracker_box\), 5 \(mug\)"),
        5: (8, "score is nan"),
        6: (9, r"R must be 9 numbers \(3x3, row-major\), got 7"),
    }
    for im, (line, what) in expect.items():
        with pytest.raises(InputError, match=rf"x_ycbv-test.csv:{line}\b.*{what}"):
            est.for_image(1, im)
        assert est.problems(1, im)
    # a row that names no image fails the file
    path.write_text("\n".join([*lines, "one,2,3"]) + "\n")
    with pytest.raises(InputError, match=r"x_ycbv-test.csv:10: .*belongs to no image"):
        read_bop19_csv(path, {2: "cracker_box"})


def test_bop19_unreadable_files(tmp_path):
    with pytest.raises(InputError, match=r"missing.csv: no such file"):
        read_bop19_csv(tmp_path / "missing.csv", {1: "mug"})
    (tmp_path / "bad.csv").write_text("scene_id,im_id,obj,score\n1,0,1,0.5\n")
    with pytest.raises(InputError, match=r"bad.csv: not a BOP19 results CSV \(header"):
        read_bop19_csv(tmp_path / "bad.csv", {1: "mug"})
    with pytest.raises(ArgumentError, match="obj_id -> class"):
        read_bop19_csv(tmp_path / "bad.csv", None)
    with pytest.raises(ArgumentError, match=r"'mugg' is not in the library \(did you mean 'mug'"):
        read_bop19_csv(tmp_path / "bad.csv", {1: "mugg"}, library=LIBRARY)


# ------------------------------------------------------------------------------ MegaPose
def _object_data_json(objects):
    """json.dumps([ObjectData(label, TWO=Transform(pose)).to_json() ...]) as MegaPose's
    save_predictions writes it: TWO = [quaternion.coeffs() (x, y, z, w), translation]."""
    return json.dumps(
        [{"label": label, "TWO": [_quat_xyzw(T), T[:3, 3].tolist()]} for label, T in objects]
    )


def _quat_xyzw(T):
    return Rotation.from_matrix(T[:3, :3]).as_quat().tolist()


def test_megapose_example_folders_and_quaternion_order(tmp_path):
    for name, objects in (
        ("000003", [("mug", T_A), ("cracker_box", T_B)]),
        ("000010", [("mug", T_C)]),
    ):
        out = tmp_path / name / "outputs"
        out.mkdir(parents=True)
        (out / "object_data.json").write_text(_object_data_json(objects))
    # the input detections file next to it (no TWO) is not read
    (tmp_path / "000003" / "inputs").mkdir()
    (tmp_path / "000003" / "inputs" / "object_data.json").write_text('[{"label": "mug"}]')
    est = read_megapose(tmp_path, library=LIBRARY, scene_id=4)
    assert est.format == "megapose" and detect_format(tmp_path) == "megapose"
    assert est.images() == [(4, 3), (4, 10)] and est.names[(4, 10)] == "000010"
    hyps = est.for_image(4, 3)
    assert [h.class_name for h in hyps] == ["mug", "cracker_box"]  # scores all 1.0: file order
    np.testing.assert_allclose(hyps[0].T_world_obj, T_A, atol=1e-12)
    np.testing.assert_allclose(hyps[1].T_world_obj, T_B, atol=1e-12)
    # the quaternion is x, y, z, w: read as w, x, y, z it would give another rotation
    q = Rotation.from_matrix(T_A[:3, :3]).as_quat()
    wrong = Rotation.from_quat(np.roll(q, -1)).as_matrix()
    assert np.abs(wrong - hyps[0].T_world_obj[:3, :3]).max() > 0.1


def test_megapose_folder_of_image_files_with_label_mapping(tmp_path):
    (tmp_path / "frame2.json").write_text(_object_data_json([("obj_000002", T_A)]))
    (tmp_path / "frame10.json").write_text(_object_data_json([("obj_000005", T_B)]))
    (tmp_path / "frame7.json").write_text(_object_data_json([("obj_000009", T_C)]))  # unknown
    (tmp_path / "frame8.json").write_text('{"label": "mug"}')  # not a list
    (tmp_path / "frame9.json").write_text("[{")  # invalid JSON
    doc = json.loads(_object_data_json([("obj_000002", T_A), ("obj_000005", T_B)]))
    doc[0]["TWO"][0] = [float("nan"), 0.0, 0.0, 1.0]
    del doc[1]["TWO"]
    (tmp_path / "frame11.json").write_text(json.dumps(doc))
    labels = {"obj_000002": "cracker_box", "obj_000005": "mustard_bottle"}
    est = read_estimates(tmp_path, classes=labels, library=LIBRARY)
    # im_ids are the numbers ending the names (never their positions)
    assert [est.names[k] for k in est.images()] == [
        "frame2", "frame7", "frame8", "frame9", "frame10", "frame11"
    ]  # fmt: skip
    assert est.images() == [(0, i) for i in (2, 7, 8, 9, 10, 11)]
    assert est.for_image(0, 2)[0].class_name == "cracker_box"
    np.testing.assert_allclose(est.for_image(0, 10)[0].T_world_obj, T_B, atol=1e-12)
    with pytest.raises(InputError, match=r"frame7.json: entry 0 .*'obj_000009' is not in the "
                       r"label -> class mapping \(did you mean 'obj_00000[25]'"):  # fmt: skip
        est.for_image(0, 7)
    with pytest.raises(InputError, match=r"frame8.json: not MegaPose estimates"):
        est.for_image(0, 8)
    with pytest.raises(InputError, match=r"frame9.json: invalid JSON"):
        est.for_image(0, 9)
    with pytest.raises(InputError, match=r"frame11.json: entry 0 .*NaN.*; .*entry 1 .*no 'TWO'"):
        est.for_image(0, 11)
    # HappyPose's example output name, a score key, identity labels with a close name
    ex = tmp_path / "hp" / "12" / "outputs"
    ex.mkdir(parents=True)
    doc = json.loads(_object_data_json([("mugs", T_A), ("mug", T_B)]))
    doc[1]["score"] = 0.7
    (ex / "object_data_inf.json").write_text(json.dumps(doc))
    est = read_megapose(tmp_path / "hp", library=LIBRARY)
    with pytest.raises(InputError, match=r"'mugs' is not in the library \(did you mean 'mug'"):
        est.for_image(0, 12)


def test_megapose_unreadable(tmp_path):
    with pytest.raises(InputError, match="nothing: no such file or folder"):
        read_megapose(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: no MegaPose estimates"):
        read_megapose(tmp_path / "empty")
    (tmp_path / "one.json").write_text('{"objects": []}')
    with pytest.raises(InputError, match="one.json: not MegaPose estimates"):
        read_megapose(tmp_path / "one.json")  # a single file that cannot be read fails whole
    (tmp_path / "5.json").write_text(_object_data_json([("mug", T_A)]))
    assert read_megapose(tmp_path / "5.json").images() == [(0, 5)]


# ------------------------------------------------------------------------------ FoundationPose
def _foundationpose_demo(debug_dir, poses):
    """What run_demo.py writes per frame: np.savetxt(f'{debug_dir}/ob_in_cam/{id_str}.txt',
    pose.reshape(4, 4))."""
    (debug_dir / "ob_in_cam").mkdir(parents=True, exist_ok=True)
    for id_str, pose in poses.items():
        np.savetxt(debug_dir / "ob_in_cam" / f"{id_str}.txt", pose.reshape(4, 4))


def test_foundationpose_one_folder_per_object(tmp_path):
    ids = ["1581120424100262102", "1581120424148532296", "1581120424213125141"]
    _foundationpose_demo(tmp_path / "mustard", {ids[0]: T_A, ids[1]: T_B, ids[2]: T_C})
    _foundationpose_demo(tmp_path / "cracker", {ids[0]: T_C, ids[1]: T_A})  # lost in frame 3
    est = read_estimates(tmp_path, classes={"mustard": "mustard_bottle", "cracker": "cracker_box"})
    assert est.format == "foundationpose"
    assert est.images() == [(0, int(i)) for i in ids]  # numeric frame ids are the im_ids
    assert est.names[(0, int(ids[2]))] == ids[2]
    hyps = est.for_image(0, int(ids[0]))
    assert sorted(h.class_name for h in hyps) == ["cracker_box", "mustard_bottle"]
    by_class = {h.class_name: h.T_world_obj for h in hyps}
    np.testing.assert_allclose(by_class["mustard_bottle"], T_A, atol=1e-15)
    np.testing.assert_allclose(by_class["cracker_box"], T_C, atol=1e-15)
    assert [h.class_name for h in est.for_image(0, int(ids[2]))] == ["mustard_bottle"]
    assert est.key_of_name(ids[1]) == (0, int(ids[1]))


def test_foundationpose_single_object_and_bad_files(tmp_path):
    debug = tmp_path / "debug"
    _foundationpose_demo(debug, {"0000": T_A, "0001": T_B, "0002": T_B, "0003": T_B, "0004": T_C})
    bad_R = T_B.copy()
    bad_R[:3, :3] *= 1.5
    np.savetxt(debug / "ob_in_cam" / "0001.txt", bad_R)
    nan = T_B.copy()
    nan[0, 3] = np.nan
    np.savetxt(debug / "ob_in_cam" / "0002.txt", nan)
    np.savetxt(debug / "ob_in_cam" / "0003.txt", T_B[:3])  # 3x4
    (debug / "ob_in_cam" / "0004.txt").write_text("1 0 0 0\n0 1 zero 0\n")
    est = read_foundationpose(debug, object_name="mug", library=LIBRARY, scene_id=2)
    assert est.images() == [(2, i) for i in range(5)] and est.bad_images() == [
        (2, i) for i in range(1, 5)
    ]
    np.testing.assert_allclose(est.for_image(2, 0)[0].T_world_obj, T_A, atol=1e-15)
    for im, what in (
        (1, "not a rotation"),
        (2, "NaN"),
        (3, r"expected a 4x4 matrix"),
        (4, "not a 4x4 matrix of numbers"),
    ):
        with pytest.raises(InputError, match=rf"ob_in_cam/000{im}.txt.*{what}"):
            est.for_image(2, im)
    # the folder's name is the object's when none is given: 'debug' is no class
    est = read_foundationpose(debug / "ob_in_cam", library=LIBRARY)
    with pytest.raises(InputError, match=r"'debug' is not in the library"):
        est.for_image(0, 0)
    with pytest.raises(InputError, match="no FoundationPose poses"):
        (tmp_path / "empty").mkdir()
        read_foundationpose(tmp_path / "empty")
    with pytest.raises(InputError, match="is a file, not a folder"):
        read_foundationpose(debug / "ob_in_cam" / "0000.txt")


# ------------------------------------------------------------------------------ CosyPose
def _cosypose_rows(preds):
    """The prediction table (infos: scene_id, view_id, label, score, batch_im_id; poses: TCO)
    as rows of the CSV."""
    return [
        {"scene_id": s, "view_id": v, "label": label, "score": score, "batch_im_id": k,
         "TCO": " ".join(map(str, T.flatten().tolist()))}
        for k, (s, v, label, score, T) in enumerate(preds)
    ]  # fmt: skip


PREDS = [
    (1, 3, "obj_000002", 0.2, T_A),
    (1, 3, "obj_000005", 0.95, T_B),
    (1, 4, "obj_000002", 0.6, T_C),
]
LABELS = {"obj_000002": "cracker_box", "obj_000005": "mustard_bottle"}


def _check_cosypose(est):
    assert est.format == "cosypose" and est.images() == [(1, 3), (1, 4)]
    hyps = est.for_image(1, 3)
    assert [(h.class_name, h.score) for h in hyps] == [
        ("mustard_bottle", 0.95),
        ("cracker_box", 0.2),
    ]
    np.testing.assert_allclose(hyps[0].T_world_obj, T_B, atol=1e-12)
    np.testing.assert_allclose(est.for_image(1, 4)[0].T_world_obj, T_C, atol=1e-12)


def test_cosypose_csv(tmp_path):
    path = tmp_path / "candidates.csv"
    rows = _cosypose_rows(PREDS)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, ["scene_id", "view_id", "label", "score", "batch_im_id", "TCO"])
        w.writeheader()
        w.writerows(rows)
    _check_cosypose(read_estimates(path, classes=LABELS))


def test_cosypose_csv_written_by_pandas(tmp_path):
    pd = pytest.importorskip("pandas")
    path = tmp_path / "preds.csv"
    pd.DataFrame(_cosypose_rows(PREDS)).to_csv(path, index=False)
    assert detect_format(path) == "cosypose"
    _check_cosypose(read_cosypose_csv(path, LABELS, library=LIBRARY))


def test_cosypose_bad_rows(tmp_path):
    path = tmp_path / "c.csv"
    good = _cosypose_rows(PREDS[:1])[0]
    lines = ["scene_id,view_id,label,score,TCO", f"1,0,obj_000002,0.5,{good['TCO']}"]
    lines += [
        "1,1,obj_000002,0.5,1 0 0 0 0 1 0 0 0 0 1 0 0 0 0",  # 15 numbers
        f"1,2,obj_000002,0.5,{good['TCO']},extra",
        f"1,3,obj_000003,0.5,{good['TCO']}",
        "1,4,obj_000002,0.5,1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1",  # last row not 0 0 0 1
    ]
    path.write_text("\n".join(lines) + "\n")
    est = read_cosypose_csv(path, LABELS)
    np.testing.assert_allclose(est.for_image(1, 0)[0].T_world_obj, T_A, atol=1e-12)
    for im, what in (
        (1, "TCO must be 16 numbers"),
        (2, "expected 5 columns, got 6"),
        (3, "'obj_000003' is not in the label -> class mapping"),
        (4, "last row"),
    ):
        with pytest.raises(InputError, match=rf"c.csv:{im + 2}\b.*{what}"):
            est.for_image(1, im)
    path.write_text("\n".join([*lines, "a,b,obj_000002,0.5,1"]) + "\n")
    with pytest.raises(InputError, match=r"c.csv:7: .*belongs to no image"):
        read_cosypose_csv(path, LABELS)
    path.write_text("scene_id,im_id,label,TCO\n")
    with pytest.raises(InputError, match=r"c.csv: not a CosyPose CSV: the header lacks view_id"):
        read_cosypose_csv(path)


# ------------------------------------------------------------------------------ detection
def test_detect_format_says_when_it_cannot(tmp_path):
    (tmp_path / "x.csv").write_text("a,b,c\n")
    with pytest.raises(InputError, match=r"x.csv: cannot tell the format: the header 'a,b,c'"):
        read_estimates(tmp_path / "x.csv")
    (tmp_path / "x.ply").write_text("ply\n")
    with pytest.raises(InputError, match="cannot tell the format from a .ply file"):
        detect_format(tmp_path / "x.ply")
    (tmp_path / "folder" / "sub").mkdir(parents=True)
    with pytest.raises(InputError, match="cannot tell the format of this folder"):
        detect_format(tmp_path / "folder")
    with pytest.raises(InputError, match="no such file or folder"):
        detect_format(tmp_path / "nothing")
    with pytest.raises(ArgumentError, match="unknown estimator format 'ppf'"):
        read_estimates(tmp_path / "x.csv", fmt="ppf")
    _foundationpose_demo(tmp_path / "fp", {"1": T_A})
    assert detect_format(tmp_path / "fp") == "foundationpose"
    assert detect_format(tmp_path / "fp" / "ob_in_cam") == "foundationpose"
