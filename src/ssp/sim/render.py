"""Depth images of posed meshes on a table by ray casting, and a Kinect-like depth noise model.

What is modelled
----------------
* An ideal pinhole camera (:class:`Camera`, OpenCV frame: x right, y down, z forward; pixel
  ``(u, v)`` has its centre at integer coordinates, ``u = fx x / z + cx``). No lens distortion.
* Geometry: the union of the posed object meshes and, optionally, a finite square table top at
  ``z = 0`` (world frame, z up). One ray per pixel through the pixel centre; the first surface
  hit gives the depth (``z`` in the camera frame, m) and the instance (which object). Triangles
  are found with Embree (float32) through ``trimesh`` when ``embreex`` is installed, else with
  trimesh's slower pure-numpy caster; the depth is then recomputed exactly (float64) on the hit
  triangle's plane, so noise-free points lie on the mesh to ~1e-9 m.
* Sensor noise (:func:`add_depth_noise`, applied separately): axial Gaussian noise growing with
  depth as measured for the Kinect by Nguyen et al. (2012), ``sigma_z = 0.0012 + 0.0019 (z -
  0.4)^2`` m; optional disparity quantisation; missing pixels at depth discontinuities.

What is not modelled
--------------------
Lateral (x-y) noise, the growth of noise at grazing incidence, shadows of the projector-camera
baseline (a real structured-light sensor sees no depth where the projector is occluded),
dark, specular or transparent surfaces, multipath, spatially correlated noise, rolling shutter,
lens distortion, and anti-aliasing (each pixel is one ray, so silhouettes are hard edges).

Colour (:func:`shade`) is not rendered by ray casting: it is a flat colour per object shaded
from the normals of the (noisy) depth image, a stand-in for a camera's RGB image with no
texture, material, shadow or light of a real scene.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from ssp.camera import Camera
from ssp.geometry import transform_points, validate_pose

__all__ = [
    "NO_HIT",
    "TABLE",
    "Camera",
    "ImageWindow",
    "RenderResult",
    "add_depth_noise",
    "cloud",
    "image_window",
    "look_at",
    "render",
    "shade",
]

#: Instance value of a pixel that sees the table top.
TABLE = -1
#: Instance value of a pixel whose ray hits nothing (its depth is 0).
NO_HIT = -2

#: An object to render: ``(instance_id, mesh in its model frame, T_world_obj (4, 4))``.
SceneObject = tuple[str, trimesh.Trimesh, np.ndarray]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` (4, 4) of a camera at ``eye`` looking at ``target`` (world, m).

    OpenCV frame: z points at the target, x to the right of the image and y down, so that
    ``up`` (world) points up in the image. When the view is (anti)parallel to ``up`` (e.g. a
    camera looking straight down with the default ``up``), world +y is used as the image's up
    direction instead (top-down view: world x to the right, world y up in the image).
    """
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    if np.linalg.norm(z) < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


