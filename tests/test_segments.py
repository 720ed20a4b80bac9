"""Each object's segment (ssp.segments.object_segments)."""

from __future__ import annotations

import logging

import numpy as np

from ssp.cells import PointCells
from ssp.geometry import make_pose, transform_points
from ssp.scene import Frame
from ssp.segments import _label_votes, _labels_present, explained_fraction, object_segments


def _two_cubes(lib):
    """A cube on the table (label 0, only its top face seen) and one on it (label 1, whole)."""
    cube = lib["cube"]
    h = float(cube.extents[2])
    T_low = make_pose(t=[0.0, 0.0, h / 2])
    T_high = make_pose(t=[0.0, 0.0, 1.5 * h])
    s = np.asarray(cube.surface_points, dtype=float)
    top = s[s[:, 2] > h / 2 - 1e-6]
    low = transform_points(T_low, top[: len(top) // 2])  # half its top face: mostly hidden
    high = transform_points(T_high, s)
    points = np.concatenate([low, high])
    labels = np.concatenate([np.zeros(len(low), int), np.ones(len(high), int)])
    return cube, T_low, T_high, Frame(0.0, points, labels=labels), len(low)


def test_label_of_the_hypotheses_segment_beats_the_vote(lib):
    """A guess reaching into the object on top votes for its label; the label the object's
    hypotheses were estimated from gives the object its own points."""
    cube, _, T_high, frame, n_low = _two_cubes(lib)
    objects = {"low": (cube, [T_high])}  # a wrong guess: where the top cube is
    seg, owner = object_segments(frame, objects, radius=0.01)
    assert owner == {"low": 1}
    seg, owner = object_segments(frame, objects, radius=0.01, labels={"low": 0})
    assert owner == {"low": 0} and len(seg["low"]) == n_low


def test_label_missing_from_the_cloud_falls_back_to_the_vote(lib, caplog):
    cube, T_low, _, frame, _ = _two_cubes(lib)
    objects = {"low": (cube, [T_low])}
    with caplog.at_level(logging.WARNING, logger="ssp.segments"):
        seg, owner = object_segments(frame, objects, radius=0.01, labels={"low": 7})
    voted, voted_owner = object_segments(frame, objects, radius=0.01)
    assert owner == voted_owner and np.array_equal(seg["low"], voted["low"])
    assert "not in the cloud" in caplog.text


def test_given_segments_come_first_and_crops_without_labels(lib):
    cube, T_low, T_high, frame, _ = _two_cubes(lib)
    own = np.zeros((5, 3)) + T_low[:3, 3]
    given = Frame(0.0, frame.points, labels=frame.labels, segments={"low": own})
    seg, owner = object_segments(given, {"low": (cube, [T_low])}, radius=0.01, labels={"low": 1})
    assert owner == {} and np.array_equal(seg["low"], own)
    bare = Frame(0.0, frame.points)
    seg, owner = object_segments(bare, {"high": (cube, [T_high])}, radius=0.01)
    assert owner == {} and len(seg["high"]) > 0  # a crop: near the pose, above the table
    assert np.all(seg["high"][:, 2] >= 0.002)


def test_explained_fraction_counts_the_points_on_the_models_surface(lib):
    cube, T_low, _, frame, n_low = _two_cubes(lib)
    low = frame.points[frame.labels == 0]
    assert explained_fraction(low, cube, T_low, 0.004) == 1.0
    beside = make_pose(t=T_low[:3, 3] + [float(cube.extents[0]) + 0.01, 0.0, 0.0])
    assert explained_fraction(low, cube, beside, 0.004) == 0.0
    half = make_pose(t=T_low[:3, 3] + [float(cube.extents[0]) / 2, 0.0, 0.0])
    assert 0.2 < explained_fraction(low, cube, half, 0.004) < 0.8
    assert explained_fraction(np.zeros((0, 3)), cube, T_low, 0.004) == 0.0


def test_one_object_per_instance_label_a_hidden_object_keeps_its_own_points(lib):
    """The mostly hidden lower cube touches more of the upper cube's points than of its own:
    known, it takes its own label, the upper cube the other one, never both the same segment;
    new, it takes the label it covers most (it must earn its place with its data)."""
    cube, T_low, T_high, frame, n_low = _two_cubes(lib)
    votes = _label_votes(frame, PointCells(frame.points, 0.01), cube, T_low, 0.01)
    assert votes[1] > votes[0]  # alone, the lower cube's vote went to the upper cube's label
    objects = {"low": (cube, [T_low]), "high": (cube, [T_high])}
    seg, owner = object_segments(frame, objects, radius=0.01, known={"low", "high"})
    assert owner == {"low": 0, "high": 1}
    assert len(seg["low"]) == n_low and len(seg["high"]) == len(frame.points) - n_low
    seg, owner = object_segments(frame, objects, radius=0.01, known={"high"})
    assert owner == {"low": 1, "high": 1}


def test_an_object_touching_only_taken_labels_gets_no_segment(lib, caplog):
    cube, T_low, T_high, frame, n_low = _two_cubes(lib)
    hidden = Frame(0.0, frame.points[n_low:], labels=frame.labels[n_low:])  # low unseen
    objects = {"low": (cube, [T_low]), "high": (cube, [T_high])}
    with caplog.at_level(logging.INFO, logger="ssp.segments"):
        seg, owner = object_segments(hidden, objects, radius=0.01, known={"low", "high"})
    assert owner == {"high": 1} and len(seg["low"]) == 0
    assert "low: the labels it touches are other objects' segments" in caplog.text
    # a label known to be an object's (its hypotheses' segment, maybe a false object's) does
    # not take a voter's data away
    seg, owner = object_segments(
        hidden, objects, radius=0.01, labels={"low": 1}, known={"low", "high"}
    )
    assert owner == {"low": 1, "high": 1} and len(seg["high"]) == len(seg["low"]) > 0


def test_cluster_labels_are_shared(lib):
    """A cluster label may hold several objects: both take their points from a crop."""
    cube, T_low, T_high, frame, _ = _two_cubes(lib)
    clusters = Frame(
        0.0, frame.points, labels=np.zeros(len(frame.points), int), label_kind="cluster"
    )
    members: dict[str, int] = {}
    objects = {"low": (cube, [T_low]), "high": (cube, [T_high])}
    seg, owner = object_segments(clusters, objects, radius=0.01, members=members)
    assert owner == {} and members == {"low": 0, "high": 0}
    assert len(seg["low"]) > 0 and len(seg["high"]) > 0


def test_a_voter_far_from_every_point_votes_for_nothing(lib):
    """A guess nowhere near the cloud (a false hypothesis across the room): no point within
    its reach, no vote, an empty crop, and the other voter's votes as without it."""
    cube, T_low, T_high, frame, _ = _two_cubes(lib)
    far = make_pose(t=[2.0, 2.0, 0.5])
    seg, owner = object_segments(frame, {"far": (cube, [far])}, radius=0.01)
    assert owner == {} and len(seg["far"]) == 0
    both, owner_both = object_segments(
        frame, {"far": (cube, [far]), "high": (cube, [T_high])}, radius=0.01
    )
    alone, owner_alone = object_segments(frame, {"high": (cube, [T_high])}, radius=0.01)
    assert owner_both == owner_alone and np.array_equal(both["high"], alone["high"])


def test_the_surface_queries_find_what_the_models_own_tree_finds():
    # explained_fraction, surface_residual and the shared volumes query a sample grid of the
    # surface samples (ssp.segments.surface_grid, kept per process: it does not pickle); it
    # must give the model's cKDTree's samples and distances, or their results would change
    # with it; at the frame's radii and beyond the first grid's reach (a grid of its own)
    from ssp.library import ObjectLibrary
    from ssp.segments import _near_surface

    rng = np.random.default_rng(0)
    library = ObjectLibrary.builtin()
    for model in (library[name] for name in library.names):
        T = make_pose(t=[0.1, -0.2, 0.05])
        pts = transform_points(T, model.surface_points) + rng.normal(
            0, 0.003, (len(model.surface_points), 3)
        )
        for radius in (0.0074, 0.00675, 0.002, 0.012):
            local, dist, idx = _near_surface(pts, model, T, radius)
            d_ref, i_ref = model.surface_tree.query(local, k=1, distance_upper_bound=radius)
            hit = np.isfinite(d_ref)
            assert hit.any() and (radius > 0.0074 or not hit.all()), model.name
            np.testing.assert_array_equal(np.isfinite(dist), hit)
            np.testing.assert_array_equal(dist[hit], d_ref[hit])
            np.testing.assert_array_equal(idx[hit], i_ref[hit])


def test_the_labels_present_are_np_uniques_nonnegative_ones():
    rng = np.random.default_rng(4)
    cases = [
        rng.integers(-1, 12, 5000),
        rng.integers(-5, 3, 40),
        np.array([-1, -1]),
        np.zeros(0, dtype=np.int64),
        np.array([5, 10**12, 5, -3]),  # sparse: not counted into a 10**12-long array
    ]
    for labels in cases:
        want = np.unique(labels)
        assert _labels_present(labels).tolist() == want[want >= 0].tolist()
