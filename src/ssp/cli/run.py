"""``ssp run``: perception and scene parsing over recorded frames (:mod:`ssp.pipeline.run`), one
input or many (:mod:`ssp.pipeline.batch`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.markup import escape
from rich.table import Table

from ssp.cli.common import (
    CacheOption,
    ConfigOption,
    ExecutorOption,
    ProcessesOption,
    RayAddressOption,
    WorkersOption,
    console,
    err_console,
    friendly,
    get_parallel,
    load_config,
    load_library,
    masks_arg,
    print_warnings,
    progress_bar,
    restore_signals,
    stop_on_sigterm,
    stopped,
)

if TYPE_CHECKING:
    from ssp.pipeline.manifest import RunOptions

__all__ = ["run_cmd"]


def _bag_option(name: str, what: str, default: str = "detected"):
    return typer.Option(
        None,
        name,
        help=f"ROS bag input: the {what} (default: {default}).",
        show_default=False,
        rich_help_panel="ROS bag input",
    )


InputsArg = typer.Argument(
    None,
    help=(
        "A folder of PLY/PCD frames, a BOP scene folder, or a ROS bag (.bag, .mcap, ROS 2 "
        "folder) (with --resume: the recorded one when omitted). Several: each is run "
        "into OUT/<its folder name>/ (with --workers, in parallel)."
    ),
    show_default=False,
    metavar="INPUT",
)
OutOption = typer.Option(
    None,
    "--out",
    "-o",
    help="Output folder, new or empty (default: ssp-out).",
    show_default=False,
)
ResumeOption = typer.Option(
    None,
    "--resume",
    help=(
        "Continue the stopped run in this output folder from its saved state; the input, "
        "--models, --config and options must be those it started with (omitted: the "
        "recorded ones)."
    ),
    show_default=False,
)
OverwriteOption = typer.Option(
    False, "--overwrite", help="Clear an earlier run's files in --out first."
)
HypothesesOption = typer.Option(
    None,
    "--hypotheses",
    help=(
        "auto (default): the input's hypotheses when present, else the built-in "
        "estimator; given: only the input's; estimated: always the built-in estimator."
    ),
    show_default=False,
)
ClassesOption = typer.Option(
    None,
    help=(
        "Comma-separated candidate classes of the estimator (default: those a BOP scene "
        "lists, else every model)."
    ),
)
MethodOption = typer.Option(
    None,
    help="BOP method name in the CSV file name, no '_' (default: ssp).",
    show_default=False,
)
SceneIdOption = typer.Option(
    None,
    "--scene-id",
    min=0,
    help=(
        "BOP scene_id of the CSV rows (default: a BOP scene's own, else 1): the scene of the "
        "dataset the frames belong to, to score them against it."
    ),
    show_default=False,
    rich_help_panel="BOP results",
)
ObjIdsOption = typer.Option(
    None,
    "--obj-ids",
    help=(
        'BOP obj_id of each class: a models.json ({"obj_ids": {"1": "cube"}}), a '
        "BOP models_info.json or models/ folder (obj_000005.ply: obj_id 5), or an earlier "
        "run's obj_ids.json; it must name every model. Default: the input's own models.json, "
        "else the obj_XXXXXX model names of a BOP models folder, else the sorted class names."
    ),
    show_default=False,
    metavar="FILE",
    rich_help_panel="BOP results",
)
TopicCloudOption = _bag_option("--topic-cloud", "PointCloud2 topic of the frames")
TopicDepthOption = _bag_option("--topic-depth", "depth Image topic of the frames")
TopicCameraInfoOption = _bag_option("--topic-camera-info", "CameraInfo topic")
TopicMaskOption = _bag_option("--topic-mask", "instance mask Image topic")
TopicHypothesesOption = _bag_option(
    "--topic-hypotheses", "Detection3DArray (or JSON String) topic of the hypotheses"
)
WorldFrameOption = _bag_option(
    "--world-frame",
    "tf frame of the world (z up, table top at z = 0) for the camera pose",
    "none: the table plane, fitted to the frames",
)
ClassMapOption = _bag_option(
    "--class-map",
    "detection class id -> class: ID=CLASS,... or a JSON/YAML file",
    "none: the class ids are the class names",
)
MasksOption = typer.Option(
    None,
    "--masks",
    help=(
        "BOP scene input: auto (default: an ssp scene's simulated segmentation, none for a "
        "published one), gt (the ground-truth mask_visib: an upper bound), none, silhouettes "
        "(the given hypotheses' rendered silhouettes), or FILE: a detector's instance masks, "
        "the BOP segmentation results JSON (CNOS, SAM-6D, the challenge's default detections; "
        "every detection used, overlaps to the higher score)."
    ),
    show_default=False,
    metavar="auto|gt|none|silhouettes|FILE",
)


PeriodOption = typer.Option(
    None,
    "--period",
    help="BOP scene input: seconds between images of a scene without stamps (1/30).",
    show_default=False,
)
ResultsBagOption = typer.Option(
    None,
    "--results-bag",
    help="ROS bag input: also write the results to this new bag (.bag: ROS 1, .mcap: "
    "MCAP, else a ROS 2 folder).",
    show_default=False,
    rich_help_panel="ROS bag input",
)
RecordOption = typer.Option(
    None,
    "--record",
    help="Also write a 3D recording of the run (rerun .rrd file; open it with ssp view).",
    show_default=False,
    metavar="RUN.rrd",
)


@friendly
def run_cmd(
    inputs: list[Path] | None = InputsArg,
    models: Path | None = typer.Option(
        None,
        "--models",
        "-m",
        help=(
            "Model folder (default: the built-in models; for BOP scenes, their dataset's "
            "models/ when its models.json names classes the built-in models lack)."
        ),
    ),
    out: Path | None = OutOption,
    resume: Path | None = ResumeOption,
    overwrite: bool = OverwriteOption,
    hypotheses: str | None = HypothesesOption,
    classes: str | None = ClassesOption,
    method: str | None = MethodOption,
    scene_id: int | None = SceneIdOption,
    obj_ids: Path | None = ObjIdsOption,
    config: Path | None = ConfigOption,
    cache: Path | None = CacheOption,
    topic_cloud: str | None = TopicCloudOption,
    topic_depth: str | None = TopicDepthOption,
    topic_camera_info: str | None = TopicCameraInfoOption,
    topic_mask: str | None = TopicMaskOption,
    topic_hypotheses: str | None = TopicHypothesesOption,
    world_frame: str | None = WorldFrameOption,
    class_map: str | None = ClassMapOption,
    masks: str | None = MasksOption,
    period: float | None = PeriodOption,
    results_bag: Path | None = ResultsBagOption,
    record: Path | None = RecordOption,
    executor: str | None = ExecutorOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
    processes: int | None = ProcessesOption,
) -> None:
    """Perception and scene parsing over recorded frames: per-frame JSON, a BOP19 CSV and a
    summary, kept current after every frame (formats: docs/formats.md). A stopped run
    (Ctrl-C, a crash, a killed process) continues with --resume OUT."""
    from ssp.pipeline.manifest import RunOptions

    if record is not None:
        from ssp.viz.record import check_recording

        check_recording(record)  # before the models load

    names = [c.strip() for c in classes.split(",") if c.strip()] if classes else None
    masks = masks_arg(masks)
    bag_given = _bag_given(topic_cloud, topic_depth, topic_camera_info, topic_mask,
                           topic_hypotheses, world_frame, class_map)  # fmt: skip
    if inputs and len(inputs) > 1:
        _check_many(resume, bag_given, results_bag, record, scene_id)
        _run_many(
            inputs, models, out, overwrite, hypotheses, names, method, config, cache,
            get_parallel(executor, workers, ray_address), masks=masks or "auto", period=period,
            obj_ids=obj_ids,
        )  # fmt: skip
        return
    given = RunOptions(inputs[0] if inputs else None, models, hypotheses, method, names,
                       bag_given, masks, period, scene_id, obj_ids)  # fmt: skip
    out, opts, cfg = _resolve(given, out, resume, overwrite, config)
    if resume is None and opts.models is None:
        opts = replace(opts, models=_input_models([opts.input]))
    if processes is not None:
        cfg.search.processes = cfg.perception.processes = processes
    bag_opts = _bag_options(opts, results_bag)
    from ssp.io.results import bop_csv_name
    from ssp.pipeline.manifest import check_out_dir

    bop_csv_name("input", opts.method)  # a bad method name fails before the models load
    if opts.obj_ids is not None:  # so does an unreadable id table
        from ssp.io.results import ObjectIds

        ObjectIds.from_file(opts.obj_ids)
    if resume is None:
        check_out_dir(out, overwrite)
    lib = load_library(opts.models, config, cache)
    summary = _run_one(opts, lib, out, cfg, resume=resume is not None, overwrite=overwrite,
                       bag_opts=bag_opts, results_bag=results_bag, record=record)  # fmt: skip
    _print_run(summary, opts.input)
    if record is not None:  # a resume records into a new file next to the earlier one
        rrd = next((f for f in summary.files if Path(f).parent == record.parent
                    and Path(f).name.startswith(record.stem)), record)  # fmt: skip
        console.print(f"view the recording with: ssp view {rrd}")
    if not summary.done:
        err_console.print(
            f"[bold red]no frame succeeded[/] (0 of {summary.frames} frames done): see the "
            "errors above"
        )
        raise typer.Exit(1)


def _bag_given(
    topic_cloud: str | None,
    topic_depth: str | None,
    topic_camera_info: str | None,
    topic_mask: str | None,
    topic_hypotheses: str | None,
    world_frame: str | None,
    class_map: str | None,
) -> dict:
    """The ROS bag options given (:class:`ssp.io.rosbag.BagOptions` fields)."""
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
    return bag_given


def _check_many(resume: Path | None, bag_given: dict, results_bag, record, scene_id) -> None:
    """The options several inputs cannot take."""
    if resume is not None:
        raise typer.BadParameter("--resume continues one run: ssp run --resume OUT/<name>")
    if scene_id is not None:
        raise typer.BadParameter(
            "--scene-id names the scene of one input: run each input with its own --scene-id "
            "(BOP scenes take theirs from their folder)"
        )
    if bag_given or results_bag is not None or record is not None:
        raise typer.BadParameter(
            "--topic-*, --world-frame, --class-map, --results-bag and --record take one "
            "input: run each bag or recording on its own"
        )


def _resolve(
    given: RunOptions, out: Path | None, resume: Path | None, overwrite: bool, config
) -> tuple[Path, RunOptions, object]:
    """The output folder, options and settings of one input's run: a resume's (the recorded
    ones where not given) or a new run's (the defaults where not given)."""
    if resume is None:
        if given.input is None:
            raise typer.BadParameter("missing INPUT (a folder of frames or a BOP scene)")
        return (out if out is not None else Path("ssp-out")), given.fresh(), load_config(config)
    from ssp.config import SSPConfig
    from ssp.pipeline.manifest import read_run

    if out is not None and out.resolve() != resume.resolve():
        raise typer.BadParameter("give the run's folder once: --resume OUT (not --out)")
    if overwrite:
        raise typer.BadParameter("--resume continues a run; --overwrite starts one afresh")
    rec = read_run(resume)
    opts = given.resumed(rec)
    cfg = load_config(config) if config is not None else SSPConfig.from_dict(rec["config"])
    return resume, opts, cfg


