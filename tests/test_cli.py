"""The command line: version, config dump, models, demo and bench write what they promise."""

import json

import pytest
import yaml
from typer.testing import CliRunner

from ssp import __version__
from ssp.cli import app
from ssp.config import SSPConfig

runner = CliRunner()


def test_version():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0
    assert __version__ in r.output and "mujoco" in r.output


def test_dump_config_is_loadable_yaml(tmp_path):
    r = runner.invoke(app, ["dump-config"])
    assert r.exit_code == 0
    assert SSPConfig.from_dict(yaml.safe_load(r.output)) == SSPConfig()
    out = tmp_path / "c.yaml"
    r = runner.invoke(app, ["dump-config", "--out", str(out)])
    assert r.exit_code == 0 and out.exists()


def test_bad_config_is_a_clean_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("physics:\n  timestep: 0\n")
    r = runner.invoke(app, ["dump-config", "--config", str(bad)])
    assert r.exit_code == 1
    assert "timestep" in r.output and "Traceback" not in r.output


def test_models_list_and_show():
    r = runner.invoke(app, ["models", "list"])
    assert r.exit_code == 0, r.output
    for name in ("cube", "block", "link", "node"):
        assert name in r.output
    r = runner.invoke(app, ["models", "show", "cube", "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    assert info["extents_mm"] == [50.8, 50.8, 50.8]
    assert info["discrete_symmetries"] == 24


def test_models_show_unknown_name_lists_known():
    r = runner.invoke(app, ["models", "show", "no_such_model"])
    assert r.exit_code == 1
    assert "cube" in r.output


def test_models_prepare_reports_each_model(tmp_path):
    folder = tmp_path / "models"
    r = runner.invoke(app, ["models", "export-builtin", str(folder)])
    assert r.exit_code == 0, r.output
    (folder / "broken.obj").write_text("this is not a mesh\n")
    fast = tmp_path / "fast.yaml"  # fewer IoU points: keep the test quick
    fast.write_text("library:\n  decomposition: {iou_samples: 20000}\n")
    r = runner.invoke(
        app,
        ["models", "prepare", str(folder), "--cache", str(tmp_path / "c"), "--config", str(fast)],
    )
    assert r.exit_code == 1  # one model failed ...
    assert "broken" in r.output and "mallet" in r.output  # ... and the others were prepared
    assert "given" in r.output  # the exported parts are the folder's own


def test_foundation_demo_writes_report(tmp_path):
    r = runner.invoke(app, ["demo", "--foundation", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "foundation.json").read_text())
    assert report["tower"]["max_drift_mm"] < 0.1
    assert report["relaxation"]["accel_from_rest_after_m_s2"] < 0.1 * 9.81
    assert (tmp_path / "foundation.png").stat().st_size > 10_000


def test_sequence_demo_writes_the_report(tmp_path):
    from ssp.eval.sequence_demo import run_sequence_demo

    result = run_sequence_demo(tmp_path, stages=2, frames_per_stage=2, stride=4)
    page = (tmp_path / "report.html").read_text()
    assert "<td>ssp</td>" in page and "frames/003.png" in page
    assert set(result["methods"]) == {
        "ssp", "estimator", "icp", "ray_slide", "bestfit", "temporal_filter", "icp_filter",
    }  # fmt: skip
    assert result["methods"]["ssp"]["max_penetration_mm"] < 1.0


def test_simulate_and_table1_commands(tmp_path):
    small = ["--stages", "1", "--frames-per-stage", "2", "--stride", "4", "--seed", "3"]
    r = runner.invoke(app, ["simulate", "--out", str(tmp_path / "sim"), *small])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "sim" / "structure" / "test" / "000000" / "scene_gt.json").exists()
    r = runner.invoke(app, ["simulate", "--out", str(tmp_path / "orbit"), "--camera", "orbit",
                            *small])  # fmt: skip
    assert r.exit_code == 0, r.output
    cams = json.loads(
        (tmp_path / "orbit" / "structure" / "test" / "000000" / "scene_camera.json").read_text()
    )
    assert cams["0"]["cam_t_w2c"] != cams["1"]["cam_t_w2c"]  # each image its own pose
    r = runner.invoke(app, ["simulate", "--out", str(tmp_path / "x"), "--camera", "drone"])
    assert r.exit_code != 0 and "--camera must be one of" in r.output
    r = runner.invoke(
        app,
        [
            "bench",
            "table1",
            "--sequences",
            "1",
            "--experiment",
            "isolated",
            "--out",
            str(tmp_path / "t1"),
            *small,
        ],
    )
    assert r.exit_code == 0, r.output
    result = json.loads((tmp_path / "t1" / "results.json").read_text())
    assert result["protocol"] == "table1" and result["experiment"] == "isolated"
    assert result["frames"] == 2 and "ssp" in result["methods"]
    assert result["command"]["camera"] == "static"
    r = runner.invoke(app, ["bench", "table1", "--experiment", "towers", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "isolated or structure" in r.output
    r = runner.invoke(app, ["bench", "table1", "--camera", "drone", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "--camera must be one of" in r.output


def test_run_reports_bad_frames_and_fails_without_good_ones(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    (src / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\n")  # no end_header
    (src / "b.pcd").write_bytes(b"not a pcd")
    r = runner.invoke(app, ["run", str(src), "--out", str(tmp_path / "out")])
    assert r.exit_code == 1
    assert "skipped" in r.output and "a.ply" in r.output and "b.pcd" in r.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["done"] == 0 and [f["frame"] for f in summary["failed"]] == ["a", "b"]


def test_run_rejects_unknown_hypotheses_mode(tmp_path):
    r = runner.invoke(app, ["run", str(tmp_path), "--hypotheses", "magic"])
    assert r.exit_code != 0


def test_an_interrupt_a_library_swallows_stops_the_run_at_the_next_frame():
    """Some libraries catch BaseException: Ctrl-C inside them was lost and the run went on.
    The handler is installed even where SIGINT is ignored (a background job inherits that):
    a run started there still stops cleanly on SIGINT."""
    import os
    import signal

    from ssp.cli.common import restore_signals, stop_on_sigterm, stopped

    before = signal.getsignal(signal.SIGINT)  # SIG_IGN in a background job
    previous = stop_on_sigterm()
    try:
        stopped()  # nothing asked yet
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
        except BaseException:  # what such a library does
            pass
        with pytest.raises(KeyboardInterrupt):
            stopped()
    finally:
        restore_signals(previous)
    assert signal.getsignal(signal.SIGINT) == before


def test_run_reads_a_bop_scene_with_its_datasets_models(lib, tmp_path):
    """A BOP scene whose dataset names objects the built-in library lacks is run with the
    dataset's models/ folder when no --models is given (as ssp refine reads it); before, the
    scene was refused ("classes not in the library")."""
    from ssp.sim.bop import simulate_to_disk

    (scene,) = simulate_to_disk("isolated", 1, 3, None, tmp_path / "ds", library=lib, stages=1,
                                frames_per_stage=1, stride=4, objects_per_stage=2)  # fmt: skip
    root = scene.parent.parent
    rename = {name: f"widget_{name}" for name in lib.names}

    def renamed(path, fix):
        path.write_text(json.dumps(fix(json.loads(path.read_text()))))

    def models_json(d):
        d["obj_ids"] = {k: rename[v] for k, v in d["obj_ids"].items()}
        for inst in d.get("instances", []):
            inst["class"] = rename[inst["class"]]
        return d

    for folder in (root, scene):
        if (folder / "models.json").exists():
            renamed(folder / "models.json", models_json)
    renamed(scene / "hypotheses.json", lambda d: {
        k: [{**h, "class": rename[h["class"]]} for h in v] for k, v in d.items()})  # fmt: skip
    renamed(scene / "sequence.json", lambda d: {**d, "models": [rename[m] for m in d["models"]]})
    r = runner.invoke(app, ["run", str(scene), "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert "models: the dataset's" in r.output
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["models"] is not None and run["models"].endswith("models")
    frame = json.loads(next((tmp_path / "out" / "frames").glob("*.json")).read_text())
    assert frame["objects"] and all(o["class"].startswith("obj_") for o in frame["objects"])
