"""The layered search (ssp.search, Alg. 3): the objects a test leaves out, the windows, the
order of the tests, the choices."""

from __future__ import annotations

import numpy as np

from ssp.config import SSPConfig
from ssp.forces import SegmentField
from ssp.geometry import make_pose, transform_points
from ssp.library import ObjectInstance
from ssp.physics import World
from ssp.scoring import SceneScorer
from ssp.search import Candidate, Simulator, _out_of_reach, layered_search
from ssp.timing import StageTimer


def test_objects_out_of_reach_are_left_out_unless_they_hold_up_the_others(lib):
    """Testing the top of a three-cube tower: the bottom cube is far from it but carries the
    middle one, so it stays; a cube farther along the table carries nothing and is left out."""
    cube = lib["cube"]
    e = float(cube.extents[2])
    poses = {f"t{k}": make_pose(t=[0.0, 0.0, e / 2 + k * e]) for k in range(3)}
    poses["far"] = make_pose(t=[0.3, 0.0, e / 2])
    world = World([ObjectInstance(oid, cube) for oid in poses])
    world.set_poses(poses)
    i = world.ids.index("t2")
    parents = {world.ids.index("t1"): [world.ids.index("t0")], i: [world.ids.index("t1")]}
    far = _out_of_reach(world, i, [poses["t2"]], [], 0.02, parents)
    assert [world.ids[k] for k in far] == ["far"]
    far = _out_of_reach(world, i, [poses["t2"]], [], 0.02, {})
    assert sorted(world.ids[k] for k in far) == ["far", "t0"]


def test_a_window_without_forces_ends_early_only_when_the_scene_is_at_rest(lib):
    """search.rest_check_every: a cube resting on the table stops after one chunk of steps;
    one in mid-air falls for the whole window; 0 (the default) always steps the window."""
    from ssp.config import SSPConfig
    from ssp.forces import SegmentField
    from ssp.search import Simulator
    from ssp.timing import StageTimer

    cube = lib["cube"]
    e = float(cube.extents[2])
    cfg = SSPConfig()
    cfg.search.rest_check_every = 4
    for z, steps in ((e / 2, 4), (e / 2 + 0.01, 20)):
        world = World([ObjectInstance("c", cube)])
        world.set_pose("c", make_pose(t=[0.0, 0.0, z]))
        world.step(40)  # settle the contacts of the resting cube
        sim = Simulator.for_world(world, [SegmentField(cube.surface_points)], cfg, StageTimer())
        if z > e / 2:
            world.set_pose("c", make_pose(t=[0.0, 0.0, z]))
        sim.settle(0.1, with_forces=False)
        assert sim.steps == steps
    cfg.search.rest_check_every = 0
    sim = Simulator.for_world(world, [None], cfg, StageTimer())
    sim.settle(0.1, with_forces=False)
    assert sim.steps == 20


# ------------------------------------------------------------------------ layered_search


def _cube_scene(lib, current: dict, data: dict):
    """Cubes at their ``current`` poses (id -> pose) whose data (segments) are their surfaces
    at the ``data`` poses: the world, its simulator and scorer (as the parser builds them, no
    camera, every object new), and a log of the candidate tests: ``(tested id, its pose at the
    start of the window, ids enabled then)``."""
    cfg = SSPConfig()
    cube = lib["cube"]
    world = World([ObjectInstance(oid, cube) for oid in current])
    world.set_poses(current)
    segments = {oid: transform_points(T, cube.surface_points) for oid, T in data.items()}
    fields = [SegmentField(segments[oid], cfg.forces.max_distance) for oid in world.ids]
    timer = StageTimer()
    sim = Simulator.for_world(world, fields, cfg, timer)
    scorer = SceneScorer(world, cfg, segments, dict.fromkeys(world.ids))
    log: list[tuple[str, np.ndarray, set[str]]] = []
    last: list = [None]
    set_pose, window = world.set_pose, sim.window

    def recording_set_pose(oid, T):
        last[0] = (oid, np.array(T, dtype=float))
        set_pose(oid, T)

    def recording_window():  # a test sets its object's pose last, then runs the window
        oid, T = last[0]
        log.append((oid, T, {o for o in world.ids if world.is_enabled(o)}))
        window()

    world.set_pose = recording_set_pose
    sim.window = recording_window
    return world, sim, scorer, timer, log


def _at(lib, x=0.0, y=0.0, level=0):
    e = float(lib["cube"].extents[2])
    return make_pose(t=[x, y, e / 2 + level * e])


def _tower_and_a_cube(lib):
    """``a`` on the table, ``b`` on it, ``c`` beside them: at their true poses, each with one
    candidate 3 mm off; layers [a, c], [b] (b is a's child)."""
    truth = {"a": _at(lib), "b": _at(lib, level=1), "c": _at(lib, x=0.07)}
    world, sim, scorer, timer, log = _cube_scene(lib, truth, truth)
    off = make_pose(t=[0.003, 0.0, 0.0])
    candidates = {oid: [Candidate(off @ T, "hypothesis", 0.9)] for oid, T in truth.items()}
    i = {oid: world.index(oid) for oid in truth}
    layers = [[i["c"], i["a"]], [i["b"]]]
    children = {i["a"]: [i["b"]]}
    return world, sim, scorer, timer, log, candidates, layers, children, i, truth


