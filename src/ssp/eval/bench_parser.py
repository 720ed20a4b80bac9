"""``ssp bench parser``: time per frame of :meth:`SceneParser.update` (issue 3's report).

Scenes are stacks of built-in cubes and blocks (1-3 high) on a grid, seen by a camera about
1 m away; frames are rendered depth with sensor noise (:func:`ssp.sim.frames.synthetic_frame`)
and ``k`` noisy hypotheses per object (5 mm / 5 deg RMS). Per scene size N, three frames:

* ``added``: the first frame, every object new (the most expensive case);
* ``changed``: one stack slid by 1.5 cm and the rest static (the usual changed frame);
* ``unchanged``: the same scene again with fresh hypothesis noise.

Everything runs single-threaded (``OMP_NUM_THREADS=1``), in ``search.processes`` processes
(``--processes``; issue 19's targets are for 2 on 2 cores); timings are wall seconds per frame
and the share of each stage (forces, stepping, contacts, scoring, the rest) in the frame's CPU
seconds. The mean symmetry-aware
error of the estimates and of the hypotheses (ground truth is known; matched as in
:mod:`ssp.eval.metrics`) is reported alongside.
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ssp.config import SSPConfig
from ssp.eval.metrics import hypothesis_errors, match_frame
from ssp.geometry import make_pose
from ssp.library import ObjectLibrary
from ssp.parser import SceneEstimate, SceneParser
from ssp.sim.frames import synthetic_frame
from ssp.sim.render import look_at

try:
    from ssp.lanes import LANES_STAGE
except ImportError:  # an older ssp timed by --compare (this file runs on its code)
    LANES_STAGE = "lanes"

__all__ = [
    "bench_parser",
    "compare_parser",
    "links_structure",
    "stacks",
    "setting",
    "write_compare",
    "write_report",
]

STAGES = ("forces", "stepping", "contacts", "scoring")
FRAMES = ("added", "changed", "unchanged")


def stacks(library: ObjectLibrary, n: int, seed: int = 0, spacing: float = 0.09) -> dict:
    """``n`` cubes and blocks in stacks 1-3 high on a grid: ``id -> (class, T_world_obj)``."""
    rng = np.random.default_rng(seed)
    heights = []
    while sum(heights) < n:
        heights.append(min(int(rng.integers(1, 4)), n - sum(heights)))
    side = int(np.ceil(np.sqrt(len(heights))))
    gt: dict[str, tuple[str, np.ndarray]] = {}
    for s, h in enumerate(heights):
        x = (s % side - (side - 1) / 2) * spacing
        y = (s // side - (side - 1) / 2) * spacing
        yaw = float(rng.uniform(-0.3, 0.3))
        z = 0.0
        for level in range(h):
            name = "block" if (s + level) % 2 else "cube"
            m = library[name]
            c, si = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
            T = make_pose(R, [x, y, z - float(m.mesh.bounds[0, 2])])
            gt[f"{name}_{len(gt)}"] = (name, T)
            z += float(m.extents[2])
    return gt


def _rot(axis: str, angle: float) -> np.ndarray:
    return Rotation.from_euler(axis, angle).as_matrix()


def row_label(row: dict) -> str:
    """A row's scene size as the tables print it (``6 (links)`` for the link/node structure)."""
    return f"{row['objects']}" + (" (links)" if row.get("scene") == "links" else "")


