"""Numba's ``njit`` for the few compiled kernels (the estimator's ICP and coarse scoring).

Compiled with ``cache=True``: the first call of a process compiles, or loads the machine code
cached beside the module by an earlier process.
"""

from __future__ import annotations

from collections.abc import Callable

import numba

__all__ = ["njit"]


def njit(function: Callable | None = None, **options) -> Callable:
    """``numba.njit`` with the cache on (``@njit`` or ``@njit(cache=..., ...)``)."""
    options.setdefault("cache", True)
    if function is None:
        return numba.njit(**options)
    return numba.njit(**options)(function)