def _input_models(inputs) -> Path | None:
    """The model folder of BOP scenes run without ``--models``: their dataset's
    (:func:`ssp.pipeline.refine.dataset_models`, as ``ssp refine`` and ``ssp estimate`` read
    a dataset), when every input is a BOP scene and they agree on it; None (the built-in
    models) for a dataset that names its objects after them, one without a ``models/``
    folder (its scene's error then says what to give) or inputs of another kind. Said on
    the console."""
    from ssp.io.bop import is_bop_scene
    from ssp.pipeline.refine import DatasetModelsError, dataset_models

    found = set()
    for p in inputs:
        if p is None or not is_bop_scene(p):
            return None
        try:
            found.add(dataset_models(p))
        except DatasetModelsError:
            return None
    folder = found.pop() if len(found) == 1 else None
    if folder is not None:
        console.print(f"models: the dataset's ({escape(str(folder))}); --models to give others")
    return folder


def _bag_options(opts: RunOptions, results_bag: Path | None) -> dict | None:
    """Check the options of one input against its kind: the bag options (None: not a bag)."""
    from ssp.io.rosbag import BagOptions, is_bag
    from ssp.pipeline.sources import HYPOTHESES_MODES

    if opts.hypotheses not in HYPOTHESES_MODES:
        raise typer.BadParameter(f"--hypotheses must be one of {', '.join(HYPOTHESES_MODES)}")
    input_is_bag = is_bag(opts.input)
    if (opts.bag or results_bag is not None) and not input_is_bag:
        raise typer.BadParameter(
            "--topic-*, --world-frame, --class-map and --results-bag are for a ROS bag input "
            "(.bag, .mcap, or a folder with metadata.yaml)"
        )
    bag_opts = BagOptions.from_dict(opts.bag).to_dict() if input_is_bag else None
    if results_bag is not None and results_bag.exists():
        raise typer.BadParameter(f"--results-bag {results_bag}: exists; give a new path")
    return bag_opts