def links_structure(library, link: str = "link_uniform", node: str = "node_uniform") -> dict:
    """A link/node structure of the paper's real experiment (``../shared/data/costar-links``):
    three nodes and three links, ``id -> (class, T_world_obj)``.

    Node ``a`` sits on the table; link 1 lies on the table along x, its end cap flush on
    ``a``'s +x face, with node ``b`` at its other end; link 3 lies along y from ``b``'s +y face
    to node ``c``; link 2 stands on ``a``'s top face. Every link end is centred on a node
    face, as the parts' magnets hold them.
    """
    ml, mn = library[link], library[node]

    def lowest(m, R) -> float:  # height of the model origin above its lowest point, m
        return -float((np.asarray(m.mesh.vertices) @ R.T)[:, 2].min())

    def along(m, R, axis: int) -> tuple[float, float]:  # extent of the rotated mesh on an axis
        v = (np.asarray(m.mesh.vertices) @ R.T)[:, axis]
        return float(v.min()), float(v.max())

    eye = np.eye(3)
    R_x = _rot("y", np.pi / 2)  # the link's long (z) axis along world x
    R_y = _rot("x", -np.pi / 2)  # ... along world y
    zn = lowest(mn, eye)
    n_lo, n_hi = along(mn, eye, 0)
    l_lo, l_hi = along(ml, R_x, 0)
    a = np.array([0.0, 0.0, zn])
    l1 = np.array([a[0] + n_hi - l_lo, 0.0, lowest(ml, R_x)])
    b = np.array([l1[0] + l_hi - n_lo, 0.0, zn])
    ny_lo, ny_hi = along(mn, eye, 1)
    ly_lo, ly_hi = along(ml, R_y, 1)
    l3 = np.array([b[0], b[1] + ny_hi - ly_lo, lowest(ml, R_y)])
    c = np.array([b[0], l3[1] + ly_hi - ny_lo, zn])
    top = a[2] + float(np.asarray(mn.mesh.vertices)[:, 2].max())
    l2 = np.array([a[0], a[1], top + lowest(ml, eye)])
    return {
        "node_a": (node, make_pose(eye, a)),
        "link_2": (link, make_pose(eye, l2)),
        "link_1": (link, make_pose(R_x, l1)),
        "node_b": (node, make_pose(eye, b)),
        "link_3": (link, make_pose(R_y, l3)),
        "node_c": (node, make_pose(eye, c)),
    }


#: How far (m, along x) the changed frame moves the scene's first stack. The link/node structure
#: moves it (node a and link 2 on it) the other way: toward +x node a would go 15 mm into the
#: end cap of link 1, flush on its +x face, a scene no parser can match.
SLIDE = 0.015


def _slide(gt: dict, dx: float) -> dict:
    """The same scene with the first stack (the objects at the first x, y) moved by dx in x."""
    first = next(iter(gt.values()))[1][:2, 3]
    out = {}
    for oid, (cls, T) in gt.items():
        T = T.copy()
        if np.linalg.norm(T[:2, 3] - first) < 1e-9:
            T[0, 3] += dx
        out[oid] = (cls, T)
    return out


def _errors(est: SceneEstimate, frame, gt: dict, library) -> tuple[list, list]:
    """Symmetry-aware (mm, deg) errors of the estimate's matched objects and of every
    hypothesis (:func:`ssp.eval.metrics.match_frame`, :func:`hypothesis_errors`)."""
    fm = match_frame(gt, [(o.class_name, o.T_world_obj) for o in est.objects], library)
    hyp_err, _ = hypothesis_errors(gt, frame.hypotheses, library)
    return [(m.trans_mm, m.rot_deg) for m in fm.matches], hyp_err


def _shares(est: SceneEstimate) -> dict[str, float]:
    """Stage shares of the frame's CPU seconds (its wall time plus what lane processes
    worked, ``search.processes``)."""
    total = est.timings.get("total", 0.0) + est.timings.get(LANES_STAGE, 0.0)
    out = {s: est.timings.get(s, 0.0) / total if total else 0.0 for s in STAGES}
    out["other"] = max(0.0, 1.0 - sum(out.values()))
    return out


def _time_scene(
    parser: SceneParser, lib, gt: dict, T_world_cam, rng, k: int, slide: float = SLIDE
) -> dict:
    """The three frames (added, changed, unchanged) of one scene: ``frame -> (wall s, estimate,
    ssp errors, hypothesis errors)``; the changed frame moves the first stack by ``slide``
    (m, along x)."""
    scenes = {"added": gt, "changed": _slide(gt, slide)}
    scenes["unchanged"] = scenes["changed"]
    out = {}
    for t, name in enumerate(FRAMES):
        f = synthetic_frame(
            lib, scenes[name], T_world_cam=T_world_cam, rng=rng, k=k, stamp=float(t)
        )
        t0 = time.perf_counter()
        est = parser.update(f)
        wall = time.perf_counter() - t0
        out[name] = (wall, est, *_errors(est, f, scenes[name], lib))
    return out


