"""3D recordings (ssp.viz.record): a run written to a rerun .rrd file and read back."""

from __future__ import annotations

import json
import sys
from collections import defaultdict

import numpy as np
import pytest
from typer.testing import CliRunner

from ssp.camera import Camera
from ssp.cli import app
from ssp.estimate import ObjectEstimate, SceneEstimate, SupportEdge
from ssp.geometry import make_pose
from ssp.pipeline.run import run
from ssp.probability import ObjectTerms
from ssp.scene import Frame, Hypothesis, TransitionMode
from ssp.sim.bop import simulate_to_disk
from ssp.viz.record import (
    GREY,
    INSTALL_HINT,
    MODE_COLOURS,
    OBJECT_ALPHA,
    TERM_COLOURS,
    TERMS,
    Recorder,
    RecordingError,
    RunRecording,
    label_colours,
    view_command,
)
from ssp.viz.record_entities import (
    BACKGROUND_SHARE,
    CLASSES,
    LABEL_MARGIN,
    LABEL_STEP,
    TABLE_BAND,
    TABLE_SHARE,
    mode_class,
    place_labels,
    split_cloud,
)

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

IGNORED = {"rerun.controls.RowId"}


@pytest.fixture(autouse=True)
def strict_rerun():
    """rerun raises on a bad log call instead of warning."""
    before = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(before)


def read(path, blueprint: bool = False) -> dict[str, list[tuple[int | None, dict]]]:
    """``entity -> [(frame or None for static, {component: value})]`` of a recording's data
    (``blueprint``: of its layout), sorted by frame (the chunking rerun chose does not
    matter)."""
    out = defaultdict(list)
    reader = RrdReader(path)
    store = reader.blueprints()[0] if blueprint else None
    for chunk in reader.stream(store=store).collect().stream():
        if chunk.entity_path == "/__properties":
            continue
        rows = chunk.to_record_batch().to_pylist()
        for row in rows:
            frame = row.pop("frame", None)
            row.pop("time", None)
            row.pop("log_time", None)
            row.pop("blueprint", None)
            cells = {k: v for k, v in row.items() if k not in IGNORED and v is not None}
            out[chunk.entity_path].append((frame, cells))
    for rows in out.values():
        rows.sort(key=lambda r: (-1 if r[0] is None else r[0], json.dumps(r[1], default=str)))
    return dict(out)


def at(rows, frame, component):
    """The value of ``component`` logged at ``frame`` (None when not logged there)."""
    vals = [c[component] for f, c in rows if f == frame and component in c]
    return vals[-1] if vals else None


@pytest.fixture(scope="module")
def scene(lib, tmp_path_factory):
    (path,) = simulate_to_disk(
        "structure",
        1,
        4,
        out_dir=tmp_path_factory.mktemp("bop"),
        library=lib,
        stages=3,
        frames_per_stage=1,
        stride=4,
        n_objects=4,
    )
    return path


