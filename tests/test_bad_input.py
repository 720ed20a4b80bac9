"""The bad-input matrix (issue 16): every case asserts its outcome.

Outcomes:

* **error**: the input as a whole cannot be used; a typed :class:`SSPError` whose message
  names the file (when there is one) and the problem;
* **skipped frame**: one bad frame among good ones is reported failed (in its frame JSON and
  in ``summary.json``) with the file and the problem, and everything else (the parser state,
  the other frames' results) equals the run without that frame;
* **warning**: the frame is processed and the output says what is suspicious;
* **bounded**: a hostile input is processed within bounded work.

The inputs are written by the tests: a short synthetic block structure (two frames with
given hypotheses, so no estimator runs) as a folder of clouds, a BOP scene, and Python
frames.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import ssp.parser
from ssp.cli import app
from ssp.config import load_config
from ssp.errors import (
    ArgumentError,
    CloudFormatError,
    ConfigError,
    InputError,
    SSPError,
    UnknownObjectError,
)
from ssp.io.clouds import write_cloud
from ssp.io.hypotheses import write_hypotheses
from ssp.parser import SceneEstimate, SceneParser, parse_sequence
from ssp.perception import segmentation
from ssp.pipeline.run import run
from ssp.pipeline.summary import without_timings
from ssp.scene import Frame, FrameError
from ssp.sim.bop import simulate_to_disk
from ssp.sim.generate import generate_sequence

cli = CliRunner()


# ------------------------------------------------------------------------------ inputs
@pytest.fixture(scope="module")
def seq(lib):
    """Three frames of a small block structure (objects added between frames)."""
    return generate_sequence(
        "structure", 3, lib, stages=3, frames_per_stage=1, stride=8, n_objects=3
    )


GOOD = ("f0", "f2")  # the good frames of the folder; a bad frame goes in between as f1
STAMPS = {"f0": 0.0, "f1": 0.5, "f2": 1.0}


def _write_frame(d: Path, name: str, seq, i: int, hyps=None) -> None:
    """World-frame cloud with instance labels (0 = background) and the frame's hypotheses."""
    f = seq.frame(i)
    write_cloud(d / f"{name}.ply", f.points, labels=f.labels + 1)
    write_hypotheses(d / f"{name}.hypotheses.json", seq.frames[i].hypotheses if hyps is None
                     else hyps)  # fmt: skip


def _scene_json(d: Path, seq, names, **extra) -> None:
    doc = {
        "frame": "world",
        "T_world_cam": seq.T_world_cam.tolist(),
        "stamps": {n: STAMPS[n] for n in names},
        **extra,
    }
    (d / "scene.json").write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def folder(seq, tmp_path_factory):
    """The good folder (f0 and f2 = frames 0 and 2 of ``seq``) and its run (the reference)."""
    d = tmp_path_factory.mktemp("good")
    _write_frame(d, "f0", seq, 0)
    _write_frame(d, "f2", seq, 2)
    _scene_json(d, seq, GOOD)
    return d


