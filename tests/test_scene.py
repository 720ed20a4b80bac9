"""Frame validation (ssp.scene)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from ssp.errors import SSPError
from ssp.geometry import make_pose
from ssp.library.library import ObjectLibrary
from ssp.scene import Frame, FrameError, Hypothesis, TransitionMode


@pytest.fixture(scope="module")
def library(make_box) -> ObjectLibrary:
    return ObjectLibrary([make_box("cube"), make_box("block", (0.1, 0.05, 0.03))])


def _points(n: int = 50) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform(-0.3, 0.3, (n, 3))


def _frame(**kw) -> Frame:
    args = dict(
        stamp=0.0,
        points=_points(),
        hypotheses=[Hypothesis("cube", make_pose(t=[0.0, 0.0, 0.0254]), 0.9)],
    )
    args.update(kw)
    return Frame(**args)


def test_valid_frame_passes_and_is_cleaned(library):
    T = make_pose(t=[0.1, 0.0, 0.0254])
    T[:3, :3] += 1e-7  # slightly off orthonormal: accepted and repaired
    f = _frame(
        hypotheses=[Hypothesis("cube", T, 1)],
        labels=np.arange(50),
        segments={"cube_0": _points(5)},
        T_world_cam=make_pose(t=[0, 0, 1]),
    ).validate(library)
    R = f.hypotheses[0].T_world_obj[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12
    assert isinstance(f.hypotheses[0].score, float)
    assert f.labels.dtype == np.int64 and f.points.shape == (50, 3)


def test_frame_error_is_ssp_and_value_error():
    assert issubclass(FrameError, SSPError) and issubclass(FrameError, ValueError)


def test_nan_points_dropped_with_labels_and_logged(library, caplog):
    pts = _points(10)
    pts[3, 1] = np.nan
    pts[7, 2] = np.inf
    labels = np.arange(10)
    with caplog.at_level(logging.INFO, logger="ssp.scene"):
        f = _frame(points=pts, labels=labels).validate(library)
    assert f.points.shape == (8, 3)
    assert list(f.labels) == [0, 1, 2, 4, 5, 6, 8, 9]
    assert "dropped 2 of 10" in caplog.text


@pytest.mark.parametrize("pts", [np.full((4, 3), np.nan), np.zeros((0, 3)), []])
def test_empty_cloud(library, pts):
    with pytest.raises(FrameError, match="empty cloud"):
        _frame(points=pts).validate(library)


@pytest.mark.parametrize("pts", [np.zeros((5, 2)), np.zeros(6), np.zeros((2, 3, 3))])
def test_wrong_point_shape(library, pts):
    with pytest.raises(FrameError, match=r"expected shape \(N, 3\)"):
        _frame(points=pts).validate(library)


def test_wrong_label_length(library):
    with pytest.raises(FrameError, match=r"labels must have shape \(50,\)"):
        _frame(labels=np.zeros(49, dtype=int)).validate(library)


def test_non_integer_labels(library):
    with pytest.raises(FrameError, match="labels must be integers"):
        _frame(labels=np.full(50, 0.5)).validate(library)


def test_bad_pose_names_index_and_class(library):
    bad = make_pose(t=[0, 0, 0])
    bad[0, 0] = 2.0
    hyps = [Hypothesis("cube", make_pose()), Hypothesis("block", bad)]
    with pytest.raises(FrameError, match=r"hypothesis 1 \('block'\).*orthonormal"):
        _frame(hypotheses=hyps).validate(library)


def test_pose_wrong_shape_and_nan(library):
    with pytest.raises(FrameError, match=r"hypothesis 0 \('cube'\).*shape"):
        _frame(hypotheses=[Hypothesis("cube", np.eye(3))]).validate(library)
    T = make_pose()
    T[0, 3] = np.nan
    with pytest.raises(FrameError, match="NaN"):
        _frame(hypotheses=[Hypothesis("cube", T)]).validate(library)


def test_bad_camera_pose(library):
    with pytest.raises(FrameError, match="camera pose"):
        _frame(T_world_cam=np.zeros((4, 4))).validate(library)


def test_unknown_class_lists_known(library):
    with pytest.raises(
        FrameError, match=r"'mug'.*unknown object class; known classes: cube, block"
    ):
        _frame(hypotheses=[Hypothesis("mug", make_pose())]).validate(library)


def test_nonfinite_score(library):
    with pytest.raises(FrameError, match="score must be finite"):
        _frame(hypotheses=[Hypothesis("cube", make_pose(), float("nan"))]).validate(library)


def test_nonfinite_stamp(library):
    with pytest.raises(FrameError, match="stamp must be finite"):
        _frame(stamp=float("inf")).validate(library)


def test_millimetre_cloud(library):
    with pytest.raises(FrameError, match="millimetres"):
        _frame(points=_points() * 1000 + 500).validate(library)


def test_millimetre_hypothesis(library):
    with pytest.raises(FrameError, match=r"hypothesis 0.*millimetres"):
        _frame(hypotheses=[Hypothesis("cube", make_pose(t=[300, 0, 25]))]).validate(library)


def test_segments_cleaned(library):
    seg = _points(4)
    seg[0] = np.nan
    f = _frame(segments={"a": seg, "b": []}).validate(library)
    assert f.segments["a"].shape == (3, 3) and f.segments["b"].shape == (0, 3)
    with pytest.raises(FrameError, match="segment 'c'"):
        _frame(segments={"c": np.zeros((3, 4))}).validate(library)


def test_transition_mode_values():
    assert {m.value for m in TransitionMode} == {
        "added",
        "removed",
        "perturbed",
        "static",
        "support_retained",
    }
    assert (
        TransitionMode("static") is TransitionMode.STATIC and str(TransitionMode.ADDED) == "added"
    )
