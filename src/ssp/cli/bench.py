"""``ssp bench``: timings and calibration (physics, calibrate, parser, estimator, soak); the
paper's experiments are in :mod:`ssp.cli.experiments`."""

from __future__ import annotations

import logging
from pathlib import Path

import typer
from rich.table import Table

from ssp.cli.common import ConfigOption, console, friendly, load_config, progress_bar

__all__ = [
    "bench_calibrate",
    "bench_docs_figures",
    "bench_camera_cmd",
    "bench_estimator_cmd",
    "bench_main",
    "bench_parser_cmd",
    "bench_physics",
    "bench_rgb_calibration_cmd",
    "bench_soak_cmd",
]


def bench_main() -> None:
    """Benchmarks; results are written to files."""
    # every frame's doubts (an object that would fall, one the camera sees through) are in the
    # estimates and the results; printed for every method and frame they would bury the table
    if logging.getLogger().level >= logging.WARNING:
        logging.getLogger("ssp.parser").setLevel(logging.ERROR)


@friendly
def bench_physics(
    out: Path = typer.Option(Path("bench-out/physics"), "--out", "-o", help="Output folder."),
    config: Path | None = ConfigOption,
    repeats: int = typer.Option(5, help="Timing repetitions (median reported)."),
) -> None:
    """Microseconds per step and per state save/restore, for 10 and 20 objects."""
    from ssp.eval.bench_physics import run_physics_bench

    results = run_physics_bench(load_config(config), out, repeats=repeats)
    table = Table(title=f"physics bench ({out / 'results.json'})")
    for col in ("scene", "objects", "step qs us", "step dyn us", "save us", "restore us"):
        table.add_column(col, justify="right")
    for r in results["scenes"]:
        table.add_row(
            r["scene"],
            str(r["objects"]),
            f"{r['step_quasi_static_us']:.0f}",
            f"{r['step_dynamic_us']:.0f}",
            f"{r['save_us']:.1f}",
            f"{r['restore_us']:.1f}",
        )
    console.print(table)


@friendly
def bench_calibrate(
    out: Path = typer.Option(Path("bench-out/calibration"), "--out", "-o", help="Output folder."),
    config: Path | None = ConfigOption,
    seeds: int = typer.Option(50, min=1, help="Seeds of the resting scenes (one set each)."),
    quick: bool = typer.Option(
        False, "--quick", help="Smoke test: towers of 2-3 cubes, bridges, one bad case of each."
    ),
) -> None:
    """Measure the stability and collision inputs on resting and bad scenes; choose s_B, a_B,
    s_c, a_c (docs/calibration.md). Writes calibration.json and calibration.png."""
    from ssp.eval.calibrate import calibrate, write_report

    kwargs = {"families": ("tower", "bridge"), "tower_sizes": (2, 3), "quick_bad": True}
    with progress_bar() as progress:
        task = progress.add_task("calibration scenes", total=None)
        result = calibrate(
            load_config(config),
            range(seeds),
            progress=lambda name: progress.update(task, advance=1, description=name),
            on_total=lambda n: progress.update(task, total=n),
            **(kwargs if quick else {}),
        )
    files = write_report(result, out)
    _print_calibration(result)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


def _print_calibration(result: dict) -> None:
    """The tables of ``ssp bench calibrate``: resting objects, bad scenes, chosen constants."""
    s = result["summary"]
    table = Table(title=f"resting objects ({result['seconds']:.1f} s, {result['scenes']} scenes)")
    for col in ("stage", "n", "beta p50", "p99", "max", "d max mm", "e_C max"):
        table.add_column(col, justify="left" if col == "stage" else "right")
    for stage, d in s["resting"].items():
        table.add_row(
            stage,
            str(d["objects"]),
            f"{d['beta']['median']:.2g}",
            f"{d['beta']['p99']:.2g}",
            f"{d['beta']['max']:.2g}",
            f"{d['depth_mm']['max']:.3f}",
            f"{d['e_c']['max']:.2g}",
        )
    console.print(table)
    bad = Table(title="bad scenes at the set pose (smallest over scenes)")
    for col in ("kind", "scenes", "beta", "d mm", "e_C"):
        bad.add_column(col, justify="left" if col == "kind" else "right")
    kinds: dict[str, list[dict]] = {}
    for row in s["bad"]:
        if row["stage"] == "set":
            kinds.setdefault(f"{row['kind']} {row['param']:g}", []).append(row)
    for kind, rows in kinds.items():
        bad.add_row(
            kind,
            str(len(rows)),
            f"{min(r['beta'] for r in rows):.2g}",
            f"{min(r['depth_mm'] for r in rows):.3f}",
            f"{min(r['e_c'] for r in rows):.2g}",
        )
    console.print(bad)
    _print_chosen(s)
    if result["rejected_scenes"]:
        console.print(
            f"[yellow]{len(result['rejected_scenes'])} scenes never came to rest and were "
            f"dropped:[/] {', '.join(result['rejected_scenes'])}"
        )