@dataclass(frozen=True, eq=False)
class RenderResult:
    """Images of one render.

    Attributes:
        depth: ``(H, W)`` float64 depth, ``z`` in the camera frame (m); 0 where nothing is hit.
        instance: ``(H, W)`` int64: index into ``ids`` of the object seen, :data:`TABLE` (-1)
            for the table top, :data:`NO_HIT` (-2) for nothing.
        ids: instance id of each rendered object, in the order given to :func:`render`.
        camera: the camera of these images (already subsampled when ``stride > 1``).
        T_world_cam: camera pose (4, 4).
        stride: the pixel stride the images were rendered with.
    """

    depth: np.ndarray
    instance: np.ndarray
    ids: tuple[str, ...]
    camera: Camera
    T_world_cam: np.ndarray
    stride: int = 1

    def _select(self, mask: np.ndarray | None, depth: np.ndarray | None) -> tuple:
        depth = self.depth if depth is None else np.asarray(depth, dtype=float)
        if depth.shape != self.depth.shape:
            raise ValueError(f"depth image has shape {depth.shape}, expected {self.depth.shape}")
        keep = depth > 0
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != keep.shape:
                raise ValueError(f"mask has shape {mask.shape}, expected {keep.shape}")
            keep &= mask
        return depth, keep

    def points_cam(self, mask=None, depth=None) -> np.ndarray:
        """Camera-frame points ``(N, 3)`` (m) of the pixels with depth > 0 (and ``mask``),
        row-major; ``depth`` replaces the rendered depth (e.g. a noisy copy)."""
        depth, keep = self._select(mask, depth)
        return self.camera.backproject(depth)[keep]

    def points_world(self, mask=None, depth=None) -> np.ndarray:
        """World points ``(N, 3)`` (m) of the same pixels as :meth:`points_cam`."""
        return transform_points(self.T_world_cam, self.points_cam(mask, depth))

    def labels(self, mask=None, depth=None) -> np.ndarray:
        """Instance value ``(N,)`` (object index, :data:`TABLE`) of the same pixels as
        :meth:`points_cam`."""
        _, keep = self._select(mask, depth)
        return self.instance[keep]

    def mask(self, instance_id: str) -> np.ndarray:
        """``(H, W)`` bool: the pixels that see object ``instance_id``."""
        return self.instance == self.ids.index(instance_id)

    def pixel_counts(self) -> dict[str, int]:
        """Number of pixels seeing each object, by instance id (0 for an unseen object)."""
        counts = np.bincount(self.instance[self.instance >= 0], minlength=len(self.ids))
        return {iid: int(c) for iid, c in zip(self.ids, counts, strict=False)}


def _table_mesh(size: float) -> tuple[np.ndarray, np.ndarray]:
    h = 0.5 * float(size)
    v = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def render(
    objects: Sequence[SceneObject],
    T_world_cam: np.ndarray,
    camera: Camera | None = None,
    *,
    table: bool = True,
    table_size: float = 2.0,
    stride: int = 1,
) -> RenderResult:
    """Ray-cast a depth image and an instance image of posed meshes (and a table top).

    Args:
        objects: ``(instance_id, mesh, T_world_obj)`` per object; the mesh is in its model
            frame (m), ``T_world_obj`` (4, 4) places it. Ids must be unique.
        T_world_cam: camera pose (4, 4), OpenCV camera frame (see :func:`look_at`).
        camera: intrinsics; :meth:`Camera.default` if None.
        table: add a square table top at ``z = 0``, ``table_size`` (m) wide, centred at the
            world origin (seen from both sides).
        stride: render only every ``stride``-th pixel in each direction (the result's camera
            is ``camera.subsample(stride)``).

    Returns:
        :class:`RenderResult` with ``(H, W)`` images (``H = ceil(height / stride)``).
    """
    cam = (camera or Camera.default()).subsample(stride)
    T_wc = validate_pose(T_world_cam, "T_world_cam")
    ids = tuple(str(o[0]) for o in objects)
    if len(set(ids)) != len(ids):
        raise ValueError(f"instance ids must be unique, got {ids}")

    verts, faces, owner = [], [], []
    n_verts = 0
    for i, (_, mesh, T_wo) in enumerate(objects):
        T_wo = validate_pose(T_wo, f"T_world_obj of {ids[i]!r}")
        v = transform_points(T_wo, np.asarray(mesh.vertices, dtype=float))
        f = np.asarray(mesh.faces, dtype=np.int64)
        verts.append(v)
        faces.append(f + n_verts)
        owner.append(np.full(len(f), i, dtype=np.int64))
        n_verts += len(v)
    if table:
        v, f = _table_mesh(table_size)
        verts.append(v)
        faces.append(f + n_verts)
        owner.append(np.full(len(f), TABLE, dtype=np.int64))

    H, W = cam.shape
    depth = np.zeros(H * W)
    instance = np.full(H * W, NO_HIT, dtype=np.int64)
    if faces and sum(len(f) for f in faces):
        V = np.concatenate(verts)
        F = np.concatenate(faces)
        owner_all = np.concatenate(owner)
        combined = trimesh.Trimesh(vertices=V, faces=F, process=False, validate=False)

        d_world = cam._rays_z1() @ T_wc[:3, :3].T  # camera z = 1 along every ray
        origin = T_wc[:3, 3]
        tri = combined.ray.intersects_first(np.broadcast_to(origin, d_world.shape), d_world)
        tri = np.asarray(tri, dtype=np.int64)
        hit = np.flatnonzero(tri >= 0)
        # exact (float64) depth on the plane of the hit triangle: t with o + t d on the plane
        # is the camera-frame z, since d has camera z = 1
        t3 = V[F[tri[hit]]]
        n = np.cross(t3[:, 1] - t3[:, 0], t3[:, 2] - t3[:, 0])
        d = d_world[hit]
        denom = np.einsum("ij,ij->i", n, d)
        num = np.einsum("ij,ij->i", n, t3[:, 0] - origin)
        scale = np.linalg.norm(n, axis=1) * np.linalg.norm(d, axis=1)
        ok = np.abs(denom) > 1e-12 * np.maximum(scale, 1e-300)
        t = np.where(ok, num / np.where(ok, denom, 1.0), 0.0)
        ok &= t > 0
        depth[hit[ok]] = t[ok]
        instance[hit[ok]] = owner_all[tri[hit[ok]]]

    return RenderResult(
        depth=depth.reshape(H, W),
        instance=instance.reshape(H, W),
        ids=ids,
        camera=cam,
        T_world_cam=T_wc,
        stride=int(stride),
    )


