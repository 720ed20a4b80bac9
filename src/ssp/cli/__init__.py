"""The ``ssp`` command line: this package builds the typer :data:`app` from the command modules
(:mod:`ssp.cli.config`, :mod:`ssp.cli.models`, :mod:`ssp.cli.bench`,
:mod:`ssp.cli.experiments`, :mod:`ssp.cli.simulate`, :mod:`ssp.cli.run`, :mod:`ssp.cli.view`,
:mod:`ssp.cli.demo`, :mod:`ssp.cli.datasets`; what they share: :mod:`ssp.cli.common`). The only
package that prints; the commands parse their options, call the library and print, and import
the heavy parts inside the commands."""

from __future__ import annotations

import logging

import typer

from ssp import __version__
from ssp.cli import bench, datasets, demo, experiments, models, run, simulate, view
from ssp.cli import config as config_cmd
from ssp.cli.common import console, state

__all__ = ["app"]

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
    state["debug"] = debug
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


bench_app.callback()(bench.bench_main)

# the commands, in the order of the help
app.command("dump-config")(config_cmd.dump_config_cmd)
models_app.command("list")(models.models_list)
models_app.command("show")(models.models_show)
models_app.command("prepare")(models.models_prepare)
models_app.command("export-builtin")(models.models_export_builtin)
bench_app.command("physics")(bench.bench_physics)
bench_app.command("calibrate")(bench.bench_calibrate)
bench_app.command("parser")(bench.bench_parser_cmd)
bench_app.command("estimator")(bench.bench_estimator_cmd)
bench_app.command("soak")(bench.bench_soak_cmd)
bench_app.command("rgb-calibration")(bench.bench_rgb_calibration_cmd)
bench_app.command("frame")(bench.bench_frame_cmd)
bench_app.command("camera")(bench.bench_camera_cmd)
app.command("simulate")(simulate.simulate)
bench_app.command("table1")(experiments.bench_table1)
bench_app.command("stream")(experiments.bench_stream)
bench_app.command("tower")(experiments.bench_tower)
bench_app.command("docs-figures")(bench.bench_docs_figures)
app.command("run")(run.run_cmd)
app.command("view")(view.view)
app.command("demo")(demo.demo)
app.command("refine")(datasets.refine_cmd)
app.command("estimate")(datasets.estimate_cmd)
app.command("evaluate")(datasets.evaluate_cmd)
