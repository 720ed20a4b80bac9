"""Candidate tests in parallel processes (``search.processes``; issue 19).

Each candidate test of the layered search (:func:`ssp.search.layered_search`) starts from a
saved world state, simulates one window and scores the result: the tests of one object are
independent, and a test's outcome depends only on the state it starts from and the candidate
(the data forces are reset before each test and cache only pure functions of a pose). So they
can run at once in several processes and the search chooses exactly what it chooses serially.

:class:`ForkLanes` forks ``n - 1`` children of the parser's process when the frame's search
first has two candidates to test. A child is a copy of the process at that moment, with the
frame's world, data forces and scorer in it (copy-on-write: nothing is serialised but the
states and the results), and runs the test function it was forked with on the jobs it is sent:
lane ``j`` takes jobs ``j, j + n, ...``, lane 0 is the calling process. The children end with
the search (:meth:`ForkLanes.close`).

Threads (the GIL) gave nothing here: a test is a Python loop of short MuJoCo steps and small
numpy operations. Processes need ``os.fork`` (Linux) and ``OMP_NUM_THREADS=1`` (ssp's default:
an OpenMP runtime that has started threads hangs in a forked child); otherwise the search runs
serially and says so once.

A single-threaded process only is forked. A child is a copy of the memory with only the
forking thread in it: a lock that another thread held at that moment (the stderr buffer's or
the console's of a progress bar refreshing the screen, a logging handler's, a recorder's) stays
held forever there, and the child hangs on its first warning or log line (until ``timeout``,
then its jobs run here). So the children are forked only while no other Python thread runs
(:func:`other_threads`, checked right before the fork); otherwise the lanes stay at one (the
results are the same) and say once which threads kept them there. A program that wants the
lanes must not run another thread meanwhile: a progress display, for one, must redraw from the
calling thread (rich's ``auto_refresh=False``), not from a refresh thread of its own. Native
threads are not Python's and hold none of its locks: OpenBLAS joins its pool before a fork (its
own at-fork handler) and OpenMP is kept single-threaded (above). (The children must be forked
from the frame's process: they hold its world, forces and scorer, which no other process has,
and the test functions are closures over them; a clean process, spawned or from a fork server,
would need all of them serialised every frame.) If a child fails or stops answering
(``timeout``), its jobs run in the calling process instead and the lanes go on with one
process: the results are the same either way.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, Pipe

from ssp.timing import StageTimer

__all__ = ["LANES_STAGE", "ForkLanes", "fork_available", "other_threads"]

log = logging.getLogger(__name__)

#: Stage name of the seconds the lane processes worked (their stages are added to the frame's
#: stages too, which then add up to more than its wall time; wall + this is the CPU time).
LANES_STAGE = "lanes"

_warned_no_fork = False
_warned_threads = False
_zombies: list[int] = []  # children that had not exited yet when closed, reaped later


def fork_available() -> bool:
    """True where :class:`ForkLanes` can fork: Linux, and OpenMP single-threaded (pykdtree's
    OpenMP runtime does not survive a fork once it has started threads)."""
    return (
        hasattr(os, "fork")
        and sys.platform.startswith("linux")
        and os.environ.get("OMP_NUM_THREADS", "1").strip() == "1"
    )


def other_threads() -> list[threading.Thread]:
    """The Python threads of this process other than the calling one that are alive (a fork
    now would copy whatever locks they hold, held; the lanes fork only when there is none)."""
    me = threading.current_thread()
    return [t for t in threading.enumerate() if t is not me and t.is_alive()]


def _reap() -> None:
    """Collect children of earlier lanes that have exited since (no zombies are left)."""
    for pid in list(_zombies):
        try:
            done, _ = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            done = pid
        if done:
            _zombies.remove(pid)


def _child(conn: Connection, test: Callable, timer: StageTimer) -> None:
    """A child's loop: ``(base, [(k, job), ...])`` in, ``(results, stage seconds)`` out;
    None or a closed pipe ends it."""
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        base, jobs = msg
        before = dict(timer.seconds)
        t0 = time.perf_counter()
        out = []
        for k, job in jobs:
            try:
                out.append((k, "ok", test(job, base)))
            except Exception:  # the caller runs the job itself and sees the error there
                out.append((k, "error", traceback.format_exc(limit=3)))
        spent = {s: t - before.get(s, 0.0) for s, t in timer.seconds.items()}
        spent[LANES_STAGE] = time.perf_counter() - t0
        conn.send((out, spent))


class ForkLanes:
    """Up to ``processes`` lanes for ``test(job, base)``; lane 0 is the calling process.

    Args:
        test: the test function, with everything it needs bound (world, simulator, scorer):
            a child runs its fork-time copy of it.
        processes: lanes wanted (1: everything runs in the calling process).
        timer: the stage timer ``test`` writes to; the children's stage seconds are added to
            it, and the seconds they worked as :data:`LANES_STAGE`.
        timeout: seconds to wait for a child's results before doing its jobs here.
    """

    def __init__(
        self, test: Callable, processes: int, timer: StageTimer, timeout: float = 120.0
    ) -> None:
        self.test = test
        self.timer = timer
        self.timeout = float(timeout)
        self.wanted = max(1, int(processes))
        self._children: list[tuple[int, Connection]] = []
        self._started = False
        if self.wanted > 1 and not fork_available():
            global _warned_no_fork
            if not _warned_no_fork:
                log.warning(
                    "search.processes = %d needs os.fork (Linux) and OMP_NUM_THREADS=1 (it is "
                    "%s); candidates are tested in this process",
                    self.wanted,
                    os.environ.get("OMP_NUM_THREADS", "unset"),
                )
                _warned_no_fork = True
            self.wanted = 1

    def __enter__(self) -> ForkLanes:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def lanes(self) -> int:
        """Lanes running now (1 until the children are forked, or after a child failed)."""
        return 1 + len(self._children)

    def _start(self) -> None:
        self._started = True
        _reap()
        for _ in range(self.wanted - 1):
            parent_end, child_end = Pipe()
            others = other_threads()
            if others:  # forking now could leave a child on a lock held forever
                parent_end.close()
                child_end.close()
                self._single_threaded_only(others)
                return
            with warnings.catch_warnings():
                # Python 3.12+ also counts native threads (OpenBLAS's pool, which its at-fork
                # handler joins before the fork); no Python thread runs (other_threads)
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
            if pid == 0:  # the child
                code = 0
                try:
                    parent_end.close()
                    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl+C
                    _child(child_end, self.test, self.timer)
                except BaseException:
                    code = 1
                finally:
                    os._exit(code)
            child_end.close()
            self._children.append((pid, parent_end))

    def _single_threaded_only(self, others: Sequence[threading.Thread]) -> None:
        """No (more) children: another Python thread runs (module docstring)."""
        global _warned_threads
        if not _warned_threads:
            log.warning(
                "%d processes were asked for, but this process runs other threads (%s): "
                "forking it could hang a child on a lock one of them holds, so this search "
                "runs in %d process(es) (the results are the same)",
                self.wanted,
                ", ".join(t.name for t in others),
                self.lanes,
            )
            _warned_threads = True
        self.wanted = self.lanes

    def run(self, base: object, jobs: Sequence[object]) -> list:
        """``test(job, base)`` for every job, in job order (what it returns, or the exception
        it raises in the calling process)."""
        if self.wanted > 1 and not self._started and len(jobs) > 1:
            self._start()
        n = min(self.lanes, len(jobs))
        if n <= 1:
            return [self.test(job, base) for job in jobs]
        sent: list[tuple[int | None, Connection | None, list[tuple[int, object]]]] = []
        for j, (pid, conn) in enumerate(self._children[: n - 1], start=1):
            batch = [(k, jobs[k]) for k in range(j, len(jobs), n)]
            try:
                conn.send((base, batch))
                sent.append((pid, conn, batch))
            except (OSError, ValueError) as exc:
                self._drop(pid, conn, f"could not be sent its jobs ({exc})")
                sent.append((None, None, batch))
        results: dict[int, object] = {k: self.test(jobs[k], base) for k in range(0, len(jobs), n)}
        for child, link, batch in sent:
            got = self._collect(child, link) if child is not None and link is not None else None
            if got is None:  # the child failed: its jobs run here
                results.update({k: self.test(job, base) for k, job in batch})
                continue
            out, spent = got
            for name, sec in spent.items():
                self.timer.add(name, sec)
            for k, status, value in out:
                if status == "ok":
                    results[k] = value
                else:
                    log.debug("candidate test failed in a lane process:\n%s", value)
                    results[k] = self.test(jobs[k], base)  # raises here, with its traceback
        return [results[k] for k in range(len(jobs))]

    def _collect(self, pid: int, conn: Connection):
        try:
            if conn.poll(self.timeout):
                return conn.recv()
            reason = f"did not answer within {self.timeout:g} s"
        except (EOFError, OSError) as exc:
            reason = f"ended ({type(exc).__name__})"
        self._drop(pid, conn, reason)
        return None

    def _drop(self, pid: int, conn: Connection, reason: str) -> None:
        log.warning(
            "lane process %d %s; its candidates are tested in this process instead", pid, reason
        )
        self._children = [(p, c) for p, c in self._children if p != pid]
        conn.close()
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        _zombies.append(pid)
        _reap()

    def close(self) -> None:
        """End the children (they exit when told, or when their pipe closes)."""
        for pid, conn in self._children:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
            conn.close()
            _zombies.append(pid)
        self._children = []
        _reap()
