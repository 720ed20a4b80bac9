"""``ssp bench table1``, ``ssp bench stream`` and ``ssp bench tower``: the paper's experiments
on synthetic sequences (:mod:`ssp.eval`)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from ssp.cli.common import (
    CacheOption,
    ConfigOption,
    ExecutorOption,
    ExperimentOption,
    FramesOption,
    ModelsOption,
    RayAddressOption,
    StagesOption,
    StrideOption,
    WorkersOption,
    check_experiment,
    console,
    experiment_library,
    friendly,
    get_parallel,
    load_config,
    load_library,
    progress_bar,
)

__all__ = ["bench_stream", "bench_table1", "bench_tower", "print_table1"]


def _methods(text: str) -> list[str]:
    """The ``--methods`` list, checked against :data:`ssp.eval.baselines.METHODS`."""
    from ssp.eval.baselines import METHODS

    names = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in names if m not in METHODS]
    if unknown or not names:
        raise typer.BadParameter(f"--methods: unknown {unknown}; known: {', '.join(METHODS)}")
    return names


def print_table1(result: dict) -> None:
    """The tables of a Table I result: accuracy and precision, then the tails."""
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
    _print_tails(result)


def _print_tails(result: dict) -> None:
    """The tails of a Table I result: BOP recall, gross errors, false objects, id switches."""
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


@friendly
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
            "distractors, mask defects and dynamic events (docs/benchmarks.md); rgb: the same "
            "scenes with an RGB estimator's stream (MegaPose-like: errors mostly in depth along "
            "the viewing ray, far outliers, flips, misses by visibility; measured on LM-O by "
            "ssp bench rgb-calibration)."
        ),
    ),
    masks: str = typer.Option(
        "instance",
        "--masks",
        help=(
            "instance: every method gets the instance masks (each point's object, each "
            "hypothesis's segment); none: a bare cloud (ssp clusters it: touching objects and "
            "distractors are not told apart by labels; with --hypotheses estimated the front end "
            "estimates on the clusters)."
        ),
    ),
    camera: str = typer.Option(
        "static",
        "--camera",
        help=(
            "static: the paper's fixed camera; orbit (3.6 deg and 3.6 mm of sideways drift per "
            "frame), handheld (shaking about the static pose) or keyframes (BOP-style views "
            "10-30 deg apart): a moving camera, its pose given with each frame "
            "(docs/benchmarks.md, moving cameras)."
        ),
    ),
    camera_pose: str = typer.Option(
        "given",
        "--camera-pose",
        help=(
            "given: each frame's camera pose is given to the methods; estimated: not given, "
            "located by ssp as ssp run does for a scene without cam_R_w2c (its error is in "
            "every method's results)."
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
    from ssp.eval.table1 import DEFAULT_METHODS, table1_report, write_table1

    _check_table1_options(hypotheses, noise, masks, camera)
    if camera_pose not in ("given", "estimated"):
        raise typer.BadParameter("--camera-pose must be 'given' or 'estimated'")
    names = _methods(methods) if methods else list(DEFAULT_METHODS)
    experiment = check_experiment(experiment)
    parallel = get_parallel(executor, workers, ray_address)
    cfg = load_config(config)
    lib = experiment_library(experiment, models, config, cache)
    command = {"experiment": experiment, "sequences": sequences, "seed": seed,
               "models": None if models is None else str(models), "stages": stages,
               "frames_per_stage": frames_per_stage, "stride": stride, "hypotheses": hypotheses,
               "noise": noise, "masks": masks, "camera": camera,
               "camera_pose": camera_pose, "methods": names,
               "vsd": vsd}  # fmt: skip
    parts = _table1_parts(command, lib, cfg, parallel)
    result = table1_report(parts, names, hypotheses=hypotheses, noise=noise, command=command)
    files = write_table1(result, out)
    print_table1(result)
    _print_estimator(result)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


def _check_table1_options(
    hypotheses: str, noise: str, masks: str = "instance", camera: str = "static"
) -> None:
    """The --hypotheses, --noise, --masks and --camera of ``ssp bench table1``."""
    from ssp.sim.camera_path import CAMERA_PATHS

    if camera not in CAMERA_PATHS:
        raise typer.BadParameter(f"--camera must be one of {', '.join(CAMERA_PATHS)}")
    if hypotheses not in ("noisy", "estimated"):
        raise typer.BadParameter("--hypotheses must be 'noisy' or 'estimated'")
    if noise not in ("paper", "realistic", "rgb"):
        raise typer.BadParameter("--noise must be 'paper', 'realistic' or 'rgb'")
    if masks not in ("instance", "none"):
        raise typer.BadParameter("--masks must be 'instance' or 'none'")


def _table1_parts(command: dict, lib, cfg, parallel) -> list:
    """The Table I parts of the sequences ``command`` (the options of ``ssp bench table1``)
    asks for, with a progress bar."""
    from ssp.eval.table1 import SequenceSpec, run_table1_parts

    experiment, sequences = command["experiment"], command["sequences"]
    specs = [
        SequenceSpec(
            experiment,
            command["seed"] + i,
            stages=command["stages"],
            frames_per_stage=command["frames_per_stage"],
            stride=command["stride"],
            realistic=command["noise"] in ("realistic", "rgb"),
            estimated=command["hypotheses"] == "estimated",
            rgb=command["noise"] == "rgb",
            masks=command.get("masks", "instance") == "instance",
            camera=command.get("camera", "static"),
            locate=command.get("camera_pose", "given") == "estimated",
        )
        for i in range(sequences)
    ]
    with progress_bar() as progress:
        task = progress.add_task(f"{experiment} sequences", total=sequences)
        return run_table1_parts(
            specs,
            lib,
            cfg,
            methods=command["methods"],
            progress=lambda msg: progress.update(task, description=msg),
            vsd=command["vsd"],
            parallel=parallel,
            on_sequence=lambda done, total: progress.update(task, completed=done),
            masks=command.get("masks", "instance") == "instance",
        )


def _print_estimator(result: dict) -> None:
    """The pose estimator's time and recall, when the result has them."""
    if "estimator" in result:
        e = result["estimator"]
        console.print(
            f"pose estimator: {e['sec_per_segment_mean']:.3f} s per segment (median "
            f"{e['sec_per_segment_median']:.3f}, {e['segments']} segments); recall within "
            f"{e['recall_mm']:.0f} mm / {e['recall_deg']:.0f} deg: {e['recall']:.2f} of all "
            f"objects, {e['recall_visible']:.2f} of those >= 10 % visible"
            + ("" if e["top1_recall_visible"] is None else
               f" (top-1 {e['top1_recall_visible']:.2f})")
            + ("" if "clusters" not in e else
               f"; {e['objects_per_cluster_mean']:.2f} objects found per cluster")
        )  # fmt: skip


