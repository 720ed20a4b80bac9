"""``ssp simulate``: synthetic sequences written in the BOP layout."""

from __future__ import annotations

from pathlib import Path

import typer

from ssp.cli.common import (
    CacheOption,
    ConfigOption,
    ExperimentOption,
    FramesOption,
    ModelsOption,
    StagesOption,
    StrideOption,
    check_experiment,
    console,
    experiment_library,
    friendly,
    progress_bar,
)

__all__ = ["simulate"]


@friendly
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
    camera: str = typer.Option(
        "static",
        "--camera",
        help="The camera's path: static, orbit, handheld or keyframes (each image's pose in "
        "scene_camera.json).",
    ),
    camera_pose: bool = typer.Option(
        True,
        "--camera-pose/--no-camera-pose",
        help="Write each image's camera pose (cam_R_w2c, cam_t_w2c); without, as a published "
        "test scene of a moving camera: the hypotheses in the camera frame, and ssp run "
        "locates the camera itself.",
    ),
) -> None:
    """Write synthetic sequences (depth, shaded rgb, masks, ground truth, test targets,
    hypotheses) in BOP layout."""
    from ssp.sim.bop import simulate_to_disk
    from ssp.sim.camera_path import CAMERA_PATHS

    if camera not in CAMERA_PATHS:
        raise typer.BadParameter(f"--camera must be one of {', '.join(CAMERA_PATHS)}")
    experiment = check_experiment(experiment)
    lib = experiment_library(experiment, models, config, cache)
    with progress_bar() as progress:
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
            camera_path=camera,
            camera_pose=camera_pose,
        )
    for p in paths:
        console.print(f"wrote [bold]{p}[/]")
