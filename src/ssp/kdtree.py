"""pykdtree's KD-tree, the nearest-neighbour queries of the hot paths (data forces, ICP, normals,
the estimator).

``OMP_NUM_THREADS`` is set to 1 unless already set, before pykdtree loads its OpenMP runtime:
threads make its small queries slower on few cores, and an OpenMP runtime that has started
threads does not survive the forks of :mod:`ssp.lanes`. Import ``KDTree`` from here so that the
setting comes first wherever pykdtree is first imported.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

from pykdtree.kdtree import KDTree  # noqa: E402

__all__ = ["KDTree"]
