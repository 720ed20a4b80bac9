"""Independent compiled work in threads (issue 34): the same results as one call after another.

Some of a frame's work is a few independent calls of code that releases the GIL: the ICP
kernel (:func:`ssp.registration.point_to_plane_icp`, compiled with ``nogil``) of each object
the polish aligns and of each candidate orientation the orientations stage aligns, the
cleaning of each instance segment (KD-tree queries and sorts). :func:`thread_map` runs such
calls in :data:`KERNEL_THREADS` threads and returns their results in the jobs' order. A job
must not depend on another's result or change what another reads, so the results are those of
the calls one after another, bit for bit.

The pool is made and joined within each call: no thread outlives it, so the search's lane
processes (:mod:`ssp.lanes`, which fork only while no other Python thread runs) are forked as
before. Making it costs some 0.1 ms; a single job, or one thread, runs in the calling thread.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

__all__ = ["KERNEL_THREADS", "thread_map"]

#: Threads of :func:`thread_map`: one per core, at most 4.
KERNEL_THREADS = max(1, min(4, os.cpu_count() or 1))

J = TypeVar("J")
R = TypeVar("R")


def thread_map(
    fn: Callable[[J], R], jobs: Sequence[J], *, name: str = "ssp", threads: int | None = None
) -> list[R]:
    """``[fn(job) for job in jobs]``, the jobs in up to ``threads`` (default
    :data:`KERNEL_THREADS`) threads named ``name``; the results in the jobs' order. An
    exception of a job is raised here (the first in the jobs' order)."""
    n = min(KERNEL_THREADS if threads is None else max(1, int(threads)), len(jobs))
    if n <= 1:
        return [fn(job) for job in jobs]
    with ThreadPoolExecutor(n, thread_name_prefix=name) as pool:
        return list(pool.map(fn, jobs))
