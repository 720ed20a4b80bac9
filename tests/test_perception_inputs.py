"""The public entry points of the perception front end (:class:`ssp.perception.Perception`)
refuse arguments they cannot use with an :class:`InputError` that says what is wrong, never a
raw IndexError or AttributeError from deep inside."""

from __future__ import annotations

import numpy as np
import pytest

from ssp.errors import InputError, PerceptionError
from ssp.perception.pipeline import Perception, check_camera_axes
from ssp.perception.segmentation import segment_cloud


@pytest.fixture(scope="module")
def perception(lib):
    return Perception(lib, classes=["cube"])


@pytest.fixture(scope="module")
def cloud():
    """Points 0.5 m in front of the camera (OpenCV axes): (100, 3)."""
    return np.random.default_rng(0).random((100, 3)) * 0.05 + [0.0, 0.0, 0.5]


@pytest.mark.parametrize(
    ("kwargs", "needles"),
    [
        ({"labels": np.zeros(99, dtype=int)}, ["labels must have shape (100,)", "(99,)"]),
        ({"labels": np.zeros((100, 2), dtype=int)}, ["labels must have shape", "(100, 2)"]),
        ({"labels": np.full(100, 0.5)}, ["labels must be integers", "label 0 is 0.5"]),
        ({"labels": np.full(100, np.nan)}, ["labels must be integers", "100 of 100"]),
        ({"labels": np.array(["a"] * 100)}, ["labels must be integers", "dtype <U1"]),
        ({"labels": np.ones(100, dtype=bool)}, ["labels must be integers", "bool"]),
        ({"label_kind": "classes"}, ["label_kind must be one of", "'classes'"]),
        ({"hypotheses_frame": "cam"}, ["hypotheses_frame must be one of", "'cam'"]),
        ({"frame": "map"}, ["frame must be one of", "'map'"]),
        ({"T_world_cam": np.diag([2.0, 1.0, 1.0, 1.0])}, ["T_world_cam"]),
        ({"T_world_cam": np.eye(3)}, ["T_world_cam"]),
    ],
    ids=lambda v: next(iter(v)) if isinstance(v, dict) else None,
)
def test_from_points_names_the_bad_argument(perception, cloud, kwargs, needles):
    with pytest.raises(InputError) as info:
        perception.from_points(cloud, **kwargs)
    for needle in needles:
        assert needle in str(info.value), (needle, str(info.value))


@pytest.mark.parametrize(
    ("points", "needle"),
    [
        (np.zeros((100, 2)), "points must have shape (N, 3)"),
        (np.zeros(300), "points must have shape (N, 3)"),
        ([["a", "b", "c"]], "points must be an (N, 3) array of numbers"),
        (np.full((10, 3), np.nan), "no finite points (of 10)"),
    ],
    ids=["n-by-2", "flat", "text", "all-nan"],
)
def test_from_points_refuses_bad_points(perception, points, needle):
    with pytest.raises(InputError) as info:
        perception.from_points(points)
    assert needle in str(info.value)


def test_non_finite_rows_are_dropped_with_their_labels(perception, cloud):
    """An organised cloud's rows without a return (NaN) go, and the labels stay aligned."""
    pts = cloud.copy()
    pts[:10] = np.nan
    labels = np.full(100, -1)
    labels[:10] = 5  # only on the dropped rows: no segment is left
    res = perception.from_points(pts, frame="world", labels=labels, hypotheses=[])
    assert len(res.frame.points) == 90 and set(res.frame.labels.tolist()) == {-1}
    # an (N, 1) label column is one label per point too
    res = perception.from_points(cloud, frame="world", labels=labels[:, None], hypotheses=[])
    assert len(res.frame.labels) == 100


def test_the_other_entry_points(perception, cloud):
    with pytest.raises(InputError, match="camera must be an ssp.camera.Camera"):
        perception.from_depth(np.ones((4, 4)), None)
    with pytest.raises(InputError, match=r"points must have shape \(N, 3\)"):
        check_camera_axes(np.zeros(5))
    seg = segment_cloud(cloud, np.zeros(100, dtype=int), min_points=5)
    with pytest.raises(InputError, match=r"shape \(100, 3\).*\(50, 3\)"):
        perception.segment_request(cloud[:50], seg, 0, None, True)
    with pytest.raises(InputError, match=r"label 7 is not a segment .*\(0\)"):
        perception.segment_request(cloud, seg, 7, None, True)
    request = perception.segment_request(cloud, seg, 0, None, True)
    assert request.points.shape == (100, 3) and request.classes == ("cube",)
    # what the front end cannot do stays a PerceptionError
    with pytest.raises(PerceptionError, match="camera pose"):
        perception.from_points(cloud, frame="world", hypotheses=[], hypotheses_frame="camera")
