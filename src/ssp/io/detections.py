"""Instance masks from a 2D detector: the BOP segmentation results file.

The file is what CNOS, SAM-6D and the BOP challenge's default detections write (BOP 2D
segmentation results, COCO style): a JSON list (``.json``, or ``.json.gz``) with one entry
per detection::

    {"scene_id": 1, "image_id": 3, "category_id": 5, "score": 0.93,
     "bbox": [x, y, w, h],                          # pixels (optional, may be [])
     "segmentation": {"counts": "...", "size": [h, w]},  # RLE, column-major
     "time": 0.21}                                  # seconds (optional)

``category_id`` is the BOP ``obj_id``; ``counts`` is a compressed RLE string (pycocotools'
``encode``) or a list of run lengths (uncompressed; starting with a background run).

* :func:`read_detections` reads and checks the file's structure: a file that is not such a
  list, an entry that is not an object, lacks a key or has a value of the wrong type is an
  :class:`~ssp.errors.InputError` naming the file and the entry (0-based position): such a
  file was written by a wrong writer, nothing in it can be trusted.
* :meth:`Detections.for_scene` keeps the usable detections of one scene; a single detection
  that cannot be used (an ``obj_id`` the dataset has no model of, a mask of another size than
  its image, an empty mask, an image the scene does not have) is skipped with a warning that
  names the entry, counted per reason. A scene the file has no detection of, or none usable,
  is an InputError. ``min_score`` drops low-score detections (default 0: every detection the
  detector wrote; the dropped ones are counted too).
* :func:`instance_labels`: one image's detections as an instance label image; overlapping
  pixels go to the higher score (ties: the earlier entry).
* :func:`match_segments`: the label of each pose hypothesis (an estimator's rows do not say
  which detection they came from): the detection of its class its visible silhouette
  overlaps most (:func:`match_segments` gives the rule).

Masks are decoded with pycocotools; the compressed strings are checked first by
:func:`rle_counts` (pycocotools reads a string whose runs do not add up to ``h * w`` without
complaint and returns uninitialised pixels).
"""

from __future__ import annotations

import gzip
import json
import logging
import math
import warnings
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ssp.camera import Camera
from ssp.errors import InputError
from ssp.io._files import file_problem
from ssp.scene import Hypothesis

__all__ = [
    "MIN_OVERLAP",
    "VISIBLE_TOLERANCE",
    "Detection",
    "Detections",
    "InstanceLabels",
    "SceneDetections",
    "instance_labels",
    "match_segments",
    "read_detections",
    "rle_counts",
]

log = logging.getLogger(__name__)

#: The keys every entry must have (``bbox`` and ``time`` are optional).
REQUIRED_KEYS = ("scene_id", "image_id", "category_id", "score", "segmentation")
#: A hypothesis takes a detection's label when at least this fraction of its visible model
#: samples falls on the detection's pixels (:func:`match_segments`).
MIN_OVERLAP = 0.25
#: A model sample counts as visible when it is at most this far (m) behind the measured depth.
VISIBLE_TOLERANCE = 0.02
#: The most model samples projected per hypothesis (evenly strided).
MAX_SAMPLES = 256
#: The largest mask side read, pixels (a 16k image: a size beyond it is a broken entry).
MAX_SIDE = 16384


