"""ssp.threads.thread_map: the calls' results in the jobs' order, no thread left behind."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from ssp import threads
from ssp.registration import icp_refine


def test_results_in_the_jobs_order_and_no_thread_outlives_the_call():
    before = threading.active_count()
    names = set()

    def job(k: int) -> int:
        names.add(threading.current_thread().name)
        return k * k

    assert threads.thread_map(job, list(range(20)), name="ssp-test", threads=2) == [
        k * k for k in range(20)
    ]
    assert threading.active_count() == before
    assert all(n.startswith("ssp-test") for n in names)
    # one job, or one thread: in the calling thread
    names.clear()
    assert threads.thread_map(job, [3], name="ssp-test") == [9]
    assert threads.thread_map(job, [1, 2], threads=1) == [1, 4]
    assert names == {threading.current_thread().name}


def test_an_exception_of_a_job_is_raised():
    def job(k: int) -> int:
        if k == 3:
            raise ValueError("job 3")
        return k

    with pytest.raises(ValueError, match="job 3"):
        threads.thread_map(job, list(range(6)), threads=2)


def test_icps_in_threads_equal_them_one_after_another(lib):
    """The ICP kernel releases the GIL; in threads it gives the same poses bit for bit."""
    model = lib["drill"]
    rng = np.random.default_rng(1)
    T_true = np.eye(4)
    T_true[:3, 3] = [0.0, 0.0, 0.05]
    segment = model.surface_points[::3] @ T_true[:3, :3].T + T_true[:3, 3]
    starts = []
    for _ in range(6):
        T = T_true.copy()
        T[:3, 3] += rng.normal(0.0, 0.004, 3)
        starts.append(T)
    cam = np.array([0.0, -0.6, 0.5])
    serial = [icp_refine(model, T, segment, cam) for T in starts]
    threaded = threads.thread_map(lambda T: icp_refine(model, T, segment, cam), starts, threads=2)
    for a, b in zip(serial, threaded, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(serial[0], starts[0])  # the ICP moved the pose
