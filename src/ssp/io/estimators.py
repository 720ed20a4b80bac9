"""Readers of the files pose estimators write, as per-image hypotheses in the **camera frame**.

Four formats (docs/formats.md, "Estimator outputs"), each with its own reader, and
:func:`read_estimates` that tells them apart:

* ``bop19`` (:func:`read_bop19_csv`): a BOP19 results CSV, ``scene_id,im_id,obj_id,score,R,t,
  time``, ``R`` row-major, ``t`` in **mm**; classes from an ``obj_id -> class`` mapping.
* ``megapose`` (:func:`read_megapose`): MegaPose / HappyPose ``ObjectData.to_json`` lists, one
  JSON file per image; ``TWO`` = ``[[qx, qy, qz, qw], [tx, ty, tz]]`` (quaternion **xyzw**,
  pinocchio's ``Quaternion.coeffs()``), metres, object-to-camera.
* ``foundationpose`` (:func:`read_foundationpose`): FoundationPose's ``ob_in_cam/<frame>.txt``,
  one 4x4 object-to-camera pose (m) per frame and object (``numpy.savetxt``).
* ``cosypose`` (:func:`read_cosypose_csv`): a CSV of CosyPose's prediction table, columns
  ``scene_id,view_id,label,score,TCO``, ``TCO`` the 16 entries of the 4x4 object-to-camera
  pose, row-major, metres, space-separated.

Every reader returns an :class:`EstimatorHypotheses`: images keyed by ``(scene_id, im_id)``
(formats without a scene id use the ``scene_id`` the caller gives, default 0), each with its
:class:`ssp.scene.Hypothesis` list, whose ``T_world_obj`` holds ``T_cam_obj`` (m) as in a
``frame: camera`` hypotheses file (:func:`ssp.io.hypotheses.to_world` moves them to the world).

**Containment.** A file or folder that cannot be read at all (missing, not the format, a bad
header) raises :class:`InputError` at once. A bad row or entry that belongs to an image (NaN,
a rotation that is not one, a wrong column count with readable ids, an unknown label or
obj_id, an unreadable per-image file in a folder) is recorded for that image only:
:meth:`EstimatorHypotheses.for_image` raises InputError for it (naming the file, line or entry,
and what is wrong) and the other images read normally. A row that names no image (its ids
cannot be read) fails the whole file.
"""

from __future__ import annotations

import csv
import difflib
import io
import logging
import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.errors import ArgumentError, InputError
from ssp.io._files import file_problem, read_json
from ssp.io.folder import natural_key
from ssp.io.hypotheses import check_rotation
from ssp.io.results import BOP_CSV_HEADER, ObjectIds, scan_bop_csv
from ssp.scene import Hypothesis

__all__ = [
    "COSYPOSE_COLUMNS",
    "FORMATS",
    "MEGAPOSE_OUTPUTS",
    "EstimatorHypotheses",
    "detect_format",
    "read_bop19_csv",
    "read_cosypose_csv",
    "read_estimates",
    "read_foundationpose",
    "read_megapose",
]

log = logging.getLogger(__name__)

#: Format names of :func:`read_estimates`.
FORMATS = ("bop19", "megapose", "foundationpose", "cosypose")
#: Required columns of a CosyPose-style CSV (``score`` may be left out: 1.0).
COSYPOSE_COLUMNS = ("scene_id", "view_id", "label", "score", "TCO")
_COSYPOSE_REQUIRED = ("scene_id", "view_id", "label", "TCO")
#: Where the upstream examples write their estimates, inside one example folder per image:
#: MegaPose ``run_inference_on_example.py`` and HappyPose ``example_inference_utils.py``.
MEGAPOSE_OUTPUTS = ("outputs/object_data.json", "outputs/object_data_inf.json")
#: A BOP19 CSV whose translations are all shorter than this (mm) was written in metres.
METRES_LIKE_MM = 5.0
#: Problems of one image shown in full in its error (the rest are counted).
_SHOWN_PROBLEMS = 3

ImageKey = tuple[int, int]


