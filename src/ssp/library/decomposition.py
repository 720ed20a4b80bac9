"""Convex parts of a model mesh, chosen for physics quality; CoACD out of process; cached.

Policy (``DecompositionConfig.mode = "auto"``), first match wins:

1. ``"convex"``: the mesh is convex within ``convex_tolerance`` (its volume is at least
   ``1 - convex_tolerance`` of its convex hull's): its single convex hull, no CoACD. A rounded
   cube with shallow recesses is one part, not 85.
2. ``"shells"``: the mesh is two or more connected shells (bodies), each convex within the
   tolerance: those shells' hulls, no CoACD (they already are an exact decomposition).
3. ``"coacd"``: CoACD with ``threshold``, ``max_convex_hull``, ``preprocess_mode``,
   ``resolution``, ``seed`` on the mesh (decimated to ``max_faces`` first when it has more, with
   fast-simplification's quadric decimation; when the decimated mesh is not watertight or its
   volume is off by more than 1 %, CoACD's own manifold preprocessing instead). If that run
   fails (non-zero exit, signal, timeout, out of memory, no usable part), one retry with
   ``fallback_threshold`` / ``fallback_max_convex_hull`` (``"coacd-coarse"``); if that fails
   too, the single convex hull (``"convex-hull"``) with a logged warning and the reasons in
   ``DecompositionInfo.note``.

Then, whatever the source (CoACD or shells), neighbouring parts are merged while the merged
part stays convex within the tolerance (the hull of the pair holds at most ``convex_tolerance``
empty volume, measured against the solid volume of the parts merged into it), cheapest merge
first, and merging goes on until at most ``max_parts`` remain (:func:`merge_parts`).
``mode = "coacd"`` skips steps 1-2; ``mode = "convex-hull"`` always takes the single hull.

Every result reports the volume IoU of the union of its parts against the mesh (Monte Carlo,
``iou_samples`` points, chunked so that no array exceeds :data:`IOU_CHUNK_ENTRIES` entries);
:func:`ssp.library.build.build_model` warns when it is below ``min_iou``.

CoACD is slow (seconds to minutes) and can use many GB of memory (notes/engines.md section 3), so
it runs in a child process (:mod:`ssp.library._coacd_worker`) with an address-space cap
(``memory_limit_gb``) and a wall-clock timeout (``timeout_s``): a crash, an out-of-memory abort
or a hang fails that run only. Its log is silenced to errors and captured; the tail of it is
attached to failure notes. While it runs, ``status(text)`` is called about once a second.

Each part is re-hulled (``trimesh.convex.convex_hull`` of its vertices) and parts with
negligible volume (< 1e-9 m^3 or < 1e-6 of the mesh volume) are dropped.

Cache: ``<cache_dir>/<bucket>.<i>.npz``. The bucket is a SHA-256 of the decomposition
parameters, :data:`CACHE_VERSION`, the vertex and face counts and the volume and area (4
significant digits); every entry of a bucket stores the mesh's vertices re-centred at its
volume centroid, and a hit needs the same vertex set within :data:`CACHE_TOLERANCE` of the
mesh size. Parts are stored in that centred frame and moved back, so a re-export (another
vertex or face order, float noise) or a re-centred copy of a mesh reuses its parts. Written
atomically (temp file + ``os.replace``). A cached fallback result made under a smaller timeout
or memory cap than the current one is recomputed. A cache hit reports ``cached=True,
seconds=0``.
"""

from __future__ import annotations

import hashlib
import heapq
import json
import logging
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ssp.caches import cache_base
from ssp.config import DecompositionConfig, LibraryConfig
from ssp.errors import DecompositionError
from ssp.geometry import in_box
from ssp.library.model import DecompositionInfo

log = logging.getLogger(__name__)

#: Bump when the cache file layout or the part post-processing changes.
CACHE_VERSION = 2
#: A cache entry matches when every vertex of the re-centred mesh lies within this fraction of
#: the mesh's largest extent of a stored vertex (and vice versa): float noise of a re-export.
CACHE_TOLERANCE = 1e-6
#: Largest number of entries of one points x facets matrix of the IoU check (32 MB float64).
IOU_CHUNK_ENTRIES = 1 << 22
#: Points per ``mesh.contains`` call of the IoU check.
CONTAINS_CHUNK = 20_000
#: Convex parts with more facets are tested by ray casting (O(log F) per point) instead of
#: one plane test per facet (the convex hull of a huge mesh can have 10^5-10^6 facets).
RAY_TEST_FACETS = 5000
#: Called with a one-line status text while a decomposition runs.
Status = Callable[[str], Any]
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
        return Path(config.cache_dir).expanduser() / "hulls"
    return cache_base() / "hulls"


