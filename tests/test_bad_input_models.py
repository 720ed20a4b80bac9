"""Bad-input matrix, object models (issue 16): every case asserts a typed error whose message
names the file and the problem, or the documented repaired / skipped outcome (docs/models.md).
Each test makes its own meshes."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from ssp.cli import app
from ssp.config import LibraryConfig
from ssp.errors import GeometryError, ModelError, ModelFileError
from ssp.library import ObjectLibrary, build_model
from ssp.library import decomposition as dec
from ssp.library.mesh import load_mesh
from ssp.library.sampling import surface_samples

BOX = (0.04, 0.03, 0.02)


def cfg(tmp_path: Path) -> LibraryConfig:
    c = LibraryConfig(cache_dir=tmp_path / "cache")
    c.decomposition.iou_samples = 20_000
    return c


def obj_text(mesh: trimesh.Trimesh, header: str = "") -> str:
    lines = [header] if header else []
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return "\n".join(lines) + "\n"


def bent_tube(sections: int = 12, rings: int = 16) -> tuple[trimesh.Trimesh, float]:
    """A mug handle: a 12-sided tube bent through 180 degrees, both ends open (two planar
    12-edge holes); and the volume of the same tube with its ends closed."""
    r_tube, r_bend = 0.006, 0.03
    verts = []
    for i in range(rings):
        a = np.pi * i / (rings - 1)
        centre = np.array([r_bend * np.cos(a), 0.0, r_bend * np.sin(a)])
        radial = np.array([np.cos(a), 0.0, np.sin(a)])
        for k in range(sections):
            b = 2 * np.pi * k / sections
            verts.append(centre + r_tube * (np.cos(b) * radial + np.sin(b) * np.array([0, 1, 0])))
    faces = []
    for i in range(rings - 1):
        for k in range(sections):
            a, b = i * sections + k, i * sections + (k + 1) % sections
            c, d = a + sections, b + sections
            faces += [[a, c, b], [b, c, d]]
    open_tube = trimesh.Trimesh(np.array(verts), np.array(faces), process=False)
    caps = []
    n = len(verts)
    verts2 = np.vstack(
        [verts, np.mean(verts[:sections], axis=0), np.mean(verts[-sections:], axis=0)]
    )
    for k in range(sections):
        caps.append([n, (k + 1) % sections, k])
        last = (rings - 1) * sections
        caps.append([n + 1, last + k, last + (k + 1) % sections])
    closed = trimesh.Trimesh(verts2, np.vstack([faces, caps]), process=False)
    trimesh.repair.fix_normals(closed)
    return open_tube, abs(float(closed.volume))


# --------------------------------------------------------------------------- cases


def _box_with_bad_vertex(value: str) -> str:
    """The OBJ text of a box whose fourth vertex has ``value`` as its x coordinate."""
    box = trimesh.creation.box(BOX)
    lines = obj_text(box).splitlines()
    lines[3] = f"v {value} " + " ".join(lines[3].split()[2:])
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_non_finite_vertex_is_rejected_naming_file_and_count(tmp_path, value):
    """A NaN vertex was dropped and its hole filled (volume 25 instead of 30 cm^3)."""
    (tmp_path / "badbox.obj").write_text(_box_with_bad_vertex(value))
    with pytest.raises(GeometryError) as err:
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))
    msg = str(err.value)
    assert "badbox.obj" in msg and "1 of 8 vertices" in msg and "NaN or infinite" in msg
    assert "does not drop vertices" in msg


def case_latin1_comment(tmp_path, monkeypatch, caplog):
    box = trimesh.creation.box(BOX)
    data = b"# mod\xe8le export\xe9 par l'atelier (Latin-1)\n" + obj_text(box).encode()
    (tmp_path / "box.obj").write_bytes(data)
    model = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["box"]
    assert model.volume == pytest.approx(np.prod(BOX), rel=1e-9)


def case_planar_holes_of_a_mug_handle(tmp_path, monkeypatch, caplog):
    handle, closed_volume = bent_tube()
    assert not handle.is_watertight
    (tmp_path / "handle.obj").write_text(obj_text(handle))
    # (one hull: this case is about the holes, not the decomposition)
    (tmp_path / "models.yaml").write_text(
        "objects:\n  handle: {decomposition: {mode: convex-hull}}\n"
    )
    with caplog.at_level(logging.WARNING, logger="ssp.library.mesh"):
        model = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["handle"]
    assert model.mesh.is_watertight
    assert model.volume == pytest.approx(closed_volume, rel=0.01)
    assert any(
        "handle.obj" in r.message and "filled 2 planar hole(s)" in r.message for r in caplog.records
    )


def case_hole_that_is_not_planar(tmp_path, monkeypatch, caplog):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    c = sphere.triangles_center
    zigzag = 0.01 * np.sign(np.sin(8 * np.arctan2(c[:, 1], c[:, 0])))
    bowl = trimesh.Trimesh(sphere.vertices, sphere.faces[c[:, 2] < zigzag], process=False)
    (tmp_path / "bowl.obj").write_text(obj_text(bowl))
    with pytest.raises(GeometryError) as err:
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))
    assert "bowl.obj" in str(err.value) and "not watertight" in str(err.value)


def _duck() -> trimesh.Trimesh:
    duck = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    duck.apply_scale([0.825, 0.6, 0.55])  # 1.65 m long
    return duck


def case_unscaled_duck_is_warned(tmp_path, monkeypatch, caplog):
    _duck().export(tmp_path / "duck.stl")
    with caplog.at_level(logging.WARNING, logger="ssp.library.build"):
        model = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["duck"]
    assert model.extents.max() == pytest.approx(1.65, rel=0.01)
    msg = " ".join(r.message for r in caplog.records)
    assert "duck.stl" in msg and "1.65 m" in msg and "kg" in msg and "scale" in msg


def case_duck_scaled_in_models_yaml(tmp_path, monkeypatch, caplog):
    _duck().export(tmp_path / "duck.stl")
    (tmp_path / "models.yaml").write_text("objects:\n  duck: {mesh: duck.stl, scale: 0.05}\n")
    with caplog.at_level(logging.WARNING, logger="ssp.library.build"):
        model = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["duck"]
    assert model.extents.max() == pytest.approx(0.0825, rel=0.01)
    assert model.mass < 1.0 and not caplog.records


def case_per_axis_scale_after_units(tmp_path, monkeypatch, caplog):
    trimesh.creation.box((40.0, 30.0, 20.0)).export(tmp_path / "box.stl")  # millimetres
    (tmp_path / "models.yaml").write_text("units: mm\nobjects:\n  box: {scale: [1, 2, 0.5]}\n")
    model = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))["box"]
    np.testing.assert_allclose(model.extents, [0.04, 0.06, 0.01], rtol=1e-9)


def case_bad_scale_value(tmp_path, monkeypatch, caplog):
    trimesh.creation.box(BOX).export(tmp_path / "box.stl")
    (tmp_path / "models.yaml").write_text("objects:\n  box: {scale: -1}\n")
    with pytest.raises(
        ModelError, match=r"(?s)models\.yaml.*objects\.box\.scale: scale must be positive"
    ):
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))


def case_non_uniform_scale_breaks_a_symmetry(tmp_path, monkeypatch, caplog):
    trimesh.creation.box((0.03, 0.03, 0.02)).export(tmp_path / "box.stl")
    (tmp_path / "models.yaml").write_text(
        "objects:\n  box: {scale: [1, 2, 1], symmetries: ['rotate 90 about z']}\n"
    )
    with pytest.raises(ModelError, match=r"models\.yaml: objects\.box: .*non-uniform scale"):
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))


def case_one_bad_mesh_leaves_the_folder_usable(tmp_path, monkeypatch, caplog):
    trimesh.creation.box(BOX).export(tmp_path / "good.stl")
    (tmp_path / "broken.obj").write_text("this is not a mesh\n")
    with pytest.raises(ModelFileError, match=r"broken\.obj"):
        ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))
    lib = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path), on_error="skip")
    assert lib.names == ("good",) and "broken.obj" in lib.skipped["broken"]
    r = CliRunner().invoke(app, ["models", "list", str(tmp_path), "--cache", str(tmp_path / "c")])
    assert r.exit_code == 0 and "good" in r.output and "skipped" in r.output
    assert "broken.obj" in r.output
    assert any((tmp_path / "c" / "hulls").glob("*.npz"))  # --cache is where the hulls went


def case_block_world_names_in_a_user_folder_are_tools(tmp_path, monkeypatch, caplog):
    from ssp.sim.generate import generate_sequence

    trimesh.creation.box((0.05, 0.04, 0.03)).export(tmp_path / "cube.stl")
    trimesh.creation.box((0.08, 0.03, 0.03)).export(tmp_path / "node.stl")
    lib = ObjectLibrary.from_folder(tmp_path, cfg(tmp_path))
    seq = generate_sequence(
        "isolated", 0, lib, stages=1, objects_per_stage=2, stride=16, frames_per_stage=1
    )
    assert sorted(seq.models) == ["cube", "node"]


def case_structure_experiment_without_cube_and_block(tmp_path, monkeypatch, caplog):
    trimesh.creation.box(BOX).export(tmp_path / "widget.stl")
    r = CliRunner().invoke(
        app,
        [
            "simulate",
            "--experiment",
            "structure",
            "--models",
            str(tmp_path),
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert r.exit_code != 0 and "Traceback" not in r.output
    flat = " ".join(r.output.split())  # rich wraps the message at the terminal width
    assert "'cube' or 'block'" in flat and len(r.output.strip().splitlines()) < 12


def case_sampler_shortfall_names_the_model(tmp_path, monkeypatch, caplog):
    bar = trimesh.creation.box((0.2, 0.004, 0.004))
    with caplog.at_level(logging.INFO):
        points, _ = surface_samples(bar, 0.003, 20_000, 0, name="thin_bar")
    assert not any("only got" in r.getMessage() for r in caplog.records)
    assert any(
        "'thin_bar'" in r.getMessage() and "surface samples" in r.getMessage()
        for r in caplog.records
    )


def case_reexported_mesh_hits_the_hull_cache(tmp_path, monkeypatch, caplog):
    runs = []
    ell = trimesh.boolean.union(
        [
            trimesh.creation.box((0.1, 0.02, 0.02)),
            trimesh.creation.box(
                (0.02, 0.02, 0.06), trimesh.transformations.translation_matrix((0.04, 0, 0.04))
            ),
        ],
        engine="manifold",
    )

    def fake(mesh, *args, **kwargs):
        runs.append(1)
        return [(np.asarray(m.vertices), np.asarray(m.faces)) for m in ell.split()] or [
            (ell.vertices, ell.faces)
        ]

    monkeypatch.setattr(dec, "_run_coacd", fake)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    ell.export(tmp_path / "a" / "ell.obj")
    moved = ell.copy()
    moved.apply_translation((0.25, 0.1, -0.05))  # re-centred elsewhere, re-exported as STL
    moved.export(tmp_path / "b" / "ell.stl")
    c = cfg(tmp_path)
    first = ObjectLibrary.from_folder(tmp_path / "a", c)["ell"]
    second = ObjectLibrary.from_folder(tmp_path / "b", c)["ell"]
    assert len(runs) == 1 and not first.decomposition.cached and second.decomposition.cached


def case_huge_mesh_is_decimated_with_bounded_memory(tmp_path, monkeypatch, caplog):
    import tracemalloc

    ball = trimesh.creation.icosphere(subdivisions=6, radius=0.05)  # 81920 faces
    c = cfg(tmp_path)
    c.max_mesh_faces = 10_000
    tracemalloc.start()
    try:
        with caplog.at_level(logging.WARNING, logger="ssp.library.mesh"):
            model = build_model("ball", ball, config=c, source=Path("ball.ply"))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(model.mesh.faces) <= 10_000 and peak < 300 * 2**20
    assert any("ball.ply" in r.message and "81920 faces" in r.message for r in caplog.records)


def case_missing_mesh_file_names_it(tmp_path, monkeypatch, caplog):
    with pytest.raises(ModelFileError, match=r"nope\.obj"):
        load_mesh(tmp_path / "nope.obj")


CASES = [v for k, v in dict(globals()).items() if k.startswith("case_")]


@pytest.mark.parametrize("case", CASES, ids=[c.__name__[5:] for c in CASES])
def test_bad_model_input(case, tmp_path, monkeypatch, caplog):
    case(tmp_path, monkeypatch, caplog)
