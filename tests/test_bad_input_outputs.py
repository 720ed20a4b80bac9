"""The bad-input matrix of the outputs (issue 35): outputs that cannot be lost or corrupted.

* nothing outside the output folder is ever touched: a symbolic link in ``OUT`` (the CSV,
  ``frames/``, ``tum/``) is refused with a typed error naming it, and its target is intact;
* an output folder is locked while a run writes it: a second writer gets a typed error naming
  the folder (and the pid holding it);
* a run killed before it wrote ``run.json`` leaves a folder ``--overwrite`` accepts;
* a resume with the same ``--record`` keeps the earlier recording;
* a stop of ``ssp run --workers N`` (SIGTERM) stops every worker at once, each input
  resumable; a worker that dies fails only its own input, named;
* every output is written with the permissions the umask gives (0644 under 022);
* a write that fails (a full disk) is one line naming the file, and the run stays resumable.

The input is a 4-frame synthetic BOP scene (``ssp simulate`` layout, given hypotheses).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ssp.cli import app
from ssp.errors import ArgumentError, SSPError
from ssp.io._files import atomic_write_text, write_json
from ssp.io.clouds import write_cloud
from ssp.pipeline.executor import ItemFailure, Parallel, map_items
from ssp.pipeline.run import run
from ssp.pipeline.summary import without_timings
from ssp.sim.bop import simulate_to_disk

FRAMES = 4
OUTSIDE = "precious"


@pytest.fixture(scope="module")
def scene(lib, tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    (path,) = simulate_to_disk("structure", 1, 3, out_dir=root, library=lib, stages=2,
                               frames_per_stage=2, stride=4, n_objects=3)  # fmt: skip
    return path


@pytest.fixture(scope="module")
def reference(lib, scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "out"
    summary = run(scene, lib, out)
    assert summary.frames == FRAMES and len(summary.done) == FRAMES
    return out


@pytest.fixture(scope="module")
def long_scene(lib, tmp_path_factory):
    """A longer scene (16 frames): its runs are still going when a test stops them."""
    root = tmp_path_factory.mktemp("long")
    (path,) = simulate_to_disk("structure", 1, 5, out_dir=root, library=lib, stages=4,
                               frames_per_stage=4, stride=4, n_objects=4)  # fmt: skip
    return path


def _strip(obj):
    return without_timings(obj, ("files",))


def _load(p: Path):
    return json.loads(p.read_text())


def _rows(out: Path) -> list[str]:
    """CSV rows without the time column."""
    (csv,) = out.glob("*.csv")
    return [line.rsplit(",", 1)[0] for line in csv.read_text().splitlines()]


def _poses_of(out: Path, scene_id: int) -> list[str]:
    """CSV rows without the scene id and time columns, after checking every row carries
    ``scene_id`` (a BOP scene folder's own id: ``000002`` writes scene_id 2)."""
    (csv,) = out.glob("*.csv")
    header, *rows = csv.read_text().splitlines()
    assert {int(r.split(",", 1)[0]) for r in rows} <= {scene_id}, out
    return [header] + [r.split(",", 1)[1].rsplit(",", 1)[0] for r in rows]


def assert_same_results(out: Path, ref: Path) -> None:
    """Frame JSONs, CSV rows and summary equal but for wall times."""
    names = sorted(p.name for p in (out / "frames").iterdir())
    assert names == sorted(p.name for p in (ref / "frames").iterdir())
    for n in names:
        assert _strip(_load(out / "frames" / n)) == _strip(_load(ref / "frames" / n)), n
    assert _rows(out) == _rows(ref)
    assert _strip(_load(out / "summary.json")) == _strip(_load(ref / "summary.json"))
    assert _load(out / "state.json")["parser"] == _load(ref / "state.json")["parser"]


def _stopped_run(lib, scene, out: Path, after: int, **kw) -> None:
    """A run of ``scene`` into ``out`` stopped (Ctrl-C) after ``after`` frames."""

    def progress(done, total, msg):
        if done == after:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(scene, lib, out, progress=progress, **kw)


def _tree(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------ 1. symlinks
def _link_csv(out: Path, outside: Path) -> Path:
    """OUT's CSV replaced by a link to a copy outside OUT that holds more than the run's rows."""
    (csv,) = out.glob("*.csv")
    target = outside / "results.csv"
    target.write_bytes(csv.read_bytes() + b"precious,rows,of,someone,else\n" * 50)
    csv.unlink()
    csv.symlink_to(target)
    return csv


def _link_dir(name: str):
    def make(out: Path, outside: Path) -> Path:
        sub = out / name
        target = outside / name
        if sub.is_dir():
            shutil.copytree(sub, target)
            shutil.rmtree(sub)
        else:
            target.mkdir()
        (target / f"{OUTSIDE}.json").write_text('{"mine": true}\n')
        (target / f"{OUTSIDE}.txt").write_text("mine\n")
        sub.symlink_to(target, target_is_directory=True)
        return sub

    return make


@pytest.mark.parametrize(
    "mode, make",
    [
        ("resume", _link_csv),
        ("overwrite", _link_csv),
        ("resume", _link_dir("frames")),
        ("overwrite", _link_dir("frames")),
        ("resume", _link_dir("tum")),
        ("overwrite", _link_dir("tum")),
    ],
    ids=[
        "resume-csv",
        "overwrite-csv",
        "resume-frames",
        "overwrite-frames",
        "resume-tum",
        "overwrite-tum",
    ],  # fmt: skip
)
def test_a_link_in_out_is_refused_and_its_target_untouched(mode, make, lib, scene, tmp_path):
    out = tmp_path / "out"
    _stopped_run(lib, scene, out, after=2)
    outside = tmp_path / "outside"
    outside.mkdir()
    link = make(out, outside)
    before = _tree(outside)
    with pytest.raises(SSPError, match="symbolic link") as err:
        run(scene, lib, out, **{mode: True})
    assert str(link) in str(err.value)
    assert _tree(outside) == before  # nothing outside OUT truncated, written or deleted
    assert link.is_symlink()


# ------------------------------------------------------------------------------ 2. lock
HOLD_LOCK = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.write(fd, str(os.getpid()).encode())
print("locked", flush=True)
time.sleep(120)
"""


def test_a_second_run_into_a_folder_being_written_is_refused(lib, scene, reference, tmp_path):
    """Two runs at once into one folder (a resume or an overwrite started while a run writes
    it): the second is refused, naming the folder and the pid; the first one's results are
    those of a lone run (no frame written twice)."""
    out = tmp_path / "out"
    _stopped_run(lib, scene, out, after=1)
    refused = []

    def progress(done, total, msg):
        if done == 2:  # a second ssp run, started while this one writes
            for opts in ({"resume": True}, {"overwrite": True}):
                try:
                    run(scene, lib, out, **opts)
                except SSPError as exc:
                    refused.append(str(exc))

    run(scene, lib, out, resume=True, progress=progress)
    assert len(refused) == 2, refused
    for msg in refused:
        assert str(out) in msg and f"pid {os.getpid()}" in msg, msg
    assert_same_results(out, reference)


@pytest.mark.parametrize("command", ["run", "refine"])
def test_a_run_into_a_folder_locked_by_another_process_is_refused(command, lib, scene, reference,
                                                                  tmp_path):  # fmt: skip
    """A folder another process holds the lock of (``ssp run``'s, or the scene folder of an
    ``ssp refine``): refused, naming the folder and the holder's pid; nothing written."""
    from ssp.pipeline.refine import refine

    out = tmp_path / "out"
    locked = out if command == "run" else out / "scenes" / scene.name
    locked.mkdir(parents=True)
    (csv,) = reference.glob("*.csv")  # the run's rows as an estimator's, of the scene's id
    header, *rows = csv.read_text().splitlines()
    est = tmp_path / "est_structure-test.csv"
    est.write_text("\n".join([header, *(f"{int(scene.name)},{r.split(',', 1)[1]}" for r in rows)]))

    def go():
        if command == "run":
            return run(scene, lib, out)
        return refine(scene, est, lib, out, scene_ids=[int(scene.name)], resume=True)

    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(locked / ".ssp.lock")],
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(SSPError, match="another ssp run") as err:
            go()
        assert str(locked) in str(err.value) and f"pid {holder.pid}" in str(err.value)
        assert not (locked / "run.json").exists()
    finally:
        holder.kill()
        holder.wait()
    if command == "run":
        go()  # once it is free, the run goes
        assert not (locked / ".ssp.lock").exists()


# ------------------------------------------------------------------------------ 3. unstarted
@pytest.mark.parametrize(
    "leftovers",
    [("frames/",), ("frames/", ".run.json.x1y2.tmp"), ("frames/", "tum/", "frames/.a.json.tmp")],
    ids=["frames", "frames-and-tmp", "frames-tum-tmp"],
)
def test_a_run_killed_before_run_json_is_replaced_by_overwrite(leftovers, lib, scene,
                                                               reference, tmp_path):  # fmt: skip
    out = tmp_path / "out"
    for name in leftovers:
        p = out / name
        if name.endswith("/"):
            p.mkdir(parents=True, exist_ok=True)
        else:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("{")
    with pytest.raises(ArgumentError, match="--overwrite"):
        run(scene, lib, out, resume=True)
    with pytest.raises(ArgumentError, match="--overwrite"):
        run(scene, lib, out)
    run(scene, lib, out, overwrite=True)
    assert_same_results(out, reference)
    assert not list(out.rglob("*.tmp"))


# ------------------------------------------------------------------------------ 4. recording
def test_a_resume_with_the_same_record_keeps_the_earlier_recording(lib, scene, tmp_path):
    pytest.importorskip("rerun")
    out, rrd = tmp_path / "out", tmp_path / "run.rrd"
    _stopped_run(lib, scene, out, after=2, record=rrd)
    first = rrd.read_bytes()
    assert first
    summary = run(scene, lib, out, resume=True, record=rrd)
    assert rrd.read_bytes() == first  # frames 0-1 are kept
    second = tmp_path / "run.1.rrd"
    assert second.stat().st_size > 0 and str(second) in summary.files


# ------------------------------------------------------------------------------ 5. workers
def _sleep_then_mark(item: str, shared: str) -> str:
    """A work item: ``die`` kills its worker; the others mark their end in ``shared``."""
    Path(shared, item).write_text("started")
    if item == "die":
        time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGKILL)
    t_end = time.monotonic() + (3.0 if item.startswith("short") else 60.0)
    try:
        while time.monotonic() < t_end:
            time.sleep(0.05)
    except KeyboardInterrupt:
        Path(shared, item).write_text("interrupted")
        raise
    Path(shared, item).write_text("finished")
    return item


