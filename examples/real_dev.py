"""Run ``ssp run`` on the real development captures and check what it wrote.

Usage::

    python examples/real_dev.py ../shared/data/real-dev [--work DIR] [--only test16,milk]

The data stays where it is (it is not part of the repository): the script reads it, builds the
model folders and input folders a user would write (in ``--work``, default a new temporary
folder), runs the documented command line on each capture, checks every output and prints a
per-capture table (docs/perception.md, "Real captures (development)").

- ``mosd-stacked-boxes/test16..23.pcd``: each frame is its own scene (the captures are not a
  sequence), so each is a single-frame run. Its box models are measured from the labelled
  points (``ssp.eval.real_captures``). Two runs per frame: ``labels``, the label field used as instance
  segments (``scene.json``: labels 0-9 are background), and ``clusters``, the same points
  without the label field (the front end clusters what stands on the table).
- ``pcl-milk/milk_cartoon_all_small_clorox.pcd``: a carton model (a box with a gable top,
  measured from ``milk.pcd``); the cloud's axes are x right, y up, z backward, declared with
  ``scene.json`` ``"camera_axes": "opengl"``.

The checks (``check_frame``): every segment has a verdict; every kept object that is new has a
data fit of at least ``verification.min_fit``; every removed or rejected object has a reason;
no kept object is floating (its support fraction from the table or other objects) or deep in
another (the collision term).
"""

# ruff: noqa: T201  (a script: it prints its table)
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ssp.config import SSPConfig
from ssp.eval.real_captures import milk_captures, mosd_captures

COLLISION_FLOOR = -50.0  # collision term below this: an object deep in another


# -------------------------------------------------------------------------------- the runs
def ssp_command() -> list[str]:
    """The documented ``ssp`` entry point, run by this interpreter (so it uses this checkout
    when it is on ``PYTHONPATH``)."""
    return [sys.executable, "-c", "import sys; sys.argv[0] = 'ssp'; from ssp.cli import app; app()"]


