"""``ssp refine``, ``ssp estimate`` and ``ssp evaluate``: ssp after a pose estimator on a BOP
dataset (:mod:`ssp.pipeline.refine`)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from ssp.cli.common import (
    CacheOption,
    ConfigOption,
    ProcessesOption,
    console,
    err_console,
    friendly,
    load_config,
    load_library,
    masks_arg,
    progress_bar,
)

__all__ = ["estimate_cmd", "evaluate_cmd", "refine_cmd"]

DatasetModelsOption = typer.Option(
    None,
    "--models",
    "-m",
    help=(
        "Model folder (default: the dataset's models/ folder; the built-in models when its "
        "models.json names only built-in classes, as ssp simulate writes it)."
    ),
    show_default=False,
)
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
        "clustered), silhouettes (the estimates' rendered silhouettes), or FILE: a detector's "
        "BOP segmentation results JSON (RLE masks, as CNOS and SAM-6D write them)."
    ),
)


def _scene_ids(text: str | None) -> list[int] | None:
    """The scene ids of ``--scenes`` (None: every scene)."""
    if not text:
        return None
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise typer.BadParameter(
            f"--scenes must be comma-separated integers, got {text!r}"
        ) from None


def _dataset_library(dataset: Path, models: Path | None, config: Path | None, cache: Path | None):
    """``--models``, else the dataset's models (:func:`ssp.pipeline.refine.dataset_models`):
    the library and its folder (None: the built-in models)."""
    from ssp.pipeline.refine import DatasetModelsError, dataset_models

    if models is not None:
        return load_library(models, config, cache), models
    try:
        folder = dataset_models(dataset)
    except DatasetModelsError as exc:
        raise typer.BadParameter(str(exc)) from None
    return load_library(folder, config, cache), folder


@friendly
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
    models: Path | None = DatasetModelsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    processes: int | None = ProcessesOption,
) -> None:
    """ssp after your pose estimator: refine its hypotheses on a BOP dataset into a BOP19 CSV
    (OUT/METHOD-ssp_DATASET-SPLIT.csv) and per-frame JSON (OUT/scenes/SCENE/)."""
    from ssp.pipeline.refine import refine

    lib, models_dir = _dataset_library(dataset, models, config, cache)
    cfg = load_config(config)
    if processes is not None:
        cfg.search.processes = cfg.perception.processes = processes
    with progress_bar() as progress:
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
            masks=masks_arg(masks),
            period=period,
            resume=resume,
            overwrite=overwrite,
            models=None if models_dir is None else str(Path(models_dir).resolve()),
            progress=lambda d, t, m: progress.update(task, completed=d, total=t, description=m),
        )
    _print_refine(summary)
    if summary.frames_done == 0:
        err_console.print(
            f"[bold red]no frame succeeded[/] (0 of {summary.frames} frames refined): see the "
            "errors above"
        )
        raise typer.Exit(1)
    if not summary.done:
        raise typer.Exit(1)


def _print_refine(summary) -> None:
    """The warnings about the estimates, one line per scene of a refine, and the CSV it
    wrote."""
    for w in summary.warnings:
        console.print(f"[yellow]warning[/] {escape(w)}", highlight=False)
    for s in summary.scenes:
        failed = s.get("failed", 0)
        extra = f", [red]{failed} failed[/]" if failed else ""
        console.print(f"scene {s['scene']}: {s['status']} ({s.get('done', '-')} of "
                      f"{s.get('frames', '-')} frames{extra}) -> {s['out']}")  # fmt: skip
    console.print(f"wrote [bold]{summary.csv}[/]")


@friendly
def estimate_cmd(
    dataset: Path = typer.Argument(..., help="A BOP dataset, split or scene folder."),
    out: Path = typer.Option(
        ..., "--out", "-o", help="The BOP19 CSV to write (METHOD_DATASET-SPLIT.csv)."
    ),
    split: str | None = SplitOption,
    scenes: str | None = ScenesOption,
    classes: str | None = typer.Option(None, help="Comma-separated candidate classes."),
    masks: str = MasksOption,
    models: Path | None = DatasetModelsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    noise: str = typer.Option(
        "depth",
        "--noise",
        help=(
            "depth: the built-in estimator on the depth images; rgb: a simulated RGB estimator "
            "(MegaPose-like, measured on LM-O: errors mostly in depth along the viewing ray) "
            "drawn at each image's ground truth (needs scene_gt.json)."
        ),
    ),
    seed: int = typer.Option(0, min=0, help="--noise rgb: the seed of the simulated errors."),
) -> None:
    """The built-in pose estimator over a BOP dataset: every hypothesis as a BOP19 CSV row
    (several per object), the input of `ssp refine`; or, with --noise rgb, a simulated RGB
    estimator's CSV."""
    from ssp.pipeline.refine import estimate

    if noise not in ("depth", "rgb"):
        raise typer.BadParameter("--noise must be 'depth' or 'rgb'")
    lib, _ = _dataset_library(dataset, models, config, cache)
    if noise == "rgb":
        _estimate_rgb(dataset, lib, out, seed, split, scenes)
        return
    names = [c.strip() for c in classes.split(",") if c.strip()] if classes else None
    with progress_bar() as progress:
        task = progress.add_task("estimating", total=None)
        rep = estimate(dataset, lib, out, load_config(config), split=split,
                       scene_ids=_scene_ids(scenes), classes=names, masks=masks_arg(masks),
                       progress=lambda d, t, m: progress.update(task, completed=d, total=t,
                                                                description=m[:60]))  # fmt: skip
    for f in rep["failed"]:
        console.print(
            f"[red]skipped[/] scene {f['scene']} image {f['im_id']}: {escape(f['error'])}"
        )
    console.print(f"{rep['rows']} hypotheses of {rep['images']} images: wrote [bold]{out}[/]")


def _estimate_rgb(dataset: Path, lib, out: Path, seed: int, split, scenes) -> None:
    """``ssp estimate --noise rgb``: the simulated RGB estimator's CSV."""
    from ssp.sim.rgb_csv import rgb_estimates

    with progress_bar() as progress:
        task = progress.add_task("simulating an RGB estimator", total=None)

        def step(d: int, t: int, m: str) -> None:
            progress.update(task, completed=d, total=t, description=m[:60])

        rep = rgb_estimates(
            dataset, lib, out, seed=seed, split=split, scene_ids=_scene_ids(scenes), progress=step
        )
    console.print(
        f"{rep['rows']} hypotheses of {rep['images']} images ({rep['missed']} of "
        f"{rep['targets']} objects missed): wrote [bold]{out}[/]"
    )


@friendly
def evaluate_cmd(
    dataset: Path = typer.Argument(..., help="A BOP dataset, split or scene folder."),
    results: list[Path] = typer.Argument(..., help="BOP19 results CSVs to compare."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Write the results as JSON."),
    split: str | None = SplitOption,
    vsd: bool = typer.Option(True, "--vsd/--no-vsd", help="Compute VSD (renders; slower)."),
    models: Path | None = DatasetModelsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
) -> None:
    """BOP19 average recall (AR = mean of AR_VSD, AR_MSSD, AR_MSPD) of results CSVs against a
    dataset's ground truth, side by side."""
    from ssp.io import write_json
    from ssp.pipeline.refine import evaluate

    lib, _ = _dataset_library(dataset, models, config, cache)
    with progress_bar() as progress:
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
