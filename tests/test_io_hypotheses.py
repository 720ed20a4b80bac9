"""Hypotheses JSON: formats of the pose, units, frames, and rejected files."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssp.errors import InputError
from ssp.io.hypotheses import read_hypotheses, to_world, write_hypotheses
from ssp.scene import Hypothesis

ROT = Rotation.from_euler("zyx", [0.7, -0.3, 0.2])
R = ROT.as_matrix()
Q_XYZW = ROT.as_quat()


def _write(path, doc):
    path.write_text(json.dumps(doc))
    return path


def _pose(R=R, t=(0.1, -0.2, 0.3)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_round_trip(tmp_path):
    hyps = [
        Hypothesis("mug", _pose(), score=0.25, instance_id="mug_1"),
        Hypothesis("box", _pose(np.eye(3), (0, 0, 0.05)), segment=4),
    ]
    path = write_hypotheses(tmp_path / "h.json", hyps, frame="camera")
    doc = json.loads(path.read_text())
    assert doc["frame"] == "camera" and doc["units"] == "m"
    assert set(doc["hypotheses"][0]) == {"class", "score", "t", "R", "quat_xyzw", "id"}
    assert "id" not in doc["hypotheses"][1] and doc["hypotheses"][1]["segment"] == 4
    hf = read_hypotheses(path)
    assert hf.frame == "camera" and len(hf.hypotheses) == 2
    for a, b in zip(hf.hypotheses, hyps, strict=True):
        assert (a.class_name, a.score, a.instance_id, a.segment) == (
            b.class_name,
            b.score,
            b.instance_id,
            b.segment,
        )
        np.testing.assert_allclose(a.T_world_obj, b.T_world_obj, atol=1e-12)


def test_rotation_forms_agree_and_quaternions_normalised(tmp_path):
    q_wxyz = np.roll(Q_XYZW, 1)
    entries = [
        {"class": "a", "t": [1, 2, 3], "R": R.tolist()},
        {"class": "a", "t": [1, 2, 3], "R": R.reshape(-1).tolist()},
        {"class": "a", "t": [1, 2, 3], "quat_xyzw": (3.0 * Q_XYZW).tolist()},
        {"class": "a", "t": [1, 2, 3], "quat_wxyz": q_wxyz.tolist()},
        {"class": "a", "T": _pose(R, (1, 2, 3)).tolist()},
    ]
    hf = read_hypotheses(_write(tmp_path / "h.json", {"hypotheses": entries}))
    assert hf.frame == "world"
    for h in hf.hypotheses:
        np.testing.assert_allclose(h.T_world_obj, _pose(R, (1, 2, 3)), atol=1e-12)
        assert h.score == 1.0 and h.instance_id is None


def test_millimetres_converted(tmp_path):
    doc = {
        "units": "mm",
        "hypotheses": [
            {"class": "a", "t": [100, -20, 5], "quat_xyzw": [0, 0, 0, 1]},
            {"class": "a", "T": _pose(np.eye(3), (100, 0, 0)).tolist()},
        ],
    }
    a, b = read_hypotheses(_write(tmp_path / "h.json", doc)).hypotheses
    np.testing.assert_allclose(a.T_world_obj[:3, 3], [0.1, -0.02, 0.005])
    np.testing.assert_allclose(b.T_world_obj[:3, 3], [0.1, 0, 0])


def test_near_rotation_accepted_and_cleaned(tmp_path):
    noisy = R + 2e-4 * np.random.default_rng(0).normal(size=(3, 3))
    hf = read_hypotheses(
        _write(
            tmp_path / "h.json",
            {"hypotheses": [{"class": "a", "t": [0, 0, 0], "R": noisy.tolist()}]},
        )
    )
    Rc = hf.hypotheses[0].T_world_obj[:3, :3]
    np.testing.assert_allclose(Rc @ Rc.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize(
    "entry, match",
    [
        ({"class": "a", "t": [0, 0, 0], "R": (1.01 * np.eye(3)).tolist()}, "not a rotation"),
        ({"class": "a", "t": [0, 0, 0], "R": np.diag([1.0, 1.0, -1.0]).tolist()}, "not a rotation"),
        ({"class": "a", "T": np.diag([2.0, 1.0, 1.0, 1.0]).tolist()}, "not a rotation"),
        ({"class": "a", "T": np.eye(4).tolist(), "t": [0, 0, 0]}, "either 'T'"),
        ({"class": "a", "t": [0, 0, 0]}, "without a rotation"),
        ({"class": "a", "R": np.eye(3).tolist()}, "no pose"),
        ({"class": "a", "t": [0, 0], "R": np.eye(3).tolist()}, "shape"),
        ({"class": "a", "t": [0, 0, 0], "quat_xyzw": [0, 0, 0, 0]}, "zero quaternion"),
        (
            {"class": "a", "t": [0, 0, 0], "quat_xyzw": [0, 0, 1, 0], "R": np.eye(3).tolist()},
            "different",
        ),
        ({"class": "a", "t": [0, "x", 0], "R": np.eye(3).tolist()}, "numbers"),
        ({"class": "", "t": [0, 0, 0], "R": np.eye(3).tolist()}, "class"),
        ({"class": "a", "score": "high", "t": [0, 0, 0], "R": np.eye(3).tolist()}, "score"),
        ({"class": "a", "id": 3, "t": [0, 0, 0], "R": np.eye(3).tolist()}, "'id'"),
        ({"class": "a", "segment": "2", "t": [0, 0, 0], "R": np.eye(3).tolist()}, "'segment'"),
        ({"class": "a", "segment": 2.5, "t": [0, 0, 0], "R": np.eye(3).tolist()}, "'segment'"),
    ],
)
def test_bad_entries_rejected(tmp_path, entry, match):
    good = {"class": "ok", "t": [0, 0, 0], "R": np.eye(3).tolist()}
    path = _write(tmp_path / "h.json", {"hypotheses": [good, entry]})
    with pytest.raises(InputError, match=match) as err:
        read_hypotheses(path)
    assert str(path) in str(err.value) and "hypothesis 1" in str(err.value)


@pytest.mark.parametrize(
    "text, match",
    [
        ("{", "invalid JSON"),
        ("[]", "JSON object"),
        ('{"hypotheses": {}}', "must be a list"),
        ('{"frame": "robot", "hypotheses": []}', "'frame'"),
        ('{"units": "cm", "hypotheses": []}', "'units'"),
    ],
)
def test_bad_files_rejected(tmp_path, text, match):
    (tmp_path / "h.json").write_text(text)
    with pytest.raises(InputError, match=match):
        read_hypotheses(tmp_path / "h.json")
    with pytest.raises(InputError, match="no such file"):
        read_hypotheses(tmp_path / "missing.json")


def test_unknown_keys_warned(tmp_path, caplog):
    doc = {
        "camera": 1,
        "hypotheses": [{"class": "a", "t": [0, 0, 0], "R": np.eye(3).tolist(), "bbox": [1]}],
    }
    with caplog.at_level(logging.WARNING, logger="ssp.io.hypotheses"):
        assert len(read_hypotheses(_write(tmp_path / "h.json", doc)).hypotheses) == 1
    assert "camera" in caplog.text and "bbox" in caplog.text


def test_to_world():
    T_world_cam = _pose(Rotation.from_euler("x", 2.5).as_matrix(), (0, -0.5, 0.8))
    h = Hypothesis("a", _pose(), score=0.5, instance_id="a_1")
    (w,) = to_world([h], T_world_cam)
    np.testing.assert_allclose(w.T_world_obj, T_world_cam @ _pose(), atol=1e-12)
    assert (w.class_name, w.score, w.instance_id) == ("a", 0.5, "a_1")
    np.testing.assert_allclose(h.T_world_obj, _pose())  # input untouched
    with pytest.raises(InputError):
        to_world([h], np.eye(3))