def test_run_recording_holds_every_frame(lib, scene, tmp_path):
    """Cloud, one entity per object, hypotheses, support arrows and the five terms per frame;
    a frame that fails is an error line and leaves the scene as it was."""
    bad = sorted((scene / "depth").glob("*.png"))[1]
    original = bad.read_bytes()
    bad.write_bytes(b"not a png")
    try:
        summary = run(scene, lib, tmp_path / "out", record=tmp_path / "rec" / "run.rrd")
    finally:
        bad.write_bytes(original)
    assert len(summary.done) == 2 and [f["index"] for f in summary.failed] == [1]
    frames = {
        n: json.loads((tmp_path / "out" / "frames" / f"{d['frame']}.json").read_text())
        for n, d in zip((0, 2), summary.done, strict=True)
    }
    data = read(tmp_path / "rec" / "run.rrd")

    cloud = data["/world/cloud/objects"]
    assert [f for f, _ in cloud] == [0, 2]
    pts = np.asarray(at(cloud, 0, "Points3D:positions"))
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 30
    assert len(at(cloud, 0, "Points3D:colors")) == len(pts)
    assert np.all(np.abs(pts) < 1.0)  # world frame, metres (not mm, not the camera frame)
    table = np.asarray(at(data["/world/cloud/table"], 0, "Points3D:positions"))
    assert len(table) > 1000 and np.all(np.abs(table[:, 2]) <= TABLE_BAND + 1e-6)
    # a BOP scene's frames carry their camera (a pinhole) and depth image into the recording
    for n in (0, 2):
        assert at(data["/world/camera"], n, "Pinhole:image_from_camera") is not None
        assert at(data["/world/camera/depth"], n, "DepthImage:meter") == [1000.0]

    for n, rec in frames.items():
        for o in rec["objects"]:
            ent = f"/world/objects/{o['id']}"
            t = at(data[ent], n, "Transform3D:translation")
            assert np.allclose(t, np.asarray(o["T_world_obj"])[:3, 3], atol=1e-6)
            label = at(data[f"{ent}/label"], n, "Points3D:labels")
            assert label == [o["id"]]
            assert at(data[f"{ent}/label"], n, "mode") == [o["mode"]]
        ids = {o["id"] for o in rec["objects"]}
        for t in TERMS:
            total = sum(o["terms"][t] for o in rec["objects"])
            assert at(data[f"/terms/scene/{t}"], n, "Scalars:scalars") == pytest.approx([total])
        assert at(data["/terms/scene/total"], n, "Scalars:scalars") == pytest.approx(
            [rec["log_prob"]]
        )
        arrows = at(data["/world/support"], n, "Arrows3D:vectors")
        assert len(arrows) == len(rec["support"]) > 0
        # every edge points up (supporter below the object it carries)
        assert all(v[2] > 0 for v in arrows)
        assert ids <= {e.split("/")[3] for e in data if e.startswith("/world/objects/")}
    # a mesh is sent once per object, then only its colour
    first = frames[0]["objects"][0]["id"]
    mesh = data[f"/world/objects/{first}/mesh"]
    assert at(mesh, 0, "Mesh3D:vertex_positions") is not None
    assert at(mesh, 2, "Mesh3D:vertex_positions") is None
    assert at(mesh, 2, "Mesh3D:albedo_factor") is not None
    # the hypotheses: one mesh per class, instanced at each hypothesis pose
    hyps = [e for e in data if e.startswith("/world/hypotheses/")]
    assert hyps and {e.rsplit("/", 1)[1] for e in hyps} <= {"cube", "block"}
    n_poses = sum(len(at(data[e], 0, "InstancePoses3D:translations") or []) for e in hyps)
    assert n_poses == frames[0]["perception"]["hypotheses"]
    # the failed frame: an error line at frame 1, nothing else logged there
    log_rows = data["/log"]
    errors = [c for f, c in log_rows if f == 1]
    assert len(errors) == 1 and errors[0]["TextLog:level"] == ["ERROR"]
    assert "failed" in errors[0]["TextLog:text"][0] and "000001.png" in errors[0]["TextLog:text"][0]
    assert all(f != 1 for e, rows in data.items() if e != "/log" for f, _ in rows)
    assert sorted({f for rows in data.values() for f, _ in rows if f is not None}) == [0, 1, 2]


def test_same_run_same_recording(lib, scene, tmp_path):
    for k in (1, 2):
        run(scene, lib, tmp_path / f"out{k}", record=tmp_path / f"{k}.rrd")
    a, b = read(tmp_path / "1.rrd"), read(tmp_path / "2.rrd")
    assert a.keys() == b.keys()
    for entity in a:
        assert a[entity] == b[entity], entity


def _model_box(lib):
    return lib["cube"], float(lib["cube"].extents[2])


def _estimate(objects, support=(), stamp=0.0, index=0):
    return SceneEstimate(stamp, index, tuple(objects), support=tuple(support), log_prob=-1.0)


def _obj(oid, T, mode=TransitionMode.ADDED, ephemeral=False):
    terms = ObjectTerms(-0.1, -0.2, -0.3, -0.4, -0.5)
    return ObjectEstimate(oid, "cube", T, mode, ephemeral=ephemeral, terms=terms)