def test_a_worker_that_dies_fails_only_its_own_item(tmp_path):
    items = ["short-a", "die", "short-b", "short-c"]
    got = map_items(_sleep_then_mark, items, shared=str(tmp_path), parallel=Parallel(
        "processes", 2), names=[f"input {i}" for i in items], on_error="collect")  # fmt: skip
    assert got[0] == "short-a" and got[2] == "short-b" and got[3] == "short-c"
    assert isinstance(got[1], ItemFailure) and got[1].name == "input die"
    assert "died" in got[1].error and "SIGKILL" in got[1].error


SIGTERM_MAP = """
import sys
sys.path.insert(0, sys.argv[2])
from ssp.cli.common import stop_on_sigterm
from ssp.pipeline.executor import Parallel, map_items
from test_bad_input_outputs import _sleep_then_mark

stop_on_sigterm()  # as ssp run does
print("started", flush=True)
map_items(_sleep_then_mark, ["long-a", "long-b", "long-c"], shared=sys.argv[1],
          parallel=Parallel("processes", 2), on_error="collect")
"""


def test_sigterm_stops_every_worker_promptly(tmp_path):
    """SIGTERM to the main process of a 2-worker map (as ``ssp run IN1 IN2 -j 2`` handles it)
    interrupts both running items at once (each writes its stop: a run its summary) and
    starts no other."""
    tests = str(Path(__file__).parent)
    proc = subprocess.Popen([sys.executable, "-c", SIGTERM_MAP, str(tmp_path), tests],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "started"
        deadline = time.monotonic() + 300  # the workers start and take their items
        while time.monotonic() < deadline and len(list(tmp_path.iterdir())) < 2:
            time.sleep(0.05)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=40)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert took < 30
    marks = {p.name: p.read_text() for p in tmp_path.iterdir()}
    assert marks == {"long-a": "interrupted", "long-b": "interrupted"}, marks


