"""Numba's ``njit`` for the few compiled kernels (the ICPs, the estimator's coarse scoring,
the sample grids), and the one array type they are compiled for.

Compiled with ``cache=True``: the first call of a process compiles, or loads the machine code
cached beside the module by an earlier process. Numba compiles one machine code per argument
type, and a strided or read-only array is another type: float arrays go to a kernel through
:func:`kernel_array`.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

__all__ = ["kernel_array", "njit"]


def njit(function: Callable) -> Callable:
    """``@njit``: ``numba.njit(cache=True)`` of ``function``."""
    return numba.njit(cache=True)(function)


def kernel_array(a) -> np.ndarray:
    """``a`` as float64, C-contiguous and writeable (copied if it is not): the one array type
    the compiled kernels are compiled for. A strided or read-only array would make numba
    compile another specialisation, seconds in the middle of a run."""
    return np.require(a, np.float64, ("C", "W"))
