"""Synthetic data: ray-cast depth images of posed object models, sensor noise, and frames."""

from ssp.sim.bop import read_bop, simulate_to_disk, write_bop
from ssp.sim.frames import perturb_pose, render_scene, synthetic_frame, visible_fractions
from ssp.sim.generate import (
    EXPERIMENTS,
    calibrate_noise,
    default_camera_pose,
    generate_sequence,
    generate_sequences,
)
from ssp.sim.hypotheses import HypothesisNoise, draw_hypotheses, induced_errors
from ssp.sim.render import (
    NO_HIT,
    TABLE,
    Camera,
    RenderResult,
    add_depth_noise,
    cloud,
    look_at,
    render,
)

__all__ = [
    "EXPERIMENTS",
    "NO_HIT",
    "TABLE",
    "Camera",
    "HypothesisNoise",
    "RenderResult",
    "add_depth_noise",
    "calibrate_noise",
    "cloud",
    "default_camera_pose",
    "draw_hypotheses",
    "generate_sequence",
    "generate_sequences",
    "induced_errors",
    "look_at",
    "perturb_pose",
    "read_bop",
    "render",
    "render_scene",
    "simulate_to_disk",
    "synthetic_frame",
    "visible_fractions",
    "write_bop",
]
