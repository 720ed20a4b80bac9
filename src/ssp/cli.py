"""The ``ssp`` command line. The only module that prints; heavy imports happen inside commands."""

from __future__ import annotations

import json
import logging
import signal
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from ssp import __version__

app = typer.Typer(
    name="ssp",
    help=(
        "Sequential Scene Parsing: physically and temporally consistent object poses.\n\n"
        "Examples:\n\n"
        "  ssp models list                      # the built-in object models\n\n"
        "  ssp models prepare path/to/meshes    # validate + convex-decompose a model folder\n\n"
        "  ssp bench physics --out bench-out    # physics engine timings\n\n"
        "  ssp bench calibrate --out cal-out    # measure the stability/collision constants\n\n"
        "  ssp dump-config > ssp.yaml           # every setting, with defaults"
    ),
    no_args_is_help=True,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
)
models_app = typer.Typer(help="List, inspect and pre-compute object models.", no_args_is_help=True)
bench_app = typer.Typer(help="Benchmarks; results are written to files.", no_args_is_help=True)
app.add_typer(models_app, name="models")
app.add_typer(bench_app, name="bench")

console = Console()
err_console = Console(stderr=True)
_state = {"debug": False}

F = TypeVar("F", bound=Callable[..., Any])


def _friendly(fn: F) -> F:
    """Turn ssp's typed errors and file-system errors (a folder that cannot be written, a full
    disk) into a one-line message and exit code 1; Ctrl-C into exit code 130. Tracebacks with
    --debug; any other exception is a bug and keeps its traceback."""

    @wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from ssp.errors import SSPError

        try:
            return fn(*args, **kwargs)
        except (SSPError, OSError) as exc:
            if _state["debug"]:
                raise
            err_console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            if _state["debug"]:
                raise
            err_console.print("[bold red]interrupted[/]")
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


def _version_callback(value: bool) -> None:
    if value:
        import mujoco

        console.print(f"ssp {__version__} (mujoco {mujoco.__version__})")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version."
    ),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks on errors."),
) -> None:
    """Sequential Scene Parsing."""
    _state["debug"] = debug
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


@bench_app.callback()
def bench_main() -> None:
    """Benchmarks; results are written to files."""
    # every frame's doubts (an object that would fall, one the camera sees through) are in the
    # estimates and the results; printed for every method and frame they would bury the table
    if logging.getLogger().level >= logging.WARNING:
        logging.getLogger("ssp.parser").setLevel(logging.ERROR)


ConfigOption = typer.Option(None, "--config", "-c", help="YAML config file (partial is fine).")


def _config(path: Path | None):
    from ssp.config import SSPConfig, load_config

    return load_config(path) if path else SSPConfig()


@app.command("dump-config")
@_friendly
def dump_config_cmd(
    config: Path | None = ConfigOption,
    out: Path | None = typer.Option(None, "--out", "-o", help="Write to this file."),
) -> None:
    """Print the effective configuration as YAML (defaults, or --config merged over them)."""
    from ssp.config import dump_config

    text = dump_config(_config(config), out)
    if out is None:
        print(text, end="")
    else:
        console.print(f"wrote {out}")


CacheOption = typer.Option(
    None, "--cache", help="Hull cache folder (default: $SSP_CACHE_DIR, else ~/.cache/ssp)."
)


def _library_config(config: Path | None, cache: Path | None):
    cfg = _config(config).library
    return cfg if cache is None else cfg.model_copy(update={"cache_dir": cache})


def _library(models: Path | None, config: Path | None, cache: Path | None = None):
    """The built-in library, or the model folder ``models``, with a progress bar.

    Models of the folder that cannot be built are skipped, each with its reason printed."""
    from ssp.library import ObjectLibrary
    from ssp.library.properties import read_folder

    cfg = _library_config(config, cache)
    if models is None:
        return ObjectLibrary.builtin(cfg)
    with _bar() as progress:
        task = progress.add_task(f"loading {models}", total=len(read_folder(models)))
        lib = ObjectLibrary.from_folder(
            models,
            cfg,
            progress=lambda name: progress.update(task, advance=1),
            status=lambda text: progress.update(task, description=text[:70]),
            on_error="skip",
        )
    for name, why in lib.skipped.items():
        err_console.print(f"[yellow]skipped model {name}:[/] {why}")
    return lib


ModelsArg = typer.Argument(None, help="Model folder (default: the built-in models).")
JsonOption = typer.Option(False, "--json", help="Machine-readable output.")


@models_app.command("list")
@_friendly
def models_list(
    models: Path | None = ModelsArg,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    as_json: bool = JsonOption,
) -> None:
    """One line per model: size, mass, convex parts, symmetries (skipped models with why)."""
    lib = _library(models, config, cache)
    if as_json:
        out = {
            "models": [
                {
                    **lib[n].summary(),
                    "decomposition_seconds": round(lib[n].decomposition.seconds, 3),
                    "decomposition_cached": lib[n].decomposition.cached,
                }
                for n in lib.names
            ],
            "skipped": lib.skipped,
        }
        print(json.dumps(out, indent=2))
        return
    table = Table(title=f"models ({'built-in' if models is None else models})")
    for col in ("name", "extents mm", "mass kg", "parts", "decomposition", "hull IoU", "sym"):
        table.add_column(col, justify="left" if col in ("name", "decomposition") else "right")
    for name in lib.names:
        s = lib[name].summary()
        sym = f"{s['discrete_symmetries']}" + ("+cont" if s["continuous_symmetries"] else "")
        iou = f"{s['hull_iou']:.3f}" + (" [yellow](low)[/]" if s["decomposition_warnings"] else "")
        table.add_row(
            name,
            " x ".join(f"{x:.1f}" for x in s["extents_mm"]),
            f"{s['mass_kg']:.3f}",
            str(s["convex_parts"]),
            s["decomposition"],
            iou,
            sym,
        )
    for name in lib.skipped:
        table.add_row(f"[red]{name}[/]", "", "", "", "[red]skipped[/]", "", "")
    console.print(table)


@models_app.command("show")
@_friendly
def models_show(
    name: str = typer.Argument(..., help="Model name."),
    models: Path | None = ModelsArg,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    as_json: bool = JsonOption,
    tolerance: float = typer.Option(
        0.002, min=0.0, help="MSSD tolerance (m) of the listed approximate symmetries."
    ),
) -> None:
    """Everything about one model: mass properties, samples, decomposition, symmetries
    (declared, and approximate ones detected within --tolerance)."""
    from ssp.library.build import cached_symmetry_detection
    from ssp.library.decomposition import default_cache_dir

    cfg = _library_config(config, cache)
    model = _library(models, config, cache)[name]
    summary = model.summary()
    summary["max_angular_acceleration_rad_s2"] = round(
        model.max_angular_acceleration(_config(config).physics.gravity), 2
    )
    summary["decomposition_seconds"] = round(model.decomposition.seconds, 3)
    summary["decomposition_cached"] = model.decomposition.cached
    if model.decomposition.note:
        summary["decomposition_note"] = model.decomposition.note
    detected = model.detected_symmetry
    if detected is None or abs(detected.tolerance - tolerance) > 1e-12:
        detected = cached_symmetry_detection(
            model.mesh, model.center_of_mass, model.inertia, tolerance, default_cache_dir(cfg)
        )
    summary["detected_symmetries"] = detected.to_dict()
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    table = Table(title=f"model {name}", show_header=False)
    for k, v in summary.items():
        table.add_row(k, str(v))
    console.print(table)