@pytest.fixture(scope="module")
def folder_ref(lib, folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "out"
    summary = run(folder, lib, out, hypotheses="given")
    assert len(summary.done) == 2 and not summary.failed
    return out


def _strip(obj, drop=()):
    """``obj`` without wall times and ``drop`` keys, at every level."""
    return without_timings(obj, tuple(drop))


def _error_class(name: str) -> type:
    import ssp.errors
    import ssp.scene

    return getattr(ssp.errors, name, None) or getattr(ssp.scene, name)


def _load(p: Path):
    return json.loads(p.read_text())


def _csv_rows(out: Path, drop_cols=(1, 6)) -> list[str]:
    """CSV rows without ``im_id`` (a folder position) and ``time`` (wall time)."""
    (path,) = out.glob("*.csv")
    rows = path.read_text().splitlines()
    return [",".join(c for k, c in enumerate(r.split(",")) if k not in drop_cols) for r in rows]


def _assert_same_as_without(out: Path, ref: Path, names, drop=("index",)) -> None:
    """The run in ``out`` equals the run ``ref`` without the bad frame: parser state, and
    the frame JSONs and CSV rows of the good frames (``drop``: keys allowed to differ)."""
    assert _load(out / "state.json")["parser"] == _load(ref / "state.json")["parser"]
    for n in names:
        a = _strip(_load(out / "frames" / f"{n}.json"), drop)
        b = _strip(_load(ref / "frames" / f"{n}.json"), drop)
        assert a == b, n
    assert _csv_rows(out) == _csv_rows(ref)


# ------------------------------------------------------------------------------ skipped frames
@dataclass
class Bad:
    """A bad frame ``f1`` put between the good frames of the folder."""

    id: str
    make: Callable[[Path, object], None]  # (folder, seq) -> writes f1's files
    needles: tuple[str, ...]  # the message names these (the file and the problem)
    error: type = SSPError
    shifts_nothing: bool = False  # also check the later frame keeps its position (index 2)
    avoid: tuple[str, ...] = ()  # the message must not say these


def _cloud_bytes(data: bytes):
    def make(d, seq):
        (d / "f1.ply").write_bytes(data)
        write_hypotheses(d / "f1.hypotheses.json", seq.frames[1].hypotheses)

    return make


def _good_cloud_and(hyp_doc=None, hyp_text=None, hyp_bytes=None):
    """f1 = frame 1's cloud with a hypotheses file from a document, text or bytes."""

    def make(d, seq):
        f = seq.frame(1)
        write_cloud(d / "f1.ply", f.points, labels=f.labels + 1)
        p = d / "f1.hypotheses.json"
        if hyp_doc is not None:
            p.write_text(json.dumps(hyp_doc))
        elif hyp_text is not None:
            p.write_text(hyp_text)
        elif hyp_bytes is not None:
            p.write_bytes(hyp_bytes)

    return make


def _cloud_array(points_fn, labels=True):
    def make(d, seq):
        f = seq.frame(1)
        write_cloud(d / "f1.ply", points_fn(f.points), labels=f.labels + 1 if labels else None)
        write_hypotheses(d / "f1.hypotheses.json", seq.frames[1].hypotheses)

    return make


def _entry(kind: str):
    """f1.ply as a file-system entry that is not a regular file."""

    def make(d, seq):
        p = d / "f1.ply"
        if kind == "dangling":
            os.symlink("no_such_cloud.ply", p)
        elif kind == "loop":
            os.symlink("f1.ply", p)
        elif kind == "fifo":
            os.mkfifo(p)
        write_hypotheses(d / "f1.hypotheses.json", seq.frames[1].hypotheses)

    return make


def _hyp_entry(kind: str):
    def make(d, seq):
        f = seq.frame(1)
        write_cloud(d / "f1.ply", f.points, labels=f.labels + 1)
        p = d / "f1.hypotheses.json"
        if kind == "dangling":
            os.symlink("gone.json", p)
        else:
            os.mkfifo(p)

    return make


def _hyps_of(seq, edit):
    """Frame 1's hypotheses (world frame, file format) with ``edit(list)`` applied."""
    items = [
        {"class": h.class_name, "score": h.score, "t": h.T_world_obj[:3, 3].tolist(),
         "R": h.T_world_obj[:3, :3].tolist()}
        for h in seq.frames[1].hypotheses
    ]  # fmt: skip
    return edit(items)


def _with_hyps(edit, **top):
    def make(d, seq):
        _good_cloud_and(hyp_doc={**top, "hypotheses": _hyps_of(seq, edit)})(d, seq)

    return make


def _set(i, **kw):
    def edit(items):
        items[i].update(kw)
        return items

    return edit


def _ply_text(body: str) -> bytes:
    return body.encode()


ASCII_HEADER = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"

BAD_FRAMES = [
    # clouds
    Bad(
        "ply-truncated",
        lambda d, s: (
            _cloud_array(lambda p: p)(d, s),
            (d / "f1.ply").write_bytes((d / "f1.ply").read_bytes()[:-50]),
        ),
        ("f1.ply",),
        CloudFormatError,
    ),  # fmt: skip
    Bad(
        "ply-no-end-header",
        _cloud_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n"),
        ("f1.ply", "end_header"),
        CloudFormatError,
    ),  # fmt: skip
    Bad("empty-file", _cloud_bytes(b""), ("f1.ply", "empty"), CloudFormatError),
    Bad("not-a-ply", _cloud_bytes(b"\x89PNG\r\n\x1a\n garbage"), ("f1.ply",), CloudFormatError),
    Bad(
        "no-xyz",
        _cloud_bytes(
            _ply_text(
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty "
                "float a\nproperty float b\nend_header\n1 2\n"
            )
        ),
        ("f1.ply", "no x, y, z"),
        CloudFormatError,
    ),  # fmt: skip
    Bad(
        "zero-points",
        _cloud_bytes(
            _ply_text(
                "ply\nformat ascii 1.0\nelement vertex 0\n"
                "property float x\nproperty float y\nproperty float z\nend_header\n"
            )
        ),
        ("f1.ply", "zero points"),
        CloudFormatError,
    ),  # fmt: skip
    Bad(
        "non-numeric",
        _cloud_bytes(_ply_text(ASCII_HEADER + "property float z\nend_header\n1 2 3\n1 two 3\n")),
        ("f1.ply",),
        CloudFormatError,
    ),  # fmt: skip
    Bad(
        "all-nan",
        _cloud_array(lambda p: np.full_like(p, np.nan)),
        ("f1.ply", "no finite"),
        CloudFormatError,
    ),  # fmt: skip
    Bad(
        "millimetres",
        _cloud_array(lambda p: p * 1000.0),
        ("f1.ply", "millimetres"),
        CloudFormatError,
    ),  # fmt: skip
    Bad(
        "dangling-symlink",
        _entry("dangling"),
        ("f1.ply", "dangling symbolic link"),
        CloudFormatError,
        shifts_nothing=True,
    ),  # fmt: skip
    Bad(
        "symlink-loop",
        _entry("loop"),
        ("f1.ply", "symbolic link loop"),
        CloudFormatError,
        shifts_nothing=True,
    ),  # fmt: skip
    Bad("fifo", _entry("fifo"), ("f1.ply", "FIFO"), CloudFormatError, shifts_nothing=True),
    # hypotheses files
    Bad(
        "hyp-invalid-json",
        _good_cloud_and(hyp_text="{oops"),
        ("f1.hypotheses.json", "invalid JSON"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-not-utf8",
        _good_cloud_and(hyp_bytes=b'{"hypotheses": ["\xff\xfe"]}'),
        ("f1.hypotheses.json", "cannot read"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-list",
        _good_cloud_and(hyp_text="[]"),
        ("f1.hypotheses.json", "JSON object"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-not-a-list",
        _good_cloud_and(hyp_doc={"hypotheses": {"class": "cube"}}),
        ("f1.hypotheses.json", "must be a list"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-no-class",
        _with_hyps(_set(0, **{"class": None})),
        ("f1.hypotheses.json", "hypothesis 0", "'class'"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-unknown-class",
        _with_hyps(_set(0, **{"class": "cubee"})),
        ("f1.hypotheses.json", "'cubee'", "not in the library", "did you mean 'cube'"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-not-a-rotation",
        _with_hyps(_set(0, R=[[1, 0, 0], [0, 2, 0], [0, 0, 1]])),
        ("f1.hypotheses.json", "not a rotation"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-nan-t",
        _with_hyps(_set(0, t=[0.0, float("nan"), 0.0])),
        ("f1.hypotheses.json", "NaN"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-zero-quaternion",
        _with_hyps(
            lambda it: [
                {**{k: v for k, v in it[0].items() if k != "R"}, "quat_xyzw": [0, 0, 0, 0]},
                *it[1:],
            ]
        ),
        ("f1.hypotheses.json", "zero quaternion"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-bad-last-row",
        _with_hyps(
            lambda it: [
                {
                    "class": it[0]["class"],
                    "T": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]],
                },
                *it[1:],
            ]
        ),
        ("f1.hypotheses.json", "last row"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-rotations-disagree",
        _with_hyps(_set(0, quat_xyzw=[1, 0, 0, 0])),
        ("f1.hypotheses.json", "different rotations"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-units-cm",
        _with_hyps(lambda it: it, units="cm"),
        ("f1.hypotheses.json", "'units'"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-frame-robot",
        _with_hyps(lambda it: it, frame="robot"),
        ("f1.hypotheses.json", "'frame'"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-score-text",
        _with_hyps(_set(0, score="high")),
        ("f1.hypotheses.json", "score"),
        InputError,
    ),  # fmt: skip
    Bad("hyp-id-int", _with_hyps(_set(0, id=7)), ("f1.hypotheses.json", "'id'"), InputError),
    Bad(
        "hyp-segment-text",
        _with_hyps(_set(0, segment="a")),
        ("f1.hypotheses.json", "'segment'"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-100m-away",
        _with_hyps(_set(0, t=[100.0, 0.0, 0.0])),
        ("f1.hypotheses.json", "hypothesis 0", "100.0 m", "outlier"),
        FrameError,
        avoid=("millimetres",),
    ),  # fmt: skip
    Bad(
        "hyp-in-mm",
        _with_hyps(lambda it: [{**h, "t": [1000 * x for x in h["t"]]} for h in it]),
        ("f1.hypotheses.json", "millimetres", "divide"),
        FrameError,
    ),  # fmt: skip
    Bad(
        "hyp-one-id-two-classes",
        _with_hyps(
            lambda it: [
                {**it[0], "class": "cube", "id": "a"},
                {**it[1], "class": "block", "id": "a"},
                *it[2:],
            ]
        ),
        ("f1.hypotheses.json", "'a'", "two classes"),
        FrameError,
    ),  # fmt: skip
    Bad(
        "hyp-missing-under-given",
        _good_cloud_and(),
        ("f1.ply", "no hypotheses file", "--hypotheses given"),
        InputError,
    ),  # fmt: skip
    Bad(
        "hyp-dangling-symlink",
        _hyp_entry("dangling"),
        ("f1.hypotheses.json", "dangling symbolic link"),
        InputError,
    ),  # fmt: skip
    Bad("hyp-fifo", _hyp_entry("fifo"), ("f1.hypotheses.json", "FIFO"), InputError),
]


@pytest.mark.parametrize("case", BAD_FRAMES, ids=lambda c: c.id)
def test_bad_frame_is_skipped_and_changes_nothing_else(case, lib, seq, folder, folder_ref,
                                                       tmp_path):  # fmt: skip
    src = tmp_path / "in"
    shutil.copytree(folder, src)
    case.make(src, seq)
    _scene_json(src, seq, ("f0", "f1", "f2"))
    out = tmp_path / "out"
    summary = run(src, lib, out, hypotheses="given")
    assert [f["frame"] for f in summary.failed] == ["f1"]
    (failed,) = summary.failed
    assert failed["index"] == 1 and not failed["unexpected"]
    assert issubclass(_error_class(failed["error_type"]), case.error), failed["error_type"]
    message = failed["error"]
    for needle in case.needles:
        assert needle in message, (needle, message)
    for word in case.avoid:
        assert word not in message, (word, message)
    rec = _load(out / "frames" / "f1.json")
    assert rec["status"] == "failed" and rec["error"] == message
    assert _load(out / "summary.json")["failed"] == summary.failed
    _assert_same_as_without(out, folder_ref, GOOD)
    if case.shifts_nothing:  # the later frame keeps its place: index 2, its own stamp
        f2 = _load(out / "frames" / "f2.json")
        assert f2["index"] == 2 and f2["stamp"] == STAMPS["f2"]


def test_a_sub_folder_named_like_a_cloud_is_ignored(lib, seq, folder, folder_ref, tmp_path):
    src = tmp_path / "in"
    shutil.copytree(folder, src)
    (src / "f1.ply").mkdir()
    out = tmp_path / "out"
    summary = run(src, lib, out, hypotheses="given")
    assert summary.frames == 2 and not summary.failed
    _assert_same_as_without(out, folder_ref, GOOD, drop=())


# ------------------------------------------------------------------------------ unexpected errors
@pytest.mark.parametrize("exc", [TypeError("bug"), MemoryError(), OverflowError("big")],
                         ids=lambda e: type(e).__name__)  # fmt: skip
def test_an_unexpected_error_fails_one_frame_and_is_counted(exc, lib, seq, folder, folder_ref,
                                                            tmp_path, monkeypatch):  # fmt: skip
    """A bug in one frame (here: perception raising) is contained: logged with its traceback,
    reported with its type, counted apart, and the run goes on from the last good frame."""
    from ssp.perception.pipeline import Perception

    src = tmp_path / "in"
    shutil.copytree(folder, src)
    _write_frame(src, "f1", seq, 1)
    _scene_json(src, seq, ("f0", "f1", "f2"))
    real = Perception.from_points

    def flaky(self, points, **kw):
        if kw["stamp"] == STAMPS["f1"]:
            raise exc
        return real(self, points, **kw)

    monkeypatch.setattr(Perception, "from_points", flaky)
    out = tmp_path / "out"
    summary = run(src, lib, out, hypotheses="given")
    (failed,) = summary.failed
    assert failed["frame"] == "f1" and failed["unexpected"]
    assert failed["error_type"] == type(exc).__name__
    doc = _load(out / "summary.json")
    assert doc["unexpected_errors"] == 1 and doc["status"] == "finished"
    _assert_same_as_without(out, folder_ref, GOOD)


def test_an_error_after_the_parser_took_the_frame_rolls_it_back(lib, seq, folder, folder_ref,
                                                                tmp_path, monkeypatch):  # fmt: skip
    """The parser accepted the frame but its results cannot be written (a bug in the CSV
    formatting): the frame fails and the parser goes on from the last good frame."""
    from ssp.io.results import BopCsvWriter

    src = tmp_path / "in"
    shutil.copytree(folder, src)
    _write_frame(src, "f1", seq, 1)
    _scene_json(src, seq, ("f0", "f1", "f2"))
    real = BopCsvWriter.format_row

    def broken(self, scene_id, im_id, *args):
        if im_id == 1:
            raise ValueError("formatting bug")
        return real(self, scene_id, im_id, *args)

    monkeypatch.setattr(BopCsvWriter, "format_row", broken)
    out = tmp_path / "out"
    summary = run(src, lib, out, hypotheses="given")
    assert [(f["frame"], f["error_type"]) for f in summary.failed] == [("f1", "ValueError")]
    _assert_same_as_without(out, folder_ref, GOOD)


def test_keyboard_interrupt_is_not_swallowed(lib, seq, folder, tmp_path, monkeypatch):
    from ssp.perception.pipeline import Perception

    def interrupt(self, points, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(Perception, "from_points", interrupt)
    with pytest.raises(KeyboardInterrupt):
        run(folder, lib, tmp_path / "out", hypotheses="given")
    assert _load(tmp_path / "out" / "summary.json")["status"] == "interrupted"


# ------------------------------------------------------------------------------ BOP scenes
@pytest.fixture(scope="module")
def bop(lib, tmp_path_factory):
    """A BOP scene of three frames, and the same scene without frame 1 (the reference)."""
    root = tmp_path_factory.mktemp("bop")
    (scene,) = simulate_to_disk("structure", 1, 3, out_dir=root, library=lib, stages=3,
                                frames_per_stage=1, stride=8, n_objects=3)  # fmt: skip
    without = root / "without"
    shutil.copytree(scene, without)
    meta = _load(without / "sequence.json")
    meta["frames"] = [f for f in meta["frames"] if f["im_id"] != 1]
    (without / "sequence.json").write_text(json.dumps(meta))
    ref = root / "ref"
    assert len(run(without, lib, ref).done) == 2
    return scene, ref


def _truncate(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])


def _drop_hyps_entry(scene: Path) -> None:
    doc = _load(scene / "hypotheses.json")
    del doc["1"]
    (scene / "hypotheses.json").write_text(json.dumps(doc))


def _fifo(p: Path) -> None:
    p.unlink()
    os.mkfifo(p)


def _small_instance(scene: Path) -> None:
    from PIL import Image

    Image.fromarray(np.zeros((4, 4), dtype=np.uint16)).save(scene / "instance" / "000001.png")


BOP_BAD = [
    ("truncated-depth-png", lambda s: _truncate(s / "depth" / "000001.png"),
     ("depth/000001.png", "cannot read the image"), "auto"),
    ("missing-depth-png", lambda s: (s / "depth" / "000001.png").unlink(),
     ("depth/000001.png", "does not exist"), "auto"),
    ("depth-png-fifo", lambda s: _fifo(s / "depth" / "000001.png"),
     ("depth/000001.png", "FIFO"), "auto"),
    ("instance-png-wrong-shape", _small_instance, ("instance/000001.png", "shape"), "auto"),
    ("frame-missing-from-hypotheses-given", _drop_hyps_entry,
     ("hypotheses.json", "no entry for im_id 1", "--hypotheses given"), "given"),
]  # fmt: skip


@pytest.mark.parametrize("case", BOP_BAD, ids=lambda c: c[0])
def test_bad_bop_frame_fails_alone_and_keeps_im_ids(case, lib, bop, tmp_path):
    """Frames are read one by one: one bad frame fails alone, the others are as in the scene
    without it, im_id included."""
    name, damage, needles, mode = case
    scene, ref = bop
    src = tmp_path / "scene"
    shutil.copytree(scene, src)
    damage(src)
    out = tmp_path / "out"
    summary = run(src, lib, out, hypotheses=mode)
    assert [(f["frame"], f["index"]) for f in summary.failed] == [("000001", 1)]
    for needle in needles:
        assert needle in summary.failed[0]["error"], (needle, summary.failed[0]["error"])
    _assert_same_as_without(out, ref, ("000000", "000002"), drop=())


def test_bop_frame_missing_from_hypotheses_auto_is_estimated_with_a_warning(lib, bop, tmp_path):
    scene, _ = bop
    src = tmp_path / "scene"
    shutil.copytree(scene, src)
    _drop_hyps_entry(src)
    summary = run(src, lib, tmp_path / "out")
    assert not summary.failed and len(summary.done) == 3
    (w,) = summary.warnings
    assert w["frame"] == "000001" and "no entry for im_id 1" in w["warning"]
    assert "estimated" in w["warning"]
    assert _load(tmp_path / "out" / "frames" / "000001.json")["warnings"] == [w["warning"]]


# ------------------------------------------------------------------------------ whole-input errors
def _bop_copy(bop, tmp_path, damage):
    src = tmp_path / "scene"
    shutil.copytree(bop[0], src)
    damage(src)
    return src


def _folder_copy(folder, tmp_path, damage=None):
    src = tmp_path / "in"
    shutil.copytree(folder, src)
    if damage is not None:
        damage(src)
    return src


def _scene_doc(**doc):
    def damage(d):
        base = _load(d / "scene.json")
        base.update(doc)
        (d / "scene.json").write_text(json.dumps(base))

    return damage


def _two_stems(d):
    shutil.copy(d / "f0.ply", d / "f0.pcd")


def _hyp_class(name):
    def damage(s):
        doc = _load(s / "hypotheses.json")
        doc["1"][0]["class"] = name
        (s / "hypotheses.json").write_text(json.dumps(doc))

    return damage


def _fifo_scene_json(d):
    (d / "scene.json").unlink()
    os.mkfifo(d / "scene.json")


INPUT_ERRORS = [
    ("missing-folder", lambda f, b, t: t / "nope", InputError, ("nope", "does not exist")),
    ("input-is-a-file", lambda f, b, t: f / "f0.ply", InputError, ("f0.ply", "not a folder")),
    ("no-frames", lambda f, b, t: t, InputError, ("no frames",)),
    ("two-clouds-one-name", lambda f, b, t: _folder_copy(f, t, _two_stems), InputError,
     ("f0.ply", "f0.pcd", "one frame name")),
    ("scene-json-invalid", lambda f, b, t: _folder_copy(f, t, lambda d: (d / "scene.json")
     .write_text("{oops")), InputError, ("scene.json", "invalid JSON")),
    ("scene-json-unknown-key", lambda f, b, t: _folder_copy(f, t, _scene_doc(stamp=1)),
     InputError, ("scene.json", "'stamp'", "did you mean 'stamps'")),
    ("scene-json-fifo", lambda f, b, t: _folder_copy(f, t, _fifo_scene_json), InputError,
     ("scene.json", "FIFO")),
    ("stamps-decrease", lambda f, b, t: _folder_copy(f, t, _scene_doc(stamps={"f0": 2.0,
     "f2": 1.0})), InputError, ("scene.json", "earlier")),
    ("stamp-nan", lambda f, b, t: _folder_copy(f, t, _scene_doc(stamps={"f0": 0.0,
     "f2": float("nan")})), InputError, ("scene.json", "finite")),
    ("classes-unknown", lambda f, b, t: _folder_copy(f, t, _scene_doc(classes={"1": "cubbe"})),
     InputError, ("scene.json", "'cubbe'", "not in the library", "did you mean 'cube'")),
    ("bop-no-hypotheses-given", lambda f, b, t: _bop_copy(b, t, lambda s:
     (s / "hypotheses.json").unlink()), InputError, ("hypotheses.json", "--hypotheses given")),
    ("bop-scene-gt-invalid", lambda f, b, t: _bop_copy(b, t, lambda s: (s / "scene_gt.json")
     .write_text("{")), InputError, ("scene_gt.json", "invalid JSON")),
    ("bop-scene-camera-invalid", lambda f, b, t: _bop_copy(b, t, lambda s: (s /
     "scene_camera.json").write_text("{")), InputError, ("scene_camera.json", "invalid JSON")),
    ("bop-class-not-in-library", lambda f, b, t: _bop_copy(b, t, lambda s: (s / "models.json")
     .write_text(json.dumps({"obj_ids": {"1": "anvil", "2": "anvil2"}}))), InputError,
     ("scene_gt.json", "not in the library", "anvil")),
    ("bop-hypothesis-class-not-in-library", lambda f, b, t: _bop_copy(b, t, _hyp_class("mugg")),
     InputError, ("hypotheses.json", "not in the library", "mugg")),
]  # fmt: skip


@pytest.mark.parametrize("case", INPUT_ERRORS, ids=lambda c: c[0])
def test_unusable_input_is_a_typed_error_naming_the_file(case, lib, folder, bop, tmp_path):
    name, make, error, needles = case
    src = make(folder, bop, tmp_path)
    mode = "given" if name.startswith("bop-no-hyp") else "auto"
    with pytest.raises(error) as err:
        run(src, lib, tmp_path / "out", hypotheses=mode)
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))


@pytest.mark.parametrize("mode", ["auto", "given", "estimated"])
def test_colour_map_naming_an_unknown_class_is_checked_in_every_mode(mode, lib, folder, tmp_path):
    src = _folder_copy(folder, tmp_path)
    doc = _load(src / "scene.json")
    doc["colors"] = {"#ff0000": "cube", "#00ff00": "mugg"}
    (src / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        run(src, lib, tmp_path / "out", hypotheses=mode)
    for needle in ("scene.json", "'#00ff00'", "'mugg'", "not in the library"):
        assert needle in str(err.value)


def test_colour_map_matching_no_colour_is_a_warning(lib, seq, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    f = seq.frame(0)
    colours = np.tile([[10, 20, 30]], (len(f.points), 1))
    write_cloud(src / "a.ply", f.points, colors=colours)
    _scene_json(src, seq, (), colors={"#ff0000": "cube"})
    doc = _load(src / "scene.json")
    del doc["stamps"]
    (src / "scene.json").write_text(json.dumps(doc))
    summary = run(src, lib, tmp_path / "out")
    assert len(summary.done) == 1 and summary.done[0]["objects"] == 0
    (w,) = _load(tmp_path / "out" / "summary.json")["warnings"]
    assert "a.ply" in w["warning"] and "no point has a colour" in w["warning"]
    assert "#0a141e" in w["warning"]  # the cloud's colour, to fix the map with
    assert _load(tmp_path / "out" / "frames" / "a.json")["warnings"] == [w["warning"]]


def test_bad_options_of_run(lib, folder, tmp_path):
    with pytest.raises(ArgumentError, match="must not contain '_'"):
        run(folder, lib, tmp_path / "o1", method="my_method")
    with pytest.raises(ArgumentError, match="hypotheses must be one of"):
        run(folder, lib, tmp_path / "o2", hypotheses="magic")
    with pytest.raises(UnknownObjectError, match="not in the library"):
        run(folder, lib, tmp_path / "o3", classes=["nosuch"])


# ------------------------------------------------------------------------------ Python API
def _api_bad(name: str, good: Frame) -> Frame:
    h0 = good.hypotheses[0]
    hyps = list(good.hypotheses)
    T_far = h0.T_world_obj.copy()
    T_far[:3, 3] = [100.0, 0.0, 0.0]
    edits = {
        "instance-id-int": lambda: replace(good, hypotheses=[replace(h0, instance_id=7), *hyps]),
        "class-as-list": lambda: replace(good, hypotheses=[replace(h0, class_name=["cube"])]),
        "hypotheses-none": lambda: replace(good, hypotheses=None),
        "dict-hypothesis": lambda: replace(good, hypotheses=[{"class": "cube", "T": np.eye(4)}]),
        "segment-text": lambda: replace(good, hypotheses=[replace(h0, segment="a")]),
        "points-n-by-2": lambda: replace(good, points=good.points[:, :2]),
        "labels-wrong-length": lambda: replace(good, labels=good.labels[:-1]),
        "stamp-nan": lambda: replace(good, stamp=float("nan")),
        "stamp-earlier": lambda: replace(good, stamp=-1.0),
        "camera-not-rigid": lambda: replace(good, T_world_cam=np.diag([2.0, 1, 1, 1])),
        "pose-nan": lambda: replace(good, hypotheses=[replace(h0, T_world_obj=np.full((4, 4),
                                                                                    np.nan))]),
        "score-inf": lambda: replace(good, hypotheses=[replace(h0, score=float("inf"))]),
        "unknown-class": lambda: replace(good, hypotheses=[replace(h0, class_name="anvil")]),
        "one-id-two-classes": lambda: replace(good, hypotheses=[
            replace(h0, class_name="cube", instance_id="x"),
            replace(h0, class_name="block", instance_id="x")]),
        "hypothesis-100m-away": lambda: replace(good, hypotheses=[*hyps, replace(h0,
                                                                   T_world_obj=T_far)]),
        "segments-not-a-mapping": lambda: replace(good, segments=[good.points]),
    }  # fmt: skip
    return edits[name]()


API_CASES = [
    ("instance-id-int", ("instance_id", "7", "'7'")),
    ("class-as-list", ("hypothesis 0", "class_name", "list")),
    ("hypotheses-none", ("hypotheses must be a list", "NoneType")),
    ("dict-hypothesis", ("hypothesis 0", "Hypothesis", "dict")),
    ("segment-text", ("segment", "'a'")),
    ("points-n-by-2", ("(N, 3)",)),
    ("labels-wrong-length", ("labels must have shape",)),
    ("stamp-nan", ("stamp", "finite")),
    ("stamp-earlier", ("earlier",)),
    ("camera-not-rigid", ("camera pose",)),
    ("pose-nan", ("invalid pose", "hypothesis 0")),
    ("score-inf", ("score", "finite")),
    ("unknown-class", ("'anvil'", "unknown object class")),
    ("one-id-two-classes", ("'x'", "two classes", "'cube'", "'block'")),
    ("hypothesis-100m-away", ("100.0 m", "outlier")),
    ("segments-not-a-mapping", ("segments must be a mapping",)),
]


@pytest.fixture(scope="module")
def api_ref(lib, seq):
    """parse_sequence over frames 0 and 1 (with a later stamp): estimates and the state."""
    frames = [seq.frame(0), replace(seq.frame(1), stamp=2.0)]
    parser = SceneParser(lib)
    results = list(parse_sequence(parser, frames))
    assert all(isinstance(e, SceneEstimate) for _, e in results)
    return frames, [_strip(e.to_dict()) for _, e in results], parser.state()


@pytest.mark.parametrize("case", API_CASES, ids=lambda c: c[0])
def test_bad_python_frame_is_a_frame_error_and_the_sequence_goes_on(case, lib, seq, api_ref):
    name, needles = case
    (f0, f1), estimates, state = api_ref
    bad = _api_bad(name, replace(seq.frame(1), stamp=1.0))
    parser = SceneParser(lib)
    results = list(parse_sequence(parser, [f0, bad, f1]))
    err = results[1][1]
    assert isinstance(err, FrameError), repr(err)
    for needle in needles:
        assert needle in str(err), (needle, str(err))
    if name == "hypothesis-100m-away":
        assert "millimetres" not in str(err)
    assert [_strip(results[k][1].to_dict()) for k in (0, 2)] == estimates
    assert parser.state() == state


def test_parse_sequence_contains_a_bug_in_one_frame(lib, api_ref, monkeypatch):
    (f0, f1), estimates, state = api_ref
    parser = SceneParser(lib)
    real = ssp.parser.run_stages
    calls = []

    def buggy(ctx, stages):
        calls.append(ctx.frame.stamp)
        if ctx.frame.stamp == 1.5:
            raise ZeroDivisionError("a bug")
        return real(ctx, stages)

    monkeypatch.setattr(ssp.parser, "run_stages", buggy)
    results = list(parse_sequence(parser, [f0, replace(f1, stamp=1.5), f1]))
    assert isinstance(results[1][1], ZeroDivisionError)
    assert [_strip(results[k][1].to_dict()) for k in (0, 2)] == estimates
    assert parser.state() == state


# ------------------------------------------------------------------------------ bounded work
@pytest.mark.parametrize("n", [20_000, 60_000])
def test_many_identical_points_cluster_with_bounded_work(n, monkeypatch):
    """A sensor that writes invalid pixels as one point: clustering stays linear (the old
    radius graph had n^2 / 2 pairs: 1.8e9 for 60k, a MemoryError)."""
    rng = np.random.default_rng(0)
    blob = rng.normal([0.1, 0.0, 0.05], 0.01, (3000, 3))
    pts = np.vstack([blob, np.tile([[0.3, 0.3, 0.3]], (n, 1))])
    sizes = []
    real = segmentation.cKDTree

    class Spy(real):
        def query_pairs(self, *a, **kw):
            out = super().query_pairs(*a, **kw)
            sizes.append(len(out))
            return out

    monkeypatch.setattr(segmentation, "cKDTree", Spy)
    labels = segmentation.euclidean_clusters(pts, tolerance=0.006, min_points=30)
    assert (labels[3000:] == labels[3000]).all() and labels[3000] >= 0  # the copies: one cluster
    assert len(set(labels[:3000][labels[:3000] >= 0])) >= 1
    assert max(sizes) < 3001 * 200  # pairs of the distinct points only


def test_a_dense_cloud_is_clustered_on_a_grid_within_the_pair_budget(monkeypatch):
    monkeypatch.setattr(segmentation, "MAX_PAIRS", 20_000)
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 0.01, (4000, 3))  # every point within ~1.7 cm of every other
    b = a + [0.1, 0, 0]
    labels = segmentation.euclidean_clusters(np.vstack([a, b]), tolerance=0.006, min_points=30)
    assert len(set(labels[:4000])) == 1 and len(set(labels[4000:])) == 1
    assert labels[0] != labels[4000] and labels.min() >= 0


def test_an_unlabelled_cloud_with_many_identical_points_is_processed(lib, seq, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    f = seq.frame(2)
    pts = np.vstack([f.points, np.tile(seq.T_world_cam[:3, 3], (20_000, 1))])  # at the camera
    write_cloud(src / "a.ply", pts)
    write_hypotheses(src / "a.hypotheses.json", seq.frames[2].hypotheses)
    _scene_json(src, seq, ())
    doc = _load(src / "scene.json")
    del doc["stamps"]
    (src / "scene.json").write_text(json.dumps(doc))
    summary = run(src, lib, tmp_path / "out", hypotheses="given")
    assert len(summary.done) == 1 and summary.done[0]["objects"] >= 2


# ------------------------------------------------------------------------------ config files
CONFIG_CASES = [
    ("settle-inf", "search:\n  settle_with_forces: .inf\n",
     ("search.settle_with_forces", "finite")),
    ("timestep-nan", "physics:\n  timestep: .nan\n", ("physics.timestep", "finite")),
    ("offset-minus-inf", "support:\n  offset: -.inf\n", ("support.offset", "finite")),
    ("solimp-inf", "physics:\n  solimp: [0.9, .inf, 0.001, 0.5, 2]\n",
     ("physics.solimp[1]", "finite")),
    ("typo", "physics:\n  time_step: 0.01\n", ("physics.time_step", "unknown setting",
     "did you mean 'physics.timestep'")),
    ("wrong-section", "physics:\n  settle_with_forces: 0.2\n",
     ("physics.settle_with_forces", "did you mean 'search.settle_with_forces'")),
    ("section-typo", "serch:\n  reach: 0.02\n", ("serch", "did you mean 'search'")),
    ("wrong-type", "physics:\n  timestep: fast\n", ("physics.timestep", "'fast'")),
    ("out-of-range", "physics:\n  timestep: -1\n", ("physics.timestep", "greater than 0")),
    ("top-level-list", "- a\n- b\n", ("mapping",)),
    ("invalid-yaml", "physics: [unclosed\n", ("not valid YAML",)),
]  # fmt: skip


@pytest.mark.parametrize("case", CONFIG_CASES, ids=lambda c: c[0])
def test_bad_config_is_one_readable_line_naming_the_field(case, tmp_path):
    name, text, needles = case
    path = tmp_path / "ssp.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert str(path) in msg
    for needle in needles:
        assert needle in msg, (needle, msg)
    assert "pydantic" not in msg and "type=" not in msg and len(msg.splitlines()) == 1


def test_several_config_problems_are_one_line_each(tmp_path):
    path = tmp_path / "ssp.yaml"
    path.write_text("physics:\n  timestep: .inf\n  time_step: 1\nsearch:\n  reach: -1\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    lines = str(err.value).splitlines()
    assert "3 problems" in lines[0] and len(lines) == 4
    assert any("physics.timestep" in ln for ln in lines)
    assert any("search.reach" in ln for ln in lines)


def test_non_utf8_config_file(tmp_path):
    path = tmp_path / "ssp.yaml"
    path.write_bytes("physics:\n  timestep: 0.005 # r\xe9glage\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="not UTF-8") as err:
        load_config(path)
    assert str(path) in str(err.value)


def test_config_that_is_a_folder(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path)


# ------------------------------------------------------------------------------ CLI options
def _cli(*args) -> tuple[int, str]:
    r = cli.invoke(app, [str(a) for a in args])
    return r.exit_code, " ".join(r.output.split())


def test_cli_method_with_underscore(folder, tmp_path):
    code, out = _cli("run", folder, "--out", tmp_path / "o", "--method", "my_method")
    assert code == 1 and "must not contain '_'" in out and "'mymethod'" in out
    assert "Traceback" not in out


def test_cli_unknown_hypotheses_mode(folder, tmp_path):
    code, out = _cli("run", folder, "--out", tmp_path / "o", "--hypotheses", "magic")
    assert code == 2 and "auto, given, estimated" in out


def test_cli_unknown_class(folder, tmp_path):
    code, out = _cli("run", folder, "--out", tmp_path / "o", "--classes", "anvil")
    assert code == 1 and "not in the library" in out and "Traceback" not in out


def test_cli_missing_input_and_no_input(tmp_path):
    code, out = _cli("run", tmp_path / "nope", "--out", tmp_path / "o")
    assert code == 1 and "does not exist" in out
    code, out = _cli("run", "--out", tmp_path / "o")
    assert code == 2 and "missing INPUT" in out


def test_cli_non_utf8_config(folder, tmp_path):
    bad = tmp_path / "c.yaml"
    bad.write_bytes(b"seed: 1 # \xff\n")
    code, out = _cli("run", folder, "--out", tmp_path / "o", "--config", bad)
    assert code == 1 and "not UTF-8" in out and "Traceback" not in out


def test_cli_non_finite_config(folder, tmp_path):
    bad = tmp_path / "c.yaml"
    bad.write_text("search:\n  settle_with_forces: .inf\n")
    code, out = _cli("run", folder, "--out", tmp_path / "o", "--config", bad)
    assert code == 1 and "search.settle_with_forces" in out and "finite" in out
    assert not (tmp_path / "o").exists()  # rejected before anything ran


def test_cli_dump_config_to_an_unwritable_place(tmp_path):
    (tmp_path / "file").write_text("x")
    code, out = _cli("dump-config", "--out", tmp_path / "file" / "c.yaml")
    assert code == 1 and "cannot write" in out and "Traceback" not in out


def test_cli_out_folder_with_other_files_is_refused(folder, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, msg = _cli("run", folder, "--out", out)
    assert code == 1 and "not empty" in msg and "new or empty --out" in msg
    assert (out / "notes.txt").read_text() == "mine"


def test_cli_resume_of_a_folder_without_a_run(tmp_path):
    code, out = _cli("run", "--resume", tmp_path)
    assert code == 1 and "nothing to resume" in out


def test_cli_resume_with_another_config_is_refused(lib, folder, folder_ref, tmp_path):
    out = tmp_path / "o"
    shutil.copytree(folder_ref, out)
    other = tmp_path / "c.yaml"
    other.write_text("search:\n  reach: 0.03\n")
    code, msg = _cli("run", "--resume", out, "--config", other)
    assert code == 1 and "cannot resume" in msg and "search.reach 0.02 -> 0.03" in msg


def test_existing_out_keeps_no_stale_frames(lib, seq, folder, tmp_path):
    """A second run into a used --out is refused (suggesting --resume or --overwrite);
    --overwrite clears the old run's files, so a frame that fails now has no old result."""
    src = _folder_copy(folder, tmp_path)
    out = tmp_path / "o"
    assert len(run(src, lib, out, hypotheses="given").done) == 2
    with pytest.raises(ArgumentError, match="--overwrite"):
        run(src, lib, out, hypotheses="given")
    (src / "f2.hypotheses.json").write_text("{oops")
    (src / "f0.ply").unlink()
    (src / "f0.hypotheses.json").unlink()
    _scene_json(src, seq, ("f2",))
    summary = run(src, lib, out, hypotheses="given", overwrite=True)
    assert [f["frame"] for f in summary.failed] == ["f2"] and not summary.done
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["f2.json"]
    assert _load(out / "frames" / "f2.json")["status"] == "failed"
    assert len(_csv_rows(out)) == 1  # the header only


# ------------------------------------------------------------------------- streaming, baselines
def test_inputs_are_read_frame_by_frame(lib, folder, bop, tmp_path, monkeypatch):
    """Neither reader reads a frame before the previous one is parsed and written."""
    from ssp.io.bop import BopScene
    from ssp.io.folder import FolderInput

    loaded = []
    for cls in (FolderInput, BopScene):
        real = cls.load
        monkeypatch.setattr(cls, "load", lambda self, k, *a, real=real, **kw: loaded.append(k)
                            or real(self, k, *a, **kw))  # fmt: skip
    seen: list[int] = []
    for src, name in ((folder, "f"), (bop[0], "b")):
        loaded.clear()
        seen.clear()
        run(src, lib, tmp_path / name, progress=lambda done, total, m: seen.append(len(loaded)))
        assert seen == list(range(1, len(seen) + 1)) and len(seen) >= 2


def test_unexpected_errors_are_logged_with_their_traceback(lib, folder, tmp_path, monkeypatch,
                                                           caplog):  # fmt: skip
    from ssp.perception.pipeline import Perception

    def bug(self, points, **kw):
        raise TypeError("a bug")

    monkeypatch.setattr(Perception, "from_points", bug)
    run(folder, lib, tmp_path / "out", hypotheses="given")
    records = [r for r in caplog.records if r.levelname == "ERROR" and r.exc_info]
    assert len(records) == 2 and "TypeError" in records[0].getMessage()


def test_ssp_baseline_contains_a_bug_in_one_frame(lib, api_ref, monkeypatch):
    from ssp.eval.baselines import SSPMethod

    (f0, f1), _, _ = api_ref
    method = SSPMethod(lib)
    first = method.update(f0)
    assert first
    monkeypatch.setattr(ssp.parser, "run_stages", lambda ctx, stages: 1 / 0)
    again = method.update(f1)  # answered with the previous output
    assert [(d.class_name, d.T_world_obj.tolist()) for d in again] == [
        (d.class_name, d.T_world_obj.tolist()) for d in first
    ]