def _print_chosen(s: dict) -> None:
    """The constants the calibration chose (``s``: its summary)."""
    st, co = s["chosen"]["stability"], s["chosen"]["collision"]
    chosen = Table(title=f"chosen constants (resting basis: {s['basis_stage']})")
    for col in ("term", "steepness", "midpoint", "separates", "from"):
        chosen.add_column(col)
    chosen.add_row(
        "stability",
        f"{st['steepness']:g}",
        f"{st['midpoint']:g}",
        "yes" if st["achievable"] else "[red]no[/]",
        f"resting {st['rest_basis']} {st['rest_reference']:.3g} / bad {st['bad_reference']:.3g}",
    )
    chosen.add_row(
        "collision",
        f"{co['steepness']:g}",
        f"{co['midpoint']:g}",
        ("yes" if co["achievable"] else "[red]no[/]")
        + ("" if co["achievable_for_requested"] else f" (>= {co['bad_overlap_mm_used']:g} mm)"),
        f"resting max {co['rest_reference']:.3g} / bad {co['bad_reference']:.3g}",
    )
    chosen.add_row("min_depth", "", f"{s['chosen']['min_depth_m'] * 1000:g} mm", "", "")
    console.print(chosen)


@friendly
def bench_parser_cmd(
    out: Path = typer.Option(Path("bench-out/parser"), "--out", "-o", help="Output folder."),
    config: Path | None = ConfigOption,
    sizes: str = typer.Option("5,10,20", help="Scene sizes N (objects), comma separated."),
    k: int = typer.Option(5, min=1, help="Hypotheses per object."),
    repeats: int = typer.Option(2, min=1, help="Scenes per size."),
    seed: int = typer.Option(0, help="Seed of the scenes and the noise."),
    links: Path | None = typer.Option(
        None,
        "--links",
        help="Folder with the paper's link_uniform and node_uniform meshes (e.g. "
        "../shared/data/costar-links): adds a 6-object link/node structure.",
    ),
    compare: str | None = typer.Option(
        None,
        "--compare",
        help="A git revision (or another checkout's folder) timed beside this code, "
        "alternately in fresh processes: the speed-up per frame kind (compare.md).",
        show_default=False,
        metavar="REV",
    ),
    rounds: int = typer.Option(2, min=1, help="With --compare: runs of each code."),
    processes: int = typer.Option(
        1,
        min=1,
        max=64,
        help="search.processes: candidate tests in this many processes (issue 19's targets "
        "are for 2, on 2 cores: run with `taskset -c 0,1`). With --compare: this code's.",
    ),
    rev_processes: int = typer.Option(
        1, min=1, max=64, help="With --compare: search.processes of REV (1 before ssp.lanes)."
    ),
) -> None:
    """Seconds per frame of the scene parser (added, changed and unchanged frames) for stacks
    of N cubes and blocks on rendered depth, with the share of each stage, and whether
    issue 19's targets are met. One process unless --processes."""
    from ssp.eval.bench_parser import bench_parser, write_report

    if compare is not None:
        _bench_parser_compare(
            compare, sizes, k, repeats, seed, links, rounds, out, processes, rev_processes
        )
        return

    ns = _sizes(sizes)
    cfg = load_config(config)
    cfg.search.processes = processes
    link_lib = None if links is None else _link_library(links, cfg)
    with console.status("timing the scene parser") as status:
        result = bench_parser(
            ns, k=k, repeats=repeats, seed=seed, config=cfg, progress=status.update,
            links=link_lib,
        )  # fmt: skip
    files = write_report(result, out)
    _print_parser_bench(result, k, repeats)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