def test_cli_sigterm_to_many_inputs_with_workers_leaves_each_resumable(lib, long_scene,
                                                                       tmp_path):  # fmt: skip
    """``ssp run IN1 IN2 --workers 2`` stopped by SIGTERM: it ends promptly (exit 130), and
    each input's run resumes to the results of an uninterrupted one."""
    scene = long_scene
    reference = tmp_path / "reference"
    run(scene, lib, reference)
    inputs = []
    for k in range(2):
        d = tmp_path / f"in{k}"
        shutil.copytree(scene, d / scene.name)
        inputs.append(d / scene.name)
    inputs[1] = inputs[1].rename(inputs[1].with_name(f"{int(scene.name) + 1:06d}"))
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "ssp.cli", "run", *map(str, inputs), "--out", str(out), "-j", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not all(
            (out / p.name / "state.json").exists() for p in inputs
        ):
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        proc.wait(timeout=120)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stderr = proc.stderr.read().decode()
    assert proc.returncode == 130, stderr
    assert took < 20, took
    statuses = {p.name: _load(out / p.name / "summary.json")["status"] for p in inputs}
    # The signal comes once both runs have committed a frame; the first may finish its 16
    # frames before the second worker has started (a loaded machine): that run ends
    # "finished", and the later one is interrupted.
    assert set(statuses.values()) <= {"interrupted", "finished"}, statuses
    assert "interrupted" in statuses.values(), statuses
    for p in inputs:
        sub = out / p.name
        if statuses[p.name] == "interrupted":
            assert _load(sub / "state.json")["next"] < 16
        r = CliRunner().invoke(app, ["run", "--resume", str(sub)])
        assert r.exit_code == 0, r.output
        assert _poses_of(sub, int(p.name)) == _poses_of(reference, int(scene.name))
        frames = sorted(x.name for x in (sub / "frames").iterdir())
        assert frames == sorted(x.name for x in (reference / "frames").iterdir())


