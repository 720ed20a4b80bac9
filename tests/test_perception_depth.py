"""Depth image to cloud (ssp.perception.depth)."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.camera import Camera
from ssp.errors import PerceptionError
from ssp.geometry import make_pose
from ssp.perception.depth import cloud_from_depth
from ssp.sim.render import look_at, render

EDGE = 0.0508


@pytest.fixture(scope="module")
def scene(cube_model):
    objects = [
        ("a", cube_model.mesh, make_pose(None, [0.0, 0.0, EDGE / 2])),
        ("b", cube_model.mesh, make_pose(None, [0.1, 0.0, EDGE / 2])),
    ]
    return render(objects, look_at([0.0, -0.6, 0.6], [0.0, 0.0, 0.0]), stride=4)


def test_matches_the_renderer(scene):
    cloud = cloud_from_depth(scene.depth, scene.camera, mask=scene.instance)
    np.testing.assert_allclose(cloud.points, scene.points_cam(), atol=1e-12)
    np.testing.assert_array_equal(cloud.labels, scene.labels())
    assert cloud.labels.dtype == np.int64
    world = cloud_from_depth(scene.depth, scene.camera, T_world_cam=scene.T_world_cam)
    np.testing.assert_allclose(world.points, scene.points_world(), atol=1e-12)
    assert world.labels is None
    assert len(world) == int((scene.depth > 0).sum())


def test_pixels_index_the_image(scene):
    cloud = cloud_from_depth(scene.depth, scene.camera)
    rows, cols = cloud.pixels.T
    assert cloud.pixels.dtype == np.int64 and cloud.pixels.shape == (len(cloud), 2)
    np.testing.assert_array_equal(cloud.points[:, 2], scene.depth[rows, cols])
    uv = scene.camera.project(cloud.points)
    np.testing.assert_allclose(uv, np.column_stack([cols, rows]), atol=1e-9)


def test_invalid_depth_is_skipped():
    cam = Camera(4, 3, 100.0, 100.0, 1.5, 1.0)
    depth = np.full((3, 4), 0.8)
    depth[0, 0], depth[1, 2], depth[2, 3], depth[2, 0] = 0.0, np.nan, -1.0, np.inf
    cloud = cloud_from_depth(depth[..., None], cam)  # (H, W, 1) is accepted
    assert len(cloud) == 8
    assert {tuple(p) for p in cloud.pixels}.isdisjoint({(0, 0), (1, 2), (2, 3), (2, 0)})
    assert np.isfinite(cloud.points).all()


def test_bool_and_float_masks():
    cam = Camera(2, 2, 100.0, 100.0, 0.5, 0.5)
    depth = np.ones((2, 2))
    cloud = cloud_from_depth(depth, cam, mask=np.array([[True, False], [False, True]]))
    np.testing.assert_array_equal(cloud.labels, [0, -1, -1, 0])
    cloud = cloud_from_depth(depth, cam, mask=np.array([[2.0, -1.0], [0.0, 1.0]]))
    np.testing.assert_array_equal(cloud.labels, [2, -1, 0, 1])
    with pytest.raises(PerceptionError, match="integer"):
        cloud_from_depth(depth, cam, mask=np.full((2, 2), 0.5))


def test_millimetres_are_refused(scene):
    mm = np.round(scene.depth * 1000).astype(np.uint16)
    with pytest.raises(PerceptionError, match="depth_scale=0.001"):
        cloud_from_depth(mm, scene.camera)
    with pytest.raises(PerceptionError, match="depth_scale=0.001"):
        cloud_from_depth(scene.depth * 1000.0, scene.camera)
    with pytest.raises(PerceptionError, match="after depth_scale"):
        cloud_from_depth(mm, scene.camera, depth_scale=1.0)
    scaled = cloud_from_depth(mm, scene.camera, depth_scale=0.001)
    ref = cloud_from_depth(scene.depth, scene.camera)
    np.testing.assert_allclose(scaled.points, ref.points, atol=0.001)
    with pytest.raises(PerceptionError, match="positive"):
        cloud_from_depth(mm, scene.camera, depth_scale=0.0)


def test_shape_mismatch(scene):
    with pytest.raises(PerceptionError, match="shape"):
        cloud_from_depth(scene.depth[:-1], scene.camera)
    with pytest.raises(PerceptionError, match="mask has shape"):
        cloud_from_depth(scene.depth, scene.camera, mask=scene.instance[:, :-1])
    with pytest.raises(PerceptionError, match="camera pose"):
        cloud_from_depth(scene.depth, scene.camera, T_world_cam=np.full((4, 4), 2.0))


def test_empty_image():
    cam = Camera(3, 2, 100.0, 100.0, 1.0, 0.5)
    cloud = cloud_from_depth(np.zeros((2, 3)), cam, mask=np.zeros((2, 3), dtype=int))
    assert cloud.points.shape == (0, 3) and cloud.pixels.shape == (0, 2)
    assert cloud.labels.shape == (0,)