@dataclass(frozen=True)
class Detection:
    """One entry of a detections file.

    Attributes:
        entry: its 0-based position in the file (named in warnings and errors).
        scene_id, im_id, obj_id: BOP ids; ``score`` the detector's confidence.
        bbox: ``(x, y, w, h)`` pixels as the file gives it, or None (absent or empty).
        size: ``(H, W)`` of the mask, pixels.
        counts: the RLE: a compressed string or a tuple of run lengths (column-major,
            starting with a background run).
    """

    entry: int
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    bbox: tuple[float, float, float, float] | None
    size: tuple[int, int]
    counts: str | tuple[int, ...]

    def runs(self) -> list[int]:
        """The run lengths (:func:`rle_counts` of a compressed string). ValueError: a string
        that is not a compressed RLE."""
        return list(self.counts) if isinstance(self.counts, tuple) else rle_counts(self.counts)

    def mask(self) -> np.ndarray:
        """The mask, ``(H, W)`` bool, decoded by pycocotools (the runs checked before by
        :meth:`Detections.for_scene`)."""
        from pycocotools import mask as mask_util

        h, w = self.size
        if isinstance(self.counts, tuple):
            rle = mask_util.frPyObjects({"size": [h, w], "counts": list(self.counts)}, h, w)
        else:
            rle = {"size": [h, w], "counts": self.counts.encode("ascii")}
        with warnings.catch_warnings():  # pycocotools' __array__ predates numpy 2's copy=
            warnings.simplefilter("ignore", DeprecationWarning)
            decoded = mask_util.decode(rle)
        return np.asarray(decoded, dtype=bool).reshape(h, w)


def rle_counts(s: str) -> list[int]:
    """The run lengths of a compressed COCO RLE string (the format of pycocotools'
    ``rleToString``: 5-bit groups in characters ``0``..``o``, each count after the second a
    difference to the count two before it). ValueError: not such a string."""
    counts: list[int] = []
    x = k = 0
    for ch in s:
        c = ord(ch) - 48
        if not 0 <= c < 64:
            raise ValueError(f"character {ch!r} is not of a compressed RLE")
        x |= (c & 0x1F) << (5 * k)
        k += 1
        if c & 0x20:
            continue
        if c & 0x10:
            x |= -1 << (5 * k)
        if len(counts) > 2:
            x += counts[-2]
        counts.append(x)
        x = k = 0
    if k:
        raise ValueError("the string ends inside a count")
    return counts


@dataclass
class Detections:
    """A detections file read by :func:`read_detections`: ``entries`` in file order."""

    source: Path
    entries: list[Detection]

    def scenes(self) -> list[int]:
        """The scene ids the file has detections of."""
        return sorted({d.scene_id for d in self.entries})

    def for_scene(
        self,
        scene_id: int,
        image_sizes: Mapping[int, tuple[int, int]],
        classes: Mapping[int, str],
        *,
        min_score: float = 0.0,
    ) -> SceneDetections:
        """The usable detections of scene ``scene_id`` (module docstring).

        Args:
            image_sizes: ``im_id -> (H, W)`` of the scene's images.
            classes: ``obj_id -> class`` of the objects ssp has a model of.
            min_score: detections scoring below it are dropped (counted).

        Raises:
            InputError: the file has no detection of the scene, or none usable (the message
                names the first entry and why).
        """
        mine = [d for d in self.entries if d.scene_id == scene_id]
        if not mine:
            raise InputError(
                f"{self.source}: no detection of scene {scene_id} (the file has scenes "
                f"{self.scenes()[:20]})"
            )
        out = SceneDetections(self.source, scene_id, min_score)
        for d in mine:
            problem = _problem(d, image_sizes, classes)
            if problem is not None:
                out.skip(d, *problem)
            elif d.score < min_score:
                out.counts["score below the minimum"] += 1
            else:
                out.images.setdefault(d.im_id, []).append(d)
        n_bad = out.skipped_entries
        if n_bad == len(mine):
            first = min(p for ps in out.problems.values() for p in ps)[1]
            more = f" (and {n_bad - 1} more)" if n_bad > 1 else ""
            raise InputError(
                f"{self.source}: none of the {n_bad} detections of scene {scene_id} can be "
                f"used: {first}{more}"
            )
        for dets in out.images.values():
            dets.sort(key=lambda d: (-d.score, d.entry))
        out.log_summary(len(mine), list(image_sizes))
        return out


