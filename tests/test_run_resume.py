"""``ssp run`` survives being stopped: killed (SIGKILL, SIGINT) or crashing at any write, the
output folder is consistent, and ``--resume`` gives the results of an uninterrupted run.

The input is a 10-frame synthetic BOP scene (``ssp simulate`` layout, given hypotheses) with
one truncated depth image, so a failed frame is among those resumed over. The stopped runs
are real subprocesses (``python -m ssp.cli run``), signalled once they have written ``k``
frame files (``k`` varies per case, so the signal lands at different points of a frame);
the crashes at given writes are injected in-process.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ssp.cli import app
from ssp.config import SSPConfig
from ssp.errors import ArgumentError
from ssp.io.results import BopCsvWriter
from ssp.pipeline.run import run
from ssp.pipeline.summary import without_timings
from ssp.sim.bop import simulate_to_disk

FRAMES = 10
BAD = "000003"  # its depth PNG is truncated: a failed frame


@pytest.fixture(scope="module")
def scene(lib, tmp_path_factory):
    root = tmp_path_factory.mktemp("resume")
    (path,) = simulate_to_disk("structure", 1, 4, out_dir=root, library=lib, stages=5,
                               frames_per_stage=2, stride=4, n_objects=5)  # fmt: skip
    png = path / "depth" / f"{BAD}.png"
    png.write_bytes(png.read_bytes()[:100])
    return path


@pytest.fixture(scope="module")
def reference(lib, scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "out"
    summary = run(scene, lib, out)
    assert summary.frames == FRAMES and [f["frame"] for f in summary.failed] == [BAD]
    return out


def _strip(obj):
    return without_timings(obj, ("files",))


def _rows(out: Path) -> list[str]:
    """CSV rows without the time column."""
    (csv,) = out.glob("*.csv")
    return [line.rsplit(",", 1)[0] for line in csv.read_text().splitlines()]


def _load(p: Path):
    return json.loads(p.read_text())


def assert_same_results(out: Path, ref: Path) -> None:
    """Frame JSONs, CSV rows and summary equal but for wall times; no leftovers."""
    names = sorted(p.name for p in (out / "frames").iterdir())
    assert names == sorted(p.name for p in (ref / "frames").iterdir())
    for n in names:
        assert _strip(_load(out / "frames" / n)) == _strip(_load(ref / "frames" / n)), n
    assert _rows(out) == _rows(ref)
    assert _strip(_load(out / "summary.json")) == _strip(_load(ref / "summary.json"))
    assert _load(out / "obj_ids.json") == _load(ref / "obj_ids.json")
    assert _load(out / "state.json")["parser"] == _load(ref / "state.json")["parser"]
    assert not list(out.rglob("*.tmp"))


def assert_consistent(out: Path, ref: Path) -> int:
    """A stopped run's folder: summary and ids present, every committed frame has its JSON
    and exactly its CSV rows (those of the reference), at most one uncommitted frame JSON;
    the summary holds the committed frames (killed between the commit and the summary's
    write, all but the last). Returns the number of committed frames."""
    summary = _load(out / "summary.json")
    assert summary["status"] in ("running", "interrupted")
    assert _load(out / "obj_ids.json") == _load(ref / "obj_ids.json")
    state = _load(out / "state.json")
    n = state["next"]
    committed = sorted(p.name for p in (ref / "frames").iterdir())[:n]
    assert summary["done"] + len(summary["failed"]) in (n - 1, n)
    for name in committed:
        assert _strip(_load(out / "frames" / name)) == _strip(_load(ref / "frames" / name))
    (csv,) = out.glob("*.csv")
    whole = csv.read_bytes()[: state["csv_bytes"]].decode().splitlines()
    rows = [line.rsplit(",", 1)[0] for line in whole]
    n_rows = 1 + sum(len(_load(ref / "frames" / c).get("objects", [])) for c in committed)
    assert rows == _rows(ref)[:n_rows]
    assert len(list((out / "frames").glob("*.json"))) <= n + 1
    return n


#: ``python -c`` of ``ssp run`` (args: OUT, k, a pipe's fd, then the command's) that, once it
#: has written its k-th frame file (k = 0: run.json), writes ``k`` to the pipe and waits for a
#: signal there: the test signals it at that point, whatever the speed of the machine.
_WAIT_AT_FRAME = """
import os, runpy, signal, sys
from pathlib import Path

out, k, ready = Path(sys.argv[1]).absolute(), int(sys.argv[2]), int(sys.argv[3])
replace, written = os.replace, []


