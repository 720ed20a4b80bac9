"""Result files: per-frame JSON records, the BOP19 CSV, and BOP object ids."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.errors import InputError, UnknownObjectError
from ssp.io.results import (
    BOP_CSV_HEADER,
    BopCsvWriter,
    ObjectIds,
    bop_csv_name,
    frame_record,
    read_bop_csv,
    write_json,
)
from ssp.parser import ObjectEstimate, SceneEstimate, SupportEdge
from ssp.probability import ObjectTerms
from ssp.scene import TransitionMode


def _pose(euler=(0.4, -0.1, 0.9), t=(0.1, 0.2, 0.03)):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", euler).as_matrix()
    T[:3, 3] = t
    return T


def _estimate():
    terms = ObjectTerms(stability=-0.1, collision=0.0, support=-0.2, data=-1.5, transition=-0.3)
    cube = ObjectEstimate("cube_0", "cube", _pose(), TransitionMode.ADDED, terms=terms, fit=0.8)
    gone = ObjectEstimate(
        "mug_0", "mug", _pose(t=(0, 0, 0.1)), TransitionMode.REMOVED, source="removed"
    )
    return SceneEstimate(
        stamp=0.2,
        frame_index=2,
        objects=(cube,),
        removed=(gone,),
        support=(SupportEdge("table", "cube_0", 1.0),),
        log_prob=terms.total,
        timings={"total": 0.5},
    )


def test_frame_record_has_pose_parts_and_extra(tmp_path):
    rec = frame_record(_estimate(), name="frame2", index=1, extra={"skipped_hypotheses": 3})
    assert rec["name"] == "frame2" and rec["index"] == 1 and rec["skipped_hypotheses"] == 3
    assert rec["frame_index"] == 2 and rec["stamp"] == 0.2
    for obj in (rec["objects"][0], rec["removed"][0]):
        T = np.array(obj["T_world_obj"])
        np.testing.assert_allclose(obj["R"], T[:3, :3])
        np.testing.assert_allclose(obj["t"], T[:3, 3])
        q = np.array(obj["quat_xyzw"])
        assert q[3] >= 0
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-12)
    assert rec["removed"][0]["log_prob"] is None
    back = json.loads(write_json(tmp_path / "frames" / "frame2.json", rec).read_text())
    assert back["objects"][0]["terms"]["data"] == -1.5 and back["objects"][0]["mode"] == "added"
    with pytest.raises(ValueError, match="overwrite"):
        frame_record(_estimate(), name="f", index=0, extra={"objects": []})


def test_write_json_strict_and_atomic(tmp_path):
    path = tmp_path / "a.json"
    path.write_text("old")
    obj = {"arr": np.arange(3.0), "n": np.int64(4), "bad": [np.nan, -np.inf], "t": (1, 2), 5: "k"}
    write_json(path, obj)
    assert json.loads(path.read_text()) == {
        "arr": [0.0, 1.0, 2.0],
        "n": 4,
        "bad": [None, None],
        "t": [1, 2],
        "5": "k",
    }
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]  # no temporary file left
    with pytest.raises(TypeError):
        write_json(tmp_path / "b.json", {"x": object()})
    assert not (tmp_path / "b.json").exists() and len(list(tmp_path.iterdir())) == 1


def test_bop_csv_rows_and_units(tmp_path):
    path = tmp_path / bop_csv_name("my_scenes-1")
    assert path.name == "ssp_myscenes1-test.csv"
    T1, T2 = _pose(), _pose((0.0, 0.0, 3.0), (-0.05, 0.0, 0.75))
    with BopCsvWriter(path, "ssp") as w:
        w.add(1, 0, 3, 0.9, T1, time=0.25)
        w.add(1, 0, 1, 0.4, T2, time=0.25)
        w.add(1, 1, 3, 0.8, T1)  # unknown time
        assert w.rows == 3
    assert w.closed
    lines = path.read_text().splitlines()
    assert lines[0] == BOP_CSV_HEADER and len(lines) == 4
    cells = lines[1].split(",")
    assert len(cells) == 7 and cells[:3] == ["1", "0", "3"]
    np.testing.assert_allclose(
        np.array(cells[4].split(), float), T1[:3, :3].reshape(-1)
    )  # row-major
    np.testing.assert_allclose(np.array(cells[5].split(), float), [100.0, 200.0, 30.0])  # mm
    rows = read_bop_csv(path)
    assert [(r["im_id"], r["obj_id"], r["time"]) for r in rows] == [
        (0, 3, 0.25),
        (0, 1, 0.25),
        (1, 3, -1.0),
    ]
    np.testing.assert_allclose(rows[1]["t"], T2[:3, 3] * 1000.0)
    np.testing.assert_allclose(rows[1]["R"], T2[:3, :3])
    with pytest.raises(ValueError, match="closed"):
        w.add(1, 2, 3, 0.5, T1)


def test_bop_csv_checks(tmp_path):
    for bad in ("", "my_method"):
        with pytest.raises(ValueError, match="method"):
            BopCsvWriter(tmp_path / "x.csv", bad)
    with pytest.raises(ValueError, match="method"):
        bop_csv_name("ds", method="a_b")
    with BopCsvWriter(tmp_path / "ssp_ds-test.csv", "ssp") as w:
        w.add(0, 0, 1, 1.0, np.eye(4), time=0.5)
        with pytest.raises(ValueError, match="time"):
            w.add(0, 0, 2, 1.0, np.eye(4), time=0.6)
        with pytest.raises(ValueError, match="obj_id"):
            w.add(0, 1, 0, 1.0, np.eye(4))
        with pytest.raises(ValueError, match="score"):
            w.add(0, 1, 1, float("nan"), np.eye(4))
        with pytest.raises(ValueError):
            w.add(0, 1, 1, 1.0, np.diag([2.0, 1, 1, 1]))
        assert w.rows == 1
    (tmp_path / "bad.csv").write_text("a,b\n")
    with pytest.raises(InputError, match="header"):
        read_bop_csv(tmp_path / "bad.csv")


def test_object_ids_from_classes_and_json(tmp_path):
    ids = ObjectIds.from_classes(["mug", "cube", "block", "cube"])
    assert ids.as_dict() == {"block": 1, "cube": 2, "mug": 3}
    assert ids["mug"] == 3 and ids.class_of(2) == "cube" and "cube" in ids and len(ids) == 3
    with pytest.raises(UnknownObjectError):
        ids["bowl"]
    write_json(tmp_path / "obj_ids.json", ids.to_json())
    again = ObjectIds.from_models_json(tmp_path / "obj_ids.json")
    assert again.as_dict() == ids.as_dict()


def test_object_ids_from_bop_models_json(tmp_path):
    # as ssp.sim.bop.write_bop writes it: 1-based library order, not sorted
    doc = {"obj_ids": {"1": "cube", "2": "block", "3": "cylinder"}, "instances": []}
    (tmp_path / "models.json").write_text(json.dumps(doc))
    ids = ObjectIds.for_input(tmp_path, ["block", "mug"])
    assert ids.as_dict() == {"cube": 1, "block": 2, "cylinder": 3, "mug": 4}
    assert ObjectIds.for_input(tmp_path / "nothing", ["b", "a"]).as_dict() == {"a": 1, "b": 2}
    (tmp_path / "models.json").write_text(json.dumps({"obj_ids": {"1": "cube", "2": "cube"}}))
    with pytest.raises(InputError, match="two obj_ids"):
        ObjectIds.for_input(tmp_path, [])
    (tmp_path / "models.json").write_text(json.dumps({"obj_ids": {"0": "cube"}}))
    with pytest.raises(InputError, match=">= 1"):
        ObjectIds.for_input(tmp_path, [])
    (tmp_path / "models.json").write_text("{}")
    with pytest.raises(InputError, match="obj_ids"):
        ObjectIds.for_input(tmp_path, [])