def _problem(
    d: Detection, image_sizes: Mapping[int, tuple[int, int]], classes: Mapping[int, str]
) -> tuple[str, str] | None:
    """Why detection ``d`` cannot be used in its scene, ``(kind, message)`` (None: it can)."""
    where = f"entry {d.entry} (im_id {d.im_id}, obj_id {d.obj_id})"
    if d.im_id not in image_sizes:
        return "image not in the scene", f"{where}: the scene has no image {d.im_id}"
    if d.obj_id not in classes:
        return (
            "unknown obj_id",
            f"{where}: no model of obj_id {d.obj_id} (known: {sorted(classes)[:30]})",
        )
    h, w = image_sizes[d.im_id]
    if d.size != (h, w):
        return (
            "mask size",
            f"{where}: mask of {d.size[1]} x {d.size[0]} pixels, the image is {w} x {h}",
        )
    try:
        runs = d.runs()
    except ValueError as exc:
        return "bad counts", f"{where}: segmentation counts: {exc}"
    if any(r < 0 for r in runs) or sum(runs) != h * w:
        return (
            "bad counts",
            f"{where}: segmentation counts: runs of {sum(runs)} pixels, the mask has {h * w}",
        )
    if not sum(runs[1::2]):
        return "empty mask", f"{where}: empty mask"
    return None


@dataclass
class SceneDetections:
    """The usable detections of one scene (:meth:`Detections.for_scene`).

    Attributes:
        images: ``im_id -> detections``, best score first (ties: file order).
        problems: ``im_id -> [(entry, why)]`` of the skipped entries.
        counts: entries not used, per reason (``score below the minimum`` included).
    """

    source: Path
    scene_id: int
    min_score: float
    images: dict[int, list[Detection]] = field(default_factory=dict)
    problems: dict[int, list[tuple[int, str]]] = field(default_factory=dict)
    counts: Counter = field(default_factory=Counter)

    @property
    def skipped_entries(self) -> int:
        """Entries skipped for a problem (not those below ``min_score``)."""
        return sum(len(v) for v in self.problems.values())

    def skip(self, d: Detection, kind: str, problem: str) -> None:
        """Record detection ``d`` as skipped for ``problem`` (counted under ``kind``)."""
        self.problems.setdefault(d.im_id, []).append((d.entry, problem))
        self.counts[kind] += 1

    def frame(self, im_id: int) -> tuple[list[Detection], list[str]]:
        """The detections of image ``im_id`` and the warnings about it: its skipped entries
        (each named) and, when it has no detection, that it has no masks."""
        dets = self.images.get(im_id, [])
        notes = [f"{self.source}: detection skipped: {p}" for _, p in self.problems.get(im_id, [])]
        if not dets:
            low = f" scoring at least {self.min_score:g}" if self.min_score > 0 else ""
            notes.append(
                f"{self.source}: no detection{low} of scene {self.scene_id}, im_id {im_id}: "
                "this frame has no masks (the cloud above the table is clustered: clutter "
                "may become objects)"
            )
        return dets, notes

    def log_summary(self, n: int, im_ids: Sequence[int]) -> None:
        """Log how many of the scene's ``n`` entries are used and why the others are not;
        the entries of images not in ``im_ids`` (no frame reports them) one by one."""
        used = sum(len(v) for v in self.images.values())
        why = ", ".join(f"{c} {r}" for r, c in sorted(self.counts.items()))
        log.info("%s: scene %d: %d of %d detections used%s", self.source, self.scene_id, used, n,
                 f" (not used: {why})" if why else "")  # fmt: skip
        known = set(im_ids)
        for im, problems in sorted(self.problems.items()):
            if im not in known:
                for _, p in problems:
                    log.warning("%s: detection skipped: %s", self.source, p)


