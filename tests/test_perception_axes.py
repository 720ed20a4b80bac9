"""A camera-frame cloud in other axes than OpenCV's fails with the reason (issue 15, real
captures: PCL's Kinect clouds have y up and z backward, and every object came out 'not in the
camera's view')."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.errors import PerceptionError
from ssp.library.library import ObjectLibrary
from ssp.perception.pipeline import Perception


def _table_cloud(rng: np.random.Generator) -> np.ndarray:
    """A table 0.8 m in front of an OpenCV camera, seen from above, and a cube on it."""
    x, y = rng.uniform(-0.4, 0.4, 20000), rng.uniform(-0.3, 0.3, 20000)
    table = np.column_stack([x, y, 0.8 + 0.5 * y])  # tilted toward the camera
    return table + rng.normal(0, 0.001, table.shape)


def test_a_cloud_behind_the_camera_is_refused_with_the_axes_named():
    rng = np.random.default_rng(0)
    pts = _table_cloud(rng)
    perception = Perception(ObjectLibrary.builtin(), classes=["cube"])
    perception.from_points(pts)  # OpenCV axes: perceived (a table, no object)
    opengl = pts * np.array([1.0, -1.0, -1.0])  # x right, y up, z backward
    with pytest.raises(PerceptionError, match="OpenCV axes"):
        perception.from_points(opengl)


def test_scene_json_declares_opengl_camera_axes(tmp_path):
    from ssp.errors import InputError
    from ssp.io import write_cloud
    from ssp.io.folder import SceneSpec, open_folder

    pts = _table_cloud(np.random.default_rng(1))
    write_cloud(tmp_path / "f.pcd", pts * np.array([1.0, -1.0, -1.0]))
    (tmp_path / "scene.json").write_text('{"camera_axes": "opengl"}')
    raw = open_folder(tmp_path).load(0)
    np.testing.assert_allclose(raw.points, pts, atol=1e-6)  # float32 on disk
    Perception(ObjectLibrary.builtin(), classes=["cube"]).from_points(raw.points)
    with pytest.raises(InputError, match="camera_axes"):
        SceneSpec.from_dict({"camera_axes": "y-up"})
    with pytest.raises(InputError, match="camera_axes"):
        SceneSpec.from_dict({"camera_axes": "opengl", "frame": "world"})
