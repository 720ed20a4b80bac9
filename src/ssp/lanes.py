"""Candidates of one object evaluated in parallel (``search.threads``; issue 19).

Each candidate test of the layered search (:func:`ssp.search.layered_search`) starts from the
same saved state, simulates one window and scores the result; the tests are independent. A
:class:`Lanes` holds ``threads`` copies of the frame's world (:meth:`World.replica`: the same
MuJoCo model, so a state saved in one restores bit for bit in another), each with its own data
forces and stage timer, and runs the candidates on them at once: lane 0 is the frame's world in
the calling thread, the others run in worker threads. MuJoCo's stepping and the KD-tree queries
release the GIL, which is where most of a test's time goes.

A test's outcome depends only on the state it starts from and the candidate (the data forces
are reset before each test and cache only pure functions of a pose), so the results, and the
search's choices, are bit-identical for any number of threads.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

from ssp.physics.world import WorldState
from ssp.timing import StageTimer

__all__ = ["Lanes", "TestResult", "in_lanes", "thread_pool"]

#: ``(total log-probability or None when the simulation failed, the state it ended in or None,
#: the error message)``
TestResult = tuple[float | None, WorldState | None, str | None]


class Lanes:
    """``len(sims)`` simulators on interchangeable worlds; ``sims[0]`` is the frame's own.

    Args:
        sims: one :class:`ssp.search.Simulator` per lane, on ``World.replica`` copies of one
            world (lane 0 on the original), each with its own stage timer.
        pool: the threads that run lanes 1, 2, ... (at least ``len(sims) - 1`` workers).
    """

    def __init__(self, sims: Sequence, pool: ThreadPoolExecutor | None) -> None:
        self.sims = list(sims)
        if len(self.sims) > 1 and pool is None:
            raise ValueError("more than one lane needs a thread pool")
        self._pool = pool

    def __len__(self) -> int:
        return len(self.sims)

    def run(
        self,
        base: WorldState,
        jobs: Sequence[object],
        test: Callable[[object, object, WorldState], TestResult],
    ) -> list[TestResult]:
        """``test(sim, job, base)`` for every job, lane ``j`` taking jobs ``j, j + L, ...``
        in order; results in job order."""
        return in_lanes(
            self._pool, len(self.sims), lambda j, job: test(self.sims[j], job, base), jobs
        )

    def merge_timers(self, timer: StageTimer) -> None:
        """Add the worker lanes' stage seconds to ``timer`` (lane 0 uses it directly): with
        several lanes the stages add up to more than the frame's wall time."""
        for sim in self.sims[1:]:
            for name, sec in sim.timer.seconds.items():
                timer.add(name, sec)
            sim.timer.seconds.clear()


def in_lanes(
    pool: ThreadPoolExecutor | None,
    lanes: int,
    fn: Callable[[int, object], object],
    jobs: Sequence[object],
) -> list:
    """``fn(lane, job)`` for every job, in ``lanes`` lanes: lane ``j`` takes jobs ``j, j + L,
    ...`` in order, lane 0 in the calling thread and the others on ``pool``; the results in job
    order. One lane (or no pool) runs everything here, in order."""
    n = min(int(lanes), len(jobs)) if pool is not None else 1
    if n <= 1:
        return [fn(0, job) for job in jobs]

    def lane(j: int) -> list[tuple[int, object]]:
        return [(k, fn(j, jobs[k])) for k in range(j, len(jobs), n)]

    futures = [pool.submit(lane, j) for j in range(1, n)]
    done = lane(0)
    for f in futures:
        done.extend(f.result())
    return [r for _, r in sorted(done, key=lambda kr: kr[0])]


def thread_pool(threads: int) -> ThreadPoolExecutor | None:
    """Worker threads for ``threads`` lanes (None for one lane)."""
    threads = int(threads)
    if threads <= 1:
        return None
    return ThreadPoolExecutor(max_workers=threads - 1, thread_name_prefix="ssp-lane")