def read_detections(path: str | Path) -> Detections:
    """Read a BOP segmentation results file (module docstring; ``.json`` or ``.json.gz``).

    Raises:
        InputError: a missing or unreadable file, invalid JSON, not a list, an entry that
            is not an object, lacks a key of :data:`REQUIRED_KEYS` or has a value of the
            wrong type (the message names the file and the entry).
    """
    p = Path(path)
    problem = file_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {problem}")
    try:
        raw = gzip.decompress(p.read_bytes()) if p.name.endswith(".gz") else p.read_bytes()
        doc = json.loads(raw.decode("utf-8"))
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: invalid JSON: {exc}") from exc
    if not isinstance(doc, list):
        raise InputError(
            f"{p}: expected a list of detections (BOP segmentation results), got "
            f"{type(doc).__name__}"
        )
    if not doc:
        raise InputError(f"{p}: no detection (an empty list)")
    return Detections(p, [_entry(p, i, e) for i, e in enumerate(doc)])


def _entry(p: Path, i: int, e: Any) -> Detection:
    """Entry ``i`` of file ``p``, its structure checked (InputError naming both)."""
    where = f"{p}: entry {i}"
    if not isinstance(e, dict):
        raise InputError(f"{where}: expected an object, got {type(e).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in e]
    if missing:
        raise InputError(f"{where}: no {', '.join(map(repr, missing))} (keys: {sorted(e)[:10]})")
    ids = {}
    for k in ("scene_id", "image_id", "category_id"):
        v = e[k]
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise InputError(f"{where}: {k!r} must be a non-negative integer, got {v!r:.40}")
        ids[k] = v
    score = e["score"]
    if isinstance(score, bool) or not isinstance(score, int | float) or not math.isfinite(score):
        raise InputError(f"{where}: 'score' must be a finite number, got {score!r:.40}")
    seg = e["segmentation"]
    if not isinstance(seg, dict) or "counts" not in seg or "size" not in seg:
        raise InputError(
            f"{where}: 'segmentation' must be an RLE {{counts, size}}, got {seg!r:.60}"
        )
    return Detection(
        entry=i,
        scene_id=ids["scene_id"],
        im_id=ids["image_id"],
        obj_id=ids["category_id"],
        score=float(score),
        bbox=_bbox(where, e.get("bbox")),
        size=_size(where, seg["size"]),
        counts=_counts(where, seg["counts"]),
    )


def _bbox(where: str, b: Any) -> tuple[float, float, float, float] | None:
    if b is None or (isinstance(b, list) and not b):
        return None
    if (
        not isinstance(b, list)
        or len(b) != 4
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in b)
        or not all(math.isfinite(v) for v in b)
    ):
        raise InputError(f"{where}: 'bbox' must be [x, y, w, h] (pixels), got {b!r:.60}")
    return (float(b[0]), float(b[1]), float(b[2]), float(b[3]))


def _size(where: str, s: Any) -> tuple[int, int]:
    if (
        not isinstance(s, list)
        or len(s) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= MAX_SIDE for v in s)
    ):
        raise InputError(
            f"{where}: segmentation 'size' must be [height, width] (positive pixels), got {s!r:.60}"
        )
    return (s[0], s[1])


def _counts(where: str, c: Any) -> str | tuple[int, ...]:
    if isinstance(c, str):
        return c
    if isinstance(c, list) and all(isinstance(v, int) and not isinstance(v, bool) for v in c):
        return tuple(c)
    raise InputError(
        f"{where}: segmentation 'counts' must be a compressed RLE string or a list of run "
        f"lengths, got {type(c).__name__}"
    )


@dataclass
class InstanceLabels:
    """One image's detections as instance labels (:func:`instance_labels`).

    Attributes:
        labels: ``(H, W)`` int32: label ``i`` = ``detections[i]``, -1 no detection.
        detections: best score first; ``pixels[i]`` the pixels label ``i`` kept.
    """

    labels: np.ndarray
    detections: list[Detection]
    pixels: list[int]

    def of(self, label: int) -> tuple[int, float]:
        """``(obj_id, score)`` of instance ``label``."""
        d = self.detections[label]
        return d.obj_id, d.score


