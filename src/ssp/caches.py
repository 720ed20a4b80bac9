"""Where ssp caches what it computes once: ``$SSP_CACHE_DIR``, else ``$XDG_CACHE_HOME/ssp``,
else ``~/.cache/ssp``; the convex parts of the models under ``hulls/``
(:func:`ssp.library.decomposition.default_cache_dir`), the compiled kernels under
``kernels/`` (:func:`ssp.jit.kernel_cache_dir`)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_base"]


def cache_base() -> Path:
    """ssp's cache folder (module docstring); not created here."""
    if os.environ.get("SSP_CACHE_DIR"):
        base = Path(os.environ["SSP_CACHE_DIR"])
    elif os.environ.get("XDG_CACHE_HOME"):
        base = Path(os.environ["XDG_CACHE_HOME"]) / "ssp"
    else:
        base = Path.home() / ".cache" / "ssp"
    return base.expanduser()
