"""Convex decomposition of a model mesh with CoACD, out of process and cached on disk.

CoACD is slow (seconds to minutes) and can use many GB of memory (notes/engines.md section 3), so
it runs in a child process (:mod:`ssp.library._coacd_worker`) with an address-space cap
(``memory_limit_gb``) and a wall-clock timeout (``timeout_s``): a crash, an out-of-memory abort
or a hang fails that run only. Its log is silenced to errors and captured; the tail of it is
attached to failure notes.

Fallbacks (never raise unless the mesh itself is unusable):

1. ``"coacd"``: CoACD with ``threshold``, ``max_convex_hull``, ``preprocess_mode``,
   ``resolution``, ``seed``.
2. ``"coacd-coarse"``: if run 1 fails (non-zero exit, signal, timeout, out of memory, no usable
   part), one retry with ``fallback_threshold`` / ``fallback_max_convex_hull``.
3. ``"convex-hull"``: if that fails too, the single convex hull of the mesh, with a logged
   warning and the reasons in ``DecompositionInfo.note``.

Each part is re-hulled (``trimesh.convex.convex_hull`` of its vertices) and parts with
negligible volume (< 1e-9 m^3 or < 1e-6 of the mesh volume) are dropped.

Cache: ``<cache_dir>/<sha256>.npz`` keyed by the mesh's vertex and face bytes, the CoACD and
fallback parameters and :data:`CACHE_VERSION`; written atomically (temp file + ``os.replace``).
A cached fallback result made under a smaller timeout or memory cap than the current one is
recomputed. A cache hit reports ``cached=True, seconds=0``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from ssp.config import DecompositionConfig, LibraryConfig
from ssp.errors import DecompositionError
from ssp.library.model import DecompositionInfo

log = logging.getLogger(__name__)

#: Bump when the cache file layout or the part post-processing changes.
CACHE_VERSION = 1
#: Parts smaller than this (m^3), or than this fraction of the mesh volume, are dropped.
MIN_PART_VOLUME = 1e-9
MIN_PART_FRACTION = 1e-6
#: Lines and characters of the worker's output attached to failure notes.
LOG_TAIL_LINES = 3
LOG_TAIL_CHARS = 400
_WORKER = Path(__file__).with_name("_coacd_worker.py")


def default_cache_dir(config: LibraryConfig | None = None) -> Path:
    """Hull cache folder: ``config.cache_dir``, else ``$SSP_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/ssp`` or ``~/.cache/ssp``; with ``/hulls`` appended."""
    if config is not None and config.cache_dir is not None:
        base = Path(config.cache_dir)
    elif os.environ.get("SSP_CACHE_DIR"):
        base = Path(os.environ["SSP_CACHE_DIR"])
    elif os.environ.get("XDG_CACHE_HOME"):
        base = Path(os.environ["XDG_CACHE_HOME"]) / "ssp"
    else:
        base = Path.home() / ".cache" / "ssp"
    return base.expanduser() / "hulls"


def _coacd_params(config: DecompositionConfig) -> dict:
    return {
        "threshold": config.threshold,
        "max_convex_hull": config.max_convex_hull,
        "preprocess_mode": config.preprocess_mode,
        "resolution": config.resolution,
        "seed": config.seed,
    }


def cache_key(mesh: trimesh.Trimesh, config: DecompositionConfig) -> str:
    """SHA-256 hex of the mesh geometry, the decomposition parameters and the cache version."""
    h = hashlib.sha256()
    h.update(f"ssp-hulls-v{CACHE_VERSION}".encode())
    h.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    params = _coacd_params(config)
    params["fallback_threshold"] = config.fallback_threshold
    params["fallback_max_convex_hull"] = config.fallback_max_convex_hull
    h.update(json.dumps(params, sort_keys=True).encode())
    return h.hexdigest()


# --------------------------------------------------------------------------- IoU


def _halfspaces(part: trimesh.Trimesh) -> np.ndarray | None:
    """(F, 4) facet planes ``n . x + d <= 0`` inside, or None for a degenerate part."""
    try:
        return ConvexHull(np.asarray(part.vertices, dtype=np.float64)).equations
    except (QhullError, ValueError):
        return None


def inside_union(points: np.ndarray, parts: Sequence[trimesh.Trimesh]) -> np.ndarray:
    """(N,) bool: which ``points`` (N, 3) lie in at least one convex part (half-space tests)."""
    points = np.asarray(points, dtype=np.float64)
    inside = np.zeros(len(points), dtype=bool)
    for part in parts:
        eq = _halfspaces(part)
        if eq is None:
            continue
        lo, hi = part.bounds
        cand = np.flatnonzero(~inside & np.all((points >= lo) & (points <= hi), axis=1))
        if len(cand) == 0:
            continue
        tol = 1e-12 * max(1.0, float(np.abs(hi - lo).max()))
        dist = points[cand] @ eq[:, :3].T + eq[:, 3]
        inside[cand[np.all(dist <= tol, axis=1)]] = True
    return inside


def hull_iou(
    mesh: trimesh.Trimesh,
    parts: Sequence[trimesh.Trimesh],
    n_samples: int = 100_000,
    seed: int = 0,
) -> float:
    """Monte Carlo volume IoU of the union of convex ``parts`` against the solid ``mesh``.

    Points are uniform in the bounding box of mesh and parts, padded by 5 %.
    """
    if not parts:
        return 0.0
    bounds = np.vstack([mesh.bounds] + [p.bounds for p in parts])
    lo, hi = bounds.min(axis=0), bounds.max(axis=0)
    pad = 0.05 * (hi - lo)
    rng = np.random.default_rng(seed)
    pts = rng.uniform(lo - pad, hi + pad, size=(int(n_samples), 3))
    in_mesh = mesh.contains(pts)
    in_parts = inside_union(pts, parts)
    union = int(np.count_nonzero(in_mesh | in_parts))
    return float(np.count_nonzero(in_mesh & in_parts) / union) if union else 0.0


# --------------------------------------------------------------------------- parts


def clean_parts(
    parts: Sequence[trimesh.Trimesh] | Sequence[tuple[np.ndarray, np.ndarray]],
    mesh_volume: float,
) -> tuple[trimesh.Trimesh, ...]:
    """Convex hull of each part's vertices; drop degenerate and negligible parts."""
    min_volume = max(MIN_PART_VOLUME, MIN_PART_FRACTION * abs(mesh_volume))
    out = []
    for part in parts:
        verts = part.vertices if isinstance(part, trimesh.Trimesh) else part[0]
        verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
        if len(verts) < 4 or not np.all(np.isfinite(verts)):
            continue
        try:
            hull = trimesh.convex.convex_hull(verts)
        except Exception:  # qhull errors for flat/degenerate point sets
            continue
        if hull.volume >= min_volume:
            out.append(hull)
    return tuple(out)