def replace_then_wait(src, dst, *args, **kwargs):
    replace(src, dst, *args, **kwargs)
    dst = Path(dst).absolute()
    if dst.parent == out / "frames" and dst.suffix == ".json":
        written.append(dst.name)
        at = len(written) == k
    else:
        at = k == 0 and dst == out / "run.json"
    if at:
        os.write(ready, b"k")
        os.close(ready)
        signal.pause()  # a handler's KeyboardInterrupt (SIGINT, SIGTERM) is raised here


os.replace = replace_then_wait
sys.argv = ["ssp", *sys.argv[4:]]
runpy.run_module("ssp.cli", run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize(
    "sig, k",
    [
        (signal.SIGKILL, 0),
        (signal.SIGKILL, 1),
        (signal.SIGINT, 3),
        (signal.SIGTERM, 5),
        (signal.SIGKILL, 7),
    ],
    ids=[
        "sigkill-at-start",
        "sigkill-after-1",
        "sigint-after-3",
        "sigterm-after-5",
        "sigkill-after-7",
    ],
)
def test_killed_run_resumes_to_the_uninterrupted_result(sig, k, lib, scene, reference,
                                                        tmp_path):  # fmt: skip
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ready_r, ready_w = os.pipe()  # the run says on it that it has reached the point, and waits
    cmd = [sys.executable, "-c", _WAIT_AT_FRAME, str(out), str(k), str(ready_w),
           "run", str(scene), "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            pass_fds=(ready_w,))  # fmt: skip
    os.close(ready_w)
    try:
        # the run writes b"k" once it has written its k-th frame file (k = 0: run.json) and
        # waits there for the signal; the pipe's end (b"") means it ended before that point.
        # The deadline is a hang guard only (the run takes seconds).
        os.set_blocking(ready_r, False)
        deadline, at = time.monotonic() + 600, None
        while at is None and time.monotonic() < deadline:
            try:
                at = os.read(ready_r, 1)
            except BlockingIOError:
                time.sleep(0.01)
        os.close(ready_r)
        if at != b"k":  # b"": it ended first; None: it hung
            proc.kill()
            proc.wait()
            pytest.fail(f"the run did not stop at frame file {k} ({at!r}): {proc.stderr.read()}")
        proc.send_signal(sig)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stderr = proc.stderr.read().decode()
    assert (out / "run.json").exists()
    assert len(list((out / "frames").glob("*.json"))) >= k
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL
    else:  # Ctrl-C and SIGTERM stop it cleanly, saying how to go on
        assert proc.returncode == 130 and "--resume" in stderr, stderr
        assert _load(out / "summary.json")["status"] == "interrupted"
    if (out / "state.json").exists():
        assert_consistent(out, reference)
    if sig != signal.SIGKILL:  # resume through the command line
        r = CliRunner().invoke(app, ["run", "--resume", str(out)])
        assert r.exit_code == 0, r.output
    else:
        summary = run(scene, lib, out, resume=True)
        assert summary.status == "finished"
    assert_same_results(out, reference)


def _crash_at(monkeypatch, where: str, frame: str) -> None:
    """Raise KeyboardInterrupt at one write of frame ``frame`` (``where``: after its JSON,
    half-way through its CSV rows, before the state commit, after it)."""
    import ssp.pipeline.run

    real_write = ssp.pipeline.run.write_json
    seen = {"frame": False}

    def write_json(path, obj, indent=1):
        p = Path(path)
        if p.name == f"{frame}.json":
            seen["frame"] = True
            real_write(path, obj, indent)
            if where == "after-json":
                raise KeyboardInterrupt
            return p
        if seen["frame"] and p.name == "state.json" and where == "before-commit":
            raise KeyboardInterrupt
        return real_write(path, obj, indent)

    real_text = ssp.pipeline.run.atomic_write_text

    def atomic_write_text(path, text):  # the summary written after each frame
        out = real_text(path, text)
        if seen["frame"] and Path(path).name == "summary.json" and where == "after-commit":
            raise KeyboardInterrupt
        return out

    real_rows = BopCsvWriter.write_rows

    def write_rows(self, lines):
        lines = list(lines)
        if seen["frame"] and where == "mid-csv" and lines:
            self._f.write(lines[0][:20])  # a torn row
            self._f.flush()
            raise KeyboardInterrupt
        return real_rows(self, lines)

    monkeypatch.setattr(ssp.pipeline.run, "write_json", write_json)
    monkeypatch.setattr(ssp.pipeline.run, "atomic_write_text", atomic_write_text)
    monkeypatch.setattr(BopCsvWriter, "write_rows", write_rows)


@pytest.mark.parametrize("where", ["after-json", "mid-csv", "before-commit", "after-commit"])
def test_crash_at_any_write_resumes_to_the_uninterrupted_result(where, lib, scene, reference,
                                                                tmp_path, monkeypatch):  # fmt: skip
    out = tmp_path / "out"
    frame = "000005"
    with monkeypatch.context() as m:
        _crash_at(m, where, frame)
        with pytest.raises(KeyboardInterrupt):
            run(scene, lib, out)
    n = assert_consistent(out, reference)
    assert n == (6 if where == "after-commit" else 5)
    assert _load(out / "summary.json")["status"] == "interrupted"
    run(scene, lib, out, resume=True)
    assert_same_results(out, reference)


def test_resume_checks_what_the_run_reads(lib, scene, reference, tmp_path):
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        _stop_after(lib, scene, out, 2)
    # a finished run resumes to itself; a changed input is refused
    with pytest.raises(ArgumentError, match="classes"):
        run(scene, lib, out, resume=True, classes=["cube"])
    cfg = SSPConfig()
    cfg.search.reach = 0.05
    with pytest.raises(ArgumentError, match="search.reach"):
        run(scene, lib, out, cfg, resume=True)
    summary = run(scene, lib, out, resume=True)
    assert summary.status == "finished"
    run(scene, lib, out, resume=True)  # nothing left to do
    assert_same_results(out, reference)
    png = scene / "depth" / "000007.png"
    os.utime(png, ns=(png.stat().st_atime_ns, png.stat().st_mtime_ns + 10**9))
    with pytest.raises(ArgumentError, match="depth/000007.png"):
        run(scene, lib, out, resume=True)
    os.utime(png, ns=(png.stat().st_atime_ns, png.stat().st_mtime_ns - 10**9))


def _stop_after(lib, scene, out, frames: int, **options) -> None:
    def progress(done, total, msg):
        if done == frames:
            raise KeyboardInterrupt

    run(scene, lib, out, progress=progress, **options)


def test_summary_written_during_the_run_is_the_summary(reference):
    """The compact summary written after each frame (records encoded once) equals the dict."""
    from ssp.pipeline.summary import RunSummary

    s = RunSummary("in", "bop", frames=FRAMES)
    s.masks = _load(reference / "summary.json")["masks"]  # set by run() from its input
    for p in sorted((reference / "frames").iterdir()):
        s.add(_load(p))
        s.time_frame(_load(p))
        compact, full = json.loads(s.to_json()), json.loads(json.dumps(s.to_dict()))
        # the wall time so far moves between the two calls; its parts do not
        assert compact["timings"]["wall"] <= full["timings"]["wall"]
        for d in (compact, full):
            d["timings"].pop("wall")
            d["timings"]["parts"].pop("other")
        assert compact == full
    assert _strip(json.loads(s.to_json())) == _strip(
        {**_load(reference / "summary.json"), "input": "in", "status": "running"}
    )


def test_a_run_resumes_with_another_process_count_to_the_same_result(lib, scene, reference,
                                                                      tmp_path):  # fmt: skip
    """search.processes changes no result, so a resume may use another count."""
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        _stop_after(lib, scene, out, 3)
    cfg = SSPConfig()
    cfg.search.processes = 2
    assert run(scene, lib, out, cfg, resume=True).status == "finished"
    assert_same_results(out, reference)


def test_a_run_with_estimated_hypotheses_resumes_with_its_segment_memory(lib, tmp_path):
    """The built-in estimator's unchanged segments keep their hypotheses
    (ssp.perception.reuse): state.json holds that memory, and a resumed run gives the
    uninterrupted results. Tools in static stages of 4 frames at 320 x 240 (the segments of
    the 160 x 120 scene above are too small to tell from noise: estimated every frame)."""
    (scene,) = simulate_to_disk("isolated", 1, 7, out_dir=tmp_path / "in", library=lib,
                                stages=2, frames_per_stage=4, stride=2)  # fmt: skip
    ref = tmp_path / "ref"
    run(scene, lib, ref, hypotheses="estimated")
    frames = [_load(p) for p in sorted((ref / "frames").iterdir())]
    assert sum(f["perception"]["reused"] for f in frames if "perception" in f) > 0
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        _stop_after(lib, scene, out, 6, hypotheses="estimated")
    assert _load(out / "state.json")["segments"]
    assert run(scene, lib, out, resume=True, hypotheses="estimated").status == "finished"
    assert_same_results(out, ref)
    assert _load(out / "state.json")["segments"] == _load(ref / "state.json")["segments"]
