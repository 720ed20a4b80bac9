"""Numba's ``njit`` for the few compiled kernels (the ICPs, the estimator's coarse scoring,
the sample grids, the data forces), the one array type they are compiled for, and numpy's
summation order.

Compiled with ``cache=True``: the first call of a process compiles, or loads the machine code
an earlier process cached, in :func:`kernel_cache_dir`. Numba compiles one machine code per
argument type, and a strided or read-only array is another type: float arrays go to a kernel
through :func:`kernel_array`.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np

from ssp.caches import cache_base

__all__ = ["KERNEL_MODULES", "kernel_array", "kernel_cache_dir", "njit", "pairwise_sum"]

#: The modules (paths under ``ssp/``) that define compiled kernels; a kernel calls kernels of
#: other modules (the cells, the pairwise sum), so their cache is keyed by all of them.
KERNEL_MODULES = (
    "cells.py",
    "components.py",
    "forces.py",
    "jit.py",
    "overlap.py",
    "perception/estimator.py",
    "registration.py",
    "sample_grid.py",
    "visibility.py",
)


@functools.cache
def kernel_cache_dir(root: Path = Path(__file__).parent) -> Path:
    """The folder of the compiled kernels' cache: ``kernels/`` of :func:`ssp.caches.cache_base`,
    one subfolder per digest of the sources of :data:`KERNEL_MODULES` (under ``root``, the
    package folder).

    Numba keys a kernel's cache by its own file only: a kernel that calls a kernel of another
    file (the ICP and the self-occlusion test call :func:`ssp.cells.cell_sort`) kept the machine
    code of the callee it was compiled with after that file changed, and a process that loaded
    both failed at the callee's call from Python ("'descr' is NULL", every frame skipped, after
    a checkout that changed cells.py). Keyed by every kernel module, a change of any compiles
    them all anew in a folder of their own (numba's own subfolders there keep copies of the
    package at other paths apart)."""
    digest = hashlib.sha256()
    for name in KERNEL_MODULES:
        digest.update(name.encode() + b"\0" + (root / name).read_bytes() + b"\0")
    return cache_base() / "kernels" / digest.hexdigest()[:16]


def njit(function: Callable) -> Callable:
    """``@njit``: ``numba.njit(cache=True, nogil=True)`` of ``function``, cached in
    :func:`kernel_cache_dir` (where numba cannot write there, beside the module as numba
    does). A kernel releases the GIL, so independent calls run at once in threads
    (:func:`ssp.threads.thread_map`)."""
    config: Any = numba.config  # its settings are set at import, unknown to type checkers
    before = config.CACHE_DIR
    config.CACHE_DIR = str(kernel_cache_dir())  # read when the dispatcher is made
    try:
        return numba.njit(cache=True, nogil=True)(function)
    finally:
        config.CACHE_DIR = before


def kernel_array(a) -> np.ndarray:
    """``a`` as float64, C-contiguous and writeable (copied if it is not): the one array type
    the compiled kernels are compiled for. A strided or read-only array would make numba
    compile another specialisation, seconds in the middle of a run."""
    return np.require(a, np.float64, ("C", "W"))


@njit
def pairwise_sum(a, n):
    """Sum of ``a[:n]`` (float64) in numpy's order (``numpy.add.reduce`` of a contiguous axis:
    pairwise halves down to blocks of at most 128, each summed with eight accumulators), so a
    kernel's sums equal the numpy code's bit for bit (numpy adds them to 0.0, so a sum of
    negative zeros is +0.0)."""
    return 0.0 + _pairwise(a, 0, n)


@njit
def _block(a, s, n):
    """numpy's sum of ``a[s:s + n]`` for n <= 128."""
    if n < 8:
        res = 0.0
        for i in range(s, s + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[s], a[s + 1], a[s + 2], a[s + 3]
    r4, r5, r6, r7 = a[s + 4], a[s + 5], a[s + 6], a[s + 7]
    i = 8
    end = n - n % 8
    while i < end:
        r0 += a[s + i]
        r1 += a[s + i + 1]
        r2 += a[s + i + 2]
        r3 += a[s + i + 3]
        r4 += a[s + i + 4]
        r5 += a[s + i + 5]
        r6 += a[s + i + 6]
        r7 += a[s + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[s + i]
        i += 1
    return res


@njit
def _pairwise(a, s, n):
    """numpy's recursion (halves rounded down to a multiple of 8, down to blocks of at most
    128), unrolled onto a stack: numba's cache cannot hold a recursive function."""
    if n <= 128:
        return _block(a, s, n)
    start = np.empty(64, dtype=np.int64)
    size = np.empty(64, dtype=np.int64)
    stage = np.zeros(64, dtype=np.int64)
    left = np.empty(64)
    top = 0
    start[0], size[0] = s, n
    ret = 0.0
    while True:
        half = size[top] // 2
        half -= half % 8
        if stage[top] == 0:
            if size[top] <= 128:
                ret = _block(a, start[top], size[top])
                top -= 1
                if top < 0:
                    return ret
                continue
            stage[top] = 1
            top += 1
            start[top], size[top], stage[top] = start[top - 1], half, 0
        elif stage[top] == 1:
            left[top] = ret
            stage[top] = 2
            top += 1
            start[top], size[top], stage[top] = start[top - 1] + half, size[top - 1] - half, 0
        else:
            ret = left[top] + ret
            top -= 1
            if top < 0:
                return ret