def _pack(parts: Sequence[trimesh.Trimesh]) -> dict[str, np.ndarray]:
    return {
        "vertices": np.concatenate([p.vertices for p in parts]).astype(np.float64),
        "faces": np.concatenate([p.faces for p in parts]).astype(np.int64),
        "vertex_counts": np.array([len(p.vertices) for p in parts], dtype=np.int64),
        "face_counts": np.array([len(p.faces) for p in parts], dtype=np.int64),
    }


def _unpack(data) -> list[tuple[np.ndarray, np.ndarray]]:
    if len(data["vertex_counts"]) == 0:
        return []
    v_split = np.cumsum(data["vertex_counts"])[:-1]
    f_split = np.cumsum(data["face_counts"])[:-1]
    verts = np.split(np.asarray(data["vertices"], dtype=np.float64), v_split)
    faces = np.split(np.asarray(data["faces"], dtype=np.int64), f_split)
    return list(zip(verts, faces, strict=True))


# --------------------------------------------------------------------------- cache


def _load_cache(
    path: Path, config: DecompositionConfig
) -> tuple[tuple[trimesh.Trimesh, ...], DecompositionInfo] | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            raw = _unpack(data)
        info = DecompositionInfo(**meta["info"])
        parts = tuple(trimesh.Trimesh(v, f, process=False) for v, f in raw)
    except Exception as exc:  # corrupt or foreign file: recompute
        log.warning("ignoring unreadable hull cache file %s: %s", path, exc)
        return None
    if len(parts) != info.n_parts or not parts:
        log.warning("ignoring inconsistent hull cache file %s", path)
        return None
    if info.method != "coacd" and (
        config.timeout_s > meta.get("timeout_s", 0)
        or config.memory_limit_gb > meta.get("memory_limit_gb", 0)
    ):
        log.info("cached %s result was made under smaller limits; recomputing", info.method)
        return None
    return parts, replace(info, cached=True, seconds=0.0)


def _save_cache(
    path: Path,
    parts: Sequence[trimesh.Trimesh],
    info: DecompositionInfo,
    config: DecompositionConfig,
) -> None:
    meta = {
        "info": asdict(info),
        "timeout_s": config.timeout_s,
        "memory_limit_gb": config.memory_limit_gb,
        "version": CACHE_VERSION,
    }
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem[:16], suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(meta)), **_pack(parts))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        log.warning("cannot write hull cache %s: %s", path, exc)


# --------------------------------------------------------------------------- CoACD runs


class _RunFailed(Exception):
    """One CoACD run failed; the message says why."""


def _worker_argv(in_path: Path, out_path: Path) -> list[str]:
    """Command line of the CoACD worker process."""
    return [sys.executable, str(_WORKER), str(in_path), str(out_path)]