def _run_one(
    opts: RunOptions,
    lib,
    out: Path,
    cfg,
    *,
    resume: bool,
    overwrite: bool,
    bag_opts: dict | None,
    results_bag: Path | None,
    record: Path | None,
):
    """:func:`ssp.pipeline.run.run` with a progress bar, then the results bag if asked for;
    Ctrl-C or SIGTERM stop it with exit code 130 and how to go on."""
    from ssp.pipeline.run import run

    frames_done = [0]
    previous = stop_on_sigterm()
    try:
        with progress_bar() as progress:
            task = progress.add_task("frames", total=None)

            def report(done: int, total: int, message: str) -> None:
                frames_done[0] = done
                progress.update(task, completed=done, total=total, description=message)
                stopped()

            summary = run(
                opts.input,
                lib,
                out,
                cfg,
                hypotheses=opts.hypotheses,
                classes=opts.classes,
                method=opts.method,
                scene_id=opts.scene_id,
                obj_ids=opts.obj_ids,
                progress=report,
                resume=resume,
                overwrite=overwrite,
                models=None if opts.models is None else str(opts.models.resolve()),
                bag=bag_opts,
                masks=opts.masks,
                period=opts.period,
                record=record,
            )
        if results_bag is not None:
            from ssp.pipeline.bag import write_run_results_bag

            write_run_results_bag(out, opts.input, results_bag, lib, bag_opts)
            summary.files.append(str(results_bag))
    except KeyboardInterrupt:
        err_console.print(
            f"[bold red]interrupted[/] after {frames_done[0]} frames; the results so far are in "
            f"{out}. Continue with: ssp run --resume {out}"
        )
        raise typer.Exit(130) from None
    finally:
        restore_signals(previous)
    return summary


