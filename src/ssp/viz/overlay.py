"""Images of estimates against the truth: outlines of posed models over the depth image.

:func:`overlay` renders the ground truth and one or more methods' estimates with the same
camera (:func:`ssp.sim.render.render`) and draws each object's silhouette outline over the
(noisy) depth image the methods saw: truth in white, each method in its own colour. An outline
that sits on the white one is a good pose; one that is shifted, turned or missing is visible at
a glance. Pure numpy (RGB uint8 arrays); :func:`save_png` writes them with matplotlib.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ssp.sim.render import Camera, render

__all__ = ["METHOD_COLOURS", "overlay", "save_png"]

#: Outline colour (RGB) per method name; others cycle through the extra colours.
METHOD_COLOURS: dict[str, tuple[int, int, int]] = {
    "truth": (255, 255, 255),
    "ssp": (40, 200, 80),
    "estimator": (235, 70, 60),
    "icp": (250, 170, 40),
    "bestfit": (70, 140, 255),
    "temporal_filter": (200, 90, 220),
}
_EXTRA = [(0, 200, 200), (180, 180, 0), (255, 120, 180)]

Posed = Sequence[tuple[str, np.ndarray]]  # (class_name, T_world_obj)


def _depth_rgb(depth: np.ndarray) -> np.ndarray:
    """Grey-scale image of a depth map (near = bright, missing = black)."""
    d = np.asarray(depth, dtype=float)
    out = np.zeros((*d.shape, 3), dtype=np.uint8)
    ok = d > 0
    if ok.any():
        lo, hi = np.percentile(d[ok], [1, 99])
        v = 1.0 - np.clip((d - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
        grey = (40 + 150 * v).astype(np.uint8)
        out[ok] = grey[ok, None]
    return out


def _outline(instance: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of an object whose right or lower neighbour differs."""
    obj = instance >= 0
    edge = np.zeros_like(obj)
    diff_x = instance[:, 1:] != instance[:, :-1]
    diff_y = instance[1:, :] != instance[:-1, :]
    edge[:, 1:] |= diff_x
    edge[:, :-1] |= diff_x
    edge[1:, :] |= diff_y
    edge[:-1, :] |= diff_y
    return edge & (obj | np.roll(obj, 1, 0) | np.roll(obj, 1, 1))


def _render_instances(
    library: Mapping, posed: Posed, T_world_cam: np.ndarray, camera: Camera
) -> np.ndarray:
    objects = [(f"o{i}", library[cls].mesh, T) for i, (cls, T) in enumerate(posed)]
    return render(objects, T_world_cam, camera, table=False).instance


def overlay(
    library: Mapping,
    depth: np.ndarray,
    camera: Camera,
    T_world_cam: np.ndarray,
    truth: Posed,
    estimates: Mapping[str, Posed],
    *,
    crop: bool = True,
    crop_margin: int = 20,
    min_size: int = 480,
) -> np.ndarray:
    """RGB image uint8: ``depth`` in grey, outlines of each method's ``estimates``
    (``METHOD_COLOURS``) and of ``truth`` (white, drawn last). ``camera`` must match ``depth``.
    ``crop``: cut to the truth's pixels plus ``crop_margin`` and enlarge (nearest pixel, integer
    factor) toward ``min_size`` pixels on the longer side."""
    img = _depth_rgb(depth)
    layers = [*estimates.items(), ("truth", truth)]  # truth last: always visible
    box = None
    for k, (name, posed) in enumerate(layers):
        if not posed:
            continue
        colour = METHOD_COLOURS.get(name, _EXTRA[k % len(_EXTRA)])
        inst = _render_instances(library, posed, T_world_cam, camera)
        img[_outline(inst)] = colour
        if name == "truth" and (inst >= 0).any():
            rows, cols = np.nonzero(inst >= 0)
            box = (rows.min(), rows.max(), cols.min(), cols.max())
    if crop and box is not None:
        pad = crop_margin
        r0, r1 = max(box[0] - pad, 0), min(box[1] + pad + 1, img.shape[0])
        c0, c1 = max(box[2] - pad, 0), min(box[3] + pad + 1, img.shape[1])
        img = img[r0:r1, c0:c1]
        scale = max(1, int(np.ceil(min_size / max(img.shape[:2]))))
        if scale > 1:
            img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    return img


def save_png(
    path: str | Path, image: np.ndarray, title: str | None = None, legend: Sequence[str] = ()
) -> Path:
    """Write ``image`` (RGB uint8) to ``path`` with an optional title and colour legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    h, w = image.shape[:2]
    fig = plt.figure(figsize=(w / 100, h / 100 + (0.35 if title else 0)), dpi=100)
    ax = fig.add_axes([0, 0, 1, h / (h + (35 if title else 0))])
    ax.imshow(image, interpolation="nearest")
    ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=9, y=0.995)
    if legend:
        handles = [
            Patch(color=np.array(METHOD_COLOURS.get(n, _EXTRA[0])) / 255, label=n) for n in legend
        ]
        ax.legend(handles=handles, loc="lower right", fontsize=7, framealpha=0.6)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
