"""Symmetries: closure into a group, models.yaml forms, approximate detection (issue 15 item 8)."""

from __future__ import annotations

import json
from pathlib import Path

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


LMO = Path(__file__).parents[1] / ".." / "shared" / "data" / "lmo-megapose"


def _bop_turn(deg: float, axis=(0, 0, 1), offset_mm=(10.0, -20.0, 0.0)) -> list[float]:
    """A models_info ``symmetries_discrete`` entry (mm): ``deg`` about ``axis`` through
    ``offset_mm``, written with six decimals as BOP publishes them."""
    T = sym.rotation_transform(axis, deg, offset_mm)
    return [round(float(x), 6) for x in T.ravel()]


@pytest.mark.parametrize("deg", [179.81, 178.47, 181.2])
def test_published_near_half_turns_snap_to_the_half_turn_with_a_warning(deg, caplog):
    """LM-O's eggbox (179.81 deg) and glue (178.47 deg) stopped ssp refine (issue 30)."""
    info = {"diameter": 100.0, "symmetries_discrete": [_bop_turn(deg)]}
    with caplog.at_level("WARNING", logger="ssp.library.symmetry"):
        s = Symmetry.from_bop(info, scale=1e-3, name="models_info.json: obj_id 10")
    assert len(s.discrete) == 2 and not s.approximate
    half = sym.rotation_transform([0, 0, 1], 180, [0.010, -0.020, 0.0])
    assert np.allclose(s.discrete[1], half, atol=1e-9)  # the exact element, same axis line
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    shown = min(deg, 360 - deg)  # 181.2 about z is 178.8 about -z
    assert len(said) == 1 and "obj_id 10" in said[0] and f"{shown:.2f} deg" in said[0]
    assert "half turn" in said[0]


def test_near_quarter_turn_snaps_and_rounding_is_silent(caplog):
    with caplog.at_level("WARNING", logger="ssp.library.symmetry"):
        four = Symmetry.from_bop({"symmetries_discrete": [_bop_turn(90.6)]}, scale=1e-3)
        assert len(four.discrete) == 4
        assert any("90.60 deg" in r.getMessage() for r in caplog.records)
        caplog.clear()
        # 60 degrees with six digits (0.866025): rounding, an exact group without a word
        six = Symmetry.from_bop({"symmetries_discrete": [_bop_turn(60.0)]}, scale=1e-3)
    assert len(six.discrete) == 6 and not caplog.records


@pytest.mark.parametrize("deg", [172.3456, 37.1234, 100.1234])
def test_turns_far_from_every_finite_group_are_still_errors(deg):
    with pytest.raises(ModelError, match=rf"obj_id 3: discrete symmetry 1 turns by {deg:.2f}.*"
                       "finite group"):  # fmt: skip
        Symmetry.from_bop({"symmetries_discrete": [_bop_turn(deg)]}, 1e-3, name="obj_id 3")


def test_screw_and_reflection_are_errors():
    screw = np.array(_bop_turn(180.0)).reshape(4, 4)
    screw[2, 3] = 30.0  # 30 mm along the axis: a screw motion
    with pytest.raises(ModelError, match="screw motion"):
        Symmetry.from_bop({"diameter": 100.0, "symmetries_discrete": [screw.ravel().tolist()]})
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ModelError, match="not a rigid transform"):
        Symmetry.from_bop({"symmetries_discrete": [mirror.ravel().tolist()]})


def test_near_elements_about_slightly_different_axes_load_as_listed(caplog):
    """A 4-fold axis listed as three elements whose axes differ by half a degree: no exact
    group, but one within the tolerance: used as listed (as the BOP toolkit does)."""
    axes = [(0, 0, 1), (0.008, 0, 1), (0, 0.008, 1)]
    info = {"diameter": 100.0, "symmetries_discrete": [
        _bop_turn(d, a) for d, a in zip((90.0, 180.0, 270.0), axes, strict=True)]}  # fmt: skip
    with caplog.at_level("WARNING", logger="ssp.library.symmetry"):
        s = Symmetry.from_bop(info, scale=1e-3, name="obj_id 7")
    assert s.approximate and 4 <= len(s.discrete) <= 8
    assert any("obj_id 7" in r.getMessage() and "within" in r.getMessage()
               for r in caplog.records)  # fmt: skip


def test_models_yaml_near_half_turn_loads(tmp_path, caplog):
    """The same tolerance for models.yaml's generators (symmetries, symmetries_discrete)."""
    trimesh.creation.box((0.04, 0.04, 0.02)).export(tmp_path / "tile.stl")
    (tmp_path / "models.yaml").write_text(
        "objects:\n  tile:\n    symmetries: ['rotate 179.5 about z']\n"
    )
    with caplog.at_level("WARNING", logger="ssp.library.symmetry"):
        from ssp.library.properties import read_folder

        (entry,) = read_folder(tmp_path)
    assert len(entry.symmetry.discrete) == 2
    assert any("179.50 deg" in r.getMessage() for r in caplog.records)


@pytest.mark.skipif(not LMO.is_dir(), reason="needs ../shared/data/lmo-megapose")
def test_published_lmo_models_info_loads(caplog):
    """What ssp refine --models loads from LM-O's published models_info.json."""
    from ssp.library.properties import read_bop_models

    with caplog.at_level("WARNING", logger="ssp.library.symmetry"):
        entries = {e.name: e for e in read_bop_models(LMO / "models")}
    assert len(entries) == 8
    for name in ("obj_000010", "obj_000011"):
        d = entries[name].symmetry.discrete
        assert len(d) == 2 and np.allclose(d[1] @ d[1], np.eye(4), atol=1e-12)
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "179.81 deg" in said and "178.47 deg" in said
    info = json.loads((LMO / "models" / "models_info.json").read_text())
    caplog.clear()
    with caplog.at_level("WARNING", logger="ssp.library.symmetry"):
        Symmetry.from_bop(info["10"], 1e-3, name="models_info.json: obj_id 10")
    assert "obj_id 10" in caplog.records[0].getMessage()