@dataclass(frozen=True)
class ImageWindow:
    """A window of an image: columns ``u0 .. u0 + w``, rows ``v0 .. v0 + h`` (pixels)."""

    u0: int
    v0: int
    w: int
    h: int

    def union(self, other: ImageWindow) -> ImageWindow:
        u0, v0 = min(self.u0, other.u0), min(self.v0, other.v0)
        u1 = max(self.u0 + self.w, other.u0 + other.w)
        v1 = max(self.v0 + self.h, other.v0 + other.h)
        return ImageWindow(u0, v0, u1 - u0, v1 - v0)

    def camera(self, camera: Camera) -> Camera:
        """The intrinsics of this window of ``camera``'s image."""
        return Camera(
            self.w, self.h, camera.fx, camera.fy, camera.cx - self.u0, camera.cy - self.v0
        )


def image_window(
    points_world: np.ndarray, T_world_cam: np.ndarray, camera: Camera
) -> ImageWindow | None:
    """The window of ``camera``'s image (with a one-pixel margin) that covers the projection of
    ``points_world`` ``(N, 3)`` (e.g. a model's hull vertices at a pose); the whole image when a
    point is behind the camera, None when the projection misses the image."""
    T = np.asarray(T_world_cam, dtype=float)
    p = (np.asarray(points_world, dtype=float) - T[:3, 3]) @ T[:3, :3]
    if (p[:, 2] <= 1e-6).any():
        return ImageWindow(0, 0, camera.width, camera.height)
    uv = camera.project(p)
    u0 = max(0, int(np.floor(uv[:, 0].min())) - 1)
    u1 = min(camera.width - 1, int(np.ceil(uv[:, 0].max())) + 1)
    v0 = max(0, int(np.floor(uv[:, 1].min())) - 1)
    v1 = min(camera.height - 1, int(np.ceil(uv[:, 1].max())) + 1)
    if u1 < u0 or v1 < v0:
        return None
    return ImageWindow(u0, v0, u1 - u0 + 1, v1 - v0 + 1)


