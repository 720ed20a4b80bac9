"""Convex decomposition policy: parts chosen for physics quality, measured IoU, warnings, the
content-keyed cache, bounded memory (issues 15 item 1 and 16). CoACD is replaced by fakes that
return what it returned on the measured failures, so the tests stay fast."""

from __future__ import annotations

import logging
import re
import sys
import tracemalloc

import numpy as np
import pytest
import trimesh

from ssp.config import DecompositionConfig, LibraryConfig
from ssp.library import ObjectLibrary, build_model
from ssp.library import decomposition as dec
from ssp.library.decomposition import decompose, hull_iou

IOU = 20_000  # Monte Carlo points of the IoU checks here


def _no_coacd(*args, **kwargs):
    raise AssertionError("CoACD must not run for this mesh")


def fake_coacd(monkeypatch, parts: list[trimesh.Trimesh]) -> list[int]:
    """Make every CoACD run return ``parts``; returns the list of calls (one entry per run)."""
    calls: list[int] = []

    def run(*args, **kwargs):
        calls.append(1)
        return [(np.asarray(p.vertices), np.asarray(p.faces)) for p in parts]

    monkeypatch.setattr(dec, "_run_coacd", run)
    return calls


def grid_boxes(extents, center, n) -> list[trimesh.Trimesh]:
    """The box ``extents`` at ``center`` cut into n x n x n touching boxes (an over-split)."""
    e = np.asarray(extents, float)
    cells = []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                c = np.asarray(center) - e / 2 + e * (np.array([i, j, k]) + 0.5) / n
                cells.append(
                    trimesh.creation.box(e / n, trimesh.transformations.translation_matrix(c))
                )
    return cells


def rounded_box(size=0.057, radius=0.006, dent=0.0015) -> trimesh.Trimesh:
    """A rounded cube (hull of corner spheres) with a shallow round recess in every face, like
    the CoSTAR node: nearly convex (it fills about 98 % of its hull)."""
    h = size / 2 - radius
    ball = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    corners = [
        ball.vertices + [sx * h, sy * h, sz * h]
        for sx in (-1, 1)
        for sy in (-1, 1)
        for sz in (-1, 1)
    ]
    body = trimesh.convex.convex_hull(np.vstack(corners))
    cutters = []
    for axis in range(3):
        for sign in (-1, 1):
            c = trimesh.creation.cylinder(radius=0.012, height=2 * dent, sections=24)
            R = trimesh.geometry.align_vectors([0, 0, 1], np.eye(3)[axis])
            c.apply_transform(R)
            c.apply_translation(sign * (size / 2) * np.eye(3)[axis])
            cutters.append(c)
    out = trimesh.boolean.difference([body, *cutters], engine="manifold")
    assert out.is_watertight
    return out


def l_shape() -> trimesh.Trimesh:
    a = trimesh.creation.box([0.1, 0.02, 0.02])
    b = trimesh.creation.box([0.02, 0.02, 0.08])
    b.apply_translation([0.04, 0.0, 0.05])
    return trimesh.boolean.union([a, b], engine="manifold")


def staircase_shells() -> trimesh.Trimesh:
    """15 boxes of different sizes, each touching (overlapping by 0.5 mm) the next: one mesh
    of 15 separate convex shells (like the 15-shell teddy of issue 15)."""
    boxes, x = [], 0.0
    for i in range(15):
        w, d, h = 0.012 + 0.001 * (i % 3), 0.02 + 0.004 * (i % 4), 0.01 + 0.006 * (i % 5)
        boxes.append(
            trimesh.creation.box(
                (w, d, h), trimesh.transformations.translation_matrix((x + w / 2, 0, h / 2))
            )
        )
        x += w - 0.0005
    return trimesh.util.concatenate(boxes)


