#!/usr/bin/env bash
# The worked example of docs/after-your-estimator.md: a BOP dataset from ssp's simulator, the
# built-in estimator's hypotheses as a BOP19 CSV, ssp refine, and the BOP19 AR before and after;
# then the same on a copy holding only the BOP toolkit's files (no world frame, no masks).
# Usage: examples/after_your_estimator.sh [WORKDIR]   (about 10 minutes on one core)
set -euo pipefail
SSP=${SSP:-ssp}
WORK=${1:-after-your-estimator}
mkdir -p "$WORK" && cd "$WORK"
export OMP_NUM_THREADS=1
for exp in structure isolated; do
  $SSP simulate --experiment "$exp" --sequences 3 --seed 1000 --out data
  $SSP estimate "data/$exp" --out "est_$exp-test.csv"
  $SSP refine "data/$exp" --hypotheses "est_$exp-test.csv" --out "out-$exp" --overwrite
  $SSP evaluate "data/$exp" "est_$exp-test.csv" "out-$exp/est-ssp_$exp-test.csv" --out "ar-$exp.json"
done
# the published copy: only the toolkit's files
rm -rf pub
python3 - <<'PY'
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
$SSP evaluate pub/structure est_structure-test.csv out-pub/est-ssp_structure-test.csv \
  out-pubgt/est-ssp_structure-test.csv --out ar-pub.json
# the figures the docs quote, in one file: copy it to docs/results/after-your-estimator.json
# (tests/test_docs_numbers.py checks that README.md and docs/after-your-estimator.md say them)
python3 - <<'PY'
import json
from pathlib import Path


def row(result: dict) -> dict:
    return {k: round(result[k], 3) for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")}


out = {}
for exp in ("structure", "isolated"):
    ar = json.loads(Path(f"ar-{exp}.json").read_text())
    est, ssp = ar[f"est_{exp}-test.csv"], ar[f"est-ssp_{exp}-test.csv"]
    out[exp] = {"targets": est["targets"], "estimator": row(est), "ssp": row(ssp)}
pub = json.loads(Path("ar-pub.json").read_text())
out["published"] = {
    "estimator": row(pub["est_structure-test.csv"]),
    "no_masks": row(pub["out-pub/est-ssp_structure-test.csv"]),
    "gt_masks": row(pub["out-pubgt/est-ssp_structure-test.csv"]),
}
Path("after-your-estimator.json").write_text(json.dumps(out, indent=2) + "\n")
print(json.dumps(out, indent=2))
PY