def _edge_mask(depth: np.ndarray, threshold: float) -> np.ndarray:
    """Valid pixels with a 4-neighbour that is invalid (0) or differs by > ``threshold`` (m)."""
    valid = depth > 0
    edge = np.zeros_like(valid)
    for a, b in (
        (np.s_[1:, :], np.s_[:-1, :]),
        (np.s_[:, 1:], np.s_[:, :-1]),
    ):
        jump = (np.abs(depth[a] - depth[b]) > threshold) | (valid[a] != valid[b])
        edge[a] |= jump
        edge[b] |= jump
    return edge & valid


#: Disparity quantisation of a Kinect-like sensor: depth step at 1 m, m (1/8-pixel disparity).
KINECT_QUANTUM = 0.0028


def add_depth_noise(
    depth: np.ndarray,
    rng: np.random.Generator,
    *,
    sigma_base: float = 0.0012,
    sigma_quad: float = 0.0019,
    z_ref: float = 0.4,
    quantum: float | None = None,
    dropout_edges: bool = True,
    edge_threshold: float = 0.01,
    edge_dropout: float = 0.5,
) -> np.ndarray:
    """A noisy copy of a depth image ``(H, W)`` (m; 0 = no depth, kept 0).

    1. Axial noise: ``z + N(0, sigma(z)^2)`` with ``sigma(z) = sigma_base + sigma_quad (z -
       z_ref)^2`` (m), the Kinect model of Nguyen et al. (2012) with the default values
       (1.9 mm at 1 m, 5.8 mm at 2 m).
    2. ``quantum`` (m, optional): disparity quantisation with depth step ``quantum`` at 1 m,
       growing as ``z^2`` (``1/z`` is rounded to multiples of ``quantum``); e.g. ~0.0028 for
       a Kinect (1/8 pixel disparity).
    3. ``dropout_edges``: each pixel at a depth discontinuity of the *clean* image (a
       4-neighbour differs by more than ``edge_threshold`` m, or has no depth) is set to 0 with
       probability ``edge_dropout``. The threshold is per pixel step, so with a stride the
       dropped band is ``stride`` times wider in the full-resolution image.

    Deterministic for a given ``rng`` state (always draws one normal and one uniform per pixel).
    Noise that would make a depth non-positive makes the pixel missing (0).
    """
    z = np.asarray(depth, dtype=float)
    valid = z > 0
    normal = rng.standard_normal(z.shape)
    uniform = rng.random(z.shape)
    sigma = sigma_base + sigma_quad * (z - z_ref) ** 2
    out = np.where(valid, z + sigma * normal, 0.0)
    if quantum is not None:
        if not quantum > 0:
            raise ValueError(f"quantum must be positive, got {quantum}")
        pos = out > 0
        steps = np.round(1.0 / (out[pos] * quantum))
        out[pos] = np.where(steps > 0, 1.0 / (np.maximum(steps, 1.0) * quantum), 0.0)
    if dropout_edges:
        out[_edge_mask(z, edge_threshold) & (uniform < edge_dropout)] = 0.0
    out[~(out > 0)] = 0.0
    return out