def _link_library(links: Path, cfg):
    """The models of ``--links``, which must hold the link and node meshes."""
    from ssp.library import ObjectLibrary

    with console.status(f"loading the models of {links}") as status:
        link_lib = ObjectLibrary.from_folder(links, cfg, status=status.update)
    missing = {"link_uniform", "node_uniform"} - set(link_lib.names)
    if missing:
        raise typer.BadParameter(
            f"--links {links} has no {', '.join(sorted(missing))} model "
            f"(it has {', '.join(link_lib.names)})"
        )
    return link_lib


def _print_parser_bench(result: dict, k: int, repeats: int) -> None:
    """The table of ``ssp bench parser`` and whether the targets are met."""
    from ssp.eval.bench_parser import FRAMES, STAGES, row_label, setting

    table = Table(title=f"scene parser, k = {k}, {repeats} scenes per size, {setting(result)}")
    for col in ("N", "frame", "s/frame", "max", "tested", *STAGES, "other"):
        table.add_column(col, justify="right")
    for r in result["rows"]:
        label = row_label(r)
        for name in FRAMES:
            d = r[name]
            table.add_row(
                label,
                name,
                f"{d['sec_per_frame_mean']:.3f}",
                f"{d['sec_per_frame_max']:.3f}",
                f"{d['hypotheses_tested_mean']:.0f}",
                *(f"{100 * d['stage_share'][s]:.0f} %" for s in (*STAGES, "other")),
            )
    console.print(table)
    for c in result["checks"]:
        mark = "[green]met[/]" if c["met"] else "[red]not met[/]"
        console.print(f"{c['what']}: {c['value']:.3f} (target <= {c['limit']:g}) {mark}")


def _sizes(text: str) -> tuple[int, ...]:
    """The scene sizes of ``--sizes`` (integers separated by commas)."""
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError as exc:
        raise typer.BadParameter(f"--sizes must be integers separated by commas: {exc}") from exc


def _bench_parser_compare(
    rev, sizes, k, repeats, seed, links, rounds, out, processes, rev_processes
) -> None:
    """``ssp bench parser --compare REV``."""
    from ssp.eval.bench_parser import compare_parser, row_label, setting, write_compare

    ns = _sizes(sizes)
    with console.status(f"timing {rev} beside this code") as status:
        result = compare_parser(
            rev, ns, k=k, repeats=repeats, seed=seed, links=links, rounds=rounds,
            progress=status.update, processes=processes, rev_processes=rev_processes,
        )  # fmt: skip
    files = write_compare(result, out)
    table = Table(
        title=f"scene parser: {rev} ({setting({'machine': result['rev_machine']})}) beside "
        f"this code ({setting(result)})"
    )
    for col in ("N", "frame", f"{rev} s", "this s", "speed-up", "tested"):
        table.add_column(col, justify="right")
    for r in result["rows"]:
        table.add_row(
            row_label(r),
            r["frame"],
            f"{r['rev_s']:.3f}",
            f"{r['this_s']:.3f}",
            f"{r['speedup']:.2f}x",
            f"{r['rev_tested']:.0f} -> {r['this_tested']:.0f}",
        )
    console.print(table)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


@friendly
def bench_estimator_cmd(
    out: Path = typer.Option(Path("bench-out/estimator"), "--out", "-o", help="Output folder."),
    experiment: str = typer.Option(
        "isolated", help="isolated (tools, 8 candidate classes) or structure (blocks)."
    ),
    sequences: int = typer.Option(3, min=1, help="Synthetic sequences (20 frames each)."),
    seed: int = typer.Option(1000, min=0, help="Seed of the first sequence."),
    compare: str | None = typer.Option(
        None,
        "--compare",
        help="A git revision (or another checkout's folder) run beside this code on the same "
        "segments, alternately in fresh processes: the speed-up and the recall of each "
        "(compare.md).",
        show_default=False,
        metavar="REV",
    ),
    rounds: int = typer.Option(1, min=1, help="With --compare: runs of each code."),
) -> None:
    """Seconds per segment and recall of the built-in pose estimator on Table I's rendered
    segments (the estimator alone, after its tables are built), and issue 19's target."""
    from ssp.eval.bench_estimator import bench_estimator, compare_estimator, write_report

    if experiment not in ("isolated", "structure"):
        raise typer.BadParameter(f"--experiment must be isolated or structure, not {experiment!r}")
    with console.status("timing the estimator") as status:
        if compare is None:
            result = bench_estimator(experiment, sequences, seed, progress=status.update)
        else:
            result = compare_estimator(
                compare, experiment, sequences, seed, rounds, progress=status.update
            )
    files = write_report(result, out)
    console.print(files[1].read_text())
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