def _row(runs: Sequence[dict]) -> dict:
    """Per frame kind: mean/max seconds, hypotheses tested, stage shares, mean seconds of every
    timer entry, mean errors."""
    row = {}
    for name in FRAMES:
        walls = [r[name][0] for r in runs]
        ests = [r[name][1] for r in runs]
        e = [x for r in runs for x in r[name][2]]
        h = [x for r in runs for x in r[name][3]]
        shares = [_shares(x) for x in ests]
        row[name] = {
            "sec_per_frame_mean": float(np.mean(walls)),
            "sec_per_frame_max": float(np.max(walls)),
            "hypotheses_tested_mean": float(np.mean([x.hypotheses_tested for x in ests])),
            "unchanged_shortcut": [bool(x.unchanged) for x in ests],
            "stage_share": {s: float(np.mean([sh[s] for sh in shares])) for s in shares[0]},
            # every timer entry of the frame (association, segments, icp, verification, ...)
            "stage_seconds": {
                s: float(np.mean([x.timings.get(s, 0.0) for x in ests]))
                for s in sorted({key for x in ests for key in x.timings})
            },
            "error": {
                "ssp_mm_mean": float(np.mean([x[0] for x in e])),
                "ssp_deg_mean": float(np.mean([x[1] for x in e])),
                # the worst object of the frame kind (judge by the tails)
                "ssp_mm_max": float(np.max([x[0] for x in e])),
                "ssp_deg_max": float(np.max([x[1] for x in e])),
                "hypotheses_mm_mean": float(np.mean([x[0] for x in h])),
                "hypotheses_deg_mean": float(np.mean([x[1] for x in h])),
            },
        }
    return row


def available_cores() -> int:
    """Cores this process may run on (``taskset`` limits them)."""
    import os

    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def setting(result: dict) -> str:
    """``one process on 1 core`` etc., for the reports' headings."""
    m = result.get("machine", {})
    p, c = int(m.get("processes", 1)), m.get("cores_available", "?")
    return f"{p} process{'es' if p > 1 else ''} on {c} core{'s' if c != 1 else ''}"


def bench_parser(
    sizes: Sequence[int] = (5, 10, 20),
    k: int = 5,
    repeats: int = 2,
    seed: int = 0,
    config: SSPConfig | None = None,
    progress: Callable[[str], None] | None = None,
    links: ObjectLibrary | None = None,
) -> dict:
    """Time the parser on ``repeats`` scenes of each size; returns a JSON-ready dict.

    ``links``: a library with the paper's ``link_uniform`` and ``node_uniform`` models
    (``../shared/data/costar-links``); adds a row for :func:`links_structure` (6 objects).
    """
    config = config if config is not None else SSPConfig()
    lib = ObjectLibrary.builtin(config)
    T_world_cam = look_at([-0.5, -0.6, 0.65], [0.0, 0.0, 0.03])
    rows = []
    for n in sizes:
        runs = []
        for r in range(repeats):
            if progress:
                progress(f"N = {n}, scene {r + 1}/{repeats}")
            rng = np.random.default_rng([seed, n, r])
            gt = stacks(lib, n, seed=seed * 1000 + n * 10 + r)
            runs.append(_time_scene(SceneParser(lib, config), lib, gt, T_world_cam, rng, k))
        rows.append({"scene": "stacks", "objects": n, "k": k, "n_times_k": n * k, **_row(runs)})
    if links is not None:
        gt = links_structure(links)
        T_links_cam = look_at([-0.4, -0.6, 0.7], [0.15, 0.1, 0.05])
        runs = []
        for r in range(repeats):
            if progress:
                progress(f"link/node structure, scene {r + 1}/{repeats}")
            rng = np.random.default_rng([seed, len(gt), r, 1])
            parser = SceneParser(links, config)
            runs.append(_time_scene(parser, links, gt, T_links_cam, rng, k, slide=-SLIDE))
        link_row = {"scene": "links", "objects": len(gt), "k": k, "n_times_k": len(gt) * k}
        link_row.update(_row(runs))
    stack_rows = list(rows)
    if links is not None:
        rows.append(link_row)
    xs = np.array([r["n_times_k"] for r in stack_rows], dtype=float)
    fits = {}
    for name in FRAMES:
        ys = np.array([r[name]["sec_per_frame_mean"] for r in stack_rows])
        if len(xs) >= 2:
            slope, icept = np.polyfit(xs, ys, 1)
            pred = slope * xs + icept
            ss_res = float(((ys - pred) ** 2).sum())
            ss_tot = float(((ys - ys.mean()) ** 2).sum()) or 1.0
            fits[name] = {
                "sec_per_hypothesis": float(slope),
                "intercept_s": float(icept),
                "r2": 1.0 - ss_res / ss_tot,
            }
    return {
        "protocol": "parser-timing",
        "sizes": list(sizes),
        "k": k,
        "repeats": repeats,
        "seed": seed,
        "machine": {
            "python": platform.python_version(),
            "cpu": platform.processor() or "?",
            "cores_available": available_cores(),
            "processes": int(getattr(config.search, "processes", 1)),
        },
        "rows": rows,
        "linear_fit_vs_n_times_k": fits,
        "checks": _checks(rows),
    }


