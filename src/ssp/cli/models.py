"""``ssp models``: list, inspect and pre-compute object models."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from ssp.cli.common import (
    CacheOption,
    ConfigOption,
    JsonOption,
    ModelsArg,
    console,
    err_console,
    friendly,
    load_config,
    load_library,
    load_library_config,
    progress_bar,
)

__all__ = ["models_export_builtin", "models_list", "models_prepare", "models_show"]


@friendly
def models_list(
    models: Path | None = ModelsArg,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    as_json: bool = JsonOption,
) -> None:
    """One line per model: size, mass, convex parts, symmetries (skipped models with why)."""
    from ssp.pipeline.models import model_record

    lib = load_library(models, config, cache)
    if as_json:
        out = {"models": [model_record(lib[n]) for n in lib.names], "skipped": lib.skipped}
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


@friendly
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
    from ssp.pipeline.models import model_details

    cfg = load_library_config(config, cache)
    model = load_library(models, config, cache)[name]
    gravity = load_config(config).physics.gravity
    summary = model_details(model, tolerance, gravity=gravity, library_config=cfg)
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    table = Table(title=f"model {name}", show_header=False)
    for k, v in summary.items():
        table.add_row(k, str(v))
    console.print(table)


@friendly
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

    cfg = load_library_config(config, cache)
    with progress_bar() as progress:
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
        _print_prepared(folder, rows)
    if failed:
        err_console.print(f"[bold red]{failed} of {len(rows)} models failed[/]")
        raise typer.Exit(1)


def _print_prepared(folder: Path, rows: list[dict]) -> None:
    """The table of ``ssp models prepare``, then each model's warnings."""
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


@friendly
def models_export_builtin(
    folder: Path = typer.Argument(..., help="Folder to write the built-in models to."),
    view_ambiguous: bool = typer.Option(
        False,
        "--view-ambiguous",
        help="Also write the models whose orientation a view often cannot decide (a mug, a "
        "nearly square tin): "
        "with --models, the isolated experiment's tools then include them.",
    ),
    names: str | None = typer.Option(
        None, "--names", help="Comma-separated models to write (default: all; e.g. mug,drill)."
    ),
) -> None:
    """Write the built-in models as meshes + convex parts + models.yaml (a template folder)."""
    from ssp.library.builtin import export_builtin

    chosen = None if names is None else [n.strip() for n in names.split(",") if n.strip()]
    paths = export_builtin(folder, chosen, view_ambiguous=view_ambiguous)
    console.print(f"wrote {len(paths)} files to {folder}")
