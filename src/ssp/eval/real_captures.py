"""The real development captures (``../shared/data/real-dev``) as run inputs, with models.

The captures have no meshes: the box models are measured from the labelled points
(:func:`measure_boxes`), the carton from its tutorial cloud (:func:`carton_size`). The data
stays where it is: :func:`mosd_captures` and :func:`milk_captures` write, in a work folder,
the model folders and input folders a user would write (symbolic links to the captures,
``scene.json``), for ``examples/real_dev.py`` (what ssp makes of them) and ``ssp bench
frame`` (how long a frame takes).

- ``mosd-stacked-boxes/test16..23.pcd``: each frame its own scene; two inputs per frame:
  ``labels`` (the label field as instance segments, labels 0-9 background) and ``clusters``
  (the same points without the label field: the front end clusters what stands on the table).
- ``pcl-milk/milk_cartoon_all_small_clorox.pcd``: a carton model (a box with a gable top);
  the cloud's axes are x right, y up, z backward (``scene.json`` ``"camera_axes": "opengl"``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ssp.io import read_cloud, write_cloud

__all__ = [
    "MILK",
    "MILK_SCENE",
    "MOSD",
    "box_mesh",
    "carton_size",
    "measure_boxes",
    "milk_captures",
    "mosd_captures",
    "plane_frame",
    "write_models",
]

MOSD = "mosd-stacked-boxes"
MILK = "pcl-milk"
MILK_SCENE = "milk_cartoon_all_small_clorox.pcd"
TABLE_LABELS = list(range(10))  # 0 = invalid or background, 1-9 = table
BOX_DENSITY = 200.0  # kg/m^3: cardboard boxes, partly filled


def plane_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares plane of ``points`` (camera frame): centre, unit normal toward the camera
    (the origin) and a ``(2, 3)`` basis of the plane."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2] if np.dot(vt[2], -c) > 0 else -vt[2]
    return c, n, vt[:2]


def measure_boxes(
    points: np.ndarray, labels: np.ndarray, table_labels: list[int]
) -> dict[int, tuple[float, float, float]]:
    """Box sizes ``(a, b, h)`` (m) of the labelled objects standing on a table.

    ``h`` is the extent along the table normal (1st to 99th percentile of the heights: a box on
    another box is measured from the top of the one below); ``a, b`` the extents along the
    principal axes of the points projected on the table (2nd to 98th percentile). The views are
    partial, so sizes are at most a few mm short.
    """
    ok = np.all(np.isfinite(points), axis=1)
    table = ok & np.isin(labels, table_labels)
    c, n, basis = plane_frame(points[table])
    sizes: dict[int, tuple[float, float, float]] = {}
    for lab in sorted(set(labels[ok].tolist()) - set(table_labels)):
        p = points[ok & (labels == lab)] - c
        h = p @ n
        uv = p @ basis.T
        uv = uv - uv.mean(axis=0)
        _, _, vt = np.linalg.svd(uv, full_matrices=False)
        q = uv @ vt.T
        a, b = (float(np.percentile(q[:, i], 98) - np.percentile(q[:, i], 2)) for i in (0, 1))
        sizes[int(lab)] = (a, b, float(np.percentile(h, 99) - np.percentile(h, 1)))
    return sizes


def box_mesh(size: tuple[float, float, float], gable: float = 0.0):
    """A closed box mesh ``size`` (m) centred at its base centre's height/2 (origin at the
    centre of the box part), with an optional gable roof of height ``gable`` along x."""
    import trimesh

    a, b, h = size
    if gable <= 0:
        return trimesh.creation.box(extents=(a, b, h))
    x, y, z = a / 2, b / 2, h / 2
    v = [[sx * x, sy * y, sz * z] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)]
    v += [[-x, 0, z + gable], [x, 0, z + gable]]
    return trimesh.Trimesh(vertices=np.array(v), process=False).convex_hull


def write_models(folder: Path, meshes: dict[str, object], density: float) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, mesh in meshes.items():
        mesh.export(folder / f"{name}.obj")
    (folder / "models.yaml").write_text(
        f"units: m\ndefaults: {{density: {density}, friction: 0.8}}\n", encoding="utf-8"
    )


def carton_size(path: Path, footprint: float = 0.07) -> tuple[float, float, float, float]:
    """Width, depth, wall height and gable height (m) of the carton in ``milk.pcd``.

    The cloud's y axis is the carton's long axis (the capture's axes: y up). The height is the
    1st to 99th percentile along y; the gable is the end where 10 mm slices are narrower than
    70 % of the median slice. The footprint is not measurable from this one-sided view (two
    faces seen at an angle): the carton's ``footprint`` (70 mm, data README) is used.
    """
    p = read_cloud(path).points
    p = p[np.all(np.isfinite(p), axis=1)]
    y = p[:, 1]
    lo, hi = np.percentile(y, [1, 99])
    edges = np.arange(lo, hi + 1e-9, 0.01)
    widths = []
    for y0 in edges[:-1]:
        s = p[(y >= y0) & (y < y0 + 0.01)][:, [0, 2]]
        s = s - s.mean(axis=0)
        _, _, vt = np.linalg.svd(s, full_matrices=False)
        q = s @ vt[0]
        widths.append(np.percentile(q, 98) - np.percentile(q, 2))
    narrow = np.asarray(widths) < 0.7 * np.median(widths)
    n_lo = int(np.argmin(narrow)) if narrow[0] else 0
    n_hi = int(np.argmin(narrow[::-1])) if narrow[-1] else 0
    gable = 0.01 * max(n_lo, n_hi)
    return footprint, footprint, float(hi - lo) - gable, gable


def mosd_captures(data: Path, work: Path, only: set[str] | None) -> list[dict]:
    """The mOSD captures of ``data`` (``real-dev``) as runs, their models and inputs written in
    ``work``: per capture (``only``: these stems), a ``labels`` and a ``clusters`` run, each
    ``{capture, input, models, note, expected}`` (``expected``: the input's instance labels,
    None without labels)."""
    runs = []
    for pcd in sorted((data / MOSD).glob("test*.pcd")):
        if only and pcd.stem not in only:
            continue
        cloud = read_cloud(pcd)
        sizes = measure_boxes(cloud.points, cloud.labels, TABLE_LABELS)
        models = work / "models" / pcd.stem
        write_models(models, {f"box{k}": box_mesh(s) for k, s in sizes.items()}, BOX_DENSITY)
        size_note = ", ".join(
            f"box{k} {'x'.join(f'{v * 1000:.0f}' for v in s)}" for k, s in sizes.items()
        )
        with_labels = work / "input" / f"{pcd.stem}-labels"
        with_labels.mkdir(parents=True, exist_ok=True)
        link = with_labels / pcd.name
        if not link.exists():
            link.symlink_to(pcd.resolve())
        scene = {"labels": "instance", "background_labels": TABLE_LABELS}
        (with_labels / "scene.json").write_text(json.dumps(scene), encoding="utf-8")
        clusters = work / "input" / f"{pcd.stem}-clusters"
        clusters.mkdir(parents=True, exist_ok=True)
        write_cloud(clusters / pcd.name, cloud.points, colors=cloud.colors)
        expected = {str(k) for k in sizes}
        for variant, inp in (("labels", with_labels), ("clusters", clusters)):
            runs.append(
                {"capture": f"{pcd.stem} {variant}", "input": inp, "models": models,
                 "note": size_note, "expected": expected if variant == "labels" else None}
            )  # fmt: skip
    return runs


def milk_captures(data: Path, work: Path, only: set[str] | None) -> list[dict]:
    """The PCL milk capture of ``data`` as a run (``only`` without ``milk``: none), like
    :func:`mosd_captures`'s."""
    if only and "milk" not in only:
        return []
    w, d, h, g = carton_size(data / MILK / "milk.pcd")
    models = work / "models" / "milk"
    write_models(models, {"carton": box_mesh((w, d, h), gable=g)}, 500.0)
    inp = work / "input" / "milk"
    inp.mkdir(parents=True, exist_ok=True)
    link = inp / MILK_SCENE
    if not link.exists():
        link.symlink_to((data / MILK / MILK_SCENE).resolve())
    (inp / "scene.json").write_text(json.dumps({"camera_axes": "opengl"}), encoding="utf-8")
    note = f"carton {w * 1000:.0f}x{d * 1000:.0f}x{h * 1000:.0f} + gable {g * 1000:.0f} mm"
    return [{"capture": "milk", "input": inp, "models": models, "note": note}]
