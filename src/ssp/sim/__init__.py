"""Synthetic data: ray-cast depth images of posed object models, sensor noise, and frames."""

from ssp.sim.frames import perturb_pose, render_scene, synthetic_frame, visible_fractions
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
    "NO_HIT",
    "TABLE",
    "Camera",
    "RenderResult",
    "add_depth_noise",
    "cloud",
    "look_at",
    "perturb_pose",
    "render",
    "render_scene",
    "synthetic_frame",
    "visible_fractions",
]