# ------------------------------------------------------------------------------ container
@dataclass
class EstimatorHypotheses:
    """Camera-frame hypotheses of a pose estimator, per image ``(scene_id, im_id)``.

    Attributes:
        format: one of :data:`FORMATS`.
        source: the file or folder read.
        names: per image, its name in the source (the file stem for per-image files, else
            ``str(im_id)``), to match it with an input frame.
        warnings: what the reader passed over or suspects, also logged: files that name no
            image, duplicated rows merged, translations that look like metres in a BOP19 CSV.
    """

    format: str
    source: Path
    names: dict[ImageKey, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    _hyps: dict[ImageKey, list[Hypothesis]] = field(default_factory=dict, repr=False)
    _problems: dict[ImageKey, list[str]] = field(default_factory=dict, repr=False)

    def images(self) -> list[ImageKey]:
        """Every image the source names (also those with problems), sorted."""
        return sorted(self.names)

    def __contains__(self, key: object) -> bool:
        return key in self.names

    def __len__(self) -> int:
        return len(self.names)

    def for_image(self, scene_id: int, im_id: int) -> list[Hypothesis]:
        """The image's hypotheses, by score descending (ties in file order): ``T_world_obj``
        holds ``T_cam_obj`` (4x4, m), ``class_name`` the library class.

        An image the source does not name has none (an estimator that found nothing writes
        nothing for it): ``[]``.

        Raises:
            InputError: a row or entry of this image could not be used (the message names the
                file, line or entry, and what is wrong).
        """
        key = (int(scene_id), int(im_id))
        problems = self._problems.get(key)
        if problems:
            shown = "; ".join(problems[:_SHOWN_PROBLEMS])
            more = len(problems) - _SHOWN_PROBLEMS
            raise InputError(shown + (f" (and {more} more problems)" if more > 0 else ""))
        return [replace(h, T_world_obj=h.T_world_obj.copy()) for h in self._hyps.get(key, [])]

    def problems(self, scene_id: int, im_id: int) -> list[str]:
        """What is wrong with the image's rows or entries (empty when nothing is)."""
        return list(self._problems.get((int(scene_id), int(im_id)), []))

    def bad_images(self) -> list[ImageKey]:
        """The images :meth:`for_image` raises for, sorted."""
        return sorted(k for k, v in self._problems.items() if v)

    def key_of_name(self, name: str) -> ImageKey | None:
        """The image named ``name`` in the source (see :attr:`names`), or None."""
        for key, n in self.names.items():
            if n == name:
                return key
        return None


# ------------------------------------------------------------------------------ classes
def _closest(name: str, known: Iterable[str]) -> str:
    known = [str(k) for k in known]
    close = difflib.get_close_matches(str(name), known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{hint}; known: {', '.join(known) or 'none'}"


class _ClassMap:
    """Label (or BOP obj_id) -> library class name, checked against ``library`` if given.

    Labels are compared as strings, so a mapping with integer keys (a dataset's ``obj_id ->
    class``) matches labels ``"2"`` (also ``"02"``); and a label that is not a key but the BOP
    model name of a numeric key (``obj_000002``) or one of the mapping's class names (the
    estimator was given the library's names) is that class."""

    def __init__(self, classes: Any, library: Any, kind: str) -> None:
        self.kind = kind
        self.alias: dict[str, str] = {}
        self.library = None if library is None else [str(c) for c in library]
        if isinstance(classes, ObjectIds):
            if kind != "obj_id":
                raise ArgumentError("ObjectIds maps classes to BOP obj_ids: give a label mapping")
            classes = {oid: cls for cls, oid in classes.as_dict().items()}
        if classes is None:
            if kind == "obj_id":
                raise ArgumentError(
                    "a BOP19 CSV names objects by obj_id: give classes (obj_id -> class name, "
                    "or an ObjectIds)"
                )
            self.map: dict[Any, str] | None = None
        elif isinstance(classes, Mapping):
            self.map = {}
            for k, v in classes.items():
                key: Any = k
                if kind == "obj_id":
                    try:
                        key = int(k)
                    except (TypeError, ValueError) as exc:
                        raise ArgumentError(f"classes: obj_id {k!r} is not an integer") from exc
                else:
                    key = _label_key(k)
                if not isinstance(v, str) or not v:
                    raise ArgumentError(f"classes[{k!r}]: class must be a non-empty string")
                if self.library is not None and v not in self.library:
                    raise ArgumentError(
                        f"classes[{k!r}]: class {v!r} is not in the library"
                        + _closest(v, self.library)
                    )
                self.map[key] = v
            if kind == "label":
                for k, v in self.map.items():
                    if k.isdigit():
                        self.alias.setdefault(f"obj_{int(k):06d}", v)
                for v in self.map.values():
                    self.alias.setdefault(v, v)
        else:
            raise ArgumentError(
                f"classes must be a mapping ({kind} -> class name) or None, "
                f"got {type(classes).__name__}"
            )

    def __call__(self, label: Any) -> str:
        """The class of ``label``; InputError (a message without the place) if none."""
        if self.map is not None:
            key = label if self.kind == "obj_id" else _label_key(label)
            if key in self.map:
                return self.map[key]
            if key in self.alias:
                return self.alias[key]
            if self.kind == "obj_id":
                known = ", ".join(f"{k} ({v})" for k, v in sorted(self.map.items()))
                raise InputError(f"obj_id {label} has no class; known obj_ids: {known or 'none'}")
            raise InputError(
                f"label {label!r} is not in the label -> class mapping"
                + _closest(str(label), self.map)
            )
        if self.library is not None and label not in self.library:
            raise InputError(
                f"class {label!r} is not in the library" + _closest(label, self.library)
            )
        return str(label)


def _label_key(label: Any) -> str:
    """A label as compared: a string, an integer's digits without leading zeros."""
    text = str(label)
    return str(int(text)) if text.isdigit() else text


# ------------------------------------------------------------------------------ collecting
class _Collector:
    """Builds an :class:`EstimatorHypotheses`, keeping each image's problems apart."""

    def __init__(self, fmt: str, source: Path, classes: _ClassMap) -> None:
        self.out = EstimatorHypotheses(fmt, source)
        self.classes = classes
        # per image, (class, pose bytes) -> position of that hypothesis: duplicates merge
        self._seen: dict[ImageKey, dict[tuple[str, bytes], int]] = {}
        self.duplicates = 0

    def image(self, key: ImageKey, name: str | None = None) -> None:
        self.out.names.setdefault(key, str(key[1]) if name is None else name)
        self.out._hyps.setdefault(key, [])

    def problem(self, key: ImageKey, message: str) -> None:
        self.image(key)
        self.out._problems.setdefault(key, []).append(message)
        log.debug("%s", message)

    def add(self, key: ImageKey, label: Any, T: np.ndarray, score: float, where: str) -> None:
        """One hypothesis (``T`` 4x4 camera-frame, m); a bad one becomes a problem."""
        self.image(key)
        try:
            cls = self.classes(label)
            T = _rigid(T)
            score = float(score)
            if not np.isfinite(score):
                raise InputError(f"score is {score}")
        except InputError as exc:
            self.problem(key, f"{where}: {exc}")
            return
        # an identical row (same image, object and pose) written twice is one hypothesis: as
        # two it would take two of the places kept per object and crowd out the others
        seen = self._seen.setdefault(key, {})
        at = seen.get((cls, T.tobytes()))
        hyps = self.out._hyps[key]
        if at is not None:
            self.duplicates += 1
            hyps[at] = replace(hyps[at], score=max(hyps[at].score, score))
            return
        seen[(cls, T.tobytes())] = len(hyps)
        hyps.append(Hypothesis(class_name=cls, T_world_obj=T, score=score))

    def warn(self, message: str) -> None:
        """A warning about the source (logged, and kept in the result's ``warnings``)."""
        self.out.warnings.append(f"{self.out.source}: {message}")
        log.warning("%s", self.out.warnings[-1])

    def result(self) -> EstimatorHypotheses:
        if self.duplicates:
            self.warn(
                f"{self.duplicates} duplicated rows or entries (the same image, object and "
                "pose as an earlier one) merged into one hypothesis each"
            )
        for hyps in self.out._hyps.values():
            hyps.sort(key=lambda h: -h.score)  # stable: ties keep the file's order
        bad = self.out.bad_images()
        if bad:
            first = self.out._problems[bad[0]][0]
            log.warning(
                "%s: %d of %d images have entries that cannot be used (they fail when asked "
                "for), the first: %s",
                self.out.source, len(bad), len(self.out.names), first,
            )  # fmt: skip
        return self.out


def _rigid(T: np.ndarray) -> np.ndarray:
    """``T`` (4x4) checked: finite, last row [0, 0, 0, 1], rotation within
    :data:`ssp.io.hypotheses.ROTATION_TOL` (re-orthonormalised). InputError otherwise."""
    T = np.array(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"pose must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError("pose contains NaN or infinite values")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise InputError(f"pose's last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    T[:3, :3] = check_rotation(T[:3, :3], "R")
    return T


_NUMBERED = re.compile(r"^(.*?)(\d+)$")


def _image_ids(names: Iterable[str], where: Path, col: _Collector | None = None) -> dict[str, int]:
    """im_id of each image name, read from the name, never from its position among the
    files: the number when the name is one (``000012`` -> 12), else the number ending the
    names of the common pattern (``frame2``, ``frame10`` -> 2, 10). The names are matched to
    the images by these ids, so a stray file (``000000_backup``) shifts nothing: a name of
    no image (not of the pattern) is left out, with a warning naming it (``col.warn``).

    Raises:
        InputError: no name carries an image number, two patterns are as common, or two
            names give one im_id.
    """
    names = sorted(set(names), key=natural_key)
    patterns: dict[str, list[str]] = {}
    for n in names:
        m = _NUMBERED.match(n)
        if m is not None:
            patterns.setdefault(m.group(1), []).append(n)
    if not patterns:
        raise InputError(
            f"{where}: no file name carries an image number ({', '.join(names[:5])}): name "
            "the files by the image's id (000012.json, frame12.json)"
        )
    most = max(len(v) for v in patterns.values())
    best = [p for p, v in patterns.items() if len(v) == most]
    if len(best) > 1 and "" not in best:
        raise InputError(
            f"{where}: cannot tell which files are images: as many are named "
            f"{' as '.join(repr(p + '<number>') for p in best)}"
        )
    prefix = "" if "" in best else best[0]
    ids: dict[str, int] = {}
    for n in patterns[prefix]:
        im = int(n[len(prefix) :])
        clash = [m for m, i in ids.items() if i == im]
        if clash:
            raise InputError(f"{where}: {clash[0]!r} and {n!r} are the same im_id {im}")
        ids[n] = im
    stray = [n for n in names if n not in ids]
    if stray and col is not None:
        col.warn(
            f"{len(stray)} files name no image (not named {prefix or ''}<image id> as the "
            f"others): {', '.join(stray[:10])}{' ...' if len(stray) > 10 else ''}; ignored"
        )
    return ids


def _check_source(path: Path, folder_ok: bool = False, file_ok: bool = True) -> None:
    if folder_ok and path.is_dir():
        return
    problem = file_problem(path)
    if problem is None and file_ok:
        return
    if problem is None:
        problem = "is a file, not a folder"
    if problem == "does not exist":
        problem = "no such file or folder" if folder_ok else "no such file"
    raise InputError(f"{path}: {problem}")


# ------------------------------------------------------------------------------ BOP19 CSV
def read_bop19_csv(
    path: str | os.PathLike, classes: Mapping[int, str] | ObjectIds, *, library: Any = None
) -> EstimatorHypotheses:
    """A BOP19 results CSV (``scene_id,im_id,obj_id,score,R,t,time``; ``R`` row-major,
    model-to-camera; ``t`` in mm, converted to m; ``time`` ignored).

    Args:
        classes: ``obj_id -> class name`` (int or numeric-string keys), or an
            :class:`ssp.io.results.ObjectIds`.
        library: the library's class names (a mapping or an iterable), to check classes.

    Identical rows (image, object, pose) are merged into one hypothesis, and translations
    that are all shorter than :data:`METRES_LIKE_MM` (metres, not mm) are warned about
    (:attr:`EstimatorHypotheses.warnings`).

    Raises:
        InputError: the file is missing or has no BOP19 header, or a row's ids cannot be read.
        ArgumentError: a bad ``classes`` mapping.
    """
    p = Path(path)
    col = _Collector("bop19", p, _ClassMap(classes, library, "obj_id"))
    t_mm: list[float] = []
    for line in scan_bop_csv(p):
        if line.ids is None:
            raise InputError(
                f"{line.where}: {line.error}: its scene_id and im_id cannot be read, so it "
                "belongs to no image"
            )
        col.image(line.ids)
        if line.row is None:
            col.problem(line.ids, f"{line.where}: {line.error}")
            continue
        row = line.row
        T = np.eye(4)
        T[:3, :3] = row["R"]
        T[:3, 3] = row["t"] / 1000.0
        t_mm.append(float(np.linalg.norm(row["t"])))
        col.add(line.ids, row["obj_id"], T, row["score"], f"{line.where} (obj_id {row['obj_id']})")
    if t_mm and np.all(np.array(t_mm) < METRES_LIKE_MM):  # NaN rows fail their image
        col.warn(
            f"every translation is shorter than {METRES_LIKE_MM:g} mm (the longest "
            f"{max(t_mm):.3g}): BOP19's t is in millimetres, these look like metres (multiply "
            "t by 1000)"
        )
    return col.result()


# ------------------------------------------------------------------------------ MegaPose
def read_megapose(
    path: str | os.PathLike,
    classes: Mapping[str, str] | None = None,
    *,
    library: Any = None,
    scene_id: int = 0,
) -> EstimatorHypotheses:
    """MegaPose / HappyPose estimates: lists of ``ObjectData.to_json()`` (``label``, ``TWO`` =
    ``[[qx, qy, qz, qw], [tx, ty, tz]]``, m, object-to-camera), one JSON file per image.

    ``path`` is one such file (one image: im_id from its stem if numeric, else 0), or a folder
    of ``<image>.json`` files, or a folder of upstream example folders ``<image>/`` each with
    :data:`MEGAPOSE_OUTPUTS`. Image names become im_ids by the number they are or end with
    (``000012``, ``frame12``: 12); a file whose name does not follow the others'
    (``000000_backup``) is left out with a warning. An entry's optional ``score`` is used
    (upstream writes none: 1.0).

    Args:
        classes: ``label -> class name``; None: labels are library class names.
        library: the library's class names, to check classes.
        scene_id: the scene_id of every image (the files have none).

    Raises:
        InputError: a missing path, a single file that is not such a list (or cannot be
            parsed: bad syntax, nested too deeply), a folder with no such files.
    """
    p = Path(path)
    _check_source(p, folder_ok=True)
    col = _Collector("megapose", p, _ClassMap(classes, library, "label"))
    sid = int(scene_id)
    if p.is_file():
        doc = _read_json_list(p)  # a single file that cannot be read fails as a whole
        im = int(p.stem) if p.stem.isdigit() else 0
        col.image((sid, im), p.stem)
        _megapose_entries(col, (sid, im), doc, p)
        return col.result()
    files = _megapose_files(p)
    ids = _image_ids(files, p, col)
    for name in sorted(ids, key=natural_key):
        key = (sid, ids[name])
        col.image(key, name)
        try:
            doc = _read_json_list(files[name])
        except InputError as exc:
            col.problem(key, str(exc))
            continue
        _megapose_entries(col, key, doc, files[name])
    return col.result()


def _megapose_files(folder: Path) -> dict[str, Path]:
    """Image name -> its estimates file in a MegaPose folder (layouts of :func:`read_megapose`)."""
    direct = {f.stem: f for f in folder.glob("*.json") if f.is_file()}
    if direct:
        return direct
    out = {}
    for sub in sorted(d for d in folder.iterdir() if d.is_dir()):
        for rel in MEGAPOSE_OUTPUTS:
            if (sub / rel).is_file():
                out[sub.name] = sub / rel
                break
    if not out:
        raise InputError(
            f"{folder}: no MegaPose estimates: expected <image>.json files, or example folders "
            f"<image>/{MEGAPOSE_OUTPUTS[0]} (HappyPose: {MEGAPOSE_OUTPUTS[1]})"
        )
    return out


def _read_json_list(p: Path) -> list:
    try:
        doc = read_json(p)
    except RecursionError:
        raise InputError(f"{p}: invalid JSON: nested too deeply to read") from None
    if not isinstance(doc, list):
        raise InputError(
            f"{p}: not MegaPose estimates: expected a JSON list of objects with 'label' and "
            f"'TWO', got a {type(doc).__name__}"
        )
    return doc


def _megapose_entries(col: _Collector, key: ImageKey, doc: list, p: Path) -> None:
    try:
        _megapose_entry_list(col, key, doc, p)
    except RecursionError:  # an entry nested too deeply to be shown or read
        col.problem(key, f"{p}: an entry is nested too deeply to read")


def _megapose_entry_list(col: _Collector, key: ImageKey, doc: list, p: Path) -> None:
    for i, entry in enumerate(doc):
        where = f"{p}: entry {i}"
        try:
            if not isinstance(entry, Mapping):
                raise InputError(f"expected an object with 'label' and 'TWO', got {entry!r:.40}")
            label = entry.get("label")
            if not isinstance(label, str) or not label:
                raise InputError(f"'label' must be a non-empty string, got {label!r}")
            where = f"{where} ({label!r})"
            if "TWO" not in entry:
                raise InputError(
                    "no 'TWO' pose (an input detections file? MegaPose writes its estimates to "
                    f"{MEGAPOSE_OUTPUTS[0]})"
                )
            T = _two_matrix(entry["TWO"])
            score = entry.get("score", 1.0)
            if isinstance(score, bool) or not isinstance(score, (int, float)):
                raise InputError(f"'score' must be a number, got {score!r}")
        except InputError as exc:
            col.problem(key, f"{where}: {exc}")
            continue
        col.add(key, label, T, score, where)


def _two_matrix(two: Any) -> np.ndarray:
    """4x4 of a MegaPose ``TWO``: ``[[qx, qy, qz, qw], [tx, ty, tz]]``."""
    if not isinstance(two, list) or len(two) != 2:
        raise InputError(f"'TWO' must be [[qx, qy, qz, qw], [tx, ty, tz]], got {two!r:.60}")
    try:
        q = np.array(two[0], dtype=np.float64)
        t = np.array(two[1], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"'TWO' must hold numbers: {exc}") from exc
    if q.shape != (4,) or t.shape != (3,):
        raise InputError(f"'TWO' must be a quaternion (4) and a translation (3), got {two!r:.60}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise InputError("'TWO' contains NaN or infinite values")
    if np.linalg.norm(q) < 1e-6:
        raise InputError("'TWO' has a zero quaternion")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()  # scipy: xyzw, as MegaPose
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------------------ FoundationPose
def read_foundationpose(
    path: str | os.PathLike,
    classes: Mapping[str, str] | None = None,
    *,
    library: Any = None,
    scene_id: int = 0,
    object_name: str | None = None,
) -> EstimatorHypotheses:
    """FoundationPose poses: one text file per frame and object holding the 4x4
    object-to-camera pose (m), as ``run_demo.py`` writes it
    (``numpy.savetxt(f"{debug_dir}/ob_in_cam/{frame id}.txt", pose)``).

    Layouts: one object: ``path/ob_in_cam/*.txt`` (the demo's ``--debug_dir``) or
    ``path/*.txt``; several objects (one demo run per object): ``path/<object>/ob_in_cam/*.txt``
    or ``path/<object>/*.txt``. The frame ids (file stems: the demo's colour image stems) become
    im_ids by the number they are or end with (a stem that does not follow the others' is
    left out with a warning). A frame missing for one
    object just lacks that object's hypothesis. Scores are 1.0 (FoundationPose writes none).

    Args:
        classes: object name (folder name) -> class name; None: the names are class names.
        library: the library's class names, to check classes.
        scene_id: the scene_id of every image.
        object_name: the object's name for the one-object layouts (default: the folder's
            name, the parent's when the folder is ``ob_in_cam``).

    Raises:
        InputError: a missing path or one in none of these layouts.
    """
    p = Path(path)
    _check_source(p, folder_ok=True, file_ok=False)
    col = _Collector("foundationpose", p, _ClassMap(classes, library, "label"))
    objects = _foundationpose_objects(p, object_name)
    ids = _image_ids([f.stem for files in objects.values() for f in files], p, col)
    for name in sorted(ids, key=natural_key):
        col.image((int(scene_id), ids[name]), name)
    for obj, files in objects.items():
        for f in files:
            if f.stem not in ids:
                continue  # a file of no image (a warning named it)
            key = (int(scene_id), ids[f.stem])
            try:
                T = _read_matrix_txt(f)
            except InputError as exc:
                col.problem(key, f"{exc} (object {obj!r})")
                continue
            col.add(key, obj, T, 1.0, f"{f} (object {obj!r})")
    return col.result()


def _txt_files(folder: Path) -> list[Path]:
    return sorted(
        (f for f in folder.glob("*.txt") if f.is_file()), key=lambda f: natural_key(f.name)
    )


def _foundationpose_objects(p: Path, object_name: str | None) -> dict[str, list[Path]]:
    """Object name -> its pose files, for the layouts of :func:`read_foundationpose`."""
    if (p / "ob_in_cam").is_dir():
        return {object_name or p.name: _txt_files(p / "ob_in_cam")}
    direct = _txt_files(p)
    if direct:
        name = object_name or (p.parent.name if p.name == "ob_in_cam" else p.name)
        return {name: direct}
    if object_name is not None:
        raise InputError(f"{p}: no ob_in_cam/ folder and no *.txt poses for object {object_name!r}")
    out = {}
    for sub in sorted((d for d in p.iterdir() if d.is_dir()), key=lambda d: natural_key(d.name)):
        files = _txt_files(sub / "ob_in_cam") if (sub / "ob_in_cam").is_dir() else _txt_files(sub)
        if files:
            out[sub.name] = files
    if not out:
        raise InputError(
            f"{p}: no FoundationPose poses: expected ob_in_cam/<frame>.txt (one object) or "
            "<object>/ob_in_cam/<frame>.txt (one folder per object)"
        )
    return out


def _read_matrix_txt(f: Path) -> np.ndarray:
    problem = file_problem(f)
    if problem is not None:
        raise InputError(f"{f}: {problem}")
    try:
        text = f.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{f}: cannot read: {exc}") from exc
    try:
        M = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise InputError(f"{f}: not a 4x4 matrix of numbers: {exc}") from exc
    if M.shape != (4, 4):
        raise InputError(f"{f}: expected a 4x4 matrix (4 lines of 4 numbers), got {M.shape}")
    return M


# ------------------------------------------------------------------------------ CosyPose
def read_cosypose_csv(
    path: str | os.PathLike, classes: Mapping[str, str] | None = None, *, library: Any = None
) -> EstimatorHypotheses:
    """A CSV of CosyPose's prediction table (``PandasTensorCollection``: ``infos`` and
    ``poses``): header with at least ``scene_id,view_id,label,TCO`` (``score`` optional, 1.0;
    other columns ignored), ``TCO`` the 16 entries of the 4x4 object-to-camera pose
    (``poses``), row-major, metres, space-separated; ``view_id`` is the im_id. Written by
    ``df.to_csv(path, index=False)`` or the csv module (standard quoting).

    Args:
        classes: ``label -> class name`` (CosyPose labels: ``obj_000001`` for BOP datasets);
            None: labels are class names.
        library: the library's class names, to check classes.

    Raises:
        InputError: a missing file, a header without the required columns, or a row whose
            scene_id and view_id cannot be read.
    """
    p = Path(path)
    _check_source(p)
    col = _Collector("cosypose", p, _ClassMap(classes, library, "label"))
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read: {exc}") from exc
    rows = csv.reader(io.StringIO(text, newline=""))
    header = next(rows, None)
    missing = [c for c in _COSYPOSE_REQUIRED if header is None or c not in header]
    if header is None or missing:
        raise InputError(
            f"{p}: not a CosyPose CSV: the header lacks {', '.join(missing)} (columns "
            f"{','.join(COSYPOSE_COLUMNS)}, TCO 16 numbers row-major in m)"
        )
    at = {c: header.index(c) for c in COSYPOSE_COLUMNS if c in header}
    try:
        for cells in rows:
            n = rows.line_num
            if not any(c.strip() for c in cells):
                continue
            where = f"{p}:{n}"
            key = _cosypose_ids(cells, at)
            if key is None:
                raise InputError(
                    f"{where}: its scene_id and view_id cannot be read, so it belongs to no image"
                )
            col.image(key)
            if len(cells) != len(header):
                col.problem(key, f"{where}: expected {len(header)} columns, got {len(cells)}")
                continue
            label = cells[at["label"]]
            where = f"{where} ({label!r})"
            try:
                T = _tco_matrix(cells[at["TCO"]])
                score = float(cells[at["score"]]) if "score" in at else 1.0
            except (InputError, ValueError) as exc:
                col.problem(key, f"{where}: {exc}")
                continue
            col.add(key, label, T, score, where)
    except csv.Error as exc:
        raise InputError(f"{p}:{rows.line_num}: malformed CSV: {exc}") from exc
    return col.result()


def _cosypose_ids(cells: list[str], at: Mapping[str, int]) -> ImageKey | None:
    try:
        return (_int_cell(cells[at["scene_id"]]), _int_cell(cells[at["view_id"]]))
    except (IndexError, ValueError):
        return None


def _int_cell(cell: str) -> int:
    """An integer cell; pandas writes an integer column holding a NaN as floats (``3.0``)."""
    try:
        return int(cell)
    except ValueError:
        v = float(cell)
        if not v.is_integer():
            raise
        return int(v)


def _tco_matrix(cell: str) -> np.ndarray:
    try:
        vals = np.array(cell.split(), dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"TCO must be 16 numbers: {exc}") from exc
    if vals.shape != (16,):
        raise InputError(f"TCO must be 16 numbers (4x4 row-major), got {vals.size}")
    return vals.reshape(4, 4)


# ------------------------------------------------------------------------------ detection
def detect_format(path: str | os.PathLike) -> str:
    """The format of ``path`` (one of :data:`FORMATS`), from its layout and a CSV's header.

    Raises:
        InputError: a missing path, or one that is none of them (the message says what each
            format looks like).
    """
    p = Path(path)
    _check_source(p, folder_ok=True)
    if p.is_file():
        if p.suffix.lower() == ".json":
            return "megapose"
        if p.suffix.lower() == ".csv":
            header = _first_line(p)
            if header.strip() == BOP_CSV_HEADER:
                return "bop19"
            cols = next(csv.reader([header]), [])
            if all(c in cols for c in _COSYPOSE_REQUIRED):
                return "cosypose"
            raise InputError(
                f"{p}: cannot tell the format: the header {header.strip()[:80]!r} is neither "
                f"BOP19's {BOP_CSV_HEADER!r} nor a CosyPose CSV's (with "
                f"{','.join(_COSYPOSE_REQUIRED)})"
            )
        raise InputError(
            f"{p}: cannot tell the format from a {p.suffix or 'suffix-less'} file: expected a "
            ".csv (BOP19, CosyPose), a .json (MegaPose) or a folder (FoundationPose, MegaPose)"
        )
    subs = [d for d in p.iterdir() if d.is_dir()]
    if (p / "ob_in_cam").is_dir() or any((d / "ob_in_cam").is_dir() for d in subs):
        return "foundationpose"
    if any(f.is_file() for f in p.glob("*.json")) or any(
        (d / rel).is_file() for d in subs for rel in MEGAPOSE_OUTPUTS
    ):
        return "megapose"
    if _txt_files(p) or any(_txt_files(d) for d in subs):
        return "foundationpose"
    raise InputError(
        f"{p}: cannot tell the format of this folder: no ob_in_cam/ or <object>/*.txt poses "
        f"(FoundationPose), no <image>.json or <image>/{MEGAPOSE_OUTPUTS[0]} (MegaPose); give "
        "the format"
    )


def _first_line(p: Path) -> str:
    try:
        with open(p, encoding="utf-8", errors="replace", newline="") as f:
            return f.readline(4096)
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc}") from exc


def read_estimates(
    path: str | os.PathLike,
    fmt: str = "auto",
    classes: Mapping | ObjectIds | None = None,
    *,
    library: Any = None,
    scene_id: int = 0,
    object_name: str | None = None,
) -> EstimatorHypotheses:
    """Read an estimator's output in format ``fmt`` (one of :data:`FORMATS`, or ``auto``:
    :func:`detect_format`).

    Args:
        classes: label (BOP19: obj_id) -> class name; None: labels are class names (BOP19
            needs a mapping).
        library: the library's class names, to check classes.
        scene_id: the scene_id of the images of formats without one (MegaPose,
            FoundationPose); BOP19 and CosyPose files carry their own.
        object_name: FoundationPose one-object layouts: the object's name.

    Raises:
        ArgumentError: an unknown ``fmt`` or a bad ``classes``.
        InputError: see the readers; ``auto`` on a path of no known format.
    """
    if fmt == "auto":
        fmt = detect_format(path)
        log.info("%s: read as %s", path, fmt)
    if fmt == "bop19":
        return read_bop19_csv(path, classes, library=library)
    if fmt == "megapose":
        return read_megapose(path, classes, library=library, scene_id=scene_id)
    if fmt == "foundationpose":
        return read_foundationpose(
            path,
            classes,
            library=library,
            scene_id=scene_id,
            object_name=object_name,
        )
    if fmt == "cosypose":
        return read_cosypose_csv(path, classes, library=library)
    raise ArgumentError(f"unknown estimator format {fmt!r}: one of auto, {', '.join(FORMATS)}")