def test_objects_that_leave_are_cleared_and_colours_follow_the_mode(lib, tmp_path):
    _, e = _model_box(lib)
    T0, T1 = make_pose(t=[0, 0, e / 2]), make_pose(t=[0, 0, 1.5 * e])
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, e], [0.0, 0.01, 2 * e]])
    labels = np.array([-1, 0, 1])
    f0 = Frame(0.0, pts, [Hypothesis("cube", T0), Hypothesis("cube", T1)], labels=labels)
    f1 = Frame(0.5, pts, [], labels=labels)
    est0 = _estimate(
        [_obj("a", T0), _obj("b", T1)],
        [SupportEdge("table", "a", 1.0), SupportEdge("a", "b", 1.0)],
    )
    est1 = _estimate(
        [_obj("a", T0, TransitionMode.STATIC, ephemeral=True)],
        [SupportEdge("table", "a", 1.0)],
        0.5,
        1,
    )
    with Recorder(tmp_path / "r.rrd", lib) as r:
        r.log_frame(0, f0, est0)
        r.log_frame(1, f1, est1)
    data = read(tmp_path / "r.rrd")
    assert at(data["/world/objects/b"], 1, "Clear:is_recursive") == [True]
    assert at(data["/world/objects/a"], 1, "Clear:is_recursive") is None
    hyp = data["/world/hypotheses/cube"]
    assert len(at(hyp, 0, "InstancePoses3D:translations")) == 2
    assert at(hyp, 1, "Clear:is_recursive") == [False]  # no hypothesis in frame 1
    mesh = data["/world/objects/a/mesh"]
    rgba = [at(mesh, f, "Mesh3D:albedo_factor")[0] for f in (0, 1)]  # 0xRRGGBBAA
    unpacked = [(c >> 24, (c >> 16) & 255, (c >> 8) & 255, c & 255) for c in rgba]
    assert unpacked[0] == (*MODE_COLOURS[TransitionMode.ADDED], OBJECT_ALPHA[0])
    assert unpacked[1] == (*MODE_COLOURS[TransitionMode.STATIC], OBJECT_ALPHA[1])  # ephemeral
    v = np.asarray(at(data["/world/support"], 0, "Arrows3D:vectors"))
    o = np.asarray(at(data["/world/support"], 0, "Arrows3D:origins"))
    assert np.allclose(o[0], [0, 0, 0]) and np.allclose(v[0], [0, 0, e / 2])  # table -> a
    assert np.allclose(o[1] + v[1], [0, 0, 1.5 * e])  # a -> b ends at b's centre
    colours = label_colours(labels, 3)
    assert (colours[0] == GREY).all() and not (colours[1] == colours[2]).all()
    stamps = [c for f, c in data["/terms/objects/a/transition"] if f is not None]
    assert len(stamps) == 2