def _print_tower(result: dict) -> None:
    """The table of a tower case study result."""
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


@friendly
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

    experiment = check_experiment(experiment)
    parallel = get_parallel(executor, workers, ray_address)
    cfg = load_config(config)
    lib = load_library(None, config)
    with progress_bar() as progress:
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


@friendly
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
    methods: str = typer.Option(  # ssp.eval.tower.DEFAULT_METHODS
        "ssp,estimator,ray_slide", help="Comma-separated methods to compare."
    ),
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
            "defects: docs/benchmarks.md), or rgb (realistic with an RGB estimator's stream, "
            "MegaPose-like: errors mostly in depth along the viewing ray)."
        ),
    ),
    camera: str = typer.Option(
        "static",
        "--camera",
        help=(
            "static: the paper's camera, 1 m away at 45 deg; wrist: on the robot's wrist, a "
            "new view of the table before each pick (its pose from the arm's kinematics)."
        ),
    ),
    config: Path | None = ConfigOption,
    executor: str | None = ExecutorOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
) -> None:
    """The paper's case study (Table III): a simulated robot stacks 8 cubes from perceived
    poses; writes results.json, results.md and a picture of a final tower per method."""
    from ssp.eval.tower import CAMERAS, HYPOTHESES, NOISE_PRESETS, write_tower

    if camera not in CAMERAS:
        raise typer.BadParameter(f"--camera must be one of {', '.join(CAMERAS)}")

    if noise not in (*NOISE_PRESETS, "realistic", "rgb"):
        raise typer.BadParameter(
            f"--noise must be one of {', '.join(NOISE_PRESETS)}, realistic, rgb"
        )
    if hypotheses not in HYPOTHESES:
        raise typer.BadParameter(f"--hypotheses must be one of {', '.join(HYPOTHESES)}")
    names = _methods(methods)
    parallel = get_parallel(executor, workers, ray_address)
    cfg = load_config(config)
    lib = load_library(None, config)
    result, pictures = _run_tower(lib, cfg, parallel, trials=trials, seed=seed, methods=names,
                                  hypotheses=hypotheses, frames_per_step=frames_per_step,
                                  noise=noise, camera=camera)  # fmt: skip
    result["command"] = {
        "trials": trials,
        "seed": seed,
        "hypotheses": hypotheses,
        "methods": names,
        "frames_per_step": frames_per_step,
        "noise": noise,
        "camera": camera,
    }
    files = write_tower(result, out, pictures)
    _print_tower(result)
    for f in files:
        console.print(f"wrote [bold]{f}[/]")


def _run_tower(
    lib,
    cfg,
    parallel,
    *,
    trials: int,
    seed: int,
    methods: list[str],
    hypotheses: str,
    frames_per_step: int,
    noise: str,
    camera: str = "static",
) -> tuple[dict, dict]:
    """The tower case study with a progress bar: the result, and a picture of the first
    trial's tower per method."""
    from ssp.eval.tower import run_tower, tower_picture
    from ssp.sim.realistic import SceneRealism

    pictures = {}
    with progress_bar() as progress:
        task = progress.add_task("tower", total=trials * len(methods))

        def on_trial(name: str, t: int, trial) -> None:
            progress.update(task, advance=1)
            if t == 0:
                pictures[name] = tower_picture(lib, trial, name)

        result = run_tower(
            trials,
            seed,
            lib,
            cfg,
            methods=methods,
            hypotheses=hypotheses,
            frames_per_step=frames_per_step,
            noise=_tower_noise(noise),
            realism=SceneRealism(events=()) if noise in ("realistic", "rgb") else None,
            camera_path=camera,
            progress=lambda msg: progress.update(task, description=msg),
            on_trial=on_trial,
            parallel=parallel,
        )
    return result, pictures


def _tower_noise(noise: str):
    """The tower's hypothesis noise of ``--noise``: a Table I preset, or a realistic stream."""
    from ssp.eval.tower import noise_preset
    from ssp.sim.realistic import RealisticNoise

    if noise == "rgb":
        return RealisticNoise.rgb()
    return RealisticNoise() if noise == "realistic" else noise_preset(noise)
