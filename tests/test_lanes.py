"""Candidate tests in forked processes (ssp.lanes, ``search.processes``): the same results."""

from __future__ import annotations

import logging
import os
import signal
import threading

import numpy as np
import pytest

import ssp.lanes as lanes_mod
from ssp.config import SSPConfig
from ssp.eval.bench_parser import _slide, stacks
from ssp.lanes import LANES_STAGE, ForkLanes
from ssp.library import ObjectLibrary
from ssp.parser import SceneParser
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at
from ssp.timing import StageTimer

LIB = ObjectLibrary.builtin()

pytestmark = pytest.mark.skipif(not lanes_mod.fork_available(), reason="os.fork is Linux-only")


@pytest.fixture(autouse=True)
def _single_threaded():
    """The lanes fork a single-threaded process only: a thread an earlier test left running
    would keep these tests in one process, so say which."""
    others = [t.name for t in threading.enumerate() if t is not threading.current_thread()]
    assert not others, f"threads left running by an earlier test: {others}"


def _square(job, base):
    """A test function: its result depends only on the job and the base, as the search's does;
    it says which process ran it."""
    return job * job + base, os.getpid()


def test_jobs_run_in_two_processes_and_come_back_in_order():
    timer = StageTimer()
    with ForkLanes(_square, 2, timer) as lanes:
        out = lanes.run(10, list(range(7)))
        assert lanes.lanes == 2
        again = lanes.run(1, [3, 4])
        children = [pid for pid, _ in lanes._children]
    assert [v for v, _ in out] == [j * j + 10 for j in range(7)]
    assert [v for v, _ in again] == [10, 17]
    pids = {p for _, p in out}
    assert pids == {os.getpid(), children[0]}  # lane 0 here, lane 1 in the child
    assert [p for _, p in out[1::2]] == [children[0]] * 3
    assert timer.seconds[LANES_STAGE] > 0.0  # the child's working time is reported
    assert lanes._children == []


def test_one_process_or_one_job_forks_nothing():
    with ForkLanes(_square, 1, StageTimer()) as lanes:
        assert [v for v, _ in lanes.run(0, [1, 2, 3])] == [1, 4, 9]
        assert lanes._children == []
    with ForkLanes(_square, 4, StageTimer()) as lanes:
        assert [v for v, _ in lanes.run(0, [5])] == [25]  # a single job: no fork yet
        assert lanes._children == []


def test_a_child_that_dies_has_its_jobs_run_here(caplog):
    with ForkLanes(_square, 2, StageTimer()) as lanes:
        lanes.run(0, [1, 2])
        ((pid, _),) = lanes._children
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        with caplog.at_level(logging.WARNING, logger="ssp.lanes"):
            out = lanes.run(0, list(range(5)))
        assert [v for v, _ in out] == [j * j for j in range(5)]
        assert {p for _, p in out} == {os.getpid()}
        assert lanes.lanes == 1  # the lanes go on with one process
    assert f"lane process {pid}" in caplog.text


def test_a_child_that_stops_answering_is_dropped(caplog):
    with ForkLanes(_square, 2, StageTimer(), timeout=0.5) as lanes:
        lanes.run(0, [1, 2])
        ((pid, _),) = lanes._children
        os.kill(pid, signal.SIGSTOP)
        with caplog.at_level(logging.WARNING, logger="ssp.lanes"):
            out = lanes.run(0, [3, 4])
        assert [v for v, _ in out] == [9, 16]
        assert lanes.lanes == 1
    assert "did not answer within 0.5 s" in caplog.text


@pytest.mark.parametrize("daemon", [False, True], ids=["thread", "daemon thread"])
def test_a_process_that_runs_another_thread_is_not_forked(monkeypatch, caplog, daemon):
    """A child forked while another thread runs holds, held for ever, every lock that thread
    held then (a progress bar's console and stderr buffer while it redraws): the lanes fork a
    single-threaded process only, and test here meanwhile (the same results)."""
    threads_at_fork = []
    fork = os.fork

    def counting_fork():
        threads_at_fork.append(threading.active_count())
        return fork()

    monkeypatch.setattr(lanes_mod.os, "fork", counting_fork)
    monkeypatch.setattr(lanes_mod, "_warned_threads", False, raising=False)
    lock, holding, release = threading.Lock(), threading.Event(), threading.Event()

    def hold() -> None:  # holds a lock until told, as a refresh thread does while it draws
        with lock:
            holding.set()
            release.wait(60)

    other = threading.Thread(target=hold, name="holds-a-lock", daemon=daemon)
    other.start()
    try:
        assert holding.wait(60)
        with caplog.at_level(logging.WARNING, logger="ssp.lanes"):
            with ForkLanes(_square, 2, StageTimer()) as lanes:
                out = lanes.run(10, list(range(5)))
                assert lanes.lanes == 1 and lanes._children == []
                assert [v for v, _ in lanes.run(0, [2, 3])] == [4, 9]
            with ForkLanes(_square, 2, StageTimer()) as lanes:  # said once per process
                lanes.run(0, [1, 2])
    finally:
        release.set()
        other.join(60)
    assert threads_at_fork == []  # today's code: [2], a threaded process forked
    assert out == [(j * j + 10, os.getpid()) for j in range(5)]
    assert caplog.text.count("runs other threads (holds-a-lock)") == 1
    # once the other thread has ended, the next lanes fork again (a single-threaded process)
    with ForkLanes(_square, 2, StageTimer()) as lanes:
        out = lanes.run(0, [1, 2, 3])
        assert lanes.lanes == 2
    assert threads_at_fork == [1]
    assert [p for _, p in out] == [os.getpid(), out[1][1], os.getpid()] != [os.getpid()] * 3