def cloud(
    result: RenderResult,
    T_world_cam: np.ndarray | None = None,
    camera: Camera | None = None,
    depth: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(N, 3)`` (m) and labels ``(N,)`` (object index, :data:`TABLE` = -1) of a
    render, from ``depth`` (e.g. :func:`add_depth_noise` of ``result.depth``) or the clean one.

    Pixels with depth 0 are dropped; labels come from the clean instance image. The camera pose
    and intrinsics are the result's; ``T_world_cam`` and ``camera`` may be given as a check
    (``camera`` either the result's or the full-resolution one it was subsampled from).
    """
    if T_world_cam is not None and not np.allclose(T_world_cam, result.T_world_cam, atol=1e-9):
        raise ValueError("cloud: T_world_cam differs from the pose the result was rendered with")
    if camera is not None and camera.subsample(result.stride) != result.camera:
        if camera != result.camera:
            raise ValueError("cloud: camera differs from the one the result was rendered with")
    return result.points_world(depth=depth), result.labels(depth=depth)


#: Colours of :func:`shade`: RGB in 0..1.
RGB = tuple[float, float, float]


def _smooth_per_label(depth: np.ndarray, labels: np.ndarray, size: int) -> np.ndarray:
    """``depth`` averaged over a ``size`` x ``size`` window, among the valid pixels of the same
    label only (an object's depth is never mixed with the table's behind it)."""
    from scipy.ndimage import uniform_filter

    out = np.zeros_like(depth)
    valid = depth > 0
    for lab in np.unique(labels[valid]):
        m = valid & (labels == lab)
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]  # the label's pixels
        mb = m[box]
        s = uniform_filter(np.where(mb, depth[box], 0.0), size=size, mode="constant")
        c = uniform_filter(mb.astype(float), size=size, mode="constant")
        out[box][mb] = s[mb] / c[mb]
    return out


def shade(
    depth: np.ndarray,
    instance: np.ndarray,
    camera: Camera,
    colors: dict[int, RGB],
    *,
    background: RGB = (0.0, 0.0, 0.0),
    ambient: float = 0.3,
    smooth: int = 5,
) -> np.ndarray:
    """A colour image ``(H, W, 3)`` uint8 of a depth image: each pixel the flat colour of what
    it sees, Lambertian-shaded by a light at the camera.

    Args:
        depth: ``(H, W)`` depth, m (0: no depth), e.g. with sensor noise.
        instance: ``(H, W)`` instance value of each pixel (as :class:`RenderResult`).
        camera: the intrinsics of ``depth``.
        colors: instance value -> RGB (0..1); values not in it are ``background``.
        background: colour of the pixels that see nothing (:data:`NO_HIT`) or an unknown value.
        ambient: the brightness of a surface seen edge-on (1: no shading).
        smooth: window (pixels) the depth is averaged over, per instance, before the normals
            are taken (the normals of single noisy pixels are noise).

    The normal of a pixel is that of its neighbours' back-projected points (central
    differences of the smoothed depth); the brightness is ``ambient + (1 - ambient) |n . l|``
    with ``l`` the direction to the camera. A pixel whose normal is unknown (no depth, or a
    neighbour of another instance or without depth) gets ``|n . l| = 0.7``. Deterministic;
    no texture, shadows, reflections or lens effects.
    """
    depth = np.asarray(depth, dtype=float)
    instance = np.asarray(instance)
    if depth.shape != instance.shape or depth.shape != camera.shape:
        raise ValueError(
            f"shade: depth {depth.shape}, instance {instance.shape} and camera {camera.shape} "
            "differ in shape"
        )
    H, W = depth.shape
    base = np.empty((H, W, 3))
    base[:] = background
    colored = np.zeros((H, W), dtype=bool)
    for value, rgb in colors.items():
        m = instance == value
        base[m] = rgb
        colored |= m
    z = _smooth_per_label(depth, instance, max(1, int(smooth)))
    P = camera.backproject(z)
    cos = np.full((H, W), 0.7)
    ok = z > 0
    same = ok[1:-1, 1:-1].copy()
    for a, b in ((np.s_[1:-1, 2:], np.s_[1:-1, :-2]), (np.s_[2:, 1:-1], np.s_[:-2, 1:-1])):
        same &= ok[a] & ok[b] & (instance[a] == instance[1:-1, 1:-1])
        same &= instance[b] == instance[1:-1, 1:-1]
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    n = np.cross(dv, du)
    p = P[1:-1, 1:-1]
    norm = np.linalg.norm(n, axis=-1) * np.linalg.norm(p, axis=-1)
    same &= norm > 0
    c = np.abs(np.einsum("ijk,ijk->ij", n, p)) / np.where(same, norm, 1.0)
    inner = cos[1:-1, 1:-1]
    inner[same] = c[same]
    light = ambient + (1.0 - ambient) * np.clip(cos, 0.0, 1.0)
    light[~colored] = 1.0  # the background is not lit
    return np.round(np.clip(base * light[..., None], 0.0, 1.0) * 255.0).astype(np.uint8)