@models_app.command("prepare")
@_friendly
def models_prepare(
    folder: Path = typer.Argument(..., help="Folder of meshes (+ optional models.yaml)."),
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    as_json: bool = JsonOption,
) -> None:
    """Validate every model of a folder, pre-compute its convex decomposition and detect its
    approximate symmetries (both cached).

    Exits with code 1 when any model failed; the others are still prepared.
    """
    from ssp.library import prepare_folder
    from ssp.library.properties import read_folder

    cfg = _library_config(config, cache)
    with _bar() as progress:
        task = progress.add_task(f"preparing {folder}", total=len(read_folder(folder)))
        rows = prepare_folder(
            folder,
            cfg,
            progress=lambda n: progress.update(task, advance=1),
            status=lambda text: progress.update(task, description=text[:70]),
        )
    failed = sum(bool(r.get("error")) for r in rows)
    if as_json:
        print(json.dumps({"folder": str(folder), "models": rows}, indent=2, default=str))
    else:
        table = Table(title=f"prepared {folder}")
        for col in ("name", "parts", "method", "hull IoU", "seconds", "cached", "sym", "error"):
            table.add_column(col)
        for r in rows:
            err = r.get("error") or ""
            det = r.get("detected_symmetries") or {}
            iou = f"{r['iou']:.3f}" if r.get("iou") is not None else ""
            if r.get("warnings"):
                iou += " [yellow](low)[/]"
            table.add_row(
                r["name"],
                str(r.get("n_parts", "")),
                str(r.get("method", "")),
                iou,
                f"{r['seconds']:.2f}" if r.get("seconds") is not None else "",
                str(r.get("cached", "")),
                f"{r['symmetries']} ({det.get('discrete_symmetries', '?')} detected)"
                if r.get("symmetries") is not None
                else "",
                f"[red]{err}[/]" if err else "",
            )
        console.print(table)
        for r in rows:
            for w in r.get("warnings") or ():
                err_console.print(f"[yellow]warning[/] {r['name']}: {w}")
    if failed:
        err_console.print(f"[bold red]{failed} of {len(rows)} models failed[/]")
        raise typer.Exit(1)


@models_app.command("export-builtin")
@_friendly
def models_export_builtin(
    folder: Path = typer.Argument(..., help="Folder to write the built-in models to."),
) -> None:
    """Write the built-in models as meshes + convex parts + models.yaml (a template folder)."""
    from ssp.library.builtin import export_builtin

    paths = export_builtin(folder)
    console.print(f"wrote {len(paths)} files to {folder}")


@bench_app.command("physics")
@_friendly
def bench_physics(
    out: Path = typer.Option(Path("bench-out/physics"), "--out", "-o", help="Output folder."),
    config: Path | None = ConfigOption,
    repeats: int = typer.Option(5, help="Timing repetitions (median reported)."),
) -> None:
    """Microseconds per step and per state save/restore, for 10 and 20 objects."""
    from ssp.eval.bench_physics import run_physics_bench

    results = run_physics_bench(_config(config), out, repeats=repeats)
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


@bench_app.command("calibrate")
@_friendly
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
    with _bar() as progress:
        task = progress.add_task("calibration scenes", total=None)
        result = calibrate(
            _config(config),
            range(seeds),
            progress=lambda name: progress.update(task, advance=1, description=name),
            on_total=lambda n: progress.update(task, total=n),
            **(kwargs if quick else {}),
        )
    files = write_report(result, out)
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
    if result["rejected_scenes"]:
        console.print(
            f"[yellow]{len(result['rejected_scenes'])} scenes never came to rest and were "
            f"dropped:[/] {', '.join(result['rejected_scenes'])}"
        )
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


@bench_app.command("parser")
@_friendly
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
    from ssp.eval.bench_parser import (
        FRAMES,
        STAGES,
        bench_parser,
        row_label,
        setting,
        write_report,
    )
    from ssp.library import ObjectLibrary

    if compare is not None:
        _bench_parser_compare(
            compare, sizes, k, repeats, seed, links, rounds, out, processes, rev_processes
        )
        return

    ns = _sizes(sizes)
    cfg = _config(config)
    cfg.search.processes = processes
    link_lib = None
    if links is not None:
        with console.status(f"loading the models of {links}") as status:
            link_lib = ObjectLibrary.from_folder(links, cfg, status=status.update)
        missing = {"link_uniform", "node_uniform"} - set(link_lib.names)
        if missing:
            raise typer.BadParameter(
                f"--links {links} has no {', '.join(sorted(missing))} model "
                f"(it has {', '.join(link_lib.names)})"
            )
    with console.status("timing the scene parser") as status:
        result = bench_parser(
            ns, k=k, repeats=repeats, seed=seed, config=cfg, progress=status.update,
            links=link_lib,
        )  # fmt: skip
    files = write_report(result, out)
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
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


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


@bench_app.command("estimator")
@_friendly
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


