"""Object library: mesh validation, mass properties, samples, CoACD decomposition, models.yaml."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ssp.config import DecompositionConfig, LibraryConfig
from ssp.errors import (
    GeometryError,
    ModelError,
    ModelFileError,
    UnitsError,
    UnknownObjectError,
)
from ssp.library import ObjectLibrary, Symmetry, build_model, prepare_folder
from ssp.library import decomposition as decomposition_module
from ssp.library.decomposition import decompose, default_cache_dir, hull_iou
from ssp.library.mesh import load_convex_parts, load_mesh, validate_mesh
from ssp.library.properties import read_folder, read_properties
from ssp.library.sampling import interior_samples, surface_samples

BOX = (0.1, 0.05, 0.03)  # m


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    """One hull cache for the module (identical meshes decompose once)."""
    return tmp_path_factory.mktemp("hulls")


@pytest.fixture()
def config(cache_dir) -> LibraryConfig:
    return LibraryConfig(cache_dir=cache_dir)


def l_shape() -> trimesh.Trimesh:
    """A non-convex L (two boxes, 10 x 2 x 2 cm and 2 x 2 x 8 cm), watertight."""
    a = trimesh.creation.box([0.1, 0.02, 0.02])
    b = trimesh.creation.box([0.02, 0.02, 0.08])
    b.apply_translation([0.04, 0.0, 0.05])
    m = trimesh.boolean.union([a, b])
    assert m.is_watertight
    return m


def open_bowl() -> trimesh.Trimesh:
    """A sphere with its top cut away along a zigzag: a hole that is not planar."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    c = sphere.triangles_center
    zigzag = 0.01 * np.sign(np.sin(8 * np.arctan2(c[:, 1], c[:, 0])))
    return trimesh.Trimesh(sphere.vertices, sphere.faces[c[:, 2] < zigzag], process=False)


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> Path:
    mesh.export(path)
    return path


