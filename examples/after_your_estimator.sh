#!/usr/bin/env bash
# The worked example of docs/after-your-estimator.md: a BOP dataset from ssp's simulator, the
# built-in estimator's hypotheses as a BOP19 CSV, ssp refine, and the BOP19 AR before and after;
# then the same on a copy holding only the BOP toolkit's files (no world frame, no masks).
# Usage: [SSP=ssp] [PYTHON=python3] examples/after_your_estimator.sh [WORKDIR]
# (about 20 minutes on one core)
set -euo pipefail
SSP=${SSP:-ssp}
PY=${PYTHON:-python3}  # the Python ssp is installed in (numpy, Pillow, pycocotools)
WORK=${1:-after-your-estimator}
mkdir -p "$WORK" && cd "$WORK"
export OMP_NUM_THREADS=1
for exp in structure isolated; do
  $SSP simulate --experiment "$exp" --sequences 3 --seed 1000 --out data
  $SSP estimate "data/$exp" --out "est_$exp-test.csv"
  $SSP refine "data/$exp" --hypotheses "est_$exp-test.csv" --out "out-$exp" --overwrite
  $SSP evaluate "data/$exp" "est_$exp-test.csv" "out-$exp/est-ssp_$exp-test.csv" --out "ar-$exp.json"
  # an RGB estimator's errors (MegaPose's on LM-O: mostly depth along the ray, flips, misses)
  $SSP estimate "data/$exp" --noise rgb --seed 0 --out "rgb_$exp-test.csv"
  $SSP refine "data/$exp" --hypotheses "rgb_$exp-test.csv" --out "out-rgb-$exp" --overwrite
  # the rule "never drop an object the estimator reported" measured: the same CSV without the
  # rows of the objects verification rejected (scored 0.0005 x fit, below every kept one)
  $PY -c "import sys; r = open(sys.argv[1]).read().splitlines(); open(sys.argv[2], 'w').write('\n'.join([r[0]] + [x for x in r[1:] if float(x.split(',')[3]) >= 0.001]) + '\n')" \
    "out-rgb-$exp/rgb-ssp_$exp-test.csv" "rgbkept-ssp_$exp-test.csv"
  $SSP evaluate "data/$exp" "rgb_$exp-test.csv" "out-rgb-$exp/rgb-ssp_$exp-test.csv" \
    "rgbkept-ssp_$exp-test.csv" --out "ar-rgb-$exp.json"
done
# the published copy: only the toolkit's files
rm -rf pub
$PY - <<'PY'
import json, shutil
from pathlib import Path
root, dest = Path("data/structure"), Path("pub/structure")
shutil.copytree(root, dest)
(dest / "models.json").unlink()
for scene in (dest / "test").iterdir():
    for extra in ("sequence.json", "hypotheses.json", "hypotheses_gt.json", "models.json",
                  "camera.json"):
        (scene / extra).unlink()
    shutil.rmtree(scene / "instance")
    cams = json.loads((scene / "scene_camera.json").read_text())
    for v in cams.values():
        del v["cam_R_w2c"], v["cam_t_w2c"]
    (scene / "scene_camera.json").write_text(json.dumps(cams))
PY
$SSP refine pub/structure --hypotheses est_structure-test.csv --out out-pub --overwrite
$SSP refine pub/structure --hypotheses est_structure-test.csv --out out-pubgt --masks gt --overwrite
$SSP refine pub/structure --hypotheses est_structure-test.csv --out out-pubsil --overwrite \
  --masks silhouettes
$SSP evaluate pub/structure est_structure-test.csv out-pub/est-ssp_structure-test.csv \
  out-pubgt/est-ssp_structure-test.csv out-pubsil/est-ssp_structure-test.csv --out ar-pub.json
# the RGB estimator's CSV on the published copy: without masks, and with a detector's masks (a
# BOP segmentation results JSON; here the ground-truth mask_visib written as one, RLE-encoded)
$PY - <<'PY'
import json
from pathlib import Path

