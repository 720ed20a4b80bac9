#!/usr/bin/env bash
# Every bench run whose figures the docs quote (README.md, docs/benchmarks.md, docs/parser.md),
# then their results files copied into docs/results (without the per-object records) and the
# marked figure blocks rewritten: `ssp bench docs-figures --collect WORK --write --check --strict`
# (src/ssp/eval/docs_figures.py names each run: SOURCES). tests/test_docs_numbers.py then checks
# the docs against those files. Rerun it after a change that moves the figures.
# Usage (from anywhere; runs in the repository's root):
#   examples/docs_figures.sh [WORK]        WORK default: bench-out/docs-figures-<git short hash>
# A run whose results file is already in WORK is skipped, so an interrupted script resumes;
# use a fresh WORK after a code change. WORKERS=2 runs table1 and tower with --workers 2 (the
# same results but wall times). Many hours on one core: Table I's baselines 8-15 minutes per
# experiment and noise, ssp 5-6, the towers 2-4 minutes per run, the parser comparison 1 hour.
set -euo pipefail
cd "$(dirname "$0")/.."
SSP=${SSP:-ssp}
WORKERS=${WORKERS:-1}
W=${1:-bench-out/docs-figures-$(git rev-parse --short HEAD)}
export OMP_NUM_THREADS=1
mkdir -p "$W"

run() {  # run NAME FILE COMMAND...: writes $W/NAME/FILE; skipped when that file exists
  local name=$1 file=$2
  shift 2
  if [ -f "$W/$name/$file" ]; then
    echo "have $W/$name/$file"
    return
  fi
  local extra=()
  case "$*" in *" bench table1 "* | *" bench tower "*) extra=(--workers "$WORKERS") ;; esac
  echo "+ $* --out $W/$name"
  "$@" "${extra[@]}" --out "$W/$name"
}