def run_ssp(inp: Path, models: Path, out: Path, cache: Path) -> tuple[int, float, str]:
    cmd = ssp_command() + ["run", str(inp), "--models", str(models), "--out", str(out)]
    cmd += ["--cache", str(cache), "--overwrite"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    return proc.returncode, time.perf_counter() - t0, proc.stdout + proc.stderr


# ------------------------------------------------------------------------------ the checks
def check_frame(
    doc: dict, min_fit: float, expected: set[str] | None = None
) -> tuple[list[str], dict]:
    """Problems in one ``frames/<name>.json`` and its numbers for the table; ``expected``: the
    instance labels of the input, each of which must have a verdict."""
    problems: list[str] = []
    if doc.get("status") != "done":
        return [f"frame failed: {doc.get('error')}"], {}
    verdicts = doc.get("segments") or {}
    n_segments = (doc.get("perception") or {}).get("segments")
    if n_segments is not None and n_segments != len(verdicts):
        problems.append(f"{n_segments} segments perceived, {len(verdicts)} verdicts")
    for label in set(expected or ()) - set(verdicts):
        problems.append(f"segment {label} of the input: no verdict")
    for label, v in verdicts.items():
        if not v:
            problems.append(f"segment {label}: empty verdict")
    objects = doc.get("objects") or []
    kept_ids = {o["id"] for o in objects}
    for label, v in verdicts.items():
        if v.startswith("object "):
            oid = v.split()[1].rstrip(":")
            if oid not in kept_ids:
                problems.append(f"segment {label}: verdict names {oid}, not in objects")
    fits = []
    for o in objects:
        # the fit verification judged a new object by (its visible surface), else the data fit
        fit = (o.get("evidence") or {}).get("fit", o.get("fit"))
        fits.append(fit if fit is not None else float("nan"))
        if fit is None or not fit >= min_fit:
            problems.append(f"{o['id']}: kept with fit {fit} < min_fit {min_fit}")
        if o.get("reason", "").startswith("unverified"):
            problems.append(f"{o['id']}: kept {o['reason']}")
        if not o.get("reason"):
            problems.append(f"{o['id']}: kept without a reason")
        col = (o.get("terms") or {}).get("collision")
        if col is not None and col < COLLISION_FLOOR:
            problems.append(f"{o['id']}: collision term {col:.1f} (interpenetrating)")
        carried = sum(s["fraction"] for s in doc.get("support", []) if s["supported"] == o["id"])
        if carried < 0.5:
            said = [w for w in doc.get("warnings") or [] if w.startswith(f"{o['id']}:")]
            note = f" (warned: {said[0]})" if said else " (no warning)"
            problems.append(f"{o['id']}: {carried:.2f} of its weight carried (floating){note}")
    for o in (doc.get("removed") or []) + (doc.get("rejected") or []):
        if not o.get("reason"):
            problems.append(f"{o.get('id')}: removed/rejected without a reason")
    skipped = {k: v for k, v in verdicts.items() if not v.startswith("object ")}
    stats = {
        "segments": len(verdicts),
        "kept": len(objects),
        "rejected": len(doc.get("rejected") or []),
        "skipped": skipped,
        "min_fit": min(fits) if fits else float("nan"),
        "warnings": doc.get("warnings") or [],
    }
    return problems, stats


def check_run(
    out: Path, min_fit: float, expected: set[str] | None = None
) -> tuple[list[str], dict]:
    summary = json.loads((out / "summary.json").read_text())
    problems = [f"{f['frame']}: failed: {f['error']}" for f in summary.get("failed", [])]
    if summary.get("done") != summary.get("frames"):
        problems.append(f"{summary.get('done')} of {summary.get('frames')} frames done")
    stats: dict = {}
    for f in sorted((out / "frames").glob("*.json")):
        p, s = check_frame(json.loads(f.read_text()), min_fit, expected)
        problems += [f"{f.stem}: {x}" for x in p]
        stats = s or stats
    return problems, stats


#: Short names of segment verdicts for the table: (words in the verdict, tag).
TAGS = (
    ("accounts for", "rej. segment"),
    ("seen empty", "rej. empty"),
    ("would fall", "rej. fall"),
    ("rejected", "rej. fit"),
    ("no candidate pose", "no match"),
    ("no pose explained", "low score"),
    ("larger than every", "too large"),
    ("fewer than", "few points"),
)


def tag(verdict: str) -> str:
    return next((t for words, t in TAGS if words in verdict), "other")


def skipped_summary(skipped: dict[str, str]) -> str:
    counts: dict[str, int] = {}
    for v in skipped.values():
        counts[tag(v)] = counts.get(tag(v), 0) + 1
    return ", ".join(f"{n} {t}" for t, n in sorted(counts.items())) or "-"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", type=Path, help="the real-dev folder (../shared/data/real-dev)")
    ap.add_argument("--work", type=Path, default=None, help="work folder (default: a temp dir)")
    ap.add_argument("--only", default=None, help="comma-separated: test16,...,milk")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="ssp-real-dev-"))
    only = set(args.only.split(",")) if args.only else None
    min_fit = SSPConfig().verification.min_fit
    runs = mosd_captures(args.data, work, only) + milk_captures(args.data, work, only)
    rows, failures = [], 0
    for r in runs:
        out = work / "out" / r["capture"].replace(" ", "-")
        rc, seconds, text = run_ssp(r["input"], r["models"], out, work / "cache")
        if not (out / "summary.json").exists():
            problems, stats = [f"ssp run exit {rc}: {text.strip().splitlines()[-1:]}"], {}
        else:
            problems, stats = check_run(out, min_fit, r.get("expected"))
            if rc != 0:
                problems.append(f"ssp run exit {rc}")
        failures += bool(problems)
        rows.append({"capture": r["capture"], "models": r["note"], "out": str(out),
                     "seconds": seconds, "problems": problems, **stats})  # fmt: skip
        print(f"{r['capture']}: {len(problems)} problems ({seconds:.1f} s)", flush=True)
    print(f"\nwork folder: {work}; verification.min_fit = {min_fit}\n")
    print("| capture | segments | kept | rejected | skipped segments | min fit | problems | s |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        mf = row.get("min_fit", float("nan"))
        print(
            f"| {row['capture']} | {row.get('segments', '-')} | {row.get('kept', '-')} | "
            f"{row.get('rejected', '-')} | {skipped_summary(row.get('skipped') or {})} | "
            f"{'-' if math.isnan(mf) else f'{mf:.2f}'} | {len(row['problems'])} | "
            f"{row['seconds']:.1f} |"
        )
    for row in rows:
        print(f"models {row['capture']}: {row['models']}")
    for row in rows:
        for p in row["problems"]:
            print(f"PROBLEM {row['capture']}: {p}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str))
    print(f"\n{len(rows) - failures} of {len(rows)} runs pass every check")
    return 1 if failures else 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
