"""Input folders: frame order, scene.json, labels, per-frame failures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ssp.errors import CloudFormatError, InputError
from ssp.io.clouds import write_cloud
from ssp.io.folder import natural_key, open_folder
from ssp.io.hypotheses import write_hypotheses
from ssp.scene import Hypothesis

RNG = np.random.default_rng(3)
PTS = RNG.uniform(-0.5, 0.5, (20, 3)) + [0, 0, 1.0]
LABELS = np.array([0, 1, 1, 2, 2, -3, 5, 5, 0, 1] * 2)


def _scene(d, **doc):
    (d / "scene.json").write_text(json.dumps(doc))


def _cloud(d, name, **kw):
    return write_cloud(d / name, PTS, **kw)


def test_natural_order_stamps_and_hypotheses(tmp_path):
    for name in ("frame10.ply", "frame2.pcd", "Frame1.ply", ".hidden.ply"):
        _cloud(tmp_path, name)
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "sub.ply").mkdir()
    write_hypotheses(
        tmp_path / "frame2.hypotheses.json", [Hypothesis("mug", np.eye(4), 0.5)], frame="camera"
    )
    write_hypotheses(tmp_path / "orphan.hypotheses.json", [])
    inp = open_folder(tmp_path)
    assert [f.name for f in inp] == ["Frame1", "frame2", "frame10"]
    assert [f.index for f in inp.frames] == [0, 1, 2]
    np.testing.assert_allclose([f.stamp for f in inp.frames], [0.0, 0.1, 0.2])
    assert [f.hypotheses_path is not None for f in inp.frames] == [False, True, False]
    assert inp.spec.frame == "camera" and inp.spec.T_world_cam is None
    raw = inp.load(inp.frames[1])
    assert raw.hypotheses_frame == "camera" and raw.hypotheses[0].class_name == "mug"
    np.testing.assert_allclose(raw.points, PTS, atol=1e-6)
    assert raw.labels is None and raw.label_kind is None and raw.label_classes is None
    assert inp.load(0).hypotheses is None and inp.load(0).hypotheses_frame is None


def test_natural_key():
    names = ["f10.ply", "f2.ply", "f1.ply", "f02b.ply", "a.ply", "F3.ply"]
    assert sorted(names, key=natural_key) == [
        "a.ply",
        "f1.ply",
        "f2.ply",
        "f02b.ply",
        "F3.ply",
        "f10.ply",
    ]


def test_instance_labels_background(tmp_path):
    _cloud(tmp_path, "a.ply", labels=LABELS)
    raw = open_folder(tmp_path).load(0)
    assert raw.label_kind == "instance" and raw.label_classes is None
    np.testing.assert_array_equal(
        raw.labels, np.where(np.isin(LABELS, [0]) | (LABELS < 0), -1, LABELS)
    )
    _scene(tmp_path, background_labels=[0, 5], classes={"2": "mug"})
    raw = open_folder(tmp_path).load(0)
    assert set(np.unique(raw.labels)) == {-1, 1, 2} and raw.label_classes == {2: "mug"}


def test_class_labels(tmp_path):
    _cloud(tmp_path, "a.pcd", labels=LABELS)
    _scene(tmp_path, labels="class", classes={"1": "cube", "2": "mug", "5": "bowl"}, frame="world",
           T_world_cam=np.eye(4).tolist(), period=0.5)  # fmt: skip
    inp = open_folder(tmp_path)
    assert inp.spec.frame == "world" and inp.spec.period == 0.5
    raw = inp.load(0)
    assert raw.frame == "world" and raw.label_kind == "class"
    assert raw.label_classes == {1: "cube", 2: "mug", 5: "bowl"}
    _scene(tmp_path, labels="class", classes={"1": "cube"})
    with pytest.raises(InputError, match=r"\[2, 5\]"):
        open_folder(tmp_path).load(0)


def test_color_coded_classes(tmp_path):
    colors = np.zeros((len(PTS), 3), dtype=np.uint8)
    colors[:5] = [255, 0, 0]
    colors[5:10] = [0, 0, 255]
    colors[10:12] = [255, 0, 1]  # not listed: background
    _cloud(tmp_path, "a.ply", colors=colors, labels=LABELS)
    _scene(tmp_path, colors={"#FF0000": "mug", "#0000ff": "cube", "#00ff00": "bowl"})
    raw = open_folder(tmp_path).load(0)
    assert raw.label_kind == "class" and raw.label_classes == {1: "cube", 2: "mug"}
    assert (
        (raw.labels[:5] == 2).all()
        and (raw.labels[5:10] == 1).all()
        and (raw.labels[10:] == -1).all()
    )
    np.testing.assert_array_equal(raw.colors, colors)
    write_cloud(tmp_path / "a.ply", PTS)  # no colours any more
    with pytest.raises(InputError, match="no colour"):
        open_folder(tmp_path).load(0)


def test_stamps(tmp_path):
    for name in ("f1.ply", "f2.ply", "f3.ply"):
        _cloud(tmp_path, name)
    _scene(tmp_path, stamps={"f1.ply": 1.0, "f2": 1.5, "f3.ply": 4.0})
    np.testing.assert_allclose([f.stamp for f in open_folder(tmp_path).frames], [1.0, 1.5, 4.0])
    for stamps, match in [
        ({"f1.ply": 1.0, "f2.ply": 1.5}, "no stamp for f3.ply"),
        ({"f1.ply": 1.0, "f2.ply": 1.5, "f3.ply": 2, "f4.ply": 3}, "no frame file"),
        ({"f1.ply": 1.0, "f2.ply": 0.5, "f3.ply": 2}, "earlier"),
    ]:
        _scene(tmp_path, stamps=stamps)
        with pytest.raises(InputError, match=match):
            open_folder(tmp_path)


@pytest.mark.parametrize(
    "doc, match",
    [
        ({"frame": "robot"}, "'frame'"),
        ({"perod": 0.2}, "did you mean 'period'"),
        ({"period": 0}, "period"),
        ({"period": 0.1, "stamps": {}}, "either 'period' or 'stamps'"),
        ({"labels": "class"}, "needs 'classes'"),
        ({"classes": {"x": "mug"}}, "not an integer"),
        ({"classes": {"0": "mug"}}, "background_labels"),
        ({"colors": {"red": "mug"}}, "#rrggbb"),
        ({"colors": {"#ff0000": "mug"}, "labels": "instance"}, "not both"),
        ({"T_world_cam": np.diag([1.0, 1, 1]).tolist()}, "T_world_cam"),
        ({"background_labels": "0"}, "list"),
    ],
)
def test_bad_scene_json(tmp_path, doc, match):
    _cloud(tmp_path, "a.ply")
    _scene(tmp_path, **doc)
    with pytest.raises(InputError, match=match) as err:
        open_folder(tmp_path)
    assert "scene.json" in str(err.value)


def test_bad_folders(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_folder(tmp_path / "missing")
    with pytest.raises(InputError, match="no frames"):
        open_folder(tmp_path)
    (tmp_path / "scene_gt.json").write_text("{}")
    (tmp_path / "scene_camera.json").write_text("{}")
    with pytest.raises(InputError, match="BOP"):
        open_folder(tmp_path)
    _cloud(tmp_path, "a.ply")
    _cloud(tmp_path, "a.pcd")
    with pytest.raises(InputError, match="one frame name"):
        open_folder(tmp_path)
    (tmp_path / "scene.json").write_text("{oops")
    with pytest.raises(InputError, match="invalid JSON"):
        open_folder(tmp_path)


def test_one_bad_frame_among_good_ones(tmp_path):
    for i in range(5):
        _cloud(tmp_path, f"f{i}.ply", labels=LABELS)
    (tmp_path / "f1.ply").write_bytes((tmp_path / "f1.ply").read_bytes()[:-10])  # truncated
    write_cloud(tmp_path / "f2.ply", PTS * 1000.0)  # millimetres
    (tmp_path / "f3.hypotheses.json").write_text('{"hypotheses": [{"class": "a"}]}')
    write_cloud(tmp_path / "f4.ply", np.full((3, 3), np.nan))
    inp = open_folder(tmp_path)
    assert len(inp) == 5
    assert inp.load(0).points.shape == (20, 3)
    for k, err, match in [
        (1, CloudFormatError, "f1.ply"),
        (2, CloudFormatError, "millimetres"),
        (3, InputError, "f3.hypotheses.json"),
        (4, CloudFormatError, "no finite points"),
    ]:
        with pytest.raises(err, match=match):
            inp.load(inp.frames[k])