import numpy as np
from PIL import Image
from pycocotools import mask as rle

dets = []
for scene in sorted(Path("pub/structure/test").iterdir()):
    gt = json.loads((scene / "scene_gt.json").read_text())
    for im, objs in gt.items():
        for k, o in enumerate(objs):
            m = np.asarray(Image.open(scene / "mask_visib" / f"{int(im):06d}_{k:06d}.png")) > 0
            if not m.any():
                continue
            enc = rle.encode(np.asfortranarray(m.astype(np.uint8)))
            dets.append({"scene_id": int(scene.name), "image_id": int(im),
                         "category_id": o["obj_id"], "score": 1.0,
                         "bbox": [float(v) for v in rle.toBbox(enc)],
                         "segmentation": {"counts": enc["counts"].decode(), "size": list(m.shape)},
                         "time": -1})
Path("detections_structure-test.json").write_text(json.dumps(dets))
PY
$SSP refine pub/structure --hypotheses rgb_structure-test.csv --out out-rgb-pub --overwrite
$SSP refine pub/structure --hypotheses rgb_structure-test.csv --out out-rgb-pubdet --overwrite \
  --masks detections_structure-test.json
$SSP refine pub/structure --hypotheses rgb_structure-test.csv --out out-rgb-pubsil --overwrite \
  --masks silhouettes
$SSP evaluate pub/structure rgb_structure-test.csv out-rgb-pub/rgb-ssp_structure-test.csv \
  out-rgb-pubdet/rgb-ssp_structure-test.csv out-rgb-pubsil/rgb-ssp_structure-test.csv \
  --out ar-rgb-pub.json
# the figures the docs quote, in one file: copy it to docs/results/after-your-estimator.json
# (tests/test_docs_numbers.py checks that README.md and docs/after-your-estimator.md say them)
$PY - <<'PY'
import json
from pathlib import Path


def row(result: dict) -> dict:
    return {k: round(result[k], 3) for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")}


out = {}
for exp in ("structure", "isolated"):
    ar = json.loads(Path(f"ar-{exp}.json").read_text())
    est, ssp = ar[f"est_{exp}-test.csv"], ar[f"est-ssp_{exp}-test.csv"]
    out[exp] = {"targets": est["targets"], "estimator": row(est), "ssp": row(ssp)}
    ar = json.loads(Path(f"ar-rgb-{exp}.json").read_text())
    est, ssp = ar[f"rgb_{exp}-test.csv"], ar[f"rgb-ssp_{exp}-test.csv"]
    kept = ar[f"rgbkept-ssp_{exp}-test.csv"]
    out[f"rgb_{exp}"] = {"targets": est["targets"], "estimator": row(est), "ssp": row(ssp),
                         "ssp_kept_only": row(kept)}
pub = json.loads(Path("ar-pub.json").read_text())
out["published"] = {
    "estimator": row(pub["est_structure-test.csv"]),
    "no_masks": row(pub["out-pub/est-ssp_structure-test.csv"]),
    "gt_masks": row(pub["out-pubgt/est-ssp_structure-test.csv"]),
    "silhouettes": row(pub["out-pubsil/est-ssp_structure-test.csv"]),
}
pub = json.loads(Path("ar-rgb-pub.json").read_text())
out["rgb_published"] = {
    "estimator": row(pub["rgb_structure-test.csv"]),
    "no_masks": row(pub["out-rgb-pub/rgb-ssp_structure-test.csv"]),
    "detector_masks": row(pub["out-rgb-pubdet/rgb-ssp_structure-test.csv"]),
    "silhouettes": row(pub["out-rgb-pubsil/rgb-ssp_structure-test.csv"]),
}
Path("after-your-estimator.json").write_text(json.dumps(out, indent=2) + "\n")
print(json.dumps(out, indent=2))
PY