@bench_app.command("soak")
@_friendly
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

    with _bar() as progress:
        task = progress.add_task("soak", total=frames)
        result = bench_soak(
            frames,
            seed=seed,
            stride=stride,
            config=_config(config),
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


ExperimentOption = typer.Option(
    "structure", "--experiment", "-e", help="isolated (tools apart) or structure (blocks built up)."
)
ModelsOption = typer.Option(
    None, "--models", "-m", help="Model folder (default: the built-in models)."
)


StagesOption = typer.Option(5, min=1, help="Static scenes per sequence.")
FramesOption = typer.Option(4, min=1, help="Repeated frames of each static scene.")
StrideOption = typer.Option(1, min=1, help="Render every n-th pixel (1: 640 x 480).")
ExecutorOption = typer.Option(
    None,
    "--executor",
    help=(
        "serial, processes or ray: how independent sequences / trials run (default: serial "
        "for --workers 1, else processes). Results are those of the serial run."
    ),
    show_default=False,
)
WorkersOption = typer.Option(
    1, "--workers", "-j", min=1, help="Worker processes (or CPUs of a local Ray), one core each."
)
ProcessesOption = typer.Option(
    None,
    "--processes",
    min=1,
    max=64,
    help="Processes per frame (search.processes and perception.processes, Linux): an object's "
    "candidates simulated at once, and the segments' hypotheses estimated at once; the results "
    "are the same for any number. 2 on a 2-core machine.",
    show_default=False,
)
RayAddressOption = typer.Option(
    None,
    "--ray-address",
    help="Join this Ray cluster (e.g. auto, ray://host:10001) instead of a local Ray.",
    show_default=False,
)


def _parallel(executor: str | None, workers: int, ray_address: str | None):
    """The :class:`ssp.executor.Parallel` of the --executor, --workers, --ray-address options."""
    from ssp.errors import ArgumentError
    from ssp.executor import Parallel

    try:
        return Parallel.from_options(executor, workers, ray_address)
    except ArgumentError as exc:
        raise typer.BadParameter(str(exc)) from None


def _bar():
    """A transient progress bar on stderr."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        console=err_console,
        transient=True,
    )


def _experiment(name: str) -> str:
    if name not in ("isolated", "structure"):
        raise typer.BadParameter(f"--experiment must be isolated or structure, not {name!r}")
    return name


def _experiment_library(
    experiment: str, models: Path | None, config: Path | None, cache: Path | None
):
    """The library of a synthetic experiment; a one-line error when it cannot be run on it."""
    lib = _library(models, config, cache)
    missing = [c for c in ("cube", "block") if c not in lib]
    if experiment == "structure" and missing:
        from ssp.errors import UnknownObjectError

        raise UnknownObjectError(
            f"--experiment structure builds its scenes of the classes 'cube' and 'block', and "
            f"{models} has no {' or '.join(repr(m) for m in missing)}: use the built-in models "
            "(no --models) or add those models to the folder"
        )
    return lib


@app.command()
@_friendly
def simulate(
    out: Path = typer.Option(Path("sim-out"), "--out", "-o", help="Output folder."),
    experiment: str = ExperimentOption,
    sequences: int = typer.Option(1, min=1, help="Number of sequences."),
    seed: int = typer.Option(
        0, help="Seed of the first sequence (0-99 development, 1000+ reports)."
    ),
    models: Path | None = ModelsOption,
    stages: int = StagesOption,
    frames_per_stage: int = FramesOption,
    stride: int = StrideOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
) -> None:
    """Write synthetic sequences (depth, masks, ground truth, hypotheses) in BOP layout."""
    from ssp.sim.bop import simulate_to_disk

    experiment = _experiment(experiment)
    lib = _experiment_library(experiment, models, config, cache)
    with _bar() as progress:
        task = progress.add_task(f"simulating {experiment}", total=sequences)
        paths = simulate_to_disk(
            experiment,
            sequences,
            seed,
            None,
            out,
            library=lib,
            stages=stages,
            frames_per_stage=frames_per_stage,
            stride=stride,
            progress=lambda done, total, path: progress.update(task, completed=done),
        )
    for p in paths:
        console.print(f"wrote [bold]{p}[/]")


def _methods(text: str) -> list[str]:
    """The ``--methods`` list, checked against :data:`ssp.eval.baselines.METHODS`."""
    from ssp.eval.baselines import METHODS

    names = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in names if m not in METHODS]
    if unknown or not names:
        raise typer.BadParameter(f"--methods: unknown {unknown}; known: {', '.join(METHODS)}")
    return names


def _print_table1(result: dict) -> None:
    table = Table(
        title=(
            f"Table I, {result['experiment']}: {result['sequences']} sequences, {result['frames']} "
            f"frames; induced noise {result['induced_noise']['trans_mm_mean']:.2f} mm / "
            f"{result['induced_noise']['rot_deg_mean']:.2f} deg"
        )
    )
    cols = (
        "method",
        "accuracy mm / deg",
        "common mm / deg",
        "precision mm / deg",
        "pen. mm",
        "unsup.",
        "s/frame",
    )
    for col in cols:
        table.add_column(col, justify="left" if col == "method" else "right")

    def pair(d: dict) -> str:
        t, r = d.get("trans_mm_mean"), d.get("rot_deg_mean")
        return "-" if t is None else f"{t:.2f} / {r:.2f}"

    for name, m in result["methods"].items():
        table.add_row(
            name,
            pair(m["accuracy"]),
            pair(m.get("accuracy_common", {})),
            pair(m["precision"]),
            f"{m['max_penetration_mm']:.2f}",
            f"{m['unsupported_objects']:.2f}",
            f"{m['sec_per_frame']:.3f}",
        )
    console.print(table)
    tails = Table(title="Tails: BOP average recall, gross errors, false objects, id switches")
    for col in ("method", "AR", "VSD / MSSD / MSPD", "gross", "gross, visible", "missed / frame",
                "false / frame", "id switches (static)"):  # fmt: skip
        tails.add_column(col, justify="left" if col == "method" else "right")
    for name, m in result["methods"].items():
        b = m["bop"]
        sw = m.get("id_switches")
        tails.add_row(
            name,
            f"{b['AR']:.3f}",
            f"{b.get('AR_VSD', float('nan')):.3f} / {b['AR_MSSD']:.3f} / {b['AR_MSPD']:.3f}",
            f"{m['gross_rate']:.3f}",
            f"{m['gross_rate_visible']:.3f}",
            f"{m['missed_per_frame']:.2f}",
            f"{m['false_positives_per_frame']:.2f}",
            "-" if sw is None else f"{sw} ({m['id_switches_static']})",
        )
    console.print(tails)


@bench_app.command("table1")
@_friendly
def bench_table1(
    out: Path = typer.Option(Path("bench-out/table1"), "--out", "-o", help="Output folder."),
    experiment: str = ExperimentOption,
    sequences: int = typer.Option(10, min=1, help="Number of sequences."),
    seed: int = typer.Option(
        1000, help="Seed of the first sequence (0-99 development, 1000+ reports)."
    ),
    models: Path | None = ModelsOption,
    stages: int = StagesOption,
    frames_per_stage: int = FramesOption,
    stride: int = StrideOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    hypotheses: str = typer.Option(
        "noisy",
        "--hypotheses",
        help=(
            "noisy: noisy ground truth (the --noise model); estimated: the perception front "
            "end's pose hypotheses on the rendered depth (also reports its time and recall)."
        ),
    ),
    noise: str = typer.Option(
        "paper",
        "--noise",
        help=(
            "paper: the paper's protocol (independent Gaussian hypotheses, clean masks, static "
            "scenes); realistic: the realistic estimator stream (gross outliers, flips, class "
            "confusions, false positives, persistent errors, dropouts) in scenes with "
            "distractors, mask defects and dynamic events (docs/benchmarks.md)."
        ),
    ),
    methods: str | None = typer.Option(
        None, help="Comma-separated methods to compare (default: ssp and all six baselines)."
    ),
    vsd: bool = typer.Option(True, help="Include VSD in the BOP average recall (slower)."),
    executor: str | None = ExecutorOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
) -> None:
    """The paper's Table I: ssp and its baselines on the same synthetic sequences, with the BOP
    average recall, gross errors, false objects and id switches; writes results.json,
    results.md and plots."""
    from ssp.eval.table1 import (
        DEFAULT_METHODS,
        SequenceSpec,
        merge_table1,
        run_table1_parts,
        write_table1,
    )
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    if hypotheses not in ("noisy", "estimated"):
        raise typer.BadParameter("--hypotheses must be 'noisy' or 'estimated'")
    if noise not in ("paper", "realistic"):
        raise typer.BadParameter("--noise must be 'paper' or 'realistic'")
    names = _methods(methods) if methods else list(DEFAULT_METHODS)
    experiment = _experiment(experiment)
    parallel = _parallel(executor, workers, ray_address)
    cfg = _config(config)
    lib = _experiment_library(experiment, models, config, cache)
    realistic = noise == "realistic"
    specs = [
        SequenceSpec(
            experiment,
            seed + i,
            stages=stages,
            frames_per_stage=frames_per_stage,
            stride=stride,
            realistic=realistic,
            estimated=hypotheses == "estimated",
        )
        for i in range(sequences)
    ]
    with _bar() as progress:
        task = progress.add_task(f"{experiment} sequences", total=sequences)
        parts = run_table1_parts(
            specs,
            lib,
            cfg,
            methods=names,
            progress=lambda msg: progress.update(task, description=msg),
            vsd=vsd,
            parallel=parallel,
            on_sequence=lambda done, total: progress.update(task, completed=done),
        )
    result = merge_table1(parts, names)
    records = [{"sequence": p.index, **r} for p in parts for r in p.estimator_records]
    result["hypotheses"] = hypotheses
    result["noise"] = noise
    if realistic:
        result["protocol_settings"] = {
            "estimator": RealisticNoise().to_dict(),
            "scene": SceneRealism().to_dict(),
            "events": [p.info.get("events") for p in parts],
            "events_skipped": [p.info.get("events_skipped") for p in parts],
        }
    if records:
        from ssp.eval.estimated import summarize_estimator

        result["estimator"] = summarize_estimator(records)
        result["estimator_records"] = records
    result["command"] = {
        "experiment": experiment,
        "sequences": sequences,
        "seed": seed,
        "models": None if models is None else str(models),
        "stages": stages,
        "frames_per_stage": frames_per_stage,
        "stride": stride,
        "hypotheses": hypotheses,
        "noise": noise,
        "methods": names,
        "vsd": vsd,
    }
    files = write_table1(result, out)
    _print_table1(result)
    if "estimator" in result:
        e = result["estimator"]
        console.print(
            f"pose estimator: {e['sec_per_segment_mean']:.3f} s per segment (median "
            f"{e['sec_per_segment_median']:.3f}, {e['segments']} segments); recall within "
            f"{e['recall_mm']:.0f} mm / {e['recall_deg']:.0f} deg: {e['recall']:.2f} of all "
            f"objects, {e['recall_visible']:.2f} of those >= 10 % visible (top-1 "
            f"{e['top1_recall_visible']:.2f})"
        )
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


def _print_tower(result: dict) -> None:
    table = Table(
        title=(
            f"Tower case study (Table III): {result['trials']} trials, seed {result['seed']}, "
            f"{result['hypotheses']} hypotheses, {result['command']['noise']} noise"
        )
    )
    for col in ("method", "stacks", "8/8", "straightness mm / deg", "consistency mm / deg",
                "s/frame", "failures"):  # fmt: skip
        table.add_column(col, justify="left" if col in ("method", "failures") else "right")

    def pair(a, b) -> str:
        return "-" if a is None else f"{a:.2f} / {b:.2f}"

    for name, m in result["methods"].items():
        table.add_row(
            name,
            f"{m['stacks_mean']:.2f} ± {m['stacks_std']:.2f}",
            f"{m['full_towers']}/{result['trials']}",
            pair(m["straightness_mm"], m["straightness_deg"]),
            pair(m["consistency_mm"], m["consistency_deg"]),
            "-" if m["sec_per_frame"] is None else f"{m['sec_per_frame']:.3f}",
            ", ".join(f"{k}: {v}" for k, v in sorted(m["failures"].items())) or "none",
        )
    console.print(table)


@bench_app.command("stream")
@_friendly
def bench_stream(
    out: Path = typer.Option(Path("bench-out/stream"), "--out", "-o", help="Output folder."),
    experiment: str = ExperimentOption,
    sequences: int = typer.Option(5, min=1, help="Number of sequences."),
    seed: int = typer.Option(0, help="Seed of the first sequence (development seeds: 0-99)."),
    config: Path | None = ConfigOption,
    executor: str | None = ExecutorOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
) -> None:
    """The realistic estimator stream beside the built-in estimator it is calibrated to: the
    same failure statistics of both on the same scenes; writes results.json and results.md."""
    from ssp.eval.bench_stream import run_stream_calibration, write_stream_calibration

    experiment = _experiment(experiment)
    parallel = _parallel(executor, workers, ray_address)
    cfg = _config(config)
    lib = _library(None, config)
    with _bar() as progress:
        task = progress.add_task("stream", total=sequences)
        result = run_stream_calibration(
            experiment,
            range(seed, seed + sequences),
            lib,
            cfg,
            progress=lambda msg: progress.update(task, advance=1, description=msg),
            parallel=parallel,
        )
    files = write_stream_calibration(result, out)
    console.print(files[1].read_text())
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


@bench_app.command("tower")
@_friendly
def bench_tower(
    out: Path = typer.Option(Path("bench-out/tower"), "--out", "-o", help="Output folder."),
    trials: int = typer.Option(10, min=1, help="Trials per method."),
    seed: int = typer.Option(1000, help="Seed (0-99 development, 1000+ reports)."),
    hypotheses: str = typer.Option(
        "noisy",
        "--hypotheses",
        help=(
            "noisy: ground truth with Table I's structure noise; estimated: the perception "
            "front end's hypotheses on the rendered depth."
        ),
    ),
    methods: str = typer.Option("ssp,estimator", help="Comma-separated methods to compare."),
    frames_per_step: int = typer.Option(
        3, min=1, help="Frames perceived before each pick (the method sees them all)."
    ),
    noise: str = typer.Option(
        "structure",
        "--noise",
        help=(
            "Noisy hypotheses: structure (Table I's structure noise), case-study (its sigmas "
            "scaled so the estimator fluctuates as ObjRecRANSAC did in the paper's Table III) "
            "or realistic (the realistic estimator stream, distractors on the table and mask "
            "defects: docs/benchmarks.md)."
        ),
    ),
    config: Path | None = ConfigOption,
    executor: str | None = ExecutorOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
) -> None:
    """The paper's case study (Table III): a simulated robot stacks 8 cubes from perceived
    poses; writes results.json, results.md and a picture of a final tower per method."""
    from ssp.eval.tower import (
        HYPOTHESES,
        NOISE_PRESETS,
        noise_preset,
        run_tower,
        tower_picture,
        write_tower,
    )
    from ssp.sim.realistic import RealisticNoise, SceneRealism

    if noise not in (*NOISE_PRESETS, "realistic"):
        raise typer.BadParameter(f"--noise must be one of {', '.join(NOISE_PRESETS)}, realistic")
    if hypotheses not in HYPOTHESES:
        raise typer.BadParameter(f"--hypotheses must be one of {', '.join(HYPOTHESES)}")
    names = _methods(methods)
    parallel = _parallel(executor, workers, ray_address)
    cfg = _config(config)
    lib = _library(None, config)
    pictures = {}

    with _bar() as progress:
        task = progress.add_task("tower", total=trials * len(names))

        def on_trial(name: str, t: int, trial) -> None:
            progress.update(task, advance=1)
            if t == 0:
                pictures[name] = tower_picture(lib, trial, name)

        result = run_tower(
            trials,
            seed,
            lib,
            cfg,
            methods=names,
            hypotheses=hypotheses,
            frames_per_step=frames_per_step,
            noise=RealisticNoise() if noise == "realistic" else noise_preset(noise),
            realism=SceneRealism(events=()) if noise == "realistic" else None,
            progress=lambda msg: progress.update(task, description=msg),
            on_trial=on_trial,
            parallel=parallel,
        )
    result["command"] = {
        "trials": trials,
        "seed": seed,
        "hypotheses": hypotheses,
        "methods": names,
        "frames_per_step": frames_per_step,
        "noise": noise,
    }
    files = write_tower(result, out, pictures)
    _print_tower(result)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


def _bag_option(name: str, what: str):
    return typer.Option(
        None,
        name,
        help=f"ROS bag input: the {what} (default: detected).",
        show_default=False,
        rich_help_panel="ROS bag input",
    )


@app.command("run")
@_friendly
def run_cmd(
    inputs: list[Path] | None = typer.Argument(
        None,
        help=(
            "A folder of PLY/PCD frames, a BOP scene folder, or a ROS bag (.bag, .mcap, ROS 2 "
            "folder) (with --resume: the recorded one when omitted). Several: each is run "
            "into OUT/<its folder name>/ (with --workers, in parallel)."
        ),
        show_default=False,
        metavar="INPUT",
    ),
    models: Path | None = ModelsOption,
    out: Path | None = typer.Option(
        None,
        "--out",
        "-o",
        help="Output folder, new or empty (default: ssp-out).",
        show_default=False,
    ),  # fmt: skip
    resume: Path | None = typer.Option(
        None,
        "--resume",
        help=(
            "Continue the stopped run in this output folder from its saved state; the input, "
            "--models, --config and options must be those it started with (omitted: the "
            "recorded ones)."
        ),
        show_default=False,
    ),
    overwrite: bool = typer.Option(
        False, "--overwrite", help="Clear an earlier run's files in --out first."
    ),
    hypotheses: str | None = typer.Option(
        None,
        "--hypotheses",
        help=(
            "auto (default): the input's hypotheses when present, else the built-in "
            "estimator; given: only the input's; estimated: always the built-in estimator."
        ),
        show_default=False,
    ),
    classes: str | None = typer.Option(
        None,
        help=(
            "Comma-separated candidate classes of the estimator (default: those a BOP scene "
            "lists, else every model)."
        ),
    ),
    method: str | None = typer.Option(
        None,
        help="BOP method name in the CSV file name, no '_' (default: ssp).",
        show_default=False,
    ),  # fmt: skip
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    topic_cloud: str | None = _bag_option("--topic-cloud", "PointCloud2 topic of the frames"),
    topic_depth: str | None = _bag_option("--topic-depth", "depth Image topic of the frames"),
    topic_camera_info: str | None = _bag_option("--topic-camera-info", "CameraInfo topic"),
    topic_mask: str | None = _bag_option("--topic-mask", "instance mask Image topic"),
    topic_hypotheses: str | None = _bag_option(
        "--topic-hypotheses", "Detection3DArray (or JSON String) topic of the hypotheses"
    ),
    world_frame: str | None = _bag_option(
        "--world-frame", "tf frame of the world (z up, table top at z = 0) for the camera pose"
    ),
    class_map: str | None = _bag_option(
        "--class-map", "detection class id -> class: ID=CLASS,... or a JSON/YAML file"
    ),
    masks: str | None = typer.Option(
        None,
        "--masks",
        help=(
            "BOP scene input: auto (default: an ssp scene's simulated segmentation, none for a "
            "published one), gt (the ground-truth mask_visib: an upper bound), none."
        ),
        show_default=False,
    ),
    period: float | None = typer.Option(
        None,
        "--period",
        help="BOP scene input: seconds between images of a scene without stamps (1/30).",
        show_default=False,
    ),
    results_bag: Path | None = typer.Option(
        None,
        "--results-bag",
        help="ROS bag input: also write the results to this new bag (.bag: ROS 1, .mcap: "
        "MCAP, else a ROS 2 folder).",
        show_default=False,
        rich_help_panel="ROS bag input",
    ),
    record: Path | None = typer.Option(
        None,
        "--record",
        help="Also write a 3D recording of the run (rerun .rrd file; open it with ssp view).",
        show_default=False,
        metavar="RUN.rrd",
    ),
    executor: str | None = ExecutorOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
    processes: int | None = ProcessesOption,
) -> None:
    """Perception and scene parsing over recorded frames: per-frame JSON, a BOP19 CSV and a
    summary, kept current after every frame (formats: docs/formats.md). A stopped run
    (Ctrl-C, a crash, a killed process) continues with --resume OUT."""
    from ssp.runner import HYPOTHESES_MODES, run

    if record is not None:
        from ssp.viz.record import check_recording

        check_recording(record)  # before the models load

    names = [c.strip() for c in classes.split(",") if c.strip()] if classes else None
    bag_given = {
        "topic_cloud": topic_cloud,
        "topic_depth": topic_depth,
        "topic_camera_info": topic_camera_info,
        "topic_mask": topic_mask,
        "topic_hypotheses": topic_hypotheses,
        "world_frame": world_frame,
    }
    bag_given = {k: v for k, v in bag_given.items() if v is not None}
    if class_map is not None:
        from ssp.io.rosbag import parse_class_map

        bag_given["class_map"] = parse_class_map(class_map)
    if inputs and len(inputs) > 1:
        if resume is not None:
            raise typer.BadParameter("--resume continues one run: ssp run --resume OUT/<name>")
        if bag_given or results_bag is not None or record is not None:
            raise typer.BadParameter(
                "--topic-*, --world-frame, --class-map, --results-bag and --record take one "
                "input: run each bag or recording on its own"
            )
        _run_many(
            inputs, models, out, overwrite, hypotheses, names, method, config, cache,
            _parallel(executor, workers, ray_address), masks=masks or "auto", period=period,
        )  # fmt: skip
        return
    input_path = inputs[0] if inputs else None
    if resume is not None:
        from ssp.config import SSPConfig
        from ssp.runner import read_run

        if out is not None and out.resolve() != resume.resolve():
            raise typer.BadParameter("give the run's folder once: --resume OUT (not --out)")
        if overwrite:
            raise typer.BadParameter("--resume continues a run; --overwrite starts one afresh")
        rec = read_run(resume)
        opts = rec["options"]
        out = resume
        input_path = input_path if input_path is not None else Path(rec["input"])
        if models is None and rec.get("models") is not None:
            models = Path(rec["models"])
        hypotheses = hypotheses or opts["hypotheses"]
        method = method or opts["method"]
        names = names if names is not None else opts["classes"]
        bag_given = bag_given or opts.get("bag") or {}
        masks = masks or opts.get("masks", "auto")
        period = period if period is not None else opts.get("period")
        cfg = _config(config) if config is not None else SSPConfig.from_dict(rec["config"])
    else:
        if input_path is None:
            raise typer.BadParameter("missing INPUT (a folder of frames or a BOP scene)")
        out = out if out is not None else Path("ssp-out")
        hypotheses = hypotheses or "auto"
        method = method or "ssp"
        masks = masks or "auto"
        cfg = _config(config)
    if processes is not None:
        cfg.search.processes = cfg.perception.processes = processes
    if hypotheses not in HYPOTHESES_MODES:
        raise typer.BadParameter(f"--hypotheses must be one of {', '.join(HYPOTHESES_MODES)}")
    from ssp.io.rosbag import BagOptions, is_bag

    input_is_bag = is_bag(input_path)
    if (bag_given or results_bag is not None) and not input_is_bag:
        raise typer.BadParameter(
            "--topic-*, --world-frame, --class-map and --results-bag are for a ROS bag input "
            "(.bag, .mcap, or a folder with metadata.yaml)"
        )
    bag_opts = BagOptions.from_dict(bag_given).to_dict() if input_is_bag else None
    if results_bag is not None and results_bag.exists():
        raise typer.BadParameter(f"--results-bag {results_bag}: exists; give a new path")
    from ssp.io.results import bop_csv_name
    from ssp.runner import check_out_dir

    bop_csv_name("input", method)  # a bad method name fails before the models load
    if resume is None:
        check_out_dir(out, overwrite)
    lib = _library(models, config, cache)
    frames_done = [0]
    previous = _stop_on_sigterm()
    try:
        with _bar() as progress:
            task = progress.add_task("frames", total=None)

            def report(done: int, total: int, message: str) -> None:
                frames_done[0] = done
                progress.update(task, completed=done, total=total, description=message[:60])
                _stopped()

            summary = run(
                input_path,
                lib,
                out,
                cfg,
                hypotheses=hypotheses,
                classes=names,
                method=method,
                progress=report,
                resume=resume is not None,
                overwrite=overwrite,
                models=None if models is None else str(models.resolve()),
                bag=bag_opts,
                masks=masks,
                period=period,
                record=record,
            )
        if results_bag is not None:
            from ssp.inputs_bag import write_run_results_bag

            write_run_results_bag(out, input_path, results_bag, lib, bag_opts)
            summary.files.append(str(results_bag))
    except KeyboardInterrupt:
        err_console.print(
            f"[bold red]interrupted[/] after {frames_done[0]} frames; the results so far are in "
            f"{out}. Continue with: ssp run --resume {out}"
        )
        raise typer.Exit(130) from None
    finally:
        _restore_signals(previous)
    _print_run(summary, input_path)
    if record is not None:
        console.print(f"wrote [bold]{record}[/]; view it with: ssp view {record}")
    if not summary.done:
        raise typer.Exit(1)


@app.command()
@_friendly
def view(
    recording: Path = typer.Argument(..., help="A recording (.rrd) written by --record."),
    web: bool = typer.Option(
        False, "--web", help="Serve it to a browser instead (no display needed here)."
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="Print the viewer command instead of running it."
    ),
) -> None:
    """Open a 3D recording of a run (ssp run --record, ssp demo) in the rerun viewer."""
    from ssp.viz.record import prepare_view, view_command
    from ssp.viz.record import view as open_viewer

    if dry_run:
        cmd = " ".join(view_command(recording, web=web))
        console.print(cmd, highlight=False, markup=False, soft_wrap=True)
        return
    cmd = prepare_view(recording, web=web)
    if web:
        console.print(
            f"serving {recording} to a browser ({' '.join(cmd)}); open the address it prints "
            "(by default http://localhost:9090). Ctrl-C stops it.",
            highlight=False,
        )
    else:
        console.print(f"opening {recording} in the rerun viewer", highlight=False)
    open_viewer(recording, web=web)


def _run_many(
    inputs,
    models,
    out,
    overwrite,
    hypotheses,
    classes,
    method,
    config,
    cache,
    parallel,
    **options,
) -> None:
    """``ssp run IN1 IN2 ...``: each input into OUT/<name>/; one summary line per input."""
    from ssp.batch import input_out_dirs, run_inputs
    from ssp.executor import ItemFailure
    from ssp.io.results import bop_csv_name
    from ssp.runner import HYPOTHESES_MODES, check_out_dir

    out = out if out is not None else Path("ssp-out")
    hypotheses = hypotheses or "auto"
    method = method or "ssp"
    if hypotheses not in HYPOTHESES_MODES:
        raise typer.BadParameter(f"--hypotheses must be one of {', '.join(HYPOTHESES_MODES)}")
    bop_csv_name("input", method)  # a bad method name fails before the models load
    for d in input_out_dirs(inputs, out):
        check_out_dir(d, overwrite)
    lib = _library(models, config, cache)
    previous = _stop_on_sigterm()
    try:
        with _bar() as progress:
            task = progress.add_task("inputs", total=len(inputs))
            results = run_inputs(
                inputs,
                lib,
                out,
                _config(config),
                parallel=parallel,
                overwrite=overwrite,
                progress=lambda done, total, name: progress.update(task, completed=done),
                hypotheses=hypotheses,
                classes=classes,
                method=method,
                models=None if models is None else str(models.resolve()),
                **options,
            )
    except KeyboardInterrupt:
        err_console.print(
            f"[bold red]interrupted[/]; each input's results so far are in {out}/<name>. "
            f"Continue one with: ssp run --resume {out}/<name>"
        )
        raise typer.Exit(130) from None
    finally:
        _restore_signals(previous)
    bad = 0
    for src, res in zip(inputs, results, strict=True):
        if isinstance(res, ItemFailure):
            bad += 1
            console.print(
                f"[red]failed[/] {src}: {escape(res.error_type)}: {escape(res.error)}",
                highlight=False,
            )
            continue
        info = res.to_dict()
        bad += not res.done
        line = f"{escape(str(src))}: {info['done']} of {info['frames']} frames done"
        if info["sec_per_frame"]:
            line += f", {info['sec_per_frame']:.2f} s per frame"
        if res.failed:
            line += f", [red]{len(res.failed)} skipped[/]"
        if info["unexpected_errors"]:
            line += f" ([bold red]{info['unexpected_errors']} unexpected errors[/])"
        console.print(line + f" -> {escape(str(out / Path(src).resolve().name))}", highlight=False)
    if bad:
        raise typer.Exit(1)


def _stop_on_sigterm():
    """Make SIGTERM stop a run like Ctrl-C (a clean 'interrupted' summary and a resume hint),
    and remember either signal: an interrupt raised inside a library that swallows exceptions
    (some catch BaseException) is raised again at the next frame (:func:`_stopped`). Returns
    the previous handlers (None when signals cannot be set here)."""
    _state["stop"] = False

    def stop(signum, frame):
        _state["stop"] = True
        raise KeyboardInterrupt

    try:
        return {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    except ValueError:  # not the main thread
        return None


def _restore_signals(previous) -> None:
    for sig, handler in (previous or {}).items():
        signal.signal(sig, handler)


def _stopped() -> None:
    """KeyboardInterrupt when a stop was asked for (between frames)."""
    if _state.get("stop"):
        raise KeyboardInterrupt


def _print_run(summary, input_path: Path) -> None:
    info = summary.to_dict()
    table = Table(title=f"ssp run: {input_path} ({summary.kind})")
    for col in ("frame", "objects", "hypotheses", "perception s", "parser s"):
        table.add_column(col, justify="left" if col == "frame" else "right")
    for d in summary.done:
        table.add_row(
            d["frame"],
            str(d["objects"]),
            str(d["hypotheses"]),
            f"{d['perception_s']:.2f}",
            f"{d['parser_s']:.2f}",
        )
    console.print(table)
    console.print(
        f"{info['done']} of {info['frames']} frames done"
        + (f", {info['sec_per_frame']:.2f} s per frame" if info["sec_per_frame"] else "")
    )
    for f in summary.failed:
        bug = f"failed ({f['error_type']}, a bug: please report it)"
        tag = bug if f["unexpected"] else "skipped"
        console.print(f"[red]{tag}[/] {f['frame']}: {escape(f['error'])}", highlight=False)
    for w in summary.warnings:
        console.print(f"[yellow]warning[/] {w['frame']}: {escape(w['warning'])}", highlight=False)
    if info["unexpected_errors"]:
        console.print(
            f"[bold red]{info['unexpected_errors']} frames failed with unexpected errors[/] "
            "(tracebacks in the log above)"
        )
    for f in summary.files:
        console.print(f"wrote [bold]{f}[/]")


@app.command()
@_friendly
def demo(
    out: Path = typer.Option(Path("ssp-demo"), "--out", "-o", help="Output folder."),
    config: Path | None = ConfigOption,
    foundation: bool = typer.Option(
        False, "--foundation", help="The physics-only foundation demo instead."
    ),
) -> None:
    """Run the built-in demo: a short synthetic block structure parsed frame by frame by ssp and
    by its baselines; prints the comparison and writes OUT/report.html (about 30 s)."""
    if foundation:
        _foundation_demo(out, config)
        return
    from ssp.eval.sequence_demo import run_sequence_demo

    with console.status("ssp demo") as status:
        result = run_sequence_demo(out, _config(config), progress=status.update)
    _print_table1(result)
    console.print(f"{result['seconds']:.0f} s; open [bold]{Path(out) / 'report.html'}[/]")
    if result.get("recording"):
        console.print(f"3D recording of ssp's run: [bold]ssp view {result['recording']}[/]")
    else:
        from ssp.viz.record import INSTALL_HINT

        console.print(f"no 3D recording (rerun is not installed: {INSTALL_HINT})")


def _foundation_demo(out: Path, config: Path | None) -> None:
    """The physics-only demo: a cube tower, the built-in tools dropped, a block relaxed."""
    from ssp.eval.demo import run_foundation_demo

    with console.status("running the foundation demo (about 10 s)"):
        r = run_foundation_demo(out, _config(config))
    t, tl, rx = r["tower"], r["tools"], r["relaxation"]
    table = Table(title="ssp foundation demo")
    table.add_column("experiment")
    table.add_column("result")
    table.add_row(
        "10-cube tower, 2 s dynamic",
        f"max drift {t['max_drift_mm']:.4f} mm, max penetration {t['max_penetration_mm']:.3f} mm,"
        f" {t['us_per_step']:.0f} us/step",
    )
    table.add_row(
        f"{tl['objects']} built-in tools dropped 2 cm",
        f"max penetration {tl['max_penetration_mm']:.3f} mm, residual acceleration "
        f"{tl['max_residual_acceleration_m_s2']:.3f} m/s^2, {tl['us_per_step']:.0f} us/step",
    )
    table.add_row(
        "block hypothesis 6 mm above a cube, tilted 4 deg",
        f"quasi-static relaxation ({rx['steps']} steps): height change "
        f"{rx['block_height_change_mm']:.2f} mm, tilt {rx['block_tilt_after_deg']:.2f} deg, "
        f"acceleration from rest {rx['accel_from_rest_before_m_s2']:.2f} -> "
        f"{rx['accel_from_rest_after_m_s2']:.3f} m/s^2",
    )
    console.print(table)
    for f in r["files"]:
        console.print(f"wrote [bold]{f}[/]")


if __name__ == "__main__":  # pragma: no cover
    app()


# ------------------------------------------------------------------------------ BOP datasets
SplitOption = typer.Option(None, "--split", help="The dataset's split folder (default: test).")
ScenesOption = typer.Option(
    None, "--scenes", help="Comma-separated scene ids (default: every scene of the split)."
)
MasksOption = typer.Option(
    "auto",
    "--masks",
    help=(
        "Segmentation: auto (an ssp scene's simulated one, none for a published scene), gt "
        "(the ground-truth mask_visib: an upper bound), none (the cloud above the table is "
        "clustered)."
    ),
)


def _scene_ids(text: str | None) -> list[int] | None:
    if not text:
        return None
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise typer.BadParameter(
            f"--scenes must be comma-separated integers, got {text!r}"
        ) from None


def _dataset_library(dataset: Path, models: Path | None, config: Path | None, cache: Path | None):
    """``--models``, else the built-in models when the dataset names its objects after them
    (``models.json``, as ``ssp simulate`` writes), else the dataset's ``models/`` folder."""
    from ssp.io.bop import bop_scenes, dataset_root
    from ssp.library.builtin import builtin_specs

    if models is not None:
        return _library(models, config, cache), models
    scene = bop_scenes(dataset)[0]
    root = dataset_root(scene)
    for folder in (scene, root):
        mj = None if folder is None else folder / "models.json"
        if mj is not None and mj.is_file():
            names = set(json.loads(mj.read_text())["obj_ids"].values())
            if names <= {spec.name for spec in builtin_specs()}:
                return _library(None, config, cache), None
    if root is not None and (root / "models").is_dir():
        return _library(root / "models", config, cache), root / "models"
    raise typer.BadParameter(
        f"{dataset}: no models/ folder in the dataset: give the object models with --models"
    )


@app.command("refine")
@_friendly
def refine_cmd(
    dataset: Path = typer.Argument(..., help="A BOP dataset, split or scene folder."),
    hypotheses: Path = typer.Option(
        ...,
        "--hypotheses",
        help=(
            "The pose estimator's output: a BOP19 results CSV, MegaPose/HappyPose JSON, "
            "FoundationPose poses or a CosyPose CSV (docs/formats.md)."
        ),
    ),
    out: Path = typer.Option(Path("ssp-refine"), "--out", "-o", help="Output folder."),
    fmt: str = typer.Option("auto", "--format", help="The hypotheses' format (auto: detected)."),
    split: str | None = SplitOption,
    scenes: str | None = ScenesOption,
    method: str | None = typer.Option(
        None, help="BOP method name of the output (default: the input's, with '-ssp')."
    ),
    masks: str = MasksOption,
    period: float | None = typer.Option(
        None, help="Seconds between images of a scene without stamps (default 1/30)."
    ),
    resume: bool = typer.Option(False, "--resume", help="Continue a stopped refine in --out."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier refine."),
    models: Path | None = ModelsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    processes: int | None = ProcessesOption,
) -> None:
    """ssp after your pose estimator: refine its hypotheses on a BOP dataset into a BOP19 CSV
    (OUT/METHOD-ssp_DATASET-SPLIT.csv) and per-frame JSON (OUT/scenes/SCENE/)."""
    from ssp.refine import refine

    lib, models_dir = _dataset_library(dataset, models, config, cache)
    cfg = _config(config)
    if processes is not None:
        cfg.search.processes = cfg.perception.processes = processes
    with _bar() as progress:
        task = progress.add_task("refining", total=None)
        summary = refine(
            dataset,
            hypotheses,
            lib,
            out,
            cfg,
            fmt=fmt,
            split=split,
            scene_ids=_scene_ids(scenes),
            method=method,
            masks=masks,
            period=period,
            resume=resume,
            overwrite=overwrite,
            models=None if models_dir is None else str(Path(models_dir).resolve()),
            progress=lambda d, t, m: progress.update(
                task, completed=d, total=t, description=m[:60]
            ),  # fmt: skip
        )
    for s in summary.scenes:
        failed = s.get("failed", 0)
        extra = f", [red]{failed} failed[/]" if failed else ""
        console.print(f"scene {s['scene']}: {s['status']} ({s.get('done', '-')} of "
                      f"{s.get('frames', '-')} frames{extra}) -> {s['out']}")  # fmt: skip
    console.print(f"wrote [bold]{summary.csv}[/]")
    if not summary.done:
        raise typer.Exit(1)


@app.command("estimate")
@_friendly
def estimate_cmd(
    dataset: Path = typer.Argument(..., help="A BOP dataset, split or scene folder."),
    out: Path = typer.Option(
        ..., "--out", "-o", help="The BOP19 CSV to write (METHOD_DATASET-SPLIT.csv)."
    ),
    split: str | None = SplitOption,
    scenes: str | None = ScenesOption,
    classes: str | None = typer.Option(None, help="Comma-separated candidate classes."),
    masks: str = MasksOption,
    models: Path | None = ModelsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
) -> None:
    """The built-in pose estimator over a BOP dataset: every hypothesis as a BOP19 CSV row
    (several per object), the input of `ssp refine`."""
    from ssp.refine import estimate

    lib, _ = _dataset_library(dataset, models, config, cache)
    names = [c.strip() for c in classes.split(",") if c.strip()] if classes else None
    with _bar() as progress:
        task = progress.add_task("estimating", total=None)
        rep = estimate(dataset, lib, out, _config(config), split=split,
                       scene_ids=_scene_ids(scenes), classes=names, masks=masks,
                       progress=lambda d, t, m: progress.update(task, completed=d, total=t,
                                                                description=m[:60]))  # fmt: skip
    for f in rep["failed"]:
        console.print(
            f"[red]skipped[/] scene {f['scene']} image {f['im_id']}: {escape(f['error'])}"
        )
    console.print(f"{rep['rows']} hypotheses of {rep['images']} images: wrote [bold]{out}[/]")


@app.command("evaluate")
@_friendly
def evaluate_cmd(
    dataset: Path = typer.Argument(..., help="A BOP dataset, split or scene folder."),
    results: list[Path] = typer.Argument(..., help="BOP19 results CSVs to compare."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Write the results as JSON."),
    split: str | None = SplitOption,
    vsd: bool = typer.Option(True, "--vsd/--no-vsd", help="Compute VSD (renders; slower)."),
    models: Path | None = ModelsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
) -> None:
    """BOP19 average recall (AR = mean of AR_VSD, AR_MSSD, AR_MSPD) of results CSVs against a
    dataset's ground truth, side by side."""
    from ssp.io._files import write_json
    from ssp.refine import evaluate

    lib, _ = _dataset_library(dataset, models, config, cache)
    with _bar() as progress:
        task = progress.add_task("evaluating", total=None)
        res = evaluate(dataset, lib, results, split=split, vsd=vsd,
                       progress=lambda d, t, m: progress.update(task, completed=d, total=t,
                                                                description=m[:60]))  # fmt: skip
    table = Table(title=f"BOP19 recall on {dataset}")
    keys = ["AR", "AR_VSD", "AR_MSSD", "AR_MSPD"] if vsd else ["AR", "AR_MSSD", "AR_MSPD"]
    table.add_column("results")
    for k in [*keys, "targets"]:
        table.add_column(k, justify="right")
    for name, r in res.items():
        cells = [("-" if r.get(k) is None else f"{r[k]:.3f}") for k in keys]
        table.add_row(name, *cells, str(r.get("targets", "")))
    console.print(table)
    if out is not None:
        write_json(out, res)
        console.print(f"wrote [bold]{out}[/]")