def write_parts_obj(path: Path, parts: list[trimesh.Trimesh]) -> Path:
    """An OBJ with one ``o`` object per part (global vertex numbering)."""
    lines, offset = [], 0
    for i, p in enumerate(parts):
        lines.append(f"o part_{i}")
        lines += [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in p.vertices]
        lines += [f"f {a + 1 + offset} {b + 1 + offset} {c + 1 + offset}" for a, b, c in p.faces]
        offset += len(p.vertices)
    path.write_text("\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------- loading errors


def test_load_missing_file(tmp_path):
    with pytest.raises(ModelFileError, match="not found"):
        load_mesh(tmp_path / "nope.obj")


def test_load_unreadable_files(tmp_path):
    (tmp_path / "text.obj").write_text("hello\nthis is not a mesh\n")
    with pytest.raises(ModelFileError, match="no triangles"):
        load_mesh(tmp_path / "text.obj")
    (tmp_path / "noise.ply").write_bytes(np.random.default_rng(0).bytes(300))
    with pytest.raises(ModelFileError, match="cannot read"):
        load_mesh(tmp_path / "noise.ply")


def test_load_scene_is_concatenated(tmp_path):
    a = trimesh.creation.box([0.02] * 3)
    b = trimesh.creation.box([0.02] * 3)
    b.apply_translation([0.05, 0, 0])
    path = tmp_path / "two.glb"
    trimesh.Scene([a, b]).export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 24


# --------------------------------------------------------------------------- validation errors


def test_mm_mesh_rejected_with_hint(config):
    mesh = trimesh.creation.box([182.0, 147.0, 116.0])  # a drill in millimetres
    with pytest.raises(UnitsError) as err:
        validate_mesh(mesh, "drill", config)
    msg = str(err.value)
    assert "182 m" in msg and "millimetres" in msg and "units: mm" in msg and "drill" in msg
    ok = validate_mesh(mesh, "drill", config, scale=0.001)
    assert np.allclose(ok.extents, [0.182, 0.147, 0.116])


def test_metre_mesh_with_mm_scale_rejected(config):
    mesh = trimesh.creation.box(BOX)
    with pytest.raises(UnitsError, match="already looks like it is in metres"):
        validate_mesh(mesh, "box", config, scale=0.001)


def test_nan_vertices_rejected(config):
    mesh = trimesh.creation.box(BOX)
    v = mesh.vertices.copy()
    v[3, 1] = np.nan
    bad = trimesh.Trimesh(v, mesh.faces, process=False)
    with pytest.raises(GeometryError, match="NaN"):
        validate_mesh(bad, "box", config)


def test_too_few_faces_rejected(config):
    bad = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(GeometryError, match="at least 4"):
        validate_mesh(bad, "tri", config)


def test_flat_mesh_rejected(config):
    box = trimesh.creation.box(BOX)
    v = box.vertices.copy()
    v[:, 2] = 0.0  # squash into a plane: closed but flat
    flat = trimesh.Trimesh(v, box.faces, process=False)
    with pytest.raises(GeometryError, match="flat or degenerate"):
        validate_mesh(flat, "sheet", config)


def test_zero_volume_rejected(config):
    # a closed surface folded onto itself (tilted so its bounding box is not flat)
    box = trimesh.creation.box(BOX)
    v = box.vertices.copy()
    v[:, 2] = 0.0
    R = trimesh.transformations.rotation_matrix(0.5, [1, 1, 0])[:3, :3]
    folded = trimesh.Trimesh(v @ R.T, box.faces, process=False)
    with pytest.raises(GeometryError, match="no volume|flat"):
        validate_mesh(folded, "folded", config)


def test_open_mesh_that_cannot_be_repaired(config):
    """A hole that is not planar stays open: an error."""
    with pytest.raises(GeometryError) as err:
        validate_mesh(open_bowl(), "bowl", config)
    msg = str(err.value)
    assert "not watertight" in msg and "boundary edges" in msg
    assert "undefined for an open surface" in msg and "in a plane" in msg


def test_missing_face_is_repaired(config):
    box = trimesh.creation.box(BOX)
    holed = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    assert not holed.is_watertight
    fixed = validate_mesh(holed, "box", config)
    assert fixed.is_watertight
    assert fixed.volume == pytest.approx(np.prod(BOX), rel=1e-9)


def test_flipped_winding_and_inverted_mesh_are_repaired(config):
    box = trimesh.creation.box(BOX)
    faces = box.faces.copy()
    faces[:3] = faces[:3, ::-1]
    flipped = trimesh.Trimesh(box.vertices, faces, process=False)
    assert not flipped.is_winding_consistent
    fixed = validate_mesh(flipped, "box", config)
    assert fixed.is_winding_consistent and fixed.volume == pytest.approx(np.prod(BOX))
    inverted = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    assert inverted.volume < 0
    fixed = validate_mesh(inverted, "box", config)
    assert fixed.volume == pytest.approx(np.prod(BOX))
    # outward normals: face normals point away from the centre
    assert np.all(np.einsum("ij,ij->i", fixed.face_normals, fixed.triangles_center) > 0)


def test_multibody_mesh_accepted(config):
    a = trimesh.creation.box([0.02] * 3)
    b = trimesh.creation.box([0.02] * 3)
    b.apply_translation([0.05, 0, 0])
    b.invert()  # one inside-out body is fixed on its own
    two = trimesh.util.concatenate([a, b])
    fixed = validate_mesh(two, "pair", config)
    assert fixed.volume == pytest.approx(2 * 0.02**3)


def test_cavity_body_is_kept_inward(config):
    outer = trimesh.creation.box([0.04] * 3)
    inner = trimesh.creation.box([0.02] * 3)
    inner.invert()  # a cavity: inward normals are correct
    shell = trimesh.util.concatenate([outer, inner])
    fixed = validate_mesh(shell, "shell", config)
    assert fixed.volume == pytest.approx(0.04**3 - 0.02**3)


# --------------------------------------------------------------------------- mass properties


def test_box_mass_properties_from_density(config):
    a, b, c = BOX
    m = build_model("box", trimesh.creation.box(BOX), config=config, density=1000.0)
    mass = 1000.0 * a * b * c
    assert m.mass == pytest.approx(mass)
    expected = np.diag([b * b + c * c, a * a + c * c, a * a + b * b]) * mass / 12
    np.testing.assert_allclose(m.inertia, expected, atol=1e-12 * mass)
    np.testing.assert_allclose(m.center_of_mass, 0.0, atol=1e-12)
    assert m.friction == config.default_friction
    assert m.decomposition.n_parts == len(m.convex_parts) >= 1


def test_mass_given_and_offset_centre_of_mass(config):
    a, b, c = BOX
    mesh = trimesh.creation.box(BOX)
    mesh.apply_translation([0.02, -0.01, 0.005])
    m = build_model("box", mesh, config=config, mass=0.5, friction=0.3)
    assert m.mass == 0.5 and m.friction == 0.3
    np.testing.assert_allclose(m.center_of_mass, [0.02, -0.01, 0.005], atol=1e-12)
    expected = np.diag([b * b + c * c, a * a + c * c, a * a + b * b]) * 0.5 / 12
    np.testing.assert_allclose(m.inertia, expected, rtol=1e-9, atol=1e-15)
    assert m.density == pytest.approx(0.5 / (a * b * c))


def test_default_density_and_property_errors(config):
    m = build_model("box", trimesh.creation.box(BOX), config=config)
    assert m.mass == pytest.approx(config.default_density * np.prod(BOX))
    with pytest.raises(ModelError, match="not both"):
        build_model("box", trimesh.creation.box(BOX), config=config, mass=1.0, density=500)
    with pytest.raises(ModelError, match="mass must be positive"):
        build_model("box", trimesh.creation.box(BOX), config=config, mass=-1.0)
    with pytest.raises(ModelError, match="friction"):
        build_model("box", trimesh.creation.box(BOX), config=config, friction=float("nan"))


# --------------------------------------------------------------------------- samples


def test_surface_samples_spacing_and_normals():
    mesh = trimesh.creation.box(BOX)
    spacing = 0.004
    pts, normals = surface_samples(mesh, spacing, 20_000, seed=0)
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    assert abs(np.median(nn) - spacing) < 0.3 * spacing
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", normals, pts) > 0)  # outward (box centred at 0)
    assert np.all(np.abs(mesh.nearest.signed_distance(pts[:200])) < 1e-9)
    pts2, _ = surface_samples(mesh, spacing, 20_000, seed=0)
    np.testing.assert_array_equal(pts, pts2)  # deterministic
    capped, _ = surface_samples(mesh, spacing, 300, seed=0)
    assert len(capped) <= 300


def test_surface_normals_outward_on_sphere():
    sphere = trimesh.creation.icosphere(3, 0.04)
    pts, normals = surface_samples(sphere, 0.003, 20_000, seed=1)
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", normals, radial) > 0.95)


def test_interior_samples_inside_and_uniform():
    mesh = l_shape()
    spacing = 0.004
    pts = interior_samples(mesh, spacing, 10_000)
    assert len(pts) > 100 and mesh.contains(pts).all()
    # a regular grid: every point's nearest neighbour is one step away
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    np.testing.assert_allclose(nn, spacing, rtol=1e-6)
    assert len(pts) == pytest.approx(mesh.volume / spacing**3, rel=0.3)
    np.testing.assert_array_equal(pts, interior_samples(mesh, spacing, 10_000))
    capped = interior_samples(mesh, spacing, 200)
    assert 50 < len(capped) <= 200 and mesh.contains(capped).all()


def test_interior_samples_strictly_inside_box_and_thin_plate():
    pts = interior_samples(trimesh.creation.box(BOX), 0.01, 4000)
    assert np.all(np.abs(pts) < np.array(BOX) / 2 - 1e-6)
    plate = trimesh.creation.box([0.006, 0.006, 0.0015])  # smaller than the grid step
    pts = interior_samples(plate, 0.004, 4000)
    assert len(pts) >= 32 and plate.contains(pts).all()


# --------------------------------------------------------------------------- decomposition


def _counted(monkeypatch, module, names: tuple[str, ...]) -> list[str]:
    """The names of ``module``'s functions ``names`` in the order they are called from now."""
    calls: list[str] = []
    for name in names:
        real = getattr(module, name)

        def counted(*args, _real=real, _name=name, **kwargs):
            calls.append(_name)
            return _real(*args, **kwargs)

        monkeypatch.setattr(module, name, counted)
    return calls


def test_coacd_nonconvex_cached_and_identical(cache_dir, monkeypatch):
    mesh = l_shape()
    cfg = DecompositionConfig(iou_samples=50_000)
    work = _counted(monkeypatch, decomposition_module, ("_run_coacd", "hull_iou"))
    parts, info = decompose(mesh, cfg, cache_dir / "coacd")
    assert info.method == "coacd" and not info.cached and info.note == ""
    assert len(parts) > 1 and info.n_parts == len(parts)
    assert info.iou > 0.85
    assert all(p.is_convex and p.is_watertight and p.volume > 1e-9 for p in parts)
    assert work == ["_run_coacd", "hull_iou"]
    parts2, info2 = decompose(mesh, cfg, cache_dir / "coacd")
    assert work == ["_run_coacd", "hull_iou"]  # a cache hit: neither CoACD nor the IoU again
    assert info2.cached and info2.seconds == 0.0 and info2.iou == info.iou
    assert len(parts2) == len(parts)
    for p, q in zip(parts, parts2, strict=True):
        np.testing.assert_array_equal(p.vertices, q.vertices)
        np.testing.assert_array_equal(p.faces, q.faces)


def test_hull_iou_known_values():
    box = trimesh.creation.box([0.04, 0.04, 0.04])
    assert hull_iou(box, [box], 20_000, seed=0) == pytest.approx(1.0, abs=1e-3)
    half = trimesh.creation.box([0.02, 0.04, 0.04])
    half.apply_translation([0.01, 0, 0])
    assert hull_iou(box, [half], 40_000, seed=0) == pytest.approx(0.5, abs=0.02)


def test_coacd_failure_falls_back_to_convex_hull(tmp_path):
    """A memory cap too small to even start the worker: both CoACD runs fail."""
    mesh = l_shape()
    cfg = DecompositionConfig(memory_limit_gb=0.02, iou_samples=20_000)
    parts, info = decompose(mesh, cfg, tmp_path)
    assert info.method == "convex-hull" and len(parts) == 1
    assert "coacd (threshold 0.05) failed" in info.note
    assert "coacd-coarse (threshold 0.1) failed" in info.note
    assert "out of memory" in info.note
    assert info.iou < 0.8  # the hull fills the L's concavity
    # with a larger cap the cached fallback is not reused
    parts, info = decompose(mesh, DecompositionConfig(iou_samples=20_000), tmp_path)
    assert info.method == "coacd" and not info.cached


def test_coacd_crash_then_coarse_retry(tmp_path, monkeypatch):
    """The first worker dies of a signal (as on a CoACD segfault); the coarse retry succeeds."""
    real = decomposition_module._worker_argv
    calls = []

    def flaky(in_path, out_path):
        calls.append(in_path)
        if len(calls) == 1:
            return [sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"]
        return real(in_path, out_path)

    monkeypatch.setattr(decomposition_module, "_worker_argv", flaky)
    parts, info = decompose(l_shape(), DecompositionConfig(iou_samples=20_000), tmp_path)
    assert len(calls) == 2
    assert info.method == "coacd-coarse" and len(parts) >= 1
    assert "killed by signal 11" in info.note


def test_coacd_timeout_is_a_failure(tmp_path, monkeypatch):
    """A worker still running at ``timeout_s`` is killed, not waited for: it never gets to the
    end of its 30 s (both runs, CoACD and its coarse retry, time out)."""
    started, finished = tmp_path / "started", tmp_path / "finished"
    worker = (
        "import os, pathlib, time; "
        f"pathlib.Path({str(started)!r}).write_text(str(os.getpid())); "
        f"time.sleep(30); pathlib.Path({str(finished)!r}).write_text('too late')"
    )
    monkeypatch.setattr(
        decomposition_module, "_worker_argv", lambda i, o: [sys.executable, "-c", worker]
    )
    cfg = DecompositionConfig(timeout_s=0.5, iou_samples=5_000)
    parts, info = decompose(l_shape(), cfg, tmp_path / "cache")
    assert info.method == "convex-hull" and "timed out after 0.5 s" in info.note
    assert not finished.exists()  # killed before its end (waiting would take 30 s and write it)
    pid = started.read_text() if started.exists() else ""  # it may not even have started
    if pid:
        with pytest.raises(ProcessLookupError):  # and reaped, not left running
            os.kill(int(pid), 0)


def test_default_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("SSP_CACHE_DIR", str(tmp_path / "env"))
    assert default_cache_dir(LibraryConfig()) == tmp_path / "env" / "hulls"
    assert default_cache_dir(LibraryConfig(cache_dir=tmp_path / "c")) == tmp_path / "c" / "hulls"
    monkeypatch.delenv("SSP_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir(None) == tmp_path / "xdg" / "ssp" / "hulls"


# --------------------------------------------------------------------------- models.yaml


def test_models_yaml_units_parts_symmetries(tmp_path, config):
    mm = trimesh.creation.box([40.0, 20.0, 20.0])  # millimetres
    write_mesh(tmp_path / "bar.obj", mm)
    half_a = trimesh.creation.box([20.0, 20.0, 20.0])
    half_a.apply_translation([-10.0, 0, 0])
    half_b = half_a.copy()
    half_b.apply_translation([20.0, 0, 0])
    write_parts_obj(tmp_path / "bar.parts.obj", [half_a, half_b])
    (tmp_path / "models.yaml").write_text(
        """
units: mm
defaults: {density: 500, friction: 0.7}
objects:
  bar:
    convex_parts: bar.parts.obj
    friction: 0.4
    symmetries_discrete:
      - [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0,  0, 0, 0, 1]
      - [-1, 0, 0, 0,  0, -1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]
    symmetries_continuous: [{axis: [1, 0, 0], offset: [5, 0, 0]}]
"""
    )
    entries = read_folder(tmp_path)
    assert [e.name for e in entries] == ["bar"]  # the parts file is not a model
    lib = ObjectLibrary.from_folder(tmp_path, config)
    bar = lib["bar"]
    np.testing.assert_allclose(bar.extents, [0.04, 0.02, 0.02])
    assert bar.mass == pytest.approx(500 * 0.04 * 0.02 * 0.02)
    assert bar.friction == 0.4
    assert bar.decomposition.method == "given" and len(bar.convex_parts) == 2
    assert bar.decomposition.iou > 0.97
    # the half turns about x and z generate the half turn about y too: a group of 4
    assert len(bar.symmetry.discrete) == 4 and len(bar.symmetry.continuous) == 1
    np.testing.assert_allclose(bar.symmetry.continuous[0].offset, [0.005, 0, 0])
    assert bar.source == (tmp_path / "bar.obj").resolve()


def test_models_yaml_typo_rejected(tmp_path):
    (tmp_path / "models.yaml").write_text("objects:\n  drill:\n    frction: 0.5\n")
    with pytest.raises(ModelError) as err:
        read_properties(tmp_path / "models.yaml")
    msg = str(err.value)
    assert "models.yaml" in msg and "objects.drill.frction" in msg and "'friction'" in msg


def test_models_yaml_bad_values_rejected(tmp_path):
    path = tmp_path / "models.yaml"
    path.write_text("objects:\n  drill: {mass: 1.0, density: 700}\n")
    with pytest.raises(ModelError, match="objects.drill: give mass or density, not both"):
        read_properties(path)
    path.write_text("units: inch\n")
    with pytest.raises(ModelError, match="units"):
        read_properties(path)
    path.write_text("objects:\n  a: {symmetries_discrete: [[1, 0, 0]]}\n")
    with pytest.raises(ModelError, match="16"):
        read_properties(path)
    path.write_text("objects: [unclosed\n")
    with pytest.raises(ModelFileError, match="not valid YAML"):
        read_properties(path)


def test_models_yaml_missing_mesh_and_unlisted_mesh(tmp_path, config):
    write_mesh(tmp_path / "cube.stl", trimesh.creation.box([0.03] * 3))
    (tmp_path / "models.yaml").write_text(
        "defaults: {friction: 0.6}\nobjects:\n  ghost: {mesh: ghost.obj, mass: 1}\n"
    )
    with pytest.raises(ModelFileError, match=r"objects\.ghost\.mesh: file not found: ghost\.obj"):
        ObjectLibrary.from_folder(tmp_path, config)
    report = prepare_folder(tmp_path, config)
    rows = {r["name"]: r for r in report}
    assert "ghost.obj" in rows["ghost"]["error"]
    assert rows["cube"]["error"] is None and rows["cube"]["n_parts"] >= 1


def test_folder_without_yaml(tmp_path, config):
    write_mesh(tmp_path / "cube.obj", trimesh.creation.box([0.03] * 3))
    write_mesh(tmp_path / "ell.ply", l_shape())
    seen = []
    lib = ObjectLibrary.from_folder(tmp_path, config, progress=seen.append)
    assert sorted(lib.names) == ["cube", "ell"] and sorted(seen) == ["cube", "ell"]
    assert lib["cube"].mass == pytest.approx(config.default_density * 0.03**3)
    assert lib["ell"].decomposition.n_parts > 1


def test_prepare_folder_reports_bad_model_and_continues(tmp_path, config):
    write_mesh(tmp_path / "a_tube.obj", open_bowl())
    write_mesh(tmp_path / "b_big.obj", trimesh.creation.box([200.0, 100.0, 50.0]))
    write_mesh(tmp_path / "c_ell.obj", l_shape())
    report = prepare_folder(tmp_path, config)
    rows = {r["name"]: r for r in report}
    assert "not watertight" in rows["a_tube"]["error"]
    assert "units: mm" in rows["b_big"]["error"]
    good = rows["c_ell"]
    assert good["error"] is None and good["method"] == "coacd" and good["n_parts"] > 1
    assert good["iou"] > 0.85 and isinstance(good["cached"], bool)
    with pytest.raises(GeometryError):
        ObjectLibrary.from_folder(tmp_path, config)


def test_convex_parts_from_groups_and_components(tmp_path):
    a = trimesh.creation.box([0.02] * 3)
    b = a.copy()
    b.apply_translation([0.05, 0, 0])
    parts = load_convex_parts(write_parts_obj(tmp_path / "p.obj", [a, b]))
    assert len(parts) == 2
    parts = load_convex_parts(write_mesh(tmp_path / "p.stl", trimesh.util.concatenate([a, b])))
    assert len(parts) == 2


# --------------------------------------------------------------------------- library


def test_library_mapping(config):
    box = build_model("box", trimesh.creation.box(BOX), config=config)
    ell = build_model("ell", l_shape(), config=config, symmetry=Symmetry())
    lib = ObjectLibrary([box, ell])
    assert len(lib) == 2 and list(lib) == ["box", "ell"] and lib.names == ("box", "ell")
    assert "box" in lib and "nope" not in lib and lib["ell"] is ell
    with pytest.raises(UnknownObjectError) as err:
        lib["bxo"]
    assert "known classes: box, ell" in str(err.value) and "'box'" in str(err.value)
    with pytest.raises(ModelError, match="two models"):
        ObjectLibrary([box, box])
    assert box.surface_points.flags.writeable is False


def test_convexity_excess_is_zero_only_for_convex_models(lib):
    """``ObjectModel.convexity_excess``: no surface sample of the cube or the block lies below
    another sample's tangent plane by more than rounding, so ``evidence`` may skip their
    self-occlusion test; a mallet's head stands far above the tangent planes of its handle."""
    assert lib["cube"].convexity_excess < 1e-9
    assert lib["block"].convexity_excess < 1e-9
    assert lib["mallet"].convexity_excess > 0.05