def _print_run(summary, input_path: Path) -> None:
    """The frames of a run, its failures and warnings, and the files it wrote."""
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
    print_warnings(((w["frame"], w["warning"]) for w in summary.warnings), full="summary.json")
    if info["unexpected_errors"]:
        console.print(
            f"[bold red]{info['unexpected_errors']} frames failed with unexpected errors[/] "
            "(tracebacks in the log above)"
        )
    for f in summary.files:
        console.print(f"wrote [bold]{f}[/]")


# ------------------------------------------------------------------------------ many inputs
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
    from ssp.io.results import bop_csv_name
    from ssp.pipeline.batch import input_out_dirs, run_inputs
    from ssp.pipeline.manifest import check_out_dir
    from ssp.pipeline.sources import HYPOTHESES_MODES

    out = out if out is not None else Path("ssp-out")
    hypotheses = hypotheses or "auto"
    method = method or "ssp"
    if hypotheses not in HYPOTHESES_MODES:
        raise typer.BadParameter(f"--hypotheses must be one of {', '.join(HYPOTHESES_MODES)}")
    bop_csv_name("input", method)  # a bad method name fails before the models load
    for d in input_out_dirs(inputs, out):
        check_out_dir(d, overwrite)
    if models is None:
        models = _input_models(inputs)
    lib = load_library(models, config, cache)
    previous = stop_on_sigterm()
    try:
        with progress_bar() as progress:
            task = progress.add_task("inputs", total=len(inputs))
            results = run_inputs(
                inputs,
                lib,
                out,
                load_config(config),
                parallel=parallel,
                overwrite=overwrite,
                progress=lambda done, total, name: progress.update(
                    task, completed=done, description=str(name)
                ),
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
        restore_signals(previous)
    if _print_many(inputs, results, out):
        raise typer.Exit(1)


def _print_many(inputs, results, out: Path) -> int:
    """One line per input of ``ssp run IN1 IN2 ...``; returns how many did not finish."""
    from ssp.pipeline.executor import ItemFailure

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
    return bad