#: Issue 19's targets: (what, frame kind, scene, N, limit); N/N: the cost ratio of two sizes.
TARGETS = (
    ("changed frame, N = 10 (s)", "changed", "stacks", 10, 0.3),
    ("unchanged frame, N = 10 (s)", "unchanged", "stacks", 10, 0.05),
    ("changed frame, N = 20 / N = 10", "changed", "stacks", (20, 10), 2.1),
    ("added frame, N = 20 / N = 10", "added", "stacks", (20, 10), 2.1),
    ("link/node structure, added frame (s)", "added", "links", 6, 0.35),
)


def _checks(rows: Sequence[dict]) -> list[dict]:
    """Each target whose rows were measured: the value, the limit and whether it is met."""
    at = {(r["scene"], r["objects"]): r for r in rows}
    out = []
    for what, frame, scene, n, limit in TARGETS:
        if isinstance(n, tuple):
            if (scene, n[0]) not in at or (scene, n[1]) not in at:
                continue
            a, b = (at[(scene, m)][frame]["sec_per_frame_mean"] for m in n)
            value = a / b
        elif (scene, n) in at:
            value = at[(scene, n)][frame]["sec_per_frame_mean"]
        else:
            continue
        out.append({"what": what, "value": value, "limit": limit, "met": bool(value <= limit)})
    return out


def _worst(error: dict) -> str:
    """The worst object's error of a row (``-`` when the row has none: an older bench)."""
    if "ssp_mm_max" not in error:
        return "-"
    return f"{error['ssp_mm_max']:.1f} mm / {error['ssp_deg_max']:.1f} deg"


