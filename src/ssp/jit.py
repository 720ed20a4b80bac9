"""Numba's ``njit`` for the few compiled kernels (the estimator's ICP and coarse scoring).

Compiled with ``cache=True``: the first call of a process compiles, or loads the machine code
cached beside the module by an earlier process.
"""

from __future__ import annotations

from collections.abc import Callable

import numba

__all__ = ["njit"]


def njit(function: Callable) -> Callable:
    """``@njit``: ``numba.njit(cache=True)`` of ``function``."""
    return numba.njit(cache=True)(function)
