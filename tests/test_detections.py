"""A detector's instance masks (BOP segmentation results) as a BOP scene's segmentation:
ssp.io.detections and ``--masks FILE`` of ssp run / ssp refine."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pycocotools import mask as mask_util
from typer.testing import CliRunner

from ssp.cli import app
from ssp.errors import ArgumentError, InputError
from ssp.io.bop import open_bop, read_png
from ssp.io.detections import (
    Detection,
    instance_labels,
    match_segments,
    read_detections,
    rle_counts,
)
from ssp.sim.bop import simulate_to_disk

runner = CliRunner()


def _rle(mask: np.ndarray) -> dict:
    rle = mask_util.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"counts": rle["counts"].decode(), "size": list(mask.shape)}


def _entry(scene_id, im_id, obj_id, score, mask, **extra) -> dict:
    return {"scene_id": scene_id, "image_id": im_id, "category_id": obj_id, "score": score,
            "bbox": [0, 0, 1, 1], "segmentation": _rle(mask), "time": 0.1, **extra}  # fmt: skip


def gt_detections(scene) -> list[dict]:
    """The scene's ground-truth visible masks as a detector's output (scores 0.9, 0.89, ...
    in scene_gt order)."""
    gt = json.loads((scene / "scene_gt.json").read_text())
    out = []
    for im, entries in gt.items():
        for j, e in enumerate(entries):
            m = read_png(scene / "mask_visib" / f"{int(im):06d}_{j:06d}.png") > 0
            if m.any():
                out.append(_entry(int(scene.name), int(im), e["obj_id"], 0.9 - 0.01 * j, m))
    return out


@pytest.fixture(scope="module")
def dataset(lib, tmp_path_factory):
    """A small structure dataset, the built-in estimator's CSV of it, and its ground-truth
    masks as a BOP segmentation results file."""
    from ssp.pipeline.refine import estimate

    tmp = tmp_path_factory.mktemp("detections")
    (scene,) = simulate_to_disk("structure", 1, 7, out_dir=tmp, library=lib, stages=2,
                                frames_per_stage=2, stride=4)  # fmt: skip
    est = tmp / "est_structure-test.csv"
    assert estimate(scene.parent.parent, lib, est)["rows"] > 0
    dets = tmp / "dets.json"
    dets.write_text(json.dumps(gt_detections(scene)))
    return scene, est, dets


# ------------------------------------------------------------------------------ the reader
def test_rle_counts_reads_pycocotools_strings():
    rng = np.random.default_rng(3)
    for t in range(60):
        h, w = rng.integers(1, 50, 2)
        m = rng.random((h, w)) < rng.random()
        m[:] = m if t % 7 else t % 2  # all empty and all full masks too
        runs = rle_counts(_rle(m)["counts"])
        assert sum(runs) == h * w and sum(runs[1::2]) == m.sum()
        d = Detection(0, 0, 0, 1, 1.0, None, (int(h), int(w)), tuple(runs))
        assert np.array_equal(d.mask(), m)  # the runs, decoded as an uncompressed RLE
    with pytest.raises(ValueError):
        rle_counts("a{")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[{", "invalid JSON"),
        ('{"a": 1}', "expected a list"),
        ("[]", "no detection"),
        ("[1]", "entry 0: expected an object"),
        ('[{"scene_id": 0, "image_id": 0, "obj_id": 1, "score": 1, "segmentation": {}}]',
         "entry 0: no 'category_id'"),
        ('[{"scene_id": 0, "image_id": "0", "category_id": 1, "score": 1, "segmentation": {}}]',
         "entry 0: 'image_id' must be"),
        ('[{"scene_id": 0, "image_id": 0, "category_id": 1, "score": NaN, "segmentation": {}}]',
         "'score' must be a finite number"),
        ('[{"scene_id": 0, "image_id": 0, "category_id": 1, "score": 1, "segmentation": []}]',
         "'segmentation' must be an RLE"),
        ('[{"scene_id": 0, "image_id": 0, "category_id": 1, "score": 1,'
         ' "segmentation": {"counts": "0", "size": [0, 4]}}]', "'size' must be"),
        ('[{"scene_id": 0, "image_id": 0, "category_id": 1, "score": 1,'
         ' "segmentation": {"counts": 3, "size": [2, 2]}}]', "'counts' must be"),
        ('[{"scene_id": 0, "image_id": 0, "category_id": 1, "score": 1, "bbox": [1, 2],'
         ' "segmentation": {"counts": [4], "size": [2, 2]}}]', "'bbox' must be"),
    ],
)  # fmt: skip
def test_a_malformed_file_is_an_input_error_naming_file_and_entry(tmp_path, text, match):
    p = tmp_path / "dets.json"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as err:
        read_detections(p)
    assert str(p) in str(err.value)


def test_bad_single_detections_are_skipped_named_and_counted(tmp_path):
    m = np.zeros((4, 6), bool)
    m[1:3, 2:4] = True
    entries = [
        _entry(1, 0, 5, 0.9, m),  # good
        _entry(1, 0, 9, 0.8, m),  # no model of obj_id 9
        _entry(1, 0, 5, 0.7, np.zeros((4, 6), bool)),  # empty
        _entry(1, 1, 5, 0.6, np.ones((3, 6), bool)),  # another size than the image
        _entry(1, 7, 5, 0.5, m),  # an image the scene does not have
        _entry(1, 1, 5, 0.1, m),  # below min_score
        _entry(2, 0, 5, 0.9, m),  # another scene
    ]
    entries.append(dict(entries[0], segmentation={"counts": "PPP", "size": [4, 6]}))
    p = tmp_path / "dets.json.gz"
    import gzip

    p.write_bytes(gzip.compress(json.dumps(entries).encode()))
    dets = read_detections(p)
    assert dets.scenes() == [1, 2] and len(dets.entries) == 8
    sizes = {0: (4, 6), 1: (4, 6)}
    sd = dets.for_scene(1, sizes, {5: "cube"}, min_score=0.2)
    assert dict(sd.counts) == {"unknown obj_id": 1, "empty mask": 1, "mask size": 1,
                               "image not in the scene": 1, "score below the minimum": 1,
                               "bad counts": 1}  # fmt: skip
    found, warnings = sd.frame(0)
    assert [d.entry for d in found] == [0]
    assert len(warnings) == 3 and all(str(p) in w for w in warnings)
    assert any("entry 1 " in w and "obj_id 9" in w for w in warnings)
    assert any("entry 2 " in w and "empty mask" in w for w in warnings)
    assert any("entry 7 " in w and "counts" in w for w in warnings)
    found, warnings = sd.frame(1)  # its only detections: a wrong size, one below 0.2
    assert found == [] and "entry 3 " in warnings[0] and "no masks" in warnings[-1]
    assert "scoring at least 0.2" in warnings[-1]
    # default: every detection the detector wrote
    assert [d.entry for d in dets.for_scene(1, sizes, {5: "cube"}).frame(1)[0]] == [5]
    with pytest.raises(InputError, match="no detection of scene 3"):
        dets.for_scene(3, sizes, {5: "cube"})
    with pytest.raises(InputError, match="none of the 1 detections of scene 2 can be used: "
                       "entry 6 .*no model of obj_id 5"):  # fmt: skip
        dets.for_scene(2, sizes, {4: "block"})


def test_overlaps_go_to_the_higher_score_and_each_detection_has_a_label():
    a = np.zeros((5, 5), bool)
    a[0:3, 0:3] = True
    b = np.zeros((5, 5), bool)
    b[1:5, 1:5] = True
    c = np.zeros((5, 5), bool)
    c[2, 2] = True
    dets = [Detection(i, 0, 0, oid, s, None, (5, 5), tuple(rle_counts(_rle(m)["counts"])))
            for i, (oid, s, m) in enumerate([(1, 0.5, a), (2, 0.8, b), (3, 0.8, c)])]  # fmt: skip
    inst = instance_labels(dets, (5, 5))
    assert [d.entry for d in inst.detections] == [1, 2, 0]  # by score, ties: file order
    assert inst.of(0) == (2, 0.8) and inst.of(2) == (1, 0.5)
    assert np.array_equal(inst.labels == 0, b)  # b wins the overlap with a, and c's pixel
    assert np.array_equal(inst.labels == 2, a & ~b)
    assert inst.pixels == [16, 0, 5] and (inst.labels == -1).sum() == 25 - 21
    assert np.array_equal(instance_labels(dets[::-1], (5, 5)).labels, inst.labels)


# ------------------------------------------------------------------------------ on a scene
def test_detection_labels_are_the_gt_masks_and_hypotheses_find_their_object(lib, dataset):
    from ssp.io.estimators import read_estimates

    scene, est, dets = dataset
    sc = open_bop(scene, lib)
    sizes = {im: (sc.camera_of(k).height, sc.camera_of(k).width) for k, im in enumerate(sc.im_ids)}
    sd = read_detections(dets).for_scene(sc.scene_id, sizes, sc.classes)
    rows = read_estimates(est, "auto", dict(sc.classes), library=lib, scene_id=sc.scene_id)
    right = unmatched = 0
    for k, im in enumerate(sc.im_ids):
        f = sc.load(k, masks="gt")
        found, warnings = sd.frame(im)
        assert not warnings
        inst = instance_labels(found, f.depth.shape)
        # the same partition of the pixels as the ground truth's masks (labels renamed)
        gt_label = {i: round((0.9 - d.score) / 0.01) for i, d in enumerate(inst.detections)}
        lut = np.array([gt_label[i] for i in range(len(gt_label))] + [-1])
        renamed = lut[inst.labels]  # label -1 indexes the last entry: -1
        assert np.array_equal(renamed, np.where(f.instance >= 0, f.instance, -1))
        hyps, n = match_segments(rows.for_image(sc.scene_id, im), inst, sc.classes, lib,
                                 f.camera, f.depth)  # fmt: skip
        gts = list(f.gt.values())
        for h in hyps:  # near an object of its class: its detection is that object's
            near = [(np.linalg.norm(T[:3, 3] - h.T_world_obj[:3, 3]), j)
                    for j, (c, T) in enumerate(gts) if c == h.class_name]  # fmt: skip
            dist, j = min(near, default=(1.0, -1))
            if dist < 0.03:
                unmatched += h.segment is None
                right += h.segment is not None and gt_label[h.segment] == j
                assert h.segment is None or gt_label[h.segment] == j
            if h.class_name not in {sc.classes[d.obj_id] for d in found}:
                assert h.segment is None
    assert right > 20 and unmatched == 0


def _frames(out):
    return {p.stem: json.loads(p.read_text()) for p in sorted(out.glob("scenes/*/frames/*.json"))}


def test_refine_with_a_detections_file_gives_the_segments_of_the_gt_masks(lib, dataset, tmp_path):
    from ssp.pipeline.refine import evaluate, refine

    scene, est, dets = dataset
    root = scene.parent.parent
    gt = refine(root, est, lib, tmp_path / "gt", masks="gt")
    det = refine(root, est, lib, tmp_path / "det", masks=str(dets))
    assert gt.done and det.done
    a, b = _frames(tmp_path / "gt"), _frames(tmp_path / "det")
    assert list(a) == list(b) and len(a) == 4
    for name in a:
        assert a[name]["perception"]["segments"] == b[name]["perception"]["segments"] > 0
        assert len(b[name]["objects"]) == len(a[name]["objects"])
        assert not any("no masks" in w for w in b[name]["warnings"])
    gt_csv = gt.csv.rename(tmp_path / "gt_structure-test.csv")  # evaluate keys by file name
    res = evaluate(root, lib, [gt_csv, det.csv], vsd=False)
    assert res[det.csv.name]["AR"] >= res[gt_csv.name]["AR"] - 0.02


def test_degraded_detections_files(lib, dataset, tmp_path):
    from ssp.pipeline.refine import refine
    from ssp.pipeline.run import run

    scene, est, dets = dataset
    entries = json.loads(dets.read_text())
    # image 2 without detections, one detection of an unknown object
    some = [e for e in entries if e["image_id"] != 2]
    some.append(dict(some[0], category_id=99))
    p = tmp_path / "some.json"
    p.write_text(json.dumps(some))
    run(scene, lib, tmp_path / "out", masks=str(p))
    docs = _frames_of(tmp_path / "out")
    assert any("no detection of scene 0, im_id 2" in w and "no masks" in w
               for w in docs["000002"]["warnings"])  # fmt: skip
    assert any(f"entry {len(some) - 1} " in w and "obj_id 99" in w
               for w in docs["000000"]["warnings"])  # fmt: skip
    assert not any(str(p) in w for w in docs["000001"]["warnings"])
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["done"] == 4
    # every mask of the wrong size: an error before any frame
    small = [dict(e, segmentation=_rle(np.ones((10, 10), bool))) for e in entries]
    p.write_text(json.dumps(small))
    with pytest.raises(InputError, match="none of the .* can be used: entry 0 .*mask of 10 x 10"):
        refine(scene.parent.parent, est, lib, tmp_path / "r", masks=str(p))
    with pytest.raises(ArgumentError, match="masks must be one of .* no such file"):
        run(scene, lib, tmp_path / "o2", masks=str(tmp_path / "absent.json"))
    # a scene with no segmentation at all: every frame says it has no masks
    import shutil

    bare = tmp_path / "bare" / scene.name
    shutil.copytree(scene, bare)
    shutil.rmtree(bare / "instance")
    shutil.rmtree(bare / "mask_visib")
    run(bare, lib, tmp_path / "o4")
    docs = _frames_of(tmp_path / "o4")
    assert len(docs) == 4
    assert all(any(w.startswith("no masks") for w in d["warnings"]) for d in docs.values())
    run(bare, lib, tmp_path / "o5", masks="none")  # asked for: not a warning
    assert not any("no masks" in w for d in _frames_of(tmp_path / "o5").values()
                   for w in d["warnings"])  # fmt: skip


def _frames_of(out):
    return {p.stem: json.loads(p.read_text()) for p in sorted((out / "frames").glob("*.json"))}


def test_cli_run_and_refine_take_a_detections_file(dataset, tmp_path, monkeypatch):
    scene, est, dets = dataset
    monkeypatch.chdir(dets.parent)
    r = runner.invoke(app, ["run", str(scene), "--out", str(tmp_path / "out"), "--masks",
                            dets.name, "--hypotheses", "estimated"])  # fmt: skip
    assert r.exit_code == 0, r.output
    manifest = json.loads((tmp_path / "out" / "run.json").read_text())
    assert manifest["options"]["masks"] == str(dets.resolve())  # a resume reads the same file
    doc = json.loads((tmp_path / "out" / "frames" / "000001.json").read_text())
    assert doc["perception"]["segments"] > 0 and doc["objects"]
    assert not any("masks" in w for w in doc["warnings"])
    r = runner.invoke(app, ["refine", str(scene.parent.parent), "--hypotheses", str(est),
                            "--masks", str(dets), "--out", str(tmp_path / "ref")])  # fmt: skip
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["run", str(scene), "--out", str(tmp_path / "o3"), "--masks",
                            "nothing.json"])  # fmt: skip
    assert r.exit_code != 0 and "masks must be one of" in r.output
