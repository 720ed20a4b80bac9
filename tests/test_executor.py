"""``ssp.pipeline.executor``: serial, process and Ray runs give the serial results, in input
order, and name the item that failed; the benchmarks and ``ssp run`` of many inputs through it.

One local Ray (2 CPUs) is started for the module; the executor uses it as it is.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ssp.cli import app
from ssp.config import SSPConfig
from ssp.errors import ArgumentError
from ssp.eval import tower
from ssp.eval.table1 import SequenceSpec, run_table1
from ssp.pipeline.executor import ItemError, ItemFailure, Parallel, map_items
from ssp.pipeline.summary import without_timings

SERIAL = Parallel()
PROCESSES = Parallel("processes", 2)
RAY = Parallel("ray", 2)


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def square_unless_three(item: int, shared: int) -> tuple[int, int]:
    """A work item: fails on 3; the result depends on the item and the shared value only."""
    if item == 3:
        raise ValueError("three is not allowed")
    return item, item * item + shared


@pytest.mark.parametrize("parallel", [SERIAL, PROCESSES], ids=["serial", "processes"])
def test_results_in_input_order_and_errors_named(parallel):
    items = [5, 0, 4, 1, 2]
    done = []
    out = map_items(
        square_unless_three,
        items,
        shared=10,
        parallel=parallel,
        names=[f"n{i}" for i in items],
        progress=lambda k, total, name: done.append((k, total, name)),
    )
    assert out == [(i, i * i + 10) for i in items]
    assert [d[0] for d in done] == [1, 2, 3, 4, 5] and {d[2] for d in done} == {
        f"n{i}" for i in items
    }
    with pytest.raises(ItemError, match="n3 failed: ValueError: three is not allowed"):
        map_items(square_unless_three, [1, 3, 2], shared=0, parallel=parallel,
                  names=["n1", "n3", "n2"])  # fmt: skip
    got = map_items(square_unless_three, [1, 3, 2], shared=0, parallel=parallel, on_error="collect")
    assert got[0] == (1, 1) and got[2] == (2, 4)
    assert isinstance(got[1], ItemFailure) and got[1].name == "item 1"
    assert got[1].error_type == "ValueError" and "three" in got[1].traceback


def test_bad_options_and_missing_ray(monkeypatch):
    with pytest.raises(ArgumentError, match="executor must be one of"):
        Parallel("threads")
    with pytest.raises(ArgumentError, match="workers"):
        Parallel("processes", 0)
    assert Parallel.from_options(None, 1) == SERIAL
    assert Parallel.from_options(None, 3).executor == "processes"
    assert Parallel.from_options(None, 1, "auto").executor == "ray"
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    with pytest.raises(ArgumentError, match=r"pip install 'sequential-scene-parsing\[ray\]'"):
        map_items(square_unless_three, [1], parallel=RAY)


# ------------------------------------------------------------------------------ benchmarks
def _table1_without_times(result: dict) -> dict:
    for m in result["methods"].values():
        m.pop("sec_per_frame")
    for rec in result["records"].values():
        rec["frames"].pop("sec")
    return result


def test_table1_is_the_serial_one_in_parallel(lib, ray_cluster):
    specs = [SequenceSpec("structure", s, stages=1, frames_per_stage=2, stride=4) for s in (3, 4)]
    kw = dict(methods=("ssp", "estimator"), vsd=False)
    ref = _table1_without_times(run_table1(specs, lib, SSPConfig(), **kw))
    assert ref["sequences"] == 2 and ref["seed"] == [3, 4]
    assert ref["records"]["ssp"]["frames"]["sequence"] == [0, 0, 1, 1]  # in input order
    for parallel in (PROCESSES, RAY):
        got = run_table1(specs, lib, SSPConfig(), parallel=parallel, **kw)
        assert _table1_without_times(got) == ref, parallel.executor
    bad = [*specs, SequenceSpec("towers", 9, stages=1, frames_per_stage=1, stride=4)]
    with pytest.raises(ItemError, match=r"sequence 3/3 \(seed 9, towers\) failed"):
        run_table1(bad, lib, SSPConfig(), parallel=RAY, **kw)


def test_tower_is_the_serial_one_in_parallel(lib, ray_cluster):
    kw = dict(methods=("estimator", "ssp"), frames_per_step=1, blocks=2, stride=4)

    def run(parallel):
        seen = []
        r = tower.run_tower(2, 5, lib, SSPConfig(), parallel=parallel,
                            on_trial=lambda m, t, tr: seen.append((m, t)), **kw)  # fmt: skip
        r.pop("wall_s")
        for m in r["methods"].values():
            m.pop("sec_per_frame")
        return r, sorted(seen)

    ref, seen = run(SERIAL)
    assert seen == [("estimator", 0), ("estimator", 1), ("ssp", 0), ("ssp", 1)]
    assert [row["trial"] for row in ref["trials_detail"]["ssp"]] == [0, 1]
    for parallel in (PROCESSES, RAY):
        assert run(parallel) == (ref, seen), parallel.executor


# ------------------------------------------------------------------------------ ssp run
def _strip(obj):
    return without_timings(obj, ("files",))


def _results(out: Path) -> dict:
    """Every file of a run folder, wall times (and the CSV's time column) left out."""
    files = {}
    for p in sorted(out.rglob("*")):
        if p.is_dir():
            continue
        key = str(p.relative_to(out))
        if p.suffix == ".csv":
            files[key] = [line.rsplit(",", 1)[0] for line in p.read_text().splitlines()]
        elif p.suffix == ".txt":  # TUM trajectories: no wall times
            files[key] = p.read_text()
        elif p.name == "state.json":  # its CSV size depends on the time column's digits
            files[key] = json.loads(p.read_text())["parser"]
        else:
            files[key] = _strip(json.loads(p.read_text()))
    return files


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> list[Path]:
    out = tmp_path_factory.mktemp("sim")
    r = CliRunner().invoke(
        app,
        ["simulate", "--out", str(out), "--sequences", "2", "--stages", "1",
         "--frames-per-stage", "1", "--stride", "4"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    return sorted((out / "structure" / "test").iterdir())


def test_run_many_inputs_in_parallel(scenes, tmp_path, ray_cluster):
    runner = CliRunner()
    single = tmp_path / "single"
    r = runner.invoke(app, ["run", str(scenes[1]), "--out", str(single)])
    assert r.exit_code == 0, r.output
    ref = None
    for name, opts in (("serial", []), ("processes", ["--workers", "2"]),
                       ("ray", ["--executor", "ray", "--workers", "2"]),
                       ("frame processes", ["--processes", "2"])):  # fmt: skip
        out = tmp_path / name
        r = runner.invoke(app, ["run", *map(str, scenes), "--out", str(out), *opts])
        assert r.exit_code == 0, r.output
        text = " ".join(r.output.split())  # rich wraps long lines at spaces
        at = [text.index(f"{s}: 1 of 1 frames done") for s in scenes]  # one line per input
        assert at == sorted(at)
        assert sorted(p.name for p in out.iterdir()) == [s.name for s in scenes]
        got = {s.name: _results(out / s.name) for s in scenes}
        ref = ref or got
        assert got == ref, name
    assert ref[scenes[1].name] == _results(single)  # the layout and files of a single run

    # one input that cannot be run is reported by name; the others go on
    missing = tmp_path / "nowhere"
    out = tmp_path / "partial"
    r = runner.invoke(app, ["run", str(missing), str(scenes[0]), "--out", str(out), "-j", "2"])
    assert r.exit_code == 1
    assert f"failed {missing}: InputError" in " ".join(r.output.split())
    assert _results(out / scenes[0].name) == ref[scenes[0].name]