def _children(pid: int) -> list[int]:
    kids = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        kids += [int(k) for k in (task / "children").read_text().split()]
    return kids


def _holder_of(pids: list[int], folder: Path) -> int | None:
    """The process among ``pids`` that has a file of ``folder`` open (a run's CSV)."""
    for pid in pids:
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                try:
                    if Path(os.readlink(fd)).parent == folder:
                        return pid
                except OSError:
                    continue
        except OSError:
            continue
    return None


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc")
def test_cli_a_killed_worker_fails_only_its_input(lib, long_scene, tmp_path):
    """``ssp run IN1 IN2 --workers 2``, the worker running IN2 killed: IN2 is reported failed
    by name (how to resume it), IN1 finishes, exit code 1; IN2 resumes to the results of an
    uninterrupted run."""
    scene = long_scene
    reference = tmp_path / "reference"
    run(scene, lib, reference)
    inputs = []
    for k in range(2):
        d = tmp_path / f"in{k}"
        shutil.copytree(scene, d / f"{k + 1:06d}")
        inputs.append(d / f"{k + 1:06d}")
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "ssp.cli", "run", *map(str, inputs), "--out", str(out), "-j", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env)  # fmt: skip
    try:
        victim, deadline = None, time.monotonic() + 300
        while victim is None and time.monotonic() < deadline:
            if (out / inputs[1].name / "state.json").exists():
                victim = _holder_of(_children(proc.pid), (out / inputs[1].name).absolute())
            time.sleep(0.05)
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        output, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = "".join(output.split())  # rich wraps long lines, paths too
    assert proc.returncode == 1, output
    assert f"failed{inputs[1]}:WorkerDied" in text and "SIGKILL" in text, output
    assert f"--resume{out / inputs[1].name}" in text, output
    assert f"failed{inputs[0]}" not in text, output
    first = out / inputs[0].name
    assert _load(first / "summary.json")["status"] == "finished"
    ref = _poses_of(reference, int(scene.name))
    assert _poses_of(first, int(inputs[0].name)) == ref
    r = CliRunner().invoke(app, ["run", "--resume", str(out / inputs[1].name)])
    assert r.exit_code == 0, r.output
    assert _poses_of(out / inputs[1].name, int(inputs[1].name)) == ref


