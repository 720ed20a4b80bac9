"""Symmetries: closure into a group, models.yaml forms, approximate detection (issue 15 item 8)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from ssp.cli import app
from ssp.config import LibraryConfig
from ssp.errors import ModelError
from ssp.library import ObjectLibrary, Symmetry, prepare_folder
from ssp.library import symmetry as sym


def cfg(tmp_path) -> LibraryConfig:
    c = LibraryConfig(cache_dir=tmp_path / "cache")
    c.decomposition.iou_samples = 20_000
    return c


def hex_prism_with_key(key: float = 0.001) -> trimesh.Trimesh:
    """A tapered hexagonal prism (axis x, 60 mm long, 30 to 22 mm across corners) with a
    ``key`` m high key on one flat: 6-fold symmetric within about ``key``, exactly only under
    the identity; its half turns about y and z are far off (the taper)."""
    ang = 2 * np.pi * np.arange(6) / 6

    def ring(r):
        return np.stack([np.zeros(6), r * np.cos(ang), r * np.sin(ang)], axis=1)

    prism = trimesh.convex.convex_hull(
        np.vstack([ring(0.015) + [-0.03, 0, 0], ring(0.011) + [0.03, 0, 0]])
    )
    h = key + 0.003
    nub = trimesh.creation.box((0.008, 0.004, h))
    nub.apply_translation((-0.02, 0.0, 0.01241 + key - h / 2))  # the flat is at z = 12.41 mm
    return trimesh.boolean.union([prism, nub], engine="manifold")


def test_two_generators_close_into_a_group_of_eight():
    """Two generators gave 3 symmetries instead of 8 (no warning)."""
    quarter_z = sym.rotation_transform([0, 0, 1], 90)
    half_x = sym.rotation_transform([1, 0, 0], 180)
    s = Symmetry(np.stack([np.eye(4), quarter_z, half_x]))
    assert len(s.discrete) == 8
    keys = {tuple(np.round(T, 9).ravel()) for T in s.discrete}
    assert all(tuple(np.round(A @ B, 9).ravel()) in keys for A in s.discrete for B in s.discrete)


def test_infinite_looking_closure_is_an_error_and_large_is_logged(caplog):
    with pytest.raises(ModelError, match="finite group"):
        sym.close_group([sym.rotation_transform([0, 0, 1], 37.1234)])
    with caplog.at_level("WARNING"):
        sym.close_group([sym.rotation_transform([0, 0, 1], 360 / 60)])  # 60 elements: large
    assert any("large group" in r.message for r in caplog.records)


def test_models_yaml_symmetry_forms(tmp_path):
    trimesh.creation.box((0.04, 0.04, 0.02)).export(tmp_path / "tile.stl")
    (tmp_path / "models.yaml").write_text(
        "objects:\n  tile:\n    symmetries: ['rotate 90 about z', {axis: [1, 0, 0], angle: 180}]\n"
    )
    tile = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["tile"]
    assert len(tile.symmetry.discrete) == 8
    # the same with BOP's 16-number form for the second generator
    (tmp_path / "models.yaml").write_text(
        "objects:\n  tile:\n    symmetries: ['rotate 90 about z']\n"
        "    symmetries_discrete: [[1,0,0,0, 0,-1,0,0, 0,0,-1,0, 0,0,0,1]]\n"
    )
    assert len(ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["tile"].symmetry.discrete) == 8
    (tmp_path / "models.yaml").write_text("objects:\n  tile:\n    symmetries: ['spin 90 z']\n")
    with pytest.raises(ModelError, match=r"objects\.tile\.symmetries.*rotate N about x\|y\|z"):
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))
    (tmp_path / "models.yaml").write_text(
        "objects:\n  tile:\n    symmetries: ['rotate 37.1234 about z']\n"
    )
    with pytest.raises(ModelError, match=r"models\.yaml: objects\.tile: .*finite group"):
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))


def test_detection_finds_approximate_six_fold_symmetry():
    mesh = hex_prism_with_key()
    props = mesh.mass_properties
    strict = sym.detect_symmetries(mesh, props["center_mass"], props["inertia"], 0.0005)
    loose = sym.detect_symmetries(mesh, props["center_mass"], props["inertia"], 0.001)
    assert len(loose.group) == 6 and len(strict.group) == 1
    axis = loose.axes[0]
    assert axis.order == 6 and axis.orders == (2, 3, 6) and abs(abs(axis.axis[0]) - 1) < 1e-3
    assert 0.0002 < axis.mssd <= 0.001
    assert json.dumps(loose.to_dict())  # plain types for --json


def test_detected_symmetry_is_used_only_on_opt_in_and_cached(tmp_path):
    hex_prism_with_key().export(tmp_path / "hexbar.stl")
    (tmp_path / "models.yaml").write_text(
        "objects:\n  hexbar: {symmetry: {detect: false, tolerance: 0.001}}\n"
    )
    m = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["hexbar"]
    assert len(m.symmetry.discrete) == 1 and len(m.detected_symmetry.group) == 6
    (tmp_path / "models.yaml").write_text(
        "objects:\n  hexbar: {symmetry: {detect: true, tolerance: 0.001}}\n"
    )
    m = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["hexbar"]
    assert len(m.symmetry.discrete) == 6
    assert any(p.name.startswith("sym-") for p in (tmp_path / "cache" / "hulls").iterdir())
    rows = prepare_folder(tmp_path, cfg(tmp_path))
    assert rows[0]["symmetries"] == 6 and rows[0]["detected_symmetries"]["discrete_symmetries"] == 6


def test_models_show_lists_detected_symmetries(tmp_path):
    hex_prism_with_key().export(tmp_path / "hexbar.stl")
    r = CliRunner().invoke(
        app,
        [
            "models",
            "show",
            "hexbar",
            str(tmp_path),
            "--json",
            "--tolerance",
            "0.001",
            "--cache",
            str(tmp_path / "c"),
        ],
    )
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    det = info["detected_symmetries"]
    assert det["discrete_symmetries"] == 6 and det["axes"][0]["order"] == 6
    assert info["discrete_symmetries"] == 1  # listed, not used (no opt-in)
