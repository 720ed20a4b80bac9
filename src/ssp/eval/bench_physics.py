"""``ssp bench physics``: cost of the physics world on tool-like scenes (10 and 20 objects).

Measures, per scene, the median wall time of one quasi-static step, one dynamic step, one
``save_state`` and one ``restore_state``, and writes ``OUT/results.json``. Scenes use the
built-in tool-like models (non-convex, several convex parts each) so no outside data is needed.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import numpy as np

from ssp import __version__
from ssp.config import SSPConfig
from ssp.eval import scenes
from ssp.library import ObjectLibrary
from ssp.library.builtin import TOOL_NAMES
from ssp.physics import World


def _median_us(fn, n_calls: int, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n_calls):
            fn()
        times.append((time.perf_counter() - t0) / n_calls)
    return float(np.median(times) * 1e6)


def _bench_scene(name, instances, poses, config: SSPConfig, repeats: int) -> dict:
    world = World(instances, config=config.physics)
    world.set_poses(poses)
    world.step(200, quasi_static=False)  # settle 1 s so contacts are those of a resting scene
    s0 = world.save_state()
    n_steps = 50

    def qs():
        world.step(n_steps, quasi_static=True)

    def dyn():
        world.step(n_steps, quasi_static=False)

    step_qs = _median_us(lambda: (world.restore_state(s0), qs()), 1, repeats) / n_steps
    step_dyn = _median_us(lambda: (world.restore_state(s0), dyn()), 1, repeats) / n_steps
    save = _median_us(world.save_state, 1000, repeats)
    restore = _median_us(lambda: world.restore_state(s0), 1000, repeats)
    world.restore_state(s0)
    c = world.contacts()
    return {
        "scene": name,
        "objects": len(instances),
        "convex_parts": int(sum(len(i.model.convex_parts) for i in instances)),
        "contacts_at_rest": int(len(c.depth)),
        "step_quasi_static_us": step_qs,
        "step_dynamic_us": step_dyn,
        "save_us": save,
        "restore_us": restore,
    }


def run_physics_bench(config: SSPConfig, out: Path, repeats: int = 5) -> dict:
    """Run the benchmark and write ``out/results.json``; returns the results dict."""
    import mujoco

    lib = ObjectLibrary.builtin(config.library)
    tools = [lib[n] for n in TOOL_NAMES]
    rows = []
    for n in (10, 20):
        rows.append(
            _bench_scene(f"tool_scatter{n}", *scenes.scatter(tools, n, 0.4), config, repeats)
        )
        rows.append(_bench_scene(f"tool_pile{n}", *scenes.pile(tools, n), config, repeats))
    rows.append(_bench_scene("cube_tower10", *scenes.tower(lib["cube"], 10), config, repeats))
    results = {
        "protocol": "physics",
        "ssp_version": __version__,
        "mujoco_version": mujoco.__version__,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": __import__("os").cpu_count(),
        },
        "timestep_s": config.physics.timestep,
        "repeats": repeats,
        "tool_classes": [m.name for m in tools],
        "scenes": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    return results