run t1-isolated-paper-ssp results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --methods ssp,ssp_single
run t1-isolated-paper-baselines results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run t1-isolated-realistic-ssp results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise realistic --methods ssp
run t1-isolated-realistic-baselines results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise realistic --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run t1-isolated-realistic-single results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise realistic --methods ssp_single
run t1-isolated-estimated results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --hypotheses estimated --methods ssp,estimator,icp,icp_filter
run t1-isolated-rgb results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise rgb
run t1-isolated-nomask results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise realistic --masks none --methods ssp,ssp_single,estimator,icp_filter
run t1-structure-paper-ssp results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --methods ssp,ssp_single
run t1-structure-paper-baselines results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run t1-structure-realistic-ssp results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods ssp
run t1-structure-realistic-baselines results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run t1-structure-realistic-single results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods ssp_single
run t1-structure-estimated results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --hypotheses estimated --methods ssp,estimator,icp,icp_filter
run t1-structure-rgb results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise rgb
$SSP models export-builtin bench-out/mug-models --names mug,tin,mallet,drill,sander,wrench
run t1-isolated-mug results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --models bench-out/mug-models --hypotheses estimated --methods ssp,ssp_single,estimator,icp_filter
run t1-isolated-mug-realistic results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --models bench-out/mug-models --noise realistic --methods ssp,ssp_single,estimator,icp_filter
run t1-isolated-mug-nomask results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --models bench-out/mug-models --hypotheses estimated --masks none --methods ssp,ssp_single,estimator,icp_filter
run t1-structure-realistic-orbit results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods ssp,icp_filter --camera orbit
run t1-structure-realistic-keyframes results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods ssp,icp_filter --camera keyframes
run t1-structure-realistic-orbit-located results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods ssp,icp_filter --camera orbit --camera-pose estimated
run t1-structure-realistic-keyframes-located results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --methods ssp,icp_filter --camera keyframes --camera-pose estimated
run t1-isolated-realistic-orbit results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise realistic --methods ssp,icp_filter --camera orbit
run t1-isolated-realistic-orbit-located results.json $SSP bench table1 --experiment isolated --sequences 10 --seed 1000 --noise realistic --methods ssp,icp_filter --camera orbit --camera-pose estimated
run camera-bench results.json $SSP bench camera --sequences 2 --seed 1000
run camera-bench-2000 results.json $SSP bench camera --sequences 3 --seed 2000
run t1-structure-nomask results.json $SSP bench table1 --experiment structure --sequences 10 --seed 1000 --noise realistic --masks none --methods ssp,ssp_single,estimator,icp_filter
run tower-realistic-ssp-1000 results.json $SSP bench tower --trials 10 --seed 1000 --noise realistic --methods ssp
run tower-realistic-single-1000 results.json $SSP bench tower --trials 10 --seed 1000 --noise realistic --methods ssp_single
run tower-realistic-base-1000 results.json $SSP bench tower --trials 10 --seed 1000 --noise realistic --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run tower-structure-ssp-1000 results.json $SSP bench tower --trials 10 --seed 1000 --methods ssp
run tower-structure-estimator-1000 results.json $SSP bench tower --trials 10 --seed 1000 --methods estimator
run tower-realistic-ssp-2000 results.json $SSP bench tower --trials 10 --seed 2000 --noise realistic --methods ssp
run tower-realistic-single-2000 results.json $SSP bench tower --trials 10 --seed 2000 --noise realistic --methods ssp_single
run tower-realistic-base-2000 results.json $SSP bench tower --trials 10 --seed 2000 --noise realistic --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run tower-structure-ssp-2000 results.json $SSP bench tower --trials 10 --seed 2000 --methods ssp
run tower-structure-estimator-2000 results.json $SSP bench tower --trials 10 --seed 2000 --methods estimator
run tower-realistic-ssp-3000 results.json $SSP bench tower --trials 10 --seed 3000 --noise realistic --methods ssp
run tower-realistic-single-3000 results.json $SSP bench tower --trials 10 --seed 3000 --noise realistic --methods ssp_single
run tower-realistic-base-3000 results.json $SSP bench tower --trials 10 --seed 3000 --noise realistic --methods estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter
run tower-structure-ssp-3000 results.json $SSP bench tower --trials 10 --seed 3000 --methods ssp
run tower-structure-estimator-3000 results.json $SSP bench tower --trials 10 --seed 3000 --methods estimator
run tower-wrist-ssp-1000 results.json $SSP bench tower --trials 10 --seed 1000 --noise realistic --methods ssp --camera wrist
run tower-wrist-ssp-2000 results.json $SSP bench tower --trials 10 --seed 2000 --noise realistic --methods ssp --camera wrist
run tower-wrist-ssp-3000 results.json $SSP bench tower --trials 10 --seed 3000 --noise realistic --methods ssp --camera wrist
run tower-wrist-base-1000 results.json $SSP bench tower --trials 10 --seed 1000 --noise realistic --methods estimator,icp_filter,ray_slide --camera wrist
run tower-case-study results.json $SSP bench tower --trials 10 --seed 1000 --noise case-study
run tower-rgb results.json $SSP bench tower --trials 10 --seed 1000 --noise rgb
run rgb-calibration results.json $SSP bench rgb-calibration --data ../shared/data/lmo-megapose
run tower-estimated-ssp results.json $SSP bench tower --trials 10 --seed 1000 --hypotheses estimated --methods ssp
run tower-estimated-estimator results.json $SSP bench tower --trials 10 --seed 1000 --hypotheses estimated --methods estimator
run parser-compare compare.json $SSP bench parser --links ../shared/data/costar-links --compare 3d6b73d --processes 2 --rev-processes 2
run frame-compare results.json $SSP bench frame --real-dev ../shared/data/real-dev --compare c436e9b --rounds 2
run frame-processes results.json $SSP bench frame --processes 2
run frame-threads results.json $SSP bench frame --real-dev ../shared/data/real-dev --compare ef47c46 --rounds 1
run frame-kernels results.json $SSP bench frame --real-dev ../shared/data/real-dev --compare 3b8973d --rounds 1

$SSP bench docs-figures --collect "$W" --write --check --strict
