"""``ssp bench camera``: locating a moving camera with no pose given (issue 32).

Simulated sequences (:func:`ssp.sim.generate.generate_sequence`) along each camera path
(:mod:`ssp.sim.camera_path`); each frame's cloud, in the camera's frame, goes to:

``table``
    :class:`ssp.perception.table.TableTracker`, what ``ssp run`` did: the table's frame,
    kept while the plane stays, fitted again when it moves (the camera's motion becomes the
    objects').
``egomotion``
    :class:`ssp.perception.egomotion.CameraTracker` on the map of the frames before, as
    ``ssp run`` uses it (no global search).
``egomotion_search``
    the same with the global search over turns when a frame does not track.
``egomotion_known``
    the same, also told the previous frame's objects (``CameraTracker.know``) as the parser's
    kept objects would tell it; here the true ones: the bound of what that feedback can give.

The world frame of a tracker is its first frame's table frame; it is compared with the truth's
through the first frame (``A = T_world_cam_true(0) inv(T_world_cam(0))``). Per frame: the error
at the scene (the largest displacement of the frame's objects' centres, the pose a robot acts
on moves by that much), the camera's rotation error, and frames not located (refused).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from ssp.errors import PerceptionError
from ssp.io import write_json
from ssp.io._files import atomic_write_text
from ssp.perception.depth import cloud_from_depth
from ssp.perception.egomotion import CameraTracker
from ssp.perception.table import TableTracker
from ssp.probability import pose_change

__all__ = ["TRACKERS", "bench_camera", "write_camera_report"]

#: The trackers compared (module docstring).
TRACKERS: tuple[str, ...] = ("table", "egomotion", "egomotion_search", "egomotion_known")


def _cloud(seq, i: int) -> np.ndarray:
    """Frame ``i``'s cloud in its camera's frame (N, 3), m."""
    return cloud_from_depth(seq.frames[i].depth, seq.camera).points


def _scene_error(T_est: np.ndarray, T_true: np.ndarray, gt) -> float:
    """Largest displacement (m) of the objects' centres ``gt`` between the world frames of
    the estimated and the true camera pose."""
    D = T_est @ np.linalg.inv(T_true)
    c = np.array([np.asarray(T, dtype=float)[:3, 3] for _, T in gt.values()])
    return float(np.linalg.norm(c @ D[:3, :3].T + D[:3, 3] - c, axis=1).max()) if len(c) else 0.0


def _track(name: str, seq, library) -> list[dict]:
    """Per frame of ``seq``: the tracker ``name``'s error, or that it refused the frame."""
    table = TableTracker(0.006) if name == "table" else None
    ego = CameraTracker(search=name == "egomotion_search") if name != "table" else None
    align = None
    rows = []
    for i, sf in enumerate(seq.frames):
        p = _cloud(seq, i)
        t0 = time.perf_counter()
        how = "table"
        try:
            if table is not None:
                T, _ = table.update(p)
            else:
                assert ego is not None
                fix = ego.update(p)
                T, how = fix.T_world_cam, fix.how
        except PerceptionError as exc:
            rows.append({"frame": i, "located": False, "why": str(exc),
                         "sec": time.perf_counter() - t0})  # fmt: skip
            continue
        sec = time.perf_counter() - t0
        if align is None:
            align = seq.camera_pose(i) @ np.linalg.inv(T)  # the tracker's world to the truth's
        if ego is not None and name == "egomotion_known":  # told in the tracker's world frame
            to_tracker = np.linalg.inv(align)
            ego.know([(library[c], to_tracker @ np.asarray(T_o)) for c, T_o in sf.gt.values()])
        T_est, T_true = align @ T, seq.camera_pose(i)
        rows.append({
            "frame": i, "located": True, "how": how, "sec": sec,
            "scene_mm": 1000.0 * _scene_error(T_est, T_true, sf.gt),
            "camera_deg": float(np.degrees(pose_change(T_true, T_est)[1])),
        })  # fmt: skip
    return rows


def _summary(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["located"]]
    mm = np.array([r["scene_mm"] for r in ok]) if ok else np.zeros(0)
    deg = np.array([r["camera_deg"] for r in ok]) if ok else np.zeros(0)

    def q(a, p):
        return None if not len(a) else round(float(np.percentile(a, p)), 3)

    return {
        "frames": len(rows),
        "located": len(ok),
        "not_located": len(rows) - len(ok),
        "scene_mm_median": q(mm, 50),
        "scene_mm_p95": q(mm, 95),
        "scene_mm_max": q(mm, 100),
        "camera_deg_median": q(deg, 50),
        "camera_deg_max": q(deg, 100),
        "within_2mm": None if not len(mm) else round(float(np.mean(mm < 2.0)), 4),
        "sec_per_frame_mean": round(float(np.mean([r["sec"] for r in rows])), 4),
    }


def bench_camera(
    library: Mapping,
    experiment: str,
    paths: Sequence[str],
    sequences: int,
    seed: int,
    trackers: Sequence[str] = TRACKERS,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The trackers on ``sequences`` sequences (seeds ``seed, seed + 1, ...``) of each camera
    path: per path and tracker, the summary and the per-frame rows."""
    from ssp.sim.generate import generate_sequence

    out: dict = {"protocol": "camera", "experiment": experiment, "seed": int(seed),
                 "sequences": int(sequences), "paths": {}}  # fmt: skip
    for path in paths:
        rows: dict[str, list[dict]] = {t: [] for t in trackers}
        for s in range(int(seed), int(seed) + int(sequences)):
            if progress is not None:
                progress(f"{path}: sequence {s}")
            seq = generate_sequence(experiment, s, library, camera_path=path)
            for t in trackers:
                rows[t] += [{"sequence": s, **r} for r in _track(t, seq, library)]
        out["paths"][path] = {t: {**_summary(r), "rows": r} for t, r in rows.items()}
    return out


def write_camera_report(result: dict, out: Path) -> tuple[Path, Path]:
    """``out/results.json`` and ``out/results.md`` (written atomically, as the umask says)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    j = write_json(out / "results.json", result)
    lines = [
        f"# Camera egomotion: {result['experiment']}, {result['sequences']} sequences from "
        f"seed {result['seed']}",
        "",
        "Error at the scene: the largest displacement of a frame's objects' centres between "
        "the tracked and the true world frames (mm); frames not located are refused.",
        "",
        "| path | tracker | located | scene mm median / p95 / max | within 2 mm | camera deg "
        "median / max | s/frame |",
        "|---|---|---|---|---|---|---|",
    ]

    def f(v):
        return "-" if v is None else f"{v:.2f}"

    for path, by in result["paths"].items():
        for t, s in by.items():
            within = "-" if s["within_2mm"] is None else f"{100 * s['within_2mm']:.0f} %"
            lines.append(
                f"| {path} | {t} | {s['located']} / {s['frames']} | {f(s['scene_mm_median'])} / "
                f"{f(s['scene_mm_p95'])} / {f(s['scene_mm_max'])} | {within} | "
                f"{f(s['camera_deg_median'])} / {f(s['camera_deg_max'])} | "
                f"{s['sec_per_frame_mean']:.3f} |"
            )
    return j, atomic_write_text(out / "results.md", "\n".join(lines) + "\n")