def bar_with_end_caps() -> trimesh.Trimesh:
    """A 24 cm bar, 2 cm square, with 5 cm cubes on its ends (the CoSTAR link's shape class)."""
    bar = trimesh.creation.box((0.02, 0.02, 0.24))
    caps = [
        trimesh.creation.box(
            (0.05, 0.05, 0.05), trimesh.transformations.translation_matrix((0, 0, s * 0.12))
        )
        for s in (-1, 1)
    ]
    return trimesh.boolean.union([bar, *caps], engine="manifold")


# --------------------------------------------------------------------------- policy classes


def test_nearly_convex_rounded_cube_is_one_hull_without_coacd(tmp_path, monkeypatch):
    """The 57 mm rounded node became 85 CoACD parts; nearly convex meshes are their hull."""
    monkeypatch.setattr(dec, "_run_coacd", _no_coacd)
    mesh = rounded_box()
    assert 0.96 < dec.convexity(mesh) < 0.995
    parts, info = decompose(mesh, DecompositionConfig(iou_samples=IOU), tmp_path)
    assert info.method == "convex" and len(parts) == 1 and info.n_parts == 1
    assert info.iou > 0.96 and "of its convex hull" in info.note


def test_over_split_parts_are_merged_back(tmp_path, monkeypatch):
    """CoACD's over-split (54 touching boxes of an L) is merged into the L's two arms."""
    a = grid_boxes([0.1, 0.02, 0.02], [0, 0, 0], 3)
    b = grid_boxes([0.02, 0.02, 0.08], [0.04, 0, 0.05], 3)
    fake_coacd(monkeypatch, a + b)
    parts, info = decompose(l_shape(), DecompositionConfig(iou_samples=IOU), tmp_path)
    assert info.method == "coacd" and len(parts) == 2
    assert info.iou > 0.98 and "merged 54 parts into 2" in info.note


def test_part_count_is_capped(tmp_path, monkeypatch):
    a = grid_boxes([0.1, 0.02, 0.02], [0, 0, 0], 3)
    b = grid_boxes([0.02, 0.02, 0.08], [0.04, 0, 0.05], 3)
    fake_coacd(monkeypatch, a + b)
    cfg = DecompositionConfig(iou_samples=IOU, max_parts=1)
    parts, info = decompose(l_shape(), cfg, tmp_path)
    assert len(parts) == 1 and info.iou < 0.8  # one hull: the L's concavity is filled


def test_union_of_convex_shells_uses_the_shells(tmp_path, monkeypatch):
    """15 touching convex shells ran CoACD for 2 x 900 s and fell back to a hull of IoU 0.45;
    they already are an exact decomposition."""
    monkeypatch.setattr(dec, "_run_coacd", _no_coacd)
    mesh = staircase_shells()
    assert mesh.body_count == 15
    parts, info = decompose(mesh, DecompositionConfig(iou_samples=IOU), tmp_path)
    assert info.method == "shells" and 8 <= len(parts) <= 15
    assert info.iou > 0.98


def test_low_iou_is_warned_in_the_log_and_the_info(tmp_path, caplog):
    """A coarse setting made the beam one hull of IoU 0.53 without a word."""
    cfg = LibraryConfig(cache_dir=tmp_path)
    cfg.decomposition.mode = "convex-hull"
    cfg.decomposition.iou_samples = IOU
    with caplog.at_level(logging.WARNING, logger="ssp.library.build"):
        model = build_model("beam", bar_with_end_caps(), config=cfg)
    d = model.decomposition
    assert d.method == "convex-hull" and d.iou < 0.6
    assert d.warnings and "IoU" in d.warnings[0] and "min_iou" in d.warnings[0]
    assert any("'beam'" in r.message and "IoU" in r.message for r in caplog.records)
    assert model.summary()["decomposition_warnings"] == list(d.warnings)


def test_good_decomposition_has_no_warning(tmp_path, monkeypatch):
    bar = trimesh.creation.box((0.02, 0.02, 0.19))
    caps = [
        trimesh.creation.box(
            (0.05,) * 3, trimesh.transformations.translation_matrix((0, 0, s * 0.12))
        )
        for s in (-1, 1)
    ]
    fake_coacd(monkeypatch, [bar, *caps])
    cfg = LibraryConfig(cache_dir=tmp_path)
    cfg.decomposition.iou_samples = IOU
    model = build_model("beam", bar_with_end_caps(), config=cfg)
    assert model.decomposition.method == "coacd" and len(model.convex_parts) == 3
    assert model.decomposition.iou > 0.98 and model.decomposition.warnings == ()