def write_report(result: dict, out: Path) -> tuple[Path, Path]:
    """``out/results.json`` and ``out/results.md`` (a table per frame kind)."""
    out.mkdir(parents=True, exist_ok=True)
    j = out / "results.json"
    j.write_text(json.dumps(result, indent=2))
    lines = [
        f"# Parser timing (k = {result['k']}, {result['repeats']} scenes per size, "
        f"{setting(result)})",
        "",
        "| N | frame | s/frame mean | s/frame max | tested | forces | stepping | contacts "
        "| scoring | other | ssp error | ssp worst | hypotheses error |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        label = row_label(r)
        for name in FRAMES:
            d = r[name]
            sh = d["stage_share"]
            lines.append(
                f"| {label} | {name} | {d['sec_per_frame_mean']:.3f} | "
                f"{d['sec_per_frame_max']:.3f} | {d['hypotheses_tested_mean']:.0f} | "
                + " | ".join(f"{100 * sh[s]:.0f} %" for s in (*STAGES, "other"))
                + f" | {d['error']['ssp_mm_mean']:.2f} mm / {d['error']['ssp_deg_mean']:.2f} deg"
                + f" | {_worst(d['error'])}"
                + f" | {d['error']['hypotheses_mm_mean']:.2f} mm / "
                + f"{d['error']['hypotheses_deg_mean']:.2f} deg |"
            )
    lines += ["", "Linear fit of s/frame against N k:", ""]
    for name, f in result["linear_fit_vs_n_times_k"].items():
        lines.append(
            f"- {name}: {1000 * f['sec_per_hypothesis']:.1f} ms per hypothesis, intercept "
            f"{f['intercept_s']:.3f} s, R^2 {f['r2']:.3f}"
        )
    if result.get("checks"):
        lines += ["", "| target | measured | limit | met |", "|---|---|---|---|"]
        lines += [
            f"| {c['what']} | {c['value']:.3f} | {c['limit']:g} | {'yes' if c['met'] else 'no'} |"
            for c in result["checks"]
        ]
    m = out / "results.md"
    m.write_text("\n".join(lines) + "\n")
    return j, m


# ------------------------------------------------------------------ side by side with a revision
_DRIVER = """
import json, sys, importlib.util
src, here, args = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
sys.path.insert(0, src)
spec = importlib.util.spec_from_file_location("ssp_bench_parser_driver", here)
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
from ssp.config import SSPConfig
from ssp.library import ObjectLibrary
cfg = SSPConfig()
if args.get("processes", 1) > 1:
    cfg.search.processes = args["processes"]
links = ObjectLibrary.from_folder(args["links"], cfg) if args["links"] else None
res = mod.bench_parser(args["sizes"], args["k"], args["repeats"], args["seed"], cfg, links=links)
print("RESULT " + json.dumps({"rows": res["rows"], "machine": res["machine"]}))
"""


def source_tree_of(rev: str, tmp: Path) -> tuple[Path, Callable[[], None]]:
    """``src`` folder of ``rev``: a checkout folder (with ``src/ssp``) as it is, else a git
    revision of the repository ssp runs from, checked out into ``tmp`` (and the call that
    removes it)."""
    import subprocess

    from ssp.errors import ArgumentError

    given = Path(rev)
    if (given / "src" / "ssp").is_dir():
        return given / "src", lambda: None
    here = Path(__file__).resolve().parent
    try:
        top = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "--show-toplevel"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()  # fmt: skip
        subprocess.run(
            ["git", "-C", top, "worktree", "add", "--detach", str(tmp), rev],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
    except (OSError, subprocess.CalledProcessError) as exc:
        err = getattr(exc, "stderr", "") or str(exc)
        raise ArgumentError(
            f"--compare {rev}: not a checkout folder, and no git revision of the repository "
            f"ssp runs from ({err.strip()})"
        ) from exc

    def remove() -> None:
        subprocess.run(["git", "-C", top, "worktree", "remove", "--force", str(tmp)], check=False)

    return tmp / "src", remove


def compare_parser(
    rev: str,
    sizes: Sequence[int] = (5, 10, 20),
    k: int = 5,
    repeats: int = 2,
    seed: int = 0,
    links: Path | None = None,
    rounds: int = 2,
    progress: Callable[[str], None] | None = None,
    processes: int = 1,
    rev_processes: int = 1,
) -> dict:
    """:func:`bench_parser` with this code and with the code of ``rev`` (a git revision or a
    checkout folder), alternately in fresh processes (``rounds`` each), on the same scenes:
    the means, their ratio (``rev`` / this code: the speed-up) and this code's stage shares.
    Side by side in one run, the ratio holds where a loaded machine's absolute times do not.
    ``processes`` / ``rev_processes``: ``search.processes`` of each side (``rev`` may predate
    it: then only 1 works).
    """
    import subprocess
    import sys
    import tempfile

    from ssp.errors import SSPError

    args = {
        "sizes": list(sizes), "k": k, "repeats": repeats, "seed": seed,
        "links": None if links is None else str(Path(links).resolve()),
    }  # fmt: skip
    here = str(Path(__file__).resolve())
    current = str(Path(__file__).resolve().parents[2])
    runs: dict[str, list] = {"rev": [], "this": []}
    machines: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="ssp-compare-") as tmp:
        src, remove = source_tree_of(rev, Path(tmp) / "tree")
        try:
            for r in range(rounds):
                for tag, tree in (("rev", str(src)), ("this", current)):
                    if progress:
                        progress(f"round {r + 1}/{rounds}: {rev if tag == 'rev' else 'this code'}")
                    side = {**args, "processes": processes if tag == "this" else rev_processes}
                    p = subprocess.run(
                        [sys.executable, "-c", _DRIVER, tree, here, json.dumps(side)],
                        capture_output=True, text=True,
                    )  # fmt: skip
                    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
                    if p.returncode or not line:
                        raise SSPError(
                            f"the parser bench failed with {rev if tag == 'rev' else 'this code'}"
                            f": {p.stderr.strip()[-2000:]}"
                        )
                    got = json.loads(line[-1][len("RESULT ") :])
                    runs[tag].append(got["rows"])
                    machines[tag] = got["machine"]
        finally:
            remove()
    rows = []
    for j, row in enumerate(runs["this"][0]):
        for name in FRAMES:
            old = float(np.mean([run[j][name]["sec_per_frame_mean"] for run in runs["rev"]]))
            new = float(np.mean([run[j][name]["sec_per_frame_mean"] for run in runs["this"]]))
            rows.append(
                {
                    "scene": row["scene"],
                    "objects": row["objects"],
                    "frame": name,
                    "rev_s": old,
                    "this_s": new,
                    "speedup": old / new if new > 0 else float("inf"),
                    "rev_tested": runs["rev"][0][j][name]["hypotheses_tested_mean"],
                    "this_tested": row[name]["hypotheses_tested_mean"],
                    "this_stage_share": row[name]["stage_share"],
                    "rev_stage_seconds": runs["rev"][0][j][name].get("stage_seconds", {}),
                    "this_stage_seconds": row[name].get("stage_seconds", {}),
                    "rev_error": runs["rev"][0][j][name]["error"],
                    "this_error": row[name]["error"],
                }
            )
    return {
        "protocol": "parser-timing-compare", "rev": rev, "rounds": rounds, **args,
        "machine": machines.get("this", {}), "rev_machine": machines.get("rev", {}),
        "rows": rows,
    }  # fmt: skip


def write_compare(result: dict, out: Path) -> tuple[Path, Path]:
    """``out/compare.json`` and ``out/compare.md``."""
    out.mkdir(parents=True, exist_ok=True)
    j = out / "compare.json"
    j.write_text(json.dumps(result, indent=2))
    lines = [
        f"# Parser timing: {result['rev']} beside this code ({result['rounds']} rounds each, "
        f"alternating; k = {result['k']}, {result['repeats']} scenes per size; "
        f"{result['rev']}: {setting({'machine': result.get('rev_machine', {})})}, "
        f"this code: {setting(result)})",
        "",
        f"| N | frame | {result['rev']} s | this s | speed-up | tested | forces | stepping "
        f"| contacts | scoring | other | error (this) | worst ({result['rev']} -> this) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        sh = r["this_stage_share"]
        label = row_label(r)
        lines.append(
            f"| {label} | {r['frame']} | {r['rev_s']:.3f} | {r['this_s']:.3f} | "
            f"{r['speedup']:.2f}x | {r['rev_tested']:.0f} -> {r['this_tested']:.0f} | "
            + " | ".join(f"{100 * sh[s]:.0f} %" for s in (*STAGES, "other"))
            + f" | {r['this_error']['ssp_mm_mean']:.2f} mm / "
            + f"{r['this_error']['ssp_deg_mean']:.2f} deg"
            + f" | {_worst(r['rev_error'])} -> {_worst(r['this_error'])} |"
        )
    m = out / "compare.md"
    m.write_text("\n".join(lines) + "\n")
    return j, m