@friendly
def bench_camera_cmd(
    out: Path = typer.Option(Path("bench-out/camera"), "--out", "-o", help="Output folder."),
    experiment: str = typer.Option("structure", help="isolated (tools) or structure (blocks)."),
    camera: str = typer.Option(
        "orbit,handheld,keyframes,static",
        "--camera",
        help="Comma-separated camera paths (static, orbit, handheld, keyframes).",
    ),
    sequences: int = typer.Option(2, min=1, help="Sequences per path (20 frames each)."),
    seed: int = typer.Option(1000, min=0, help="Seed of the first sequence."),
) -> None:
    """Locating a moving camera with no pose given: the table's frame (what ssp run did),
    egomotion on the map of the frames before, and egomotion told the objects; the error at
    the scene and the frames refused, per camera path (docs/benchmarks.md, moving cameras)."""
    from ssp.cli.common import load_library
    from ssp.eval.camera_bench import bench_camera, write_camera_report
    from ssp.sim.camera_path import CAMERA_PATHS

    if experiment not in ("isolated", "structure"):
        raise typer.BadParameter(f"--experiment must be isolated or structure, not {experiment!r}")
    paths = [c.strip() for c in camera.split(",") if c.strip()]
    bad = [c for c in paths if c not in CAMERA_PATHS]
    if bad or not paths:
        raise typer.BadParameter(f"--camera must list paths of {', '.join(CAMERA_PATHS)}")
    lib = load_library(None, None, None)
    with console.status("tracking cameras") as status:
        result = bench_camera(lib, experiment, paths, sequences, seed, progress=status.update)
    result["command"] = {"experiment": experiment, "camera": paths, "sequences": sequences,
                         "seed": seed}  # fmt: skip
    files = write_camera_report(result, out)
    console.print(files[1].read_text())
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


@friendly
def bench_soak_cmd(
    frames: int = typer.Option(1000, min=1, help="Length of the synthetic sequence."),
    out: Path = typer.Option(Path("bench-out/soak"), "--out", "-o", help="Output folder."),
    seed: int = typer.Option(0, help="Seed of the first structure cycle."),
    stride: int = typer.Option(4, min=1, help="Render every n-th pixel (4: 160 x 120)."),
    runner: bool = typer.Option(
        False,
        "--runner",
        help="Through ssp run (files in, crash-safe files out) instead of the parser alone.",
    ),
    config: Path | None = ConfigOption,
) -> None:
    """Wall time and memory (RSS) per frame of the scene parser over a long synthetic
    sequence (cycles of block structures built up); writes OUT/results.json."""
    from ssp.eval.bench_soak import WINDOW, bench_soak, write_report

    with progress_bar() as progress:
        task = progress.add_task("soak", total=frames)
        result = bench_soak(
            frames,
            seed=seed,
            stride=stride,
            config=load_config(config),
            runner=runner,
            progress=lambda done, total: progress.update(task, completed=done),
        )
    result["command"] = {"frames": frames, "seed": seed, "stride": stride, "runner": runner}
    path = write_report(result, out)
    s = result["summary"]
    w = min(WINDOW, frames)
    table = Table(title=f"soak: {frames} frames{' through ssp run' if runner else ''}")
    for col in ("frames", "s/frame mean", "median", "p95", "RSS MiB (end)"):
        table.add_column(col, justify="right")
    for name, rss in ((f"first_{w}", f"rss_mib_after_{w}"), (f"last_{w}", "rss_mib_end")):
        d = s[name]
        table.add_row(
            name.replace("_", " "),
            f"{d['mean']:.3f}",
            f"{d['median']:.3f}",
            f"{d['p95']:.3f}",
            f"{s[rss]:.1f}",
        )
    console.print(table)
    half = s.get("rss_growth_mib_second_half")
    console.print(
        f"RSS growth after frame {w}: {s[f'rss_growth_mib_after_{w}']:+.1f} MiB"
        + ("" if half is None else f", over the second half: {half:+.1f} MiB")
        + f"; {s['failed']} failed frames; wrote [bold]{path}[/]"
    )