def test_user_supplied_parts_are_measured_and_warned(tmp_path):
    """Supplied parts were called "exact" whatever they covered."""
    cfg = LibraryConfig(cache_dir=tmp_path)
    cfg.decomposition.iou_samples = IOU
    arm = trimesh.creation.box([0.1, 0.02, 0.02])  # one arm of the L only
    model = build_model("ell", l_shape(), config=cfg, convex_parts=[arm])
    d = model.decomposition
    assert d.method == "given" and 0.5 < d.iou < 0.6 and d.warnings


def test_per_model_decomposition_settings_in_models_yaml(tmp_path):
    bar_with_end_caps().export(tmp_path / "beam.stl")
    rounded_box().export(tmp_path / "node.stl")
    (tmp_path / "models.yaml").write_text(
        "objects:\n  beam:\n    decomposition: {mode: convex-hull, min_iou: 0.4}\n"
        "  node:\n    decomposition: {convex_tolerance: 0.001, mode: convex-hull}\n"
    )
    lib = ObjectLibrary.from_folder(tmp_path, LibraryConfig(cache_dir=tmp_path / "c"))
    assert lib["beam"].decomposition.method == "convex-hull"
    assert lib["beam"].decomposition.warnings == ()  # min_iou 0.4 for this model only
    assert lib["node"].decomposition.method == "convex-hull"
    (tmp_path / "models.yaml").write_text("objects:\n  beam:\n    decomposition: {treshold: 0.1}\n")
    from ssp.errors import ModelError

    with pytest.raises(ModelError, match=r"objects.beam.decomposition.treshold.*'threshold'"):
        ObjectLibrary.from_folder(tmp_path, LibraryConfig(cache_dir=tmp_path / "c"))
    (tmp_path / "models.yaml").write_text("objects:\n  beam:\n    decomposition: {max_parts: 0}\n")
    with pytest.raises(ModelError, match=r"objects.beam.decomposition.max_parts"):
        ObjectLibrary.from_folder(tmp_path, LibraryConfig(cache_dir=tmp_path / "c"))


def test_merge_parts_is_bounded_by_the_tolerance():
    """Two boxes side by side merge (their hull is their union); an L's arms do not."""
    from ssp.library.decomposition import merge_parts

    a = trimesh.creation.box([0.02] * 3)
    b = a.copy()
    b.apply_translation([0.02, 0, 0])
    assert len(merge_parts([a, b], 0.04, 10)) == 1
    c = trimesh.creation.box([0.02, 0.02, 0.06])
    c.apply_translation([0.0, 0.0, 0.04])
    d = trimesh.creation.box([0.06, 0.02, 0.02])
    d.apply_translation([0.04, 0.0, 0.0])
    assert len(merge_parts([c, d], 0.04, 10)) == 2
    assert len(merge_parts([c, d], 0.04, 1)) == 1  # the cap forces it


# --------------------------------------------------------------------------- cache