def _coacd_params(config: DecompositionConfig) -> dict:
    return {
        "threshold": config.threshold,
        "max_convex_hull": config.max_convex_hull,
        "preprocess_mode": config.preprocess_mode,
        "resolution": config.resolution,
        "seed": config.seed,
    }


def _policy_params(config: DecompositionConfig) -> dict:
    """Every parameter that changes the parts (the cache bucket depends on all of them)."""
    params = _coacd_params(config)
    params.update(
        fallback_threshold=config.fallback_threshold,
        fallback_max_convex_hull=config.fallback_max_convex_hull,
        mode=config.mode,
        convex_tolerance=config.convex_tolerance,
        max_parts=config.max_parts,
        max_faces=config.max_faces,
        iou_samples=config.iou_samples,
    )
    return params


def _sig(x: float) -> str:
    return f"{float(x):.4g}"


def cache_key(mesh: trimesh.Trimesh, config: DecompositionConfig) -> str:
    """SHA-256 hex of the cache bucket of ``mesh``: the decomposition parameters, the cache
    version, the vertex and face counts, and the volume and area to 4 significant digits.

    These survive a re-export (vertex/face order, float noise) and a translation; the entries
    of a bucket are told apart by their vertices (:func:`decompose`).
    """
    h = hashlib.sha256()
    h.update(f"ssp-hulls-v{CACHE_VERSION}".encode())
    with np.errstate(all="ignore"):
        geometry = [len(mesh.vertices), len(mesh.faces), _sig(mesh.volume), _sig(mesh.area)]
    h.update(json.dumps(geometry).encode())
    h.update(json.dumps(_policy_params(config), sort_keys=True).encode())
    return h.hexdigest()


def _centre(mesh: trimesh.Trimesh) -> np.ndarray:
    """The frame cached parts are stored in: the volume centroid (vertex mean if degenerate)."""
    with np.errstate(all="ignore"):
        c = np.asarray(mesh.center_mass, dtype=np.float64)
    if not np.all(np.isfinite(c)):
        c = np.asarray(mesh.vertices, dtype=np.float64).mean(axis=0)
    return c