# ------------------------------------------------------------------------------ 6. umask
@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def _mode(p: Path) -> int:
    return p.stat().st_mode & 0o777


@pytest.mark.parametrize(
    "writer",
    ["write_json", "atomic_write_text", "write_cloud-ply", "write_cloud-pcd"],
)
def test_a_written_file_is_readable_as_the_umask_says(writer, umask_022, tmp_path):
    if writer == "write_json":  # ssp evaluate --out, every JSON of a run
        p = write_json(tmp_path / "eval.json", {"ar": 0.5})
    elif writer == "atomic_write_text":  # refine's merged CSV
        p = atomic_write_text(tmp_path / "merged.csv", "scene_id\n")
    else:
        p = write_cloud(tmp_path / f"c.{writer[-3:]}", np.zeros((3, 3)))
    assert _mode(p) == 0o644, oct(_mode(p))


def test_every_run_output_is_readable_as_the_umask_says(lib, scene, umask_022, tmp_path):
    out = tmp_path / "out"
    run(scene, lib, out)
    modes = {str(p.relative_to(out)): oct(_mode(p)) for p in out.rglob("*") if p.is_file()}
    assert {"run.json", "state.json", "summary.json", "obj_ids.json"} <= set(modes)
    assert any(k.startswith("frames/") for k in modes) and any(k.endswith(".csv") for k in modes)
    assert set(modes.values()) == {"0o644"}, modes


# ------------------------------------------------------------------------------ 7. full disk
def _enospc_writing(monkeypatch, match) -> None:
    """``os.fsync`` of a file whose name ``match``es fails as on a full disk."""
    fsync = os.fsync

    def full(fd):
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        if match(name):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", full)


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")
@pytest.mark.parametrize(
    "failing, nth, named, stays_full",
    [
        (".000002.json.", 1, "frames/000002.json", False),
        (".csv", 1, ".csv", False),
        (".state.json.", 3, "state.json", False),
        (".000002.json.", 1, "frames/000002.json", True),
    ],
    ids=["frame-json", "csv", "state-json", "frame-json-then-every-file"],
)
def test_a_full_disk_is_one_line_naming_the_file_and_the_run_resumes(
    failing, nth, named, stays_full, lib, scene, reference, tmp_path, monkeypatch, caplog
):
    seen = []

    def match(name: str) -> bool:  # the nth write of that file fails (and every later one)
        if stays_full and len(seen) >= nth:
            return True
        if failing not in name:
            return False
        seen.append(name)
        return len(seen) == nth

    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _enospc_writing(m, match)
        r = CliRunner().invoke(app, ["run", str(scene), "--out", str(out)])
    text = "".join(r.output.split())  # rich wraps long lines, paths too
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output, r.output
    assert text.count("error:") == 1, r.output
    error = text[text.index("error:") :]
    assert named in error and "Nospaceleftondevice" in error, r.output
    assert "summary.json" not in error  # not blamed on another file
    assert not [r.getMessage() for r in caplog.records if r.exc_info], "a traceback was logged"
    r = CliRunner().invoke(app, ["run", "--resume", str(out)])
    assert r.exit_code == 0, r.output
    assert_same_results(out, reference)