def test_cache_survives_reexport_and_recentring(tmp_path, monkeypatch):
    """The key was the raw vertex bytes: a re-export or a re-centring reran CoACD."""
    mesh = l_shape()
    calls = fake_coacd(
        monkeypatch,
        [trimesh.creation.box([0.1, 0.02, 0.02])]
        + grid_boxes([0.02, 0.02, 0.08], [0.04, 0, 0.05], 1),
    )
    cfg = DecompositionConfig(iou_samples=IOU)
    parts, info = decompose(mesh, cfg, tmp_path)
    assert len(calls) == 1 and not info.cached
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(mesh.vertices))
    inverse = np.argsort(perm)
    noisy = mesh.vertices[perm] + rng.normal(0, 1e-9, (len(mesh.vertices), 3))
    shift = np.array([0.3, -0.2, 0.1])
    moved = trimesh.Trimesh(
        noisy + shift, inverse[mesh.faces][rng.permutation(len(mesh.faces))], process=False
    )
    parts2, info2 = decompose(moved, cfg, tmp_path)
    assert len(calls) == 1 and info2.cached and info2.n_parts == info.n_parts
    lo1 = np.min([p.bounds[0] for p in parts], axis=0)
    lo2 = np.min([p.bounds[0] for p in parts2], axis=0)
    np.testing.assert_allclose(lo2, lo1 + shift, atol=1e-7)
    # a different mesh with the same counts is not mistaken for it
    other = trimesh.Trimesh(mesh.vertices * [1, 1, 1.01], mesh.faces, process=False)
    decompose(other, cfg, tmp_path)
    assert len(calls) == 2


# --------------------------------------------------------------------------- progress, memory


def test_coacd_progress_reports_running_time(tmp_path):
    """While the worker runs, ``status`` gets its running time (about once a second). The
    worker here ends only once it has been reported on (exit 3 if it never is, in 30 s)."""
    reported = tmp_path / "reported"
    seen = []

    def status(text: str) -> None:
        seen.append(text)
        reported.touch()

    worker = (
        f"import pathlib, sys, time\np = pathlib.Path({str(reported)!r})\nt = time.monotonic()\n"
        "while not p.exists():\n"
        "    if time.monotonic() - t > 30:\n        sys.exit(3)\n"
        "    time.sleep(0.01)\n"
    )
    code, _ = dec._communicate(
        [sys.executable, "-c", worker],
        DecompositionConfig(timeout_s=120),
        2**33,
        ".",
        {},
        status,
        "CoACD (threshold 0.05)",
    )
    assert code == 0 and seen
    assert all(re.fullmatch(r"CoACD \(threshold 0\.05\): \d+ s \(cap 120 s\)", s) for s in seen)


def test_iou_of_a_many_facet_hull_has_bounded_memory():
    """The convex-hull fallback of a 5-million-face mesh allocated a samples x facets matrix
    (1.37 TiB); the checks are chunked (here 80k facets x 3000 points, 2 GB unchunked)."""
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=0.05)
    assert len(sphere.faces) > 80_000
    tracemalloc.start()
    try:
        iou = hull_iou(sphere, [sphere], n_samples=3000, seed=0)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert iou > 0.98
    assert peak < 200 * 2**20


def test_plane_tests_are_chunked(monkeypatch):
    """inside_convex never holds more than IOU_CHUNK_ENTRIES distances at once."""
    from ssp.library.decomposition import inside_convex

    hull = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    planes = np.hstack(
        [
            hull.face_normals,
            -np.einsum("ij,ij->i", hull.face_normals, hull.triangles[:, 0])[:, None],
        ]
    )
    pts = np.random.default_rng(0).uniform(-0.06, 0.06, (4000, 3))
    whole = inside_convex(pts, planes)
    monkeypatch.setattr(dec, "IOU_CHUNK_ENTRIES", 10 * len(planes))
    chunked = inside_convex(pts, planes)
    assert np.array_equal(whole, chunked) and 0.3 < whole.mean() < 0.4
    assert dec._chunk_rows(len(planes)) * len(planes) <= 10 * len(planes)


def test_huge_mesh_is_decimated_at_load(tmp_path, caplog):
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=0.05)
    cfg = LibraryConfig(cache_dir=tmp_path, max_mesh_faces=20_000)
    cfg.decomposition.iou_samples = IOU
    with caplog.at_level(logging.WARNING, logger="ssp.library.mesh"):
        model = build_model("ball", sphere, config=cfg)
    assert len(model.mesh.faces) <= 20_000 and model.mesh.is_watertight
    assert model.volume == pytest.approx(sphere.volume, rel=0.01)
    assert any("'ball'" in r.message and "decimated" in r.message for r in caplog.records)
    assert model.decomposition.method == "convex"