def _same_vertices(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether the vertex sets (V, 3) match within ``tol`` m, in both directions."""
    if a.shape != b.shape:
        return False
    da, _ = cKDTree(a).query(b, distance_upper_bound=2 * tol)
    if not np.all(da <= tol):
        return False
    db, _ = cKDTree(b).query(a, distance_upper_bound=2 * tol)
    return bool(np.all(db <= tol))


# --------------------------------------------------------------------------- IoU


def _halfspaces(part: trimesh.Trimesh) -> np.ndarray | None:
    """(F, 4) facet planes ``n . x + d <= 0`` inside, or None for a degenerate part."""
    try:
        return ConvexHull(np.asarray(part.vertices, dtype=np.float64)).equations
    except (QhullError, ValueError):
        return None


def _chunk_rows(n_columns: int) -> int:
    """Rows of one chunk so that rows x ``n_columns`` <= :data:`IOU_CHUNK_ENTRIES`."""
    return max(1, IOU_CHUNK_ENTRIES // max(1, int(n_columns)))


def inside_convex(points: np.ndarray, planes: np.ndarray, tol: float = 0.0) -> np.ndarray:
    """(N,) bool: ``points`` (N, 3) on the inner side of every plane (F, 4) ``n . x + d``.

    Chunked: no intermediate array has more than :data:`IOU_CHUNK_ENTRIES` entries, whatever
    N and F (a 5-million-face hull against 100k points would need 1.4 TiB at once).
    """
    points = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(points), dtype=bool)
    step = _chunk_rows(len(planes))
    normals, offsets = planes[:, :3].T, planes[:, 3]
    for a in range(0, len(points), step):
        d = points[a : a + step] @ normals
        d += offsets
        out[a : a + step] = np.all(d <= tol, axis=1)
    return out


def inside_union(points: np.ndarray, parts: Sequence[trimesh.Trimesh]) -> np.ndarray:
    """(N,) bool: which ``points`` (N, 3) lie in at least one convex part (half-space tests)."""
    points = np.asarray(points, dtype=np.float64)
    inside = np.zeros(len(points), dtype=bool)
    for part in parts:
        eq = _halfspaces(part)
        if eq is None:
            continue
        lo, hi = part.bounds
        cand = np.flatnonzero(~inside & in_box(points, lo, hi))
        if len(cand) == 0:
            continue
        if len(eq) > RAY_TEST_FACETS:
            hull = trimesh.convex.convex_hull(np.asarray(part.vertices, dtype=np.float64))
            for a in range(0, len(cand), CONTAINS_CHUNK):
                idx = cand[a : a + CONTAINS_CHUNK]
                inside[idx[hull.contains(points[idx])]] = True
            continue
        tol = 1e-12 * max(1.0, float(np.abs(hi - lo).max()))
        inside[cand[inside_convex(points[cand], eq, tol)]] = True
    return inside


def _bodies(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """The connected shells of ``mesh`` (one face-connected piece each)."""
    if len(mesh.faces) == 0:
        return []
    groups = trimesh.graph.connected_components(
        mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1
    )
    if len(groups) <= 1:
        return [mesh]
    # append=True: one mesh per call (trimesh types submesh's result as a mesh or a list)
    return [
        cast(trimesh.Trimesh, mesh.submesh([np.sort(g)], append=True, repair=False)) for g in groups
    ]


def inside_mesh(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """(N,) bool: which ``points`` lie inside the solid ``mesh``, in chunks of
    :data:`CONTAINS_CHUNK` points.

    A mesh of several shells that all enclose positive volume (touching or overlapping convex
    pieces, say) is the union of its shells; otherwise ray parity decides (so cavities, as
    inward-facing inner shells, stay empty).
    """
    points = np.asarray(points, dtype=np.float64)
    bodies = _bodies(mesh)
    with np.errstate(all="ignore"):
        if len(bodies) > 1 and not all(float(b.volume) > 0 for b in bodies):
            bodies = [mesh]
    inside = np.zeros(len(points), dtype=bool)
    for body in bodies:
        lo, hi = body.bounds
        cand = np.flatnonzero(~inside & in_box(points, lo, hi))
        for a in range(0, len(cand), CONTAINS_CHUNK):
            idx = cand[a : a + CONTAINS_CHUNK]
            inside[idx] = body.contains(points[idx])
    return inside


def hull_iou(
    mesh: trimesh.Trimesh,
    parts: Sequence[trimesh.Trimesh],
    n_samples: int = 100_000,
    seed: int = 0,
) -> float:
    """Monte Carlo volume IoU of the union of convex ``parts`` against the solid ``mesh``.

    Points are uniform in the bounding box of mesh and parts, padded by 5 %. Memory is bounded
    (:func:`inside_convex`, :func:`inside_mesh`) whatever the face counts.
    """
    if not parts:
        return 0.0
    bounds = np.vstack([mesh.bounds] + [p.bounds for p in parts])
    lo, hi = bounds.min(axis=0), bounds.max(axis=0)
    pad = 0.05 * (hi - lo)
    rng = np.random.default_rng(seed)
    pts = rng.uniform(lo - pad, hi + pad, size=(int(n_samples), 3))
    in_mesh = inside_mesh(mesh, pts)
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


def convexity(mesh: trimesh.Trimesh) -> float:
    """Volume of ``mesh`` over the volume of its convex hull (1 for a convex solid)."""
    with np.errstate(all="ignore"):
        volume = float(mesh.volume)
    try:
        hull = ConvexHull(np.asarray(mesh.vertices, dtype=np.float64)).volume
    except (QhullError, ValueError):
        return 0.0
    return volume / hull if hull > 0 else 0.0


def convex_shells(mesh: trimesh.Trimesh, tolerance: float) -> list[trimesh.Trimesh] | None:
    """The shells of a mesh made of two or more connected shells that are each convex within
    ``tolerance`` (see :func:`convexity`), or None."""
    bodies = _bodies(mesh)
    if len(bodies) < 2:
        return None
    for b in bodies:
        if convexity(b) < 1.0 - tolerance:
            return None
    return bodies


def _hull(points: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(volume, hull vertices) of ``points``, or None when degenerate."""
    try:
        h = ConvexHull(points)
    except (QhullError, ValueError):
        return None
    return float(h.volume), points[h.vertices]


def merge_parts(
    parts: Sequence[trimesh.Trimesh],
    tolerance: float,
    max_parts: int,
    solid_volumes: Sequence[float] | None = None,
) -> tuple[trimesh.Trimesh, ...]:
    """Merge neighbouring convex parts into their hull while it stays convex within tolerance.

    A merge of a set of parts costs the empty fraction of their joint hull,
    ``1 - sum(s) / V(hull)``, where ``s`` is the solid volume a part stands for (its own
    volume at first, ``solid_volumes`` if given; the sum for a merged part). First, every
    cluster of parts linked by pairwise merges within ``tolerance`` is merged whole if its
    own cost is within it (an over-split box becomes one box again, whatever the order);
    then pairs are merged cheapest first while the cost is at most ``tolerance``, and
    (cheapest first) until at most ``max_parts`` parts are left. Parts whose padded bounding
    boxes (5 % of the whole) do not meet are only merged when the cap demands it.
    Deterministic.
    """
    verts = [np.asarray(p.vertices, dtype=np.float64) for p in parts]
    solid = [float(v) for v in (solid_volumes or [p.volume for p in parts])]
    if len(verts) <= 1:
        return tuple(parts)
    merger = _PartMerger(verts, solid)
    merger.merge_clusters(tolerance)
    merger.merge_pairs(tolerance, max_parts)
    return tuple(
        parts[k] if k < len(parts) else trimesh.convex.convex_hull(verts[k])
        for k in sorted(merger.alive)
    )


class _PartMerger:
    """The state of :func:`merge_parts`: the parts' vertices and solid volumes (a merged part
    appended to them), their bounding boxes, the parts alive, a heap of candidate pairs
    ``(cost, i, j)`` and the cost of every group tried."""

    def __init__(self, verts: list[np.ndarray], solid: list[float]) -> None:
        self.verts = verts
        self.solid = solid
        self.lo = [v.min(axis=0) for v in verts]
        self.hi = [v.max(axis=0) for v in verts]
        self.pad = 0.05 * float(np.linalg.norm(np.max(self.hi, axis=0) - np.min(self.lo, axis=0)))
        self.costs: dict[tuple[int, ...], tuple[float, np.ndarray]] = {}
        self.alive = set(range(len(verts)))
        self.heap: list[tuple[float, int, int]] = []
        for i in sorted(self.alive):
            self.push_pairs(i, [j for j in self.alive if j > i])

    def near(self, i: int, j: int) -> bool:
        """Do the padded bounding boxes of parts ``i`` and ``j`` meet?"""
        lo, hi, pad = self.lo, self.hi, self.pad
        return bool(np.all(lo[i] - pad <= hi[j]) and np.all(lo[j] - pad <= hi[i]))

    def cost(self, group: tuple[int, ...]) -> tuple[float, np.ndarray]:
        """``(empty fraction of the joint hull, its vertices)`` of the parts ``group``."""
        costs = self.costs
        if group not in costs:
            both = np.vstack([self.verts[k] for k in group])
            h = _hull(both)
            total = sum(self.solid[k] for k in group)
            costs[group] = (np.inf, both) if h is None else (1.0 - total / h[0], h[1])
        return costs[group]

    def push_pairs(self, k: int, others) -> None:
        """Push the pairs of part ``k`` with the parts ``others`` near it."""
        for j in sorted(others):
            if j != k and self.near(k, j):
                pair = (min(j, k), max(j, k))
                heapq.heappush(self.heap, (self.cost(pair)[0], *pair))

    def merge(self, group: tuple[int, ...]) -> None:
        """Replace the parts ``group`` by their hull."""
        hull_vertices = self.cost(group)[1]
        self.verts.append(hull_vertices)
        self.solid.append(sum(self.solid[k] for k in group))
        self.lo.append(hull_vertices.min(axis=0))
        self.hi.append(hull_vertices.max(axis=0))
        k = len(self.verts) - 1
        self.alive -= set(group)
        self.push_pairs(k, self.alive)
        self.alive.add(k)

    def merge_clusters(self, tolerance: float) -> None:
        """1. clusters of cheap pairs, merged whole when the cluster itself is nearly convex."""
        import networkx as nx

        graph = nx.Graph()
        graph.add_nodes_from(self.alive)
        graph.add_edges_from((i, j) for c, i, j in self.heap if c <= tolerance)
        for component in sorted(nx.connected_components(graph), key=min):
            group = tuple(sorted(component))
            if len(group) > 1 and self.cost(group)[0] <= tolerance:
                self.merge(group)

    def merge_pairs(self, tolerance: float, max_parts: int) -> None:
        """2. pairs, cheapest first; beyond the cap whatever the cost."""
        alive, heap = self.alive, self.heap
        while len(alive) > 1:
            while heap and not (heap[0][1] in alive and heap[0][2] in alive):
                heapq.heappop(heap)
            over = len(alive) > max_parts
            if not heap:
                if not over:
                    break
                for i in sorted(alive):  # far apart parts: only the cap merges them
                    for j in sorted(alive):
                        if j > i:
                            heapq.heappush(heap, (self.cost((i, j))[0], i, j))
                continue
            c, i, j = heap[0]
            if not (c <= tolerance or over):
                break
            heapq.heappop(heap)
            self.merge((i, j))


#: A decimated mesh is used only if its volume is within this fraction of the original's.
DECIMATION_VOLUME_TOLERANCE = 0.01


def simplified(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh | None:
    """``mesh`` decimated to at most about ``max_faces`` faces (fast-simplification's quadric
    decimation, through trimesh), ``mesh`` itself when it is small enough, or None when the
    decimation fails its check (not watertight, or the volume off by more than
    :data:`DECIMATION_VOLUME_TOLERANCE`: quadric decimation can fold very regular meshes)."""
    if len(mesh.faces) <= max_faces:
        return mesh
    out = mesh.simplify_quadric_decimation(face_count=int(max_faces))
    with np.errstate(all="ignore"):
        change = abs(float(out.volume) / float(mesh.volume) - 1.0)
    return out if out.is_watertight and change <= DECIMATION_VOLUME_TOLERANCE else None


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


def centred_vertices(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre (3,), vertices re-centred at it (V, 3), match tolerance m) of a cache entry."""
    centre = _centre(mesh)
    centred = np.asarray(mesh.vertices, dtype=np.float64) - centre
    tol = CACHE_TOLERANCE * max(float(np.abs(np.ptp(centred, axis=0)).max()), 1e-9)
    return centre, centred, tol


def find_entry(
    bucket: Path, centred: np.ndarray, tol: float
) -> tuple[Path, dict, dict[str, np.ndarray]] | None:
    """The entry ``(path, meta, arrays)`` of ``bucket`` (a path without suffix) whose stored
    ``mesh_vertices`` match ``centred`` within ``tol``, or None."""
    for path in sorted(bucket.parent.glob(f"{bucket.name}.*.npz")):
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: np.asarray(data[k]) for k in data.files}
            meta = json.loads(str(arrays.pop("meta")))
        except Exception as exc:  # corrupt or foreign file: recompute
            log.warning("ignoring unreadable cache file %s: %s", path, exc)
            continue
        vertices = np.asarray(arrays.get("mesh_vertices", np.zeros((0, 3))), dtype=np.float64)
        if _same_vertices(vertices, centred, tol):
            return path, meta, arrays
    return None


def write_entry(bucket: Path, centred: np.ndarray, meta: dict, **arrays: np.ndarray) -> None:
    """Add an entry (the centred mesh vertices, ``meta`` as JSON, ``arrays``) to ``bucket``,
    atomically (temp file + ``os.replace``); a failure to write is logged, not raised."""
    try:
        bucket.parent.mkdir(parents=True, exist_ok=True)
        k = 0
        while (bucket.parent / f"{bucket.name}.{k}.npz").exists():
            k += 1
        path = bucket.parent / f"{bucket.name}.{k}.npz"
        fd, tmp = tempfile.mkstemp(dir=bucket.parent, prefix=bucket.name[:16], suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(
                    fh,
                    meta=np.array(json.dumps(meta)),
                    mesh_vertices=np.asarray(centred, dtype=np.float64),
                    # numpy's stub lets ** reach savez's allow_pickle: bool; arrays are arrays
                    **arrays,  # type: ignore[arg-type]
                )
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        log.warning("cannot write cache %s: %s", bucket, exc)


def _load_cache(
    bucket: Path, centred: np.ndarray, tol: float, config: DecompositionConfig
) -> tuple[tuple[trimesh.Trimesh, ...], DecompositionInfo] | None:
    """The cached parts of the centred mesh vertices (centred frame), or None."""
    entry = find_entry(bucket, centred, tol)
    if entry is None:
        return None
    path, meta, arrays = entry
    try:
        info = meta["info"]
        info = DecompositionInfo(**{**info, "warnings": tuple(info.get("warnings", ()))})
        parts = tuple(trimesh.Trimesh(v, f, process=False) for v, f in _unpack(arrays))
    except Exception as exc:
        log.warning("ignoring unreadable hull cache file %s: %s", path, exc)
        return None
    if len(parts) != info.n_parts or not parts:
        log.warning("ignoring inconsistent hull cache file %s", path)
        return None
    if info.method in ("coacd-coarse", "convex-hull") and (
        config.timeout_s > meta.get("timeout_s", 0)
        or config.memory_limit_gb > meta.get("memory_limit_gb", 0)
    ):
        log.info("cached %s result was made under smaller limits; recomputing", info.method)
        return None
    log.debug("hull cache hit %s", path.name)
    return parts, replace(info, cached=True, seconds=0.0)


def _save_cache(
    bucket: Path,
    centred: np.ndarray,
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
    write_entry(bucket, centred, meta, **_pack(parts))


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


def _communicate(
    argv: list[str],
    config: DecompositionConfig,
    limit: int,
    cwd: str,
    env: dict,
    status: Status | None,
    label: str,
) -> tuple[int, str]:
    """Run the worker; (return code, output). ``status`` gets the elapsed time every second.

    Raises _RunFailed on the timeout (the worker is killed)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        preexec_fn=lambda: _limit_memory(limit),
        cwd=cwd,
        env=env,
    )
    chunks: list[bytes] = []
    while True:
        left = config.timeout_s - (time.monotonic() - t0)
        try:
            out, _ = proc.communicate(timeout=max(0.01, min(1.0, left)))
            chunks.append(out or b"")
            break
        except subprocess.TimeoutExpired:
            if time.monotonic() - t0 >= config.timeout_s:
                proc.kill()
                out, _ = proc.communicate()
                text = (b"".join(chunks) + (out or b"")).decode(errors="replace")
                raise _RunFailed(
                    f"timed out after {config.timeout_s:g} s"
                    + (f"; log: {_tail(text)}" if text.strip() else "")
                ) from None
            if status is not None:
                status(f"{label}: {time.monotonic() - t0:.0f} s (cap {config.timeout_s:g} s)")
    return proc.returncode, b"".join(chunks).decode(errors="replace")


def _run_coacd(
    mesh: trimesh.Trimesh,
    params: dict,
    config: DecompositionConfig,
    status: Status | None = None,
    label: str = "CoACD",
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
        code, out = _communicate(
            _worker_argv(in_path, out_path), config, limit, tmp, env, status, label
        )
        if code != 0:
            how = f"killed by signal {-code}" if code < 0 else f"exit status {code}"
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
            if memory_hint or code in (-6, -9):
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


def _coacd_parts(
    mesh: trimesh.Trimesh, config: DecompositionConfig, status: Status | None
) -> tuple[tuple[trimesh.Trimesh, ...], str, list[str]]:
    """CoACD, then the coarse retry: (parts, method, notes); no parts if both failed."""
    volume = float(mesh.volume)
    notes: list[str] = []
    source = simplified(mesh, config.max_faces)
    primary = _coacd_params(config)
    if source is None:  # decimation failed its check: CoACD's own manifold remeshing instead
        source = mesh
        primary["preprocess_mode"] = "on"
        notes.append(
            f"the mesh has {len(mesh.faces)} faces (> max_faces {config.max_faces}) and does "
            "not decimate cleanly; CoACD ran with its manifold preprocessing on"
        )
        log.info("convex decomposition: %s", notes[-1])
    elif source is not mesh:
        notes.append(
            f"CoACD ran on the mesh decimated from {len(mesh.faces)} to {len(source.faces)} faces"
        )
        log.info("convex decomposition: %s", notes[-1])
    coarse = {
        **primary,
        "threshold": config.fallback_threshold,
        "max_convex_hull": config.fallback_max_convex_hull,
    }
    for name, params in (("coacd", primary), ("coacd-coarse", coarse)):
        label = f"CoACD (threshold {params['threshold']:g})"
        if status is not None:
            status(label)
        try:
            parts = clean_parts(_run_coacd(source, params, config, status, label), volume)
            if not parts:
                raise _RunFailed("CoACD returned no usable part")
            return parts, name, notes
        except _RunFailed as exc:
            notes.append(f"{name} (threshold {params['threshold']:g}) failed: {exc}")
            log.warning("convex decomposition: %s", notes[-1])
    return (), "convex-hull", notes


def decompose(
    mesh: trimesh.Trimesh,
    config: DecompositionConfig,
    cache_dir: Path | str,
    status: Status | None = None,
) -> tuple[tuple[trimesh.Trimesh, ...], DecompositionInfo]:
    """Convex parts of the watertight ``mesh`` (metres) and how they were obtained.

    See the module docstring for the policy, the fallbacks and the cache. ``info.iou`` uses
    ``config.iou_samples`` Monte Carlo points seeded with ``config.seed``. ``status(text)``
    is called with what is being done (about once a second while CoACD runs).

    Raises:
        DecompositionError: not even the convex hull of the mesh could be built.
    """
    centre, centred, tol = centred_vertices(mesh)
    bucket = Path(cache_dir) / cache_key(mesh, config)
    hit = _load_cache(bucket, centred, tol, config)
    if hit is not None:
        cached, info = hit
        return tuple(_moved(p, centre) for p in cached), info

    t0 = time.perf_counter()
    volume = float(mesh.volume)
    notes: list[str] = []
    parts: tuple[trimesh.Trimesh, ...] = ()
    shells = None
    ratio = convexity(mesh)
    if config.mode == "convex-hull":
        method = "convex-hull"
        notes.append("decomposition mode is convex-hull")
    elif config.mode == "auto" and ratio >= 1.0 - config.convex_tolerance:
        method = "convex"
        notes.append(f"the mesh fills {100 * ratio:.1f} % of its convex hull")
    elif config.mode == "auto" and (shells := convex_shells(mesh, config.convex_tolerance)):
        method = "shells"
        parts = clean_parts(shells, volume)
        notes.append(f"the mesh is {len(shells)} convex shells")
    else:
        parts, method, notes = _coacd_parts(mesh, config, status)
        if method == "convex-hull":
            log.warning(
                "convex decomposition fell back to the single convex hull of the mesh; the "
                "physics will fill its concavities"
            )
            notes = ["single convex hull used because " + "; ".join(notes)]
    if not parts:
        parts = clean_parts([mesh], volume)
        if not parts:
            raise DecompositionError("cannot build even the convex hull of the mesh")
    if len(parts) > 1:
        if status is not None:
            status(f"merging {len(parts)} parts")
        n_before = len(parts)
        solid = [float(p.volume) for p in parts]
        parts = merge_parts(parts, config.convex_tolerance, config.max_parts, solid)
        if len(parts) < n_before:
            notes.append(f"merged {n_before} parts into {len(parts)}")
    if status is not None:
        status("measuring the volume IoU")
    iou = hull_iou(mesh, parts, config.iou_samples, config.seed)
    seconds = time.perf_counter() - t0
    info = DecompositionInfo(method, len(parts), iou, seconds, False, "; ".join(notes))
    log.info(
        "convex decomposition: %s, %d parts, IoU %.3f, %.1f s", method, len(parts), iou, seconds
    )
    _save_cache(bucket, centred, [_moved(p, -centre) for p in parts], info, config)
    return parts, info


def _moved(part: trimesh.Trimesh, offset: np.ndarray) -> trimesh.Trimesh:
    """``part`` translated by ``offset`` (3,), m (a new mesh)."""
    return trimesh.Trimesh(
        np.asarray(part.vertices, dtype=np.float64) + offset, part.faces, process=False
    )