def test_without_rerun_a_clear_error_and_nothing_written(lib, scene, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(RecordingError, match=r"pip install 'sequential-scene-parsing\[record\]'"):
        run(scene, lib, tmp_path / "out", record=tmp_path / "run.rrd")
    assert not (tmp_path / "out").exists() and not (tmp_path / "run.rrd").exists()
    r = CliRunner().invoke(app, ["run", str(scene), "-o", str(tmp_path / "o"), "--record", "x"])
    assert r.exit_code == 1 and INSTALL_HINT in " ".join(r.output.split())


def test_view_without_display_says_what_to_do(lib, tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    path = tmp_path / "run.rrd"
    with Recorder(path, lib):
        pass
    cli = CliRunner()
    r = cli.invoke(app, ["view", str(path)])
    text = " ".join(r.output.split())
    assert r.exit_code == 1 and "no display" in text and "ssp view --web" in text
    r = cli.invoke(app, ["view", str(tmp_path / "missing.rrd")])
    assert r.exit_code == 1 and "no such recording" in " ".join(r.output.split())
    (tmp_path / "file").write_text("")
    with pytest.raises(RecordingError, match="not a writable folder"):
        Recorder(tmp_path / "file" / "run.rrd", lib)
    r = cli.invoke(app, ["view", "--dry-run", str(path)])
    assert r.exit_code == 0 and r.output.splitlines() == [" ".join(view_command(path))]
    assert view_command(path)[-1] == str(path) and "rerun" in " ".join(view_command(path))
    assert view_command(path, web=True)[-2:] == ["--serve-web", str(path)]


def test_a_recording_that_breaks_does_not_stop_the_run(lib, scene, tmp_path, monkeypatch):
    calls = []
    original = Recorder.log_frame

    def flaky(self, index, *args, **kwargs):
        calls.append(index)
        if index == 1:
            raise OSError("disk full")
        original(self, index, *args, **kwargs)

    monkeypatch.setattr(Recorder, "log_frame", flaky)
    summary = run(scene, lib, tmp_path / "out", record=tmp_path / "run.rrd")
    assert len(summary.done) == 3 and not summary.failed
    assert calls == [0, 1]  # stopped recording after the failure
    frames = {f for rows in read(tmp_path / "run.rrd").values() for f, _ in rows}
    assert frames - {None} == {0}


def test_demo_records_ssp_with_the_truth(tmp_path):
    from ssp.eval.sequence_demo import RECORDING, run_sequence_demo

    result = run_sequence_demo(tmp_path, stages=2, frames_per_stage=1, stride=4)
    assert (
        result["recording"] == str(tmp_path / RECORDING) and result["recording"] in result["files"]
    )
    data = read(tmp_path / RECORDING)
    assert sorted(f for f, _ in data["/world/cloud/objects"]) == [0, 1]
    assert any(e.startswith("/world/truth/") for e in data)
    assert "ssp view" in (tmp_path / "report.html").read_text()


# ------------------------------------------------------------------ what a user meets (issue 35)
CAM = Camera(64, 48, 50.0, 52.0, 31.5, 23.5)
T_WC = make_pose(t=[0.0, -0.5, 0.5])


def _views(path) -> dict[str, dict]:
    """The layout's views by display name: ``{name: {component: value}}`` (the view's own
    row merged with its sub-entities', e.g. ``ViewContents:query``, ``PlotLegend:visible``)."""
    bp = read(path, blueprint=True)
    views: dict[str, dict] = {}
    for ent, rows in bp.items():
        if ent.startswith("/view/") and ent.count("/") == 2:
            name = rows[-1][1]["ViewBlueprint:display_name"][0]
            views[name] = {k: v for e, r in bp.items() if e.startswith(ent) for _, c in r
                           for k, v in c.items()}  # fmt: skip
    return views


def test_camera_is_a_pinhole_with_its_depth_image(lib, tmp_path):
    """Item 1: the camera entity carries its pose and a pinhole of its intrinsics (the viewer
    draws the frustum); the depth image (m) is logged under it as uint16 mm with meter 1000,
    shown in a 2D view and left out of the 3D view; without a depth image (a cloud input)
    none is made up, and the last one is cleared."""
    e = float(lib["cube"].extents[2])
    est = _estimate([_obj("a", make_pose(t=[0, 0, e / 2]))])
    frame = Frame(0.0, np.array([[0.0, 0.0, e]]), [], labels=np.array([0]), T_world_cam=T_WC)
    depth = np.full((48, 64), 0.7)
    depth[0, 0], depth[0, 1] = 0.0, np.nan  # no return
    with Recorder(tmp_path / "r.rrd", lib) as r:
        r.log_frame(0, frame, est, camera=CAM, depth=depth)
        r.log_frame(1, frame, est, camera=CAM)  # a frame without a depth image
        with pytest.raises(RecordingError, match="depth image"):
            r.log_frame(2, frame, est, camera=CAM, depth=np.ones((10, 10)))
    data = read(tmp_path / "r.rrd")
    cam = data["/world/camera"]
    K = np.asarray(at(cam, 0, "Pinhole:image_from_camera")[0]).reshape(3, 3).T  # column-major
    assert np.allclose(K, [[50, 0, 31.5], [0, 52, 23.5], [0, 0, 1]])
    assert at(cam, 0, "Pinhole:resolution") == [[64.0, 48.0]]
    assert np.allclose(at(cam, 0, "Transform3D:translation"), [T_WC[:3, 3]])
    img = data["/world/camera/depth"]
    assert at(img, 0, "DepthImage:meter") == [1000.0]
    fmt = at(img, 0, "DepthImage:format")[0]
    assert (fmt["width"], fmt["height"]) == (64, 48)
    mm = np.frombuffer(bytes(at(img, 0, "DepthImage:buffer")[0]), dtype=np.uint16).reshape(48, 64)
    assert mm[0, 0] == mm[0, 1] == 0 and np.all(mm.ravel()[2:] == 700)
    assert at(img, 1, "Clear:is_recursive") == [False]
    views = _views(tmp_path / "r.rrd")
    assert views["depth"]["ViewBlueprint:space_origin"] == ["world/camera"]
    assert "- /world/camera/depth" in views["scene"]["ViewContents:query"]

    # a cloud input: no intrinsics, no image; the pose only
    with Recorder(tmp_path / "cloud.rrd", lib) as r:
        r.log_frame(0, frame, est)
    data = read(tmp_path / "cloud.rrd")
    assert "/world/camera/depth" not in data
    assert at(data["/world/camera"], 0, "Pinhole:image_from_camera") is None
    assert at(data["/world/camera"], 0, "Transform3D:translation") is not None
    assert "depth" not in _views(tmp_path / "cloud.rrd")

    # ssp run: a perceived frame with intrinsics and a depth image (read from depth) has them
    class Perceived:
        def __init__(self, **kw):
            self.frame = frame
            self.__dict__.update(kw)

    with RunRecording(tmp_path / "run.rrd", lib) as rec:
        rec.add(0, "000000", {"status": "done"}, Perceived(camera=CAM, depth=depth), est)
        rec.add(1, "000001", {"status": "done"}, Perceived(), est)
    data = read(tmp_path / "run.rrd")
    assert at(data["/world/camera/depth"], 0, "DepthImage:meter") == [1000.0]
    assert at(data["/world/camera/depth"], 1, "Clear:is_recursive") == [False]


def test_background_does_not_swamp_the_objects(lib, tmp_path):
    """Item 2: object-segment points, table and background are three entities; the object
    points are all kept, the table and background cut to an evenly spaced (deterministic)
    subset of their share and drawn smaller, by class (dim greys)."""
    rng = np.random.default_rng(0)
    obj = rng.uniform([-0.02, -0.02, 0.01], [0.02, 0.02, 0.05], (300, 3))
    table = np.column_stack([rng.uniform(-1, 1, (20_000, 2)), rng.normal(0, 0.002, 20_000)])
    back = rng.uniform([-1, -1, 0.3], [1, 1, 1.0], (5_000, 3))
    pts = np.concatenate([table[:10_000], obj, back, table[10_000:]])
    labels = np.concatenate([np.full(10_000, -1), np.arange(300) % 3, np.full(15_000, -1)])
    frame = Frame(0.0, pts, [], labels=labels)
    est = _estimate([])
    for name in ("a.rrd", "b.rrd"):
        with Recorder(tmp_path / name, lib, max_points=2_000) as r:
            r.log_frame(0, frame, est)
    data = read(tmp_path / "a.rrd")
    assert data == read(tmp_path / "b.rrd")  # deterministic
    got = {k: np.asarray(at(data[f"/world/cloud/{k}"], 0, "Points3D:positions"))
           for k in ("objects", "table", "background")}  # fmt: skip
    assert len(got["objects"]) == 300 and np.allclose(np.sort(got["objects"], 0), np.sort(obj, 0))
    assert len(got["table"]) == int(TABLE_SHARE * 2_000) == 400
    assert len(got["background"]) == int(BACKGROUND_SHARE * 2_000) == 100
    assert np.all(got["background"][:, 2] >= 0.3) and np.all(np.abs(got["table"][:, 2]) < 0.01)
    # evenly spaced: the subset spans the whole table, not its first rows
    assert got["table"][:, 0].min() < -0.9 and got["table"][:, 0].max() > 0.9
    radius = {k: -at(data[f"/world/cloud/{k}"], 0, "Points3D:radii")[0] for k in got}  # ui pts
    assert radius["background"] < radius["table"] < radius["objects"]
    ids = {i: name for i, name, _ in CLASSES}
    assert ids[at(data["/world/cloud/table"], 0, "Points3D:class_ids")[0]] == "table"
    assert ids[at(data["/world/cloud/background"], 0, "Points3D:class_ids")[0]] == "background"
    # no labels: nothing is an object segment; the table still split off
    parts = split_cloud(pts, None, 2_000)
    assert len(parts.objects) == 0 and len(parts.table) == 400 and len(parts.background) == 100


def test_one_label_per_object_above_its_top(lib, tmp_path):
    """Item 3: one label per object (its id), above the top of the object on a line down to
    it; neighbours' labels at least LABEL_STEP apart in height; hypotheses, truth and support
    arrows show no label."""
    e = float(lib["cube"].extents[2])
    Ta, Tb = make_pose(t=[0, 0, e / 2]), make_pose(t=[0, 0, 1.5 * e])  # b stacked on a
    Tc = make_pose(t=[e + 0.002, 0, e / 2])  # c beside a, as high
    frame = Frame(0.0, np.array([[0.0, 0.0, e]]), [Hypothesis("cube", T) for T in (Ta, Tb, Tc)],
                  labels=np.array([0]), T_world_cam=T_WC)  # fmt: skip
    est = _estimate(
        [_obj("a", Ta), _obj("b", Tb, TransitionMode.STATIC), _obj("c", Tc)],
        [SupportEdge("table", "a", 1.0), SupportEdge("a", "b", 1.0)],
    )
    truth = {"a": ("cube", Ta), "b": ("cube", Tb)}
    with Recorder(tmp_path / "r.rrd", lib) as r:
        r.log_frame(0, frame, est, truth=truth)
    data = read(tmp_path / "r.rrd")

    def drawn(c):  # labels the viewer draws (the support arrows' are hidden)
        arrows = c.get("Arrows3D:labels") and c.get("Arrows3D:show_labels") != [False]
        return c.get("Points3D:labels") or c.get("LineStrips3D:labels") or arrows

    shown = {ent: c["Points3D:labels"] for ent, rows in data.items() for _, c in rows if drawn(c)}
    assert shown == {f"/world/objects/{i}/label": [i] for i in "abc"}
    world = {}
    for oid, T in zip("abc", (Ta, Tb, Tc), strict=True):
        ent = data[f"/world/objects/{oid}/label"]
        p = T[:3, :3] @ np.asarray(at(ent, 0, "Points3D:positions")[0]) + T[:3, 3]
        top = T[2, 3] + e / 2
        assert p[2] >= top + LABEL_MARGIN - 1e-6 and np.allclose(p[:2], T[:2, 3])
        strip = np.asarray(at(ent, 0, "LineStrips3D:strips")[0]) @ T[:3, :3].T + T[:3, 3]
        assert np.allclose(strip[0], [*T[:2, 3], top], atol=1e-6)  # from the object's top
        assert at(ent, 0, "Points3D:class_ids") == [mode_class(est.objects["abc".index(oid)].mode)]
        world[oid] = p
    assert abs(world["a"][2] - world["c"][2]) >= LABEL_STEP - 1e-6  # side by side: apart
    assert world["b"][2] - world["a"][2] >= LABEL_STEP - 1e-6  # stacked: apart


def test_labels_of_neighbours_rise_farther_from_the_camera():
    """place_labels: of two neighbours at one height the one nearer the camera keeps the low
    label (nearer and lower on screen, the other farther and higher); far apart, neither
    rises; the same input, the same heights."""
    tops = np.array([[0.0, 0.05, 0.05], [0.0, 0.0, 0.05], [0.5, 0.0, 0.05]])
    z = place_labels(tops, eye=np.array([0.0, -0.5, 0.5]))
    assert z[1] == pytest.approx(0.05 + LABEL_MARGIN) == z[2]
    assert z[0] == pytest.approx(z[1] + LABEL_STEP)
    z = place_labels(tops, eye=np.array([0.0, 0.5, 0.5]))  # seen from the other side
    assert z[0] == pytest.approx(0.05 + LABEL_MARGIN) and z[1] == pytest.approx(z[0] + LABEL_STEP)
    assert np.array_equal(place_labels(tops), place_labels(tops))


def test_legend_is_bounded_by_the_classes(lib, tmp_path):
    """Item 4: twelve objects give no more key entries than the classes: the 3D view's
    classes (an AnnotationContext: background, table, five modes), the per-object term
    plot without a legend, its series in the six term colours and names of the scene's."""
    e = float(lib["cube"].extents[2])
    objs = [_obj(f"cube_{k}", make_pose(t=[0.06 * k, 0, e / 2])) for k in range(12)]
    frame = Frame(0.0, np.array([[0.0, 0.0, e]]), [], labels=np.array([0]))
    with Recorder(tmp_path / "r.rrd", lib) as r:
        r.log_frame(0, frame, _estimate(objs))
        r.log_frame(1, frame, _estimate(objs, stamp=0.5, index=1))
    data = read(tmp_path / "r.rrd")
    (context,) = at(data["/world"], None, "AnnotationContext:context")
    assert [c["class_id"] for c in context] == [i for i, _, _ in CLASSES]
    assert len(CLASSES) == 7
    styles = set()
    for ent, rows in data.items():
        if ent.startswith("/terms/"):
            style = at(rows, None, "SeriesLines:names"), at(rows, None, "SeriesLines:colors")
            assert style[0] is not None, ent  # every series named and coloured by its term
            styles.add((style[0][0], style[1][0]))
    assert len([e for e in data if e.startswith("/terms/objects/")]) == 12 * len(TERMS)
    assert {n for n, _ in styles} == {*TERMS, "total"} and len(styles) == len(TERM_COLOURS)
    views = _views(tmp_path / "r.rrd")
    assert views["terms (objects)"]["PlotLegend:visible"] == [False]
    assert views["terms (scene)"].get("PlotLegend:visible") != [False]
