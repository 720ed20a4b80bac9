"""``ssp.eval.table1``: the physics columns, the result schema and the written report."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ssp.config import SSPConfig
from ssp.eval.baselines import Detection
from ssp.eval.table1 import DEFAULT_METHODS, PhysicsCheck, run_table1, write_table1
from ssp.library import ObjectLibrary
from ssp.library.symmetry import Symmetry
from ssp.scene import Hypothesis
from ssp.sim.frames import render_scene
from ssp.sim.render import add_depth_noise, look_at
from ssp.sim.sequence import SimFrame, SimSequence

EDGE = 0.0508
T_WORLD_CAM = look_at([0.3, -0.35, 0.45], [0.0, 0.0, 0.02])
STAT_KEYS = {"trans_mm_mean", "trans_mm_std", "rot_deg_mean", "rot_deg_std"}


def pose(x=0.0, y=0.0, z=EDGE / 2, yaw_deg=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


@pytest.fixture(scope="module")
def lib(make_box) -> ObjectLibrary:
    R = Rotation.create_group("O").as_matrix()
    S = np.tile(np.eye(4), (len(R), 1, 1))
    S[:, :3, :3] = R
    cube = make_box("cube", (EDGE,) * 3, 0.09)
    pts, faces = trimesh.sample.sample_surface_even(cube.mesh, 1500, seed=0)
    cube = dataclasses.replace(
        cube,
        surface_points=np.asarray(pts, dtype=float),
        surface_normals=np.asarray(cube.mesh.face_normals[faces], dtype=float),
        symmetry=Symmetry(S),
    )
    return ObjectLibrary([cube])


@pytest.fixture(scope="module")
def seq(lib) -> SimSequence:
    """Three frames of one static scene (two cubes side by side), 2 hypotheses per cube;
    the third frame is a second static scene with one cube slid by 3 cm."""
    rng = np.random.default_rng(0)
    gt0 = {"a": ("cube", pose(0.0, 0.0, yaw_deg=20)), "b": ("cube", pose(0.09, 0.04))}
    gt1 = {"a": gt0["a"], "b": ("cube", pose(0.09, 0.07))}
    frames = []
    for i, gt in enumerate((gt0, gt0, gt1)):
        r = render_scene(lib, gt, T_world_cam=T_WORLD_CAM, stride=2)
        hyps = []
        for _, T in gt.values():
            for j in range(2):
                H = T.copy()
                H[:3, 3] += rng.normal(0.0, 0.002, 3)
                hyps.append(Hypothesis("cube", H, score=1.0 - 0.5 * j))
        frames.append(
            SimFrame(
                index=i,
                stamp=float(i),
                gt=gt,
                depth=add_depth_noise(r.depth, rng).astype(np.float32),
                instance=r.instance.astype(np.int16),
                visib_fract={"a": 1.0, "b": 0.8},
                hypotheses=hyps,
                static_group=0 if i < 2 else 1,
            )
        )
    sources = [[iid for iid in f.gt for _ in range(2)] for f in frames]
    info = {"hypothesis_sources": sources}
    return SimSequence("structure", 7, r.camera, T_WORLD_CAM, frames, ("cube",), info)


def test_physics_check_penetration_and_support(lib):
    check = PhysicsCheck(lib, SSPConfig())
    assert check([]) == (0.0, 0)
    depth, bad = check([Detection("cube", pose())])  # resting on the table
    assert depth < 1e-4 and bad == 0
    depth, bad = check([Detection("cube", pose(z=EDGE / 2 + 0.005))])  # floating 5 mm
    assert bad == 1
    depth, bad = check([Detection("cube", pose(z=EDGE / 2 - 0.004))])  # sunk 4 mm
    assert depth == pytest.approx(0.004, abs=3e-4) and bad == 0
    # a cube on another one, but 3 mm into it
    stack = [Detection("cube", pose()), Detection("cube", pose(z=1.5 * EDGE - 0.003))]
    depth, bad = check(stack)
    assert depth == pytest.approx(0.003, abs=3e-4) and bad == 0
    # tipping: a cube resting on the edge of another, its centre well beyond it
    tip = [Detection("cube", pose()), Detection("cube", pose(x=0.045, z=1.5 * EDGE))]
    assert check(tip)[1] == 1


def test_run_table1_returns_the_schema(lib, seq):
    messages = []
    result = run_table1([seq], lib, SSPConfig(), progress=messages.append)
    assert len(messages) == 3
    assert result["protocol"] == "table1"
    assert result["experiment"] == "structure" and result["seed"] == 7
    assert result["sequences"] == 1 and result["frames"] == 3
    noise = result["induced_noise"]
    assert {"trans_mm_mean", "rot_deg_mean", "trans_mm_std", "rot_deg_std"} <= set(noise)
    assert noise["hypotheses"] == 12 and noise["outliers"] == 0
    assert 1.0 < noise["trans_mm_mean"] < 6.0 and noise["rot_deg_mean"] == pytest.approx(0.0)
    assert list(result["methods"]) == list(DEFAULT_METHODS)
    for name, d in result["methods"].items():
        assert set(d["accuracy"]) == STAT_KEYS, name
        assert set(d["precision"]) == STAT_KEYS, name
        assert d["accuracy"]["trans_mm_mean"] < 6.0, name
        assert d["precision"]["trans_mm_mean"] is not None, name  # frames 0-1: a static scene
        for key in ("max_penetration_mm", "unsupported_objects", "sec_per_frame"):
            assert isinstance(d[key], float) and d[key] >= 0.0, (name, key)
        assert d["sec_per_frame"] > 0
        assert d["matched"] + d["missed"] == 6
        rec = result["records"][name]
        assert len(rec["objects"]["trans_mm"]) == 6
        assert rec["objects"]["visib_fract"][:2] == [1.0, 0.8]
        assert len(rec["frames"]["penetration_mm"]) == 3
    # ssp's output is physically consistent: nothing floats, nothing sinks
    ssp = result["methods"]["ssp"]
    assert ssp["unsupported_objects"] == 0.0
    assert ssp["max_penetration_mm"] < 1.0
    json.dumps(result)  # JSON-ready


def test_run_table1_rejects_unknown_methods(lib, seq):
    with pytest.raises(ValueError, match="unknown methods"):
        run_table1([seq], lib, methods=("estimator", "magic"))


def test_write_table1_writes_the_report(lib, seq, tmp_path):
    result = run_table1([seq], lib, SSPConfig(), methods=("estimator", "temporal_filter"))
    paths = write_table1(result, tmp_path / "out")
    names = sorted(p.name for p in paths)
    assert names == [
        "error_over_frames.png",
        "error_vs_visibility.png",
        "results.json",
        "results.md",
    ]
    for p in paths:
        assert p.exists() and p.stat().st_size > 0
    loaded = json.loads((tmp_path / "out" / "results.json").read_text())
    assert loaded["methods"].keys() == result["methods"].keys()
    assert loaded["records"]["estimator"]["objects"]["trans_mm"] == pytest.approx(
        result["records"]["estimator"]["objects"]["trans_mm"]
    )
    md = (tmp_path / "out" / "results.md").read_text()
    assert "| hypotheses | Induced Noise |" in md
    assert "| estimator | Accuracy |" in md and "| temporal_filter | Precision |" in md
    assert "3.05 ± 1.11" in md and "2.49 ± 3.34" in md  # the paper's numbers


def test_run_table1_reports_the_tails_on_the_realistic_stream(tmp_path):
    from ssp.library import ObjectLibrary
    from ssp.sim.generate import generate_sequence
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    lib = ObjectLibrary.builtin()
    seq = generate_sequence(
        "structure", 5, lib, stages=2, frames_per_stage=1, stride=4,
        hypotheses=RealisticNoise(), realism=SceneRealism(events=("move",)),
    )  # fmt: skip
    methods = ("estimator", "temporal_filter", "icp_filter")
    result = run_table1([seq], lib, SSPConfig(), methods=methods)
    for name in methods:
        d = result["methods"][name]
        assert 0.0 <= d["bop"]["AR"] <= 1.0 and d["bop"]["targets"] > 0
        assert {"AR_VSD", "AR_MSSD", "AR_MSPD"} <= set(d["bop"])
        assert 0.0 <= d["gross_rate"] <= 1.0
        conds = d["gross_by_condition"]
        assert sum(v["object_frames"] for v in conds.values()) == sum(len(f.gt) for f in seq.frames)
        assert d["false_positives_per_frame"] == d["false_positives"] / len(seq)
        assert sum(d["false_object_causes"].values()) == d["false_positives"]
    assert result["methods"]["estimator"]["id_switches"] is None
    assert isinstance(result["methods"]["icp_filter"]["id_switches"], int)
    for name in methods:  # orientation flips of unmoved objects: counted, at most all
        d = result["methods"][name]
        assert 0 <= d["flips_from_right"] <= d["flips"] <= sum(len(f.gt) for f in seq.frames)
        assert d["static_spread"] is None  # one frame per static scene: no spread
    for name in methods:  # per class: every object-frame counted once, AR where targets
        pc = result["methods"][name]["per_class"]
        assert set(pc) == {c for f in seq.frames for c, _ in f.gt.values()}
        assert sum(v["object_frames"] for v in pc.values()) == sum(len(f.gt) for f in seq.frames)
        assert sum(v["gross"] for v in pc.values()) == result["methods"][name]["gross"]
        assert all(v["AR"] is None or 0.0 <= v["AR"] <= 1.0 for v in pc.values())
    write_table1(result, tmp_path)
    md = (tmp_path / "results.md").read_text()
    assert "Tails" in md and "nominal" in md  # the per-condition table
    assert "| cube |" in md and "Per class" in md


def test_the_static_spread_counts_object_scenes_within_2_mm_and_the_worst():
    from ssp.eval.table1 import _spread

    assert _spread([]) is None
    out = _spread([(0.4, 0.2), (1.99, 0.5), (2.0, 0.1), (23.0, 90.0)])
    assert out == {"object_scenes": 4, "within_2mm": 0.5, "worst_mm": 23.0, "worst_deg": 90.0}


def test_run_table1_without_masks_gives_bare_clouds():
    """``masks=False`` (``ssp bench table1 --masks none``): ssp gets the cloud's clusters, as
    ``ssp run --masks none`` does, and hypotheses without segments."""
    import typer

    from ssp.cli.experiments import _check_table1_options
    from ssp.library import ObjectLibrary
    from ssp.perception.segmentation import segment_cloud
    from ssp.sim.generate import generate_sequence
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    lib = ObjectLibrary.builtin()
    seq = generate_sequence(
        "isolated", 5, lib, stages=1, frames_per_stage=2, stride=4,
        hypotheses=RealisticNoise(), realism=SceneRealism(),
    )  # fmt: skip
    with_masks = seq.frame(0)
    assert with_masks.labels is not None
    assert any(h.segment is not None for h in with_masks.hypotheses)
    seen = []
    result = run_table1([seq], lib, SSPConfig(), methods=("ssp",), masks=False,
                        on_estimate=lambda s, i, frame, est: seen.append(frame))  # fmt: skip
    assert len(seen) == len(seq)
    assert all(f.label_kind == "cluster" and f.labels is not None for f in seen)
    pc = SSPConfig().perception
    clusters = segment_cloud(
        seen[0].points,
        None,
        table_height=pc.table_height,
        tolerance=pc.cluster_tolerance,
        min_points=pc.min_segment_points,
    )
    np.testing.assert_array_equal(seen[0].labels, clusters.labels)
    assert all(h.segment is None for f in seen for h in f.hypotheses)
    assert result["methods"]["ssp"]["matched"] > 0
    _check_table1_options("noisy", "realistic", "none")
    _check_table1_options("estimated", "realistic", "none")
    for bad in (("guessed", "realistic", "none"), ("noisy", "paper", "labels")):
        with pytest.raises(typer.BadParameter):
            _check_table1_options(*bad)


def test_estimated_hypotheses_without_masks_come_from_the_clusters():
    """``ssp bench table1 --hypotheses estimated --masks none``: the front end estimates on
    the cloud's clusters; the object records have no segment (their recall is over all the
    frame's hypotheses), each cluster has a record with its time and what it gave."""
    from ssp.eval.estimated import estimate_sequence, summarize_estimator
    from ssp.library import ObjectLibrary
    from ssp.sim.generate import generate_sequence

    lib = ObjectLibrary.builtin()
    seq = generate_sequence("structure", 3, lib, stages=1, frames_per_stage=1, stride=2)
    est, records = estimate_sequence(seq, lib, SSPConfig(), masks=False)
    objects = [r for r in records if r["object"] is not None]
    clusters = [r for r in records if r["object"] is None]
    assert len(objects) == len(seq.frames[0].gt) and clusters
    assert all(r["seconds"] is None and r["top1"] is None for r in objects)
    assert all(r["seconds"] > 0 and r["segment_points"] >= 30 for r in clusters)
    assert all(h.segment is None for h in est.frames[0].hypotheses)
    found = sum(r["objects_found"] for r in clusters)
    assert found >= len(seq.frames[0].gt) // 2
    summary = summarize_estimator(records)
    assert summary["segments"] == len(clusters) and summary["objects"] == len(objects)
    assert summary["top1_recall_visible"] is None and summary["recall"] > 0.5
    assert summary["objects_per_frame_mean"] == found
