"""CoACD in a child process: ``python _coacd_worker.py IN.npz OUT.npz``.

Run by :mod:`ssp.library.decomposition` under a memory cap and a timeout, so that a crash, an
out-of-memory kill or a hang of CoACD cannot take the caller down. Imports only numpy and coacd
(no ssp package import, to start fast).

IN.npz: ``vertices`` (V, 3) float64, ``faces`` (F, 3) int32, ``params`` JSON text of
:func:`coacd.run_coacd` keyword arguments plus ``log_level``.
OUT.npz: ``vertices`` (sum V_i, 3), ``faces`` (sum F_i, 3) (indices local to each part),
``vertex_counts`` (P,), ``face_counts`` (P,), ``peak_rss_kb`` (the worker's peak RSS, KiB).
Exit status 0 on success; anything else (or a signal) is a failure, with the reason on stderr.
"""

from __future__ import annotations

import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))
if __name__ == "__main__" and sys.path and os.path.abspath(sys.path[0] or ".") == _HERE:
    # run as a script: do not let this package folder shadow top-level modules
    del sys.path[0]

import json  # noqa: E402
import resource  # noqa: E402

import numpy as np  # noqa: E402


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        sys.stderr.write("usage: _coacd_worker.py IN.npz OUT.npz\n")
        return 2
    with np.load(argv[1], allow_pickle=False) as data:
        vertices = np.ascontiguousarray(data["vertices"], dtype=np.float64)
        faces = np.ascontiguousarray(data["faces"], dtype=np.int32)
        params = json.loads(str(data["params"]))

    import coacd

    coacd.set_log_level(params.pop("log_level", "error"))
    result = coacd.run_coacd(coacd.Mesh(vertices, faces), **params)
    if result:
        verts = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v, _ in result])
        tris = np.concatenate([np.asarray(f, dtype=np.int64).reshape(-1, 3) for _, f in result])
    else:
        verts, tris = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with open(argv[2], "wb") as fh:
        np.savez(
            fh,
            vertices=verts,
            faces=tris,
            vertex_counts=np.array([len(v) for v, _ in result], dtype=np.int64),
            face_counts=np.array([len(f) for _, f in result], dtype=np.int64),
            peak_rss_kb=np.array(peak, dtype=np.int64),
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
