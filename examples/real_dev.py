"""Run ``ssp run`` on the real development captures and check what it wrote.

Usage::

    python examples/real_dev.py ../shared/data/real-dev [--work DIR] [--only test16,milk]

The data stays where it is (it is not part of the repository): the script reads it, builds the
model folders and input folders a user would write (in ``--work``, default a new temporary
folder), runs the documented command line on each capture, checks every output and prints a
per-capture table (docs/perception.md, "Real captures (development)").

- ``mosd-stacked-boxes/test16..23.pcd``: each frame is its own scene (the captures are not a
  sequence), so each is a single-frame run. Its box models are measured from the labelled
  points (``measure_boxes``). Two runs per frame: ``labels``, the label field used as instance
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

import numpy as np

from ssp.config import SSPConfig
from ssp.io import read_cloud, write_cloud

MOSD = "mosd-stacked-boxes"
MILK = "pcl-milk"
MILK_SCENE = "milk_cartoon_all_small_clorox.pcd"
TABLE_LABELS = list(range(10))  # 0 = invalid or background, 1-9 = table
BOX_DENSITY = 200.0  # kg/m^3: cardboard boxes, partly filled
COLLISION_FLOOR = -50.0  # collision term below this: an object deep in another


# ------------------------------------------------------------------------ models from points
def plane_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares plane of ``points`` (camera frame): centre, unit normal toward the camera
    (the origin) and a ``(2, 3)`` basis of the plane."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2] if np.dot(vt[2], -c) > 0 else -vt[2]
    return c, n, vt[:2]


def measure_boxes(
    points: np.ndarray, labels: np.ndarray, table_labels: list[int]
) -> dict[int, tuple[float, float, float]]:
    """Box sizes ``(a, b, h)`` (m) of the labelled objects standing on a table.

    ``h`` is the extent along the table normal (1st to 99th percentile of the heights: a box on
    another box is measured from the top of the one below); ``a, b`` the extents along the
    principal axes of the points projected on the table (2nd to 98th percentile). The views are
    partial, so sizes are at most a few mm short.
    """
    ok = np.all(np.isfinite(points), axis=1)
    table = ok & np.isin(labels, table_labels)
    c, n, basis = plane_frame(points[table])
    sizes: dict[int, tuple[float, float, float]] = {}
    for lab in sorted(set(labels[ok].tolist()) - set(table_labels)):
        p = points[ok & (labels == lab)] - c
        h = p @ n
        uv = p @ basis.T
        uv = uv - uv.mean(axis=0)
        _, _, vt = np.linalg.svd(uv, full_matrices=False)
        q = uv @ vt.T
        a, b = (float(np.percentile(q[:, i], 98) - np.percentile(q[:, i], 2)) for i in (0, 1))
        sizes[int(lab)] = (a, b, float(np.percentile(h, 99) - np.percentile(h, 1)))
    return sizes


def box_mesh(size: tuple[float, float, float], gable: float = 0.0):
    """A closed box mesh ``size`` (m) centred at its base centre's height/2 (origin at the
    centre of the box part), with an optional gable roof of height ``gable`` along x."""
    import trimesh

    a, b, h = size
    if gable <= 0:
        return trimesh.creation.box(extents=(a, b, h))
    x, y, z = a / 2, b / 2, h / 2
    v = [[sx * x, sy * y, sz * z] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)]
    v += [[-x, 0, z + gable], [x, 0, z + gable]]
    return trimesh.Trimesh(vertices=np.array(v), process=False).convex_hull


def write_models(folder: Path, meshes: dict[str, object], density: float) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, mesh in meshes.items():
        mesh.export(folder / f"{name}.obj")
    (folder / "models.yaml").write_text(
        f"units: m\ndefaults: {{density: {density}, friction: 0.8}}\n", encoding="utf-8"
    )


def carton_size(path: Path, footprint: float = 0.07) -> tuple[float, float, float, float]:
    """Width, depth, wall height and gable height (m) of the carton in ``milk.pcd``.

    The cloud's y axis is the carton's long axis (the capture's axes: y up). The height is the
    1st to 99th percentile along y; the gable is the end where 10 mm slices are narrower than
    70 % of the median slice. The footprint is not measurable from this one-sided view (two
    faces seen at an angle): the carton's ``footprint`` (70 mm, data README) is used.
    """
    p = read_cloud(path).points
    p = p[np.all(np.isfinite(p), axis=1)]
    y = p[:, 1]
    lo, hi = np.percentile(y, [1, 99])
    edges = np.arange(lo, hi + 1e-9, 0.01)
    widths = []
    for y0 in edges[:-1]:
        s = p[(y >= y0) & (y < y0 + 0.01)][:, [0, 2]]
        s = s - s.mean(axis=0)
        _, _, vt = np.linalg.svd(s, full_matrices=False)
        q = s @ vt[0]
        widths.append(np.percentile(q, 98) - np.percentile(q, 2))
    narrow = np.asarray(widths) < 0.7 * np.median(widths)
    n_lo = int(np.argmin(narrow)) if narrow[0] else 0
    n_hi = int(np.argmin(narrow[::-1])) if narrow[-1] else 0
    gable = 0.01 * max(n_lo, n_hi)
    return footprint, footprint, float(hi - lo) - gable, gable


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


def mosd_captures(data: Path, work: Path, only: set[str] | None) -> list[dict]:
    runs = []
    for pcd in sorted((data / MOSD).glob("test*.pcd")):
        if only and pcd.stem not in only:
            continue
        cloud = read_cloud(pcd)
        sizes = measure_boxes(cloud.points, cloud.labels, TABLE_LABELS)
        models = work / "models" / pcd.stem
        write_models(models, {f"box{k}": box_mesh(s) for k, s in sizes.items()}, BOX_DENSITY)
        size_note = ", ".join(
            f"box{k} {'x'.join(f'{v * 1000:.0f}' for v in s)}" for k, s in sizes.items()
        )
        with_labels = work / "input" / f"{pcd.stem}-labels"
        with_labels.mkdir(parents=True, exist_ok=True)
        link = with_labels / pcd.name
        if not link.exists():
            link.symlink_to(pcd.resolve())
        scene = {"labels": "instance", "background_labels": TABLE_LABELS}
        (with_labels / "scene.json").write_text(json.dumps(scene), encoding="utf-8")
        clusters = work / "input" / f"{pcd.stem}-clusters"
        clusters.mkdir(parents=True, exist_ok=True)
        write_cloud(clusters / pcd.name, cloud.points, colors=cloud.colors)
        expected = {str(k) for k in sizes}
        for variant, inp in (("labels", with_labels), ("clusters", clusters)):
            runs.append(
                {"capture": f"{pcd.stem} {variant}", "input": inp, "models": models,
                 "note": size_note, "expected": expected if variant == "labels" else None}
            )  # fmt: skip
    return runs


def milk_captures(data: Path, work: Path, only: set[str] | None) -> list[dict]:
    if only and "milk" not in only:
        return []
    w, d, h, g = carton_size(data / MILK / "milk.pcd")
    models = work / "models" / "milk"
    write_models(models, {"carton": box_mesh((w, d, h), gable=g)}, 500.0)
    inp = work / "input" / "milk"
    inp.mkdir(parents=True, exist_ok=True)
    link = inp / MILK_SCENE
    if not link.exists():
        link.symlink_to((data / MILK / MILK_SCENE).resolve())
    (inp / "scene.json").write_text(json.dumps({"camera_axes": "opengl"}), encoding="utf-8")
    note = f"carton {w * 1000:.0f}x{d * 1000:.0f}x{h * 1000:.0f} + gable {g * 1000:.0f} mm"
    return [{"capture": "milk", "input": inp, "models": models, "note": note}]


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