def instance_labels(detections: Sequence[Detection], shape: tuple[int, int]) -> InstanceLabels:
    """The instance label image ``shape`` ``(H, W)`` of ``detections``: best score first
    (ties: the earlier entry), each pixel to the best detection covering it. A detection
    whose pixels all go to better ones keeps its label, with no pixel."""
    order = sorted(detections, key=lambda d: (-d.score, d.entry))
    labels = np.full(shape, -1, dtype=np.int32)
    pixels = []
    for i, d in enumerate(order):
        free = d.mask() & (labels < 0)
        labels[free] = i
        pixels.append(int(free.sum()))
    return InstanceLabels(labels, order, pixels)


def match_segments(
    hypotheses: Sequence[Hypothesis],
    labels: InstanceLabels,
    class_of: Mapping[int, str],
    library: Mapping,
    camera: Camera,
    depth: np.ndarray,
    T_cam_frame: np.ndarray | None = None,
) -> tuple[list[Hypothesis], int]:
    """Each hypothesis with the label of its detection as ``segment``, and how many have one.

    The rule: the model's surface samples (at most :data:`MAX_SAMPLES`) at the hypothesis'
    pose are projected into the image; those at most :data:`VISIBLE_TOLERANCE` behind the
    measured ``depth`` ``(H, W)`` (m; or where there is none) are its visible silhouette,
    all of them when none is. Of the detections of its class (``class_of``: ``obj_id ->
    class``), it takes the one whose pixels hold the largest fraction of those samples, if
    that is at least :data:`MIN_OVERLAP` (ties: the better score, then the earlier label);
    else ``segment`` None (the parser then votes its label). Samples behind another object
    are not counted, so an object mostly hidden behind one of its class takes its own mask.

    ``T_cam_frame`` ``(4, 4)`` moves the hypotheses' poses into the camera (None: they are
    camera-frame already).
    """
    by_class: dict[str, list[int]] = {}
    for i, d in enumerate(labels.detections):
        by_class.setdefault(class_of[d.obj_id], []).append(i)
    out, n = [], 0
    for h in hypotheses:
        cands = by_class.get(h.class_name, [])
        seg = None
        if cands and h.class_name in library:
            T = np.asarray(h.T_world_obj, dtype=float)
            T_co = T if T_cam_frame is None else np.asarray(T_cam_frame, dtype=float) @ T
            hits = _sample_labels(library[h.class_name].surface_points, T_co, camera, depth,
                                  labels.labels)  # fmt: skip
            seg = _best(hits, cands, labels)
        n += seg is not None
        out.append(replace(h, segment=seg))
    return out, n


def _sample_labels(
    samples: np.ndarray, T_cam_obj: np.ndarray, camera: Camera, depth: np.ndarray, lab: np.ndarray
) -> np.ndarray:
    """The labels under the visible projected samples (:func:`match_segments`)."""
    pts = np.asarray(samples, dtype=float)
    pts = pts[:: max(1, -(-len(pts) // MAX_SAMPLES))]
    cam = pts @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    uv = camera.project(cam)
    ok = np.all(np.isfinite(uv), axis=1)
    col = np.floor(uv[ok, 0] + 0.5).astype(np.int64)
    row = np.floor(uv[ok, 1] + 0.5).astype(np.int64)
    inside = (col >= 0) & (col < lab.shape[1]) & (row >= 0) & (row < lab.shape[0])
    row, col, z = row[inside], col[inside], cam[ok, 2][inside]
    d = depth[row, col]
    seen = (d <= 0) | (z <= d + VISIBLE_TOLERANCE)
    if seen.any():
        row, col = row[seen], col[seen]
    return lab[row, col]


def _best(hits: np.ndarray, cands: Sequence[int], labels: InstanceLabels) -> int | None:
    """The candidate label holding the largest fraction of ``hits`` (at least
    :data:`MIN_OVERLAP`; ties: better score, then lower label), or None."""
    if not len(hits):
        return None
    counts = np.bincount(hits[hits >= 0], minlength=len(labels.detections))
    best = max(cands, key=lambda i: (counts[i], labels.detections[i].score, -i))
    return best if counts[best] >= MIN_OVERLAP * len(hits) and counts[best] > 0 else None