def _fails_on_three(job, base):
    if job == 3:
        raise ValueError(f"job {job} is bad")
    return job


def test_an_error_in_a_child_is_raised_here_with_its_own_traceback():
    with ForkLanes(_fails_on_three, 2, StageTimer()) as lanes:
        assert lanes.run(0, [0, 1]) == [0, 1]
        with pytest.raises(ValueError, match="job 3 is bad"):
            lanes.run(0, [2, 3])  # job 3 runs in the child first, then here


def test_without_fork_it_says_so_once_and_runs_here(monkeypatch, caplog):
    monkeypatch.setattr(lanes_mod, "fork_available", lambda: False)
    monkeypatch.setattr(lanes_mod, "_warned_no_fork", False)
    with caplog.at_level(logging.WARNING, logger="ssp.lanes"):
        a = ForkLanes(_square, 2, StageTimer())
        b = ForkLanes(_square, 2, StageTimer())
    assert [v for v, _ in a.run(0, [1, 2])] == [1, 4] and a._children == []
    assert b.wanted == 1
    assert caplog.text.count("needs os.fork") == 1


def test_openmp_threads_keep_the_search_in_one_process(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    assert not lanes_mod.fork_available()


def _parse(processes: int, frames) -> list:
    cfg = SSPConfig()
    cfg.search.processes = processes
    parser = SceneParser(LIB, cfg)
    return [parser.update(f) for f in frames]


def test_two_processes_give_the_same_scenes_as_one():
    rng = np.random.default_rng(5)
    gt = stacks(LIB, 5, seed=2)
    cam = look_at([-0.5, -0.6, 0.65], [0.0, 0.0, 0.03])
    frames = [
        synthetic_frame(LIB, g, T_world_cam=cam, rng=rng, k=3, stamp=float(t))
        for t, g in enumerate([gt, _slide(gt, 0.015)])
    ]
    one, two = _parse(1, frames), _parse(2, frames)
    for a, b in zip(one, two, strict=True):
        assert a.hypotheses_tested == b.hypotheses_tested > 0
        assert [o.id for o in a.objects] == [o.id for o in b.objects]
        for oa, ob in zip(a.objects, b.objects, strict=True):
            np.testing.assert_array_equal(oa.T_world_obj, ob.T_world_obj)
            assert oa.source == ob.source and oa.terms == ob.terms
        assert a.log_prob == b.log_prob
        assert LANES_STAGE not in a.timings and b.timings[LANES_STAGE] > 0.0


def test_two_processes_estimate_the_same_hypotheses_as_one():
    """perception.processes: the segments' hypotheses are estimated in two processes, the
    same as in one (the estimator's caches built before the fork)."""
    from ssp.perception.pipeline import Perception

    rng = np.random.default_rng(3)
    gt = stacks(LIB, 4, seed=1)
    cam = look_at([-0.5, -0.6, 0.65], [0.0, 0.0, 0.03])
    frame = synthetic_frame(LIB, gt, T_world_cam=cam, rng=rng, k=3)
    out = []
    for processes in (1, 2):
        cfg = SSPConfig()
        cfg.perception.processes = processes
        per = Perception(LIB, cfg, classes=["cube", "block"])
        res = per.from_points(frame.points, frame="world", T_world_cam=cam, labels=frame.labels)
        out.append(res)
    one, two = out
    assert len(one.segments) >= 3
    assert one.verdicts == two.verdicts
    for a, b in zip(one.frame.hypotheses, two.frame.hypotheses, strict=True):
        assert a.class_name == b.class_name and a.segment == b.segment and a.score == b.score
        np.testing.assert_array_equal(a.T_world_obj, b.T_world_obj)
    assert LANES_STAGE not in one.timings and two.timings[LANES_STAGE] > 0.0


def test_the_clis_live_displays_run_no_thread(monkeypatch):
    """On a terminal the CLI's progress bar and status spinner are redrawn by the calling
    thread, so a run's process stays single-threaded and the search can fork its lanes."""
    import io
    import threading

    from ssp.cli import common

    def terminal():
        return common._Console(file=io.StringIO(), force_terminal=True, force_interactive=True)

    monkeypatch.setattr(common, "err_console", terminal())
    before = threading.active_count()
    with common.progress_bar() as bar:
        task = bar.add_task("frames", total=3)
        for _ in range(3):
            bar.advance(task)
            assert threading.active_count() == before
    status_console = terminal()
    with status_console.status("timing") as status:
        status.update("still timing")
        assert threading.active_count() == before
    assert "still timing" in status_console.file.getvalue()