def _limit_memory(limit_bytes: int) -> None:  # runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (limit_bytes, limit_bytes))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def _tail(text: str) -> str:
    """Last lines of the worker's output (the error is at the end), on one line."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    tail = " | ".join(lines[-LOG_TAIL_LINES:])
    return ("..." + tail[-LOG_TAIL_CHARS:]) if len(tail) > LOG_TAIL_CHARS else tail


def _run_coacd(
    mesh: trimesh.Trimesh, params: dict, config: DecompositionConfig
) -> list[tuple[np.ndarray, np.ndarray]]:
    """One CoACD run in a capped child process; raw parts (vertices, faces) or _RunFailed."""
    limit = int(config.memory_limit_gb * 2**30)
    env = dict(os.environ)
    # the worker needs no BLAS threads; their buffers count against the address-space cap
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("MKL_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory(prefix="ssp-coacd-") as tmp:
        in_path, out_path = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(
            in_path,
            vertices=np.asarray(mesh.vertices, dtype=np.float64),
            faces=np.asarray(mesh.faces, dtype=np.int32),
            params=np.array(json.dumps({**params, "log_level": "error"})),
        )
        try:
            proc = subprocess.run(
                _worker_argv(in_path, out_path),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                timeout=config.timeout_s,
                preexec_fn=lambda: _limit_memory(limit),
                cwd=tmp,
                env=env,
                check=False,
            )
        except subprocess.TimeoutExpired as exc:
            out = exc.output.decode(errors="replace") if exc.output else ""
            raise _RunFailed(
                f"timed out after {config.timeout_s:g} s" + (f"; log: {_tail(out)}" if out else "")
            ) from None
        out = proc.stdout.decode(errors="replace") if proc.stdout else ""
        if proc.returncode != 0:
            if proc.returncode < 0:
                how = f"killed by signal {-proc.returncode}"
            else:
                how = f"exit status {proc.returncode}"
            memory_hint = any(
                s in out
                for s in (
                    "MemoryError",
                    "bad_alloc",
                    "Cannot allocate",
                    "failed to map segment",
                    "std::length_error",
                )
            )
            if memory_hint or proc.returncode in (-6, -9):
                how += f" (likely out of memory under the {config.memory_limit_gb:g} GiB cap)"
            raise _RunFailed(how + (f"; log: {_tail(out)}" if out else ""))
        try:
            with np.load(out_path, allow_pickle=False) as data:
                raw = _unpack(data)
                peak_kb = int(data["peak_rss_kb"])
        except Exception as exc:
            raise _RunFailed(f"unreadable worker result: {exc}") from None
    log.info("CoACD run: %d raw parts, worker peak RSS %.0f MB", len(raw), peak_kb / 1024)
    return raw


def decompose(
    mesh: trimesh.Trimesh, config: DecompositionConfig, cache_dir: Path | str
) -> tuple[tuple[trimesh.Trimesh, ...], DecompositionInfo]:
    """Convex parts of the watertight ``mesh`` (metres) and how they were obtained.

    See the module docstring for the fallbacks and the cache. ``info.iou`` uses
    ``config.iou_samples`` Monte Carlo points seeded with ``config.seed``.

    Raises:
        DecompositionError: not even the convex hull of the mesh could be built.
    """
    cache_path = Path(cache_dir) / f"{cache_key(mesh, config)}.npz"
    hit = _load_cache(cache_path, config)
    if hit is not None:
        log.debug("hull cache hit %s", cache_path.name)
        return hit

    t0 = time.perf_counter()
    volume = float(mesh.volume)
    primary = _coacd_params(config)
    coarse = {
        **primary,
        "threshold": config.fallback_threshold,
        "max_convex_hull": config.fallback_max_convex_hull,
    }
    reasons: list[str] = []
    parts: tuple[trimesh.Trimesh, ...] = ()
    method = "convex-hull"
    for name, params in (("coacd", primary), ("coacd-coarse", coarse)):
        try:
            parts = clean_parts(_run_coacd(mesh, params, config), volume)
            if not parts:
                raise _RunFailed("CoACD returned no usable part")
            method = name
            break
        except _RunFailed as exc:
            reasons.append(f"{name} (threshold {params['threshold']:g}) failed: {exc}")
            log.warning("convex decomposition: %s", reasons[-1])
    if not parts:
        parts = clean_parts([mesh], volume)
        if not parts:
            raise DecompositionError("cannot build even the convex hull of the mesh")
        log.warning(
            "convex decomposition fell back to the single convex hull of the mesh; the physics "
            "will fill its concavities"
        )
    note = "; ".join(reasons)
    if method == "convex-hull":
        note = "single convex hull used because " + note
    iou = hull_iou(mesh, parts, config.iou_samples, config.seed)
    seconds = time.perf_counter() - t0
    info = DecompositionInfo(method, len(parts), iou, seconds, False, note)
    log.info(
        "convex decomposition: %s, %d parts, IoU %.3f, %.1f s", method, len(parts), iou, seconds
    )
    _save_cache(cache_path, parts, info, config)
    return parts, info