@friendly
def bench_docs_figures(
    check: bool = typer.Option(False, "--check", help="Exit 1 when a figure differs."),
    write: bool = typer.Option(False, "--write", help="Render every complete figure block."),
    collect: Path | None = typer.Option(
        None,
        help="Copy the results files of the bench runs under this folder (one per "
        "source, named as in examples/docs_figures.sh) into docs/results first.",
    ),
    strict: bool = typer.Option(
        False, "--strict", help="With --check: a figure whose results are missing fails too."
    ),
    root: Path = typer.Option(Path("."), help="The repository's root (README.md, docs/)."),
) -> None:
    """The figures the docs quote (README.md, docs/*.md), from the bench results under
    docs/results (ssp.eval.docs_figures): --collect copies them, --write renders every marked
    block, --check names each block or sentence that says other figures."""
    from ssp.eval import docs_figures as df

    if collect is not None:
        for f in df.collect(collect, root):
            console.print(f"copied [bold]{f}[/]")
    if write:
        changed = df.write(root)
        console.print(f"rewrote {', '.join(changed) if changed else 'nothing'}")
    problems = df.check(root)
    for p in problems:
        color = "yellow" if p.kind == "incomplete" else "red"
        console.print(f"[{color}]{p.kind}[/] {p}", highlight=False, soft_wrap=True)
    failed = [p for p in problems if strict or p.kind != "incomplete"]
    if not problems:
        console.print("every figure block and sentence matches its results")
    if check and failed:
        raise typer.Exit(1)


@friendly
def bench_rgb_calibration_cmd(
    data: Path = typer.Option(
        ...,
        "--data",
        help=(
            "A BOP dataset folder with models/models_info.json, test/<scene>/scene_gt.json and "
            "scene_gt_info.json, and a BOP19 results CSV of an RGB estimator (e.g. "
            "../shared/data/lmo-megapose)."
        ),
    ),
    out: Path = typer.Option(
        Path("bench-out/rgb-calibration"), "--out", "-o", help="Output folder."
    ),
    csv: Path | None = typer.Option(
        None, "--csv", help="The results CSV (default: the one in --data)."
    ),
) -> None:
    """How a real RGB pose estimator errs against ground truth: along-ray, lateral and rotation
    errors, flips, far outliers, misses and rows per target by visible fraction, scores (the
    numbers behind `--noise rgb`); writes results.json and results.md."""
    from ssp.eval.rgb_calibration import calibrate_rgb, write_rgb_calibration

    result = calibrate_rgb(data, csv)
    files = write_rgb_calibration(result, out)
    console.print(files[1].read_text(), highlight=False)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


@friendly
def bench_frame_cmd(
    out: Path = typer.Option(Path("bench-out/frame"), "--out", "-o", help="Output folder."),
    sequences: int = typer.Option(
        1,
        min=1,
        help="Simulated sequences per experiment (20-24 frames each: 2-3 stages of 4 frames, "
        "then the realistic stream's moves and pushes).",
    ),
    seed: int = typer.Option(1000, min=0, help="Seed of the first sequence."),
    real_dev: Path | None = typer.Option(
        None,
        "--real-dev",
        help="The real captures' folder (../shared/data/real-dev): also time them.",
        show_default=False,
        metavar="DIR",
    ),
    repeats: int = typer.Option(5, min=2, help="Frames of each real capture's sequence."),
    compare: str | None = typer.Option(
        None,
        "--compare",
        help="A git revision (or another checkout's folder) timed beside this code on the same "
        "inputs, alternately in fresh processes: both and the speed-up (results.md).",
        show_default=False,
        metavar="REV",
    ),
    rounds: int = typer.Option(1, min=1, help="Runs of each code over every input."),
    processes: int = typer.Option(
        1, min=1, max=64, help="As ssp run --processes: estimator and search processes."
    ),
) -> None:
    """Whole-frame latency of ssp run (reading to writing) on 640 x 480 frames: simulated
    clutter with masks and without, hypotheses given and estimated, and the real captures;
    median, p95, the stages' shares, and issue 34's targets. Writes results.json, results.md
    and shares.png."""
    from ssp.eval.bench_frame import bench_frame, write_report

    if out.is_symlink():
        raise typer.BadParameter(f"--out {out} is a symbolic link; give the folder itself")
    with console.status("timing whole frames") as status:
        result = bench_frame(out, sequences=sequences, seed=seed, real_dev=real_dev,
                             repeats=repeats, compare=compare, rounds=rounds,
                             processes=processes, progress=status.update)  # fmt: skip
    files = write_report(result, out)
    console.print(files[1].read_text())
    for f in files:
        console.print(f"wrote [bold]{f}[/]")
