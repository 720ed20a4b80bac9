"""3D recordings (ssp.viz.record): a run written to a rerun .rrd file and read back."""

from __future__ import annotations

import json
import sys
from collections import defaultdict

import numpy as np
import pytest
from typer.testing import CliRunner

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
    TERMS,
    Recorder,
    RecordingError,
    label_colours,
    view_command,
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


def read(path) -> dict[str, list[tuple[int | None, dict]]]:
    """``entity -> [(frame or None for static, {component: value})]`` of a recording's data,
    sorted by frame (the chunking rerun chose does not matter)."""
    out = defaultdict(list)
    for chunk in RrdReader(path).stream().collect().stream():
        if chunk.entity_path == "/__properties":
            continue
        rows = chunk.to_record_batch().to_pylist()
        for row in rows:
            frame = row.pop("frame", None)
            row.pop("time", None)
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

    cloud = data["/world/cloud"]
    assert [f for f, _ in cloud] == [0, 2]
    pts = np.asarray(at(cloud, 0, "Points3D:positions"))
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 1000
    assert len(at(cloud, 0, "Points3D:colors")) == len(pts)
    assert np.all(np.abs(pts) < 1.0)  # world frame, metres (not mm, not the camera frame)

    for n, rec in frames.items():
        for o in rec["objects"]:
            ent = f"/world/objects/{o['id']}"
            t = at(data[ent], n, "Transform3D:translation")
            assert np.allclose(t, np.asarray(o["T_world_obj"])[:3, 3], atol=1e-6)
            label = at(data[f"{ent}/label"], n, "Points3D:labels")
            assert label == [f"{o['id']} ({o['mode']})"]
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
    assert sorted(f for f, _ in data["/world/cloud"]) == [0, 1]
    assert any(e.startswith("/world/truth/") for e in data)
    assert "ssp view" in (tmp_path / "report.html").read_text()