def test_layered_search_goes_layer_by_layer_with_the_children_of_the_tested_object(lib):
    world, sim, scorer, timer, log, cands, layers, children, i, truth = _tower_and_a_cube(lib)
    result = layered_search(world, sim, scorer, cands, layers, children, timer)
    # layer 0 (its objects by id), then layer 1; per object its current pose, then candidates
    assert [oid for oid, _, _ in log] == ["a", "a", "c", "c", "b", "b"]
    assert result.tested == 6 and result.failed == []
    for oid, T, _ in log[1::2]:
        np.testing.assert_array_equal(T, cands[oid][0].T_world_obj)
    # a is tested with b on it (AddChildOf); c, of the same layer, without b (not its child)
    assert all("b" in on for oid, _, on in log if oid == "a")
    assert all("b" not in on and {"a", "c"} <= on for oid, _, on in log if oid == "c")
    assert all(on == {"a", "b", "c"} for oid, _, on in log if oid == "b")
    # b's own tests start from its first-guess pose, whatever a's tests did to it
    np.testing.assert_allclose(log[4][1], truth["b"], atol=1e-12)
    assert set(result.chosen) == {"a", "b", "c"}
    assert all(world.is_enabled(o) for o in world.ids)
    assert result.score.ids == world.ids


def test_layered_search_keeps_the_candidate_the_data_supports(lib):
    """``a``'s first guess is 5 cm from its data; of its two other candidates the one on the
    data wins, whichever source it has and wherever it is in the list; a worse one never."""
    truth = _at(lib)
    good = make_pose(t=[0.002, -0.001, 0.0]) @ truth  # within the data forces' reach
    bad = _at(lib, y=-0.05)  # 5 cm off: no data pulls it
    for sources in (("hypothesis", "previous"), ("previous", "hypothesis")):
        world, sim, scorer, timer, log = _cube_scene(lib, {"a": _at(lib, y=0.05)}, {"a": truth})
        cands = {"a": [Candidate(bad, sources[0], 0.9), Candidate(good, sources[1], 0.5)]}
        result = layered_search(world, sim, scorer, cands, [[0]], {}, timer)
        assert result.chosen == {"a": sources[1]} and result.tested == 3
        np.testing.assert_allclose(world.get_pose("a")[:3, 3], truth[:3, 3], atol=0.002)
    # the first guess on the data keeps its place against both
    world, sim, scorer, timer, log = _cube_scene(lib, {"a": truth}, {"a": truth})
    cands = {"a": [Candidate(bad, "hypothesis", 0.9), Candidate(_at(lib, y=0.05), "previous")]}
    assert layered_search(world, sim, scorer, cands, [[0]], {}, timer).chosen == {"a": "current"}


def test_settled_objects_keep_their_pose_untested(lib):
    world, sim, scorer, timer, log, cands, layers, children, i, truth = _tower_and_a_cube(lib)
    result = layered_search(world, sim, scorer, cands, layers, children, timer, settled={i["c"]})
    assert [oid for oid, _, _ in log] == ["a", "a", "b", "b"]
    assert result.tested == 4
    assert result.chosen["c"] == "previous (settled)"
    assert {result.chosen["a"], result.chosen["b"]} <= {"current", "hypothesis"}


def test_layered_search_is_deterministic(lib):
    runs = []
    for _ in range(2):
        world, sim, scorer, timer, log, cands, layers, children, i, _t = _tower_and_a_cube(lib)
        result = layered_search(world, sim, scorer, cands, layers, children, timer)
        runs.append((result, world.pose_array(), log))
    (r1, p1, log1), (r2, p2, log2) = runs
    assert r1.chosen == r2.chosen and r1.tested == r2.tested
    assert r1.score.total == r2.score.total
    np.testing.assert_array_equal(p1, p2)
    assert [(o, on) for o, _, on in log1] == [(o, on) for o, _, on in log2]


def test_a_candidate_starting_where_an_earlier_one_did_is_not_tested_again(lib):
    """search.same_start_translation / same_start_rotation: of ``a``'s candidates, one 0.5 mm
    and 0.5 deg from its first guess and one 0.5 mm from the 3 mm candidate start the same
    windows and are merged (counted, the earlier kept); one 3 mm off is tested; 0 tests all."""
    from ssp.geometry import yaw_pose
    from ssp.search import distinct_starts

    world, sim, scorer, timer, log, cands, layers, children, i, truth = _tower_and_a_cube(lib)
    off = cands["a"][0].T_world_obj
    near_first = make_pose(t=[0.0005, 0.0, 0.0]) @ truth["a"] @ yaw_pose(np.radians(0.5))
    near_off = make_pose(t=[0.0, 0.0005, 0.0]) @ off
    cands["a"] = [Candidate(near_first, "hypothesis", 0.8), *cands["a"],
                  Candidate(near_off, "previous")]  # fmt: skip
    result = layered_search(world, sim, scorer, cands, layers, children, timer)
    tested_a = [T for oid, T, _ in log if oid == "a"]
    assert len(tested_a) == 2 and result.tested == 6 and result.merged == 2
    np.testing.assert_array_equal(tested_a[1], off)
    assert result.chosen["a"] in {"current", "hypothesis"}

    # the rule itself: the earlier of two close starts is kept, in order; 0 keeps every one
    tests = [Candidate(truth["a"], "current"), Candidate(near_first, "hypothesis"),
             Candidate(off, "hypothesis"), Candidate(near_off, "previous")]  # fmt: skip
    kept = distinct_starts(tests, 1e-3, np.radians(1.0))
    assert [c.source for c in kept] == ["current", "hypothesis"]
    assert kept[1] is tests[2]
    turned = Candidate(truth["a"] @ yaw_pose(np.radians(2.0)), "hypothesis")
    assert len(distinct_starts([tests[0], turned], 1e-3, np.radians(1.0))) == 2
    assert distinct_starts(tests, 0.0, np.radians(1.0)) == tests
