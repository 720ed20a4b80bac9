"""Map a function over independent work items: in this process, in worker processes, or on Ray.

:func:`map_items` runs ``fn(item, shared)`` for every item and returns the results **in the
order of the items**, whatever the executor and whatever order the items finish in. The
results equal the serial run's when ``fn`` is a pure function of its arguments: each item
carries everything it depends on (its seed included); nothing is shared between items but the
read-only ``shared`` value.

Executors (:class:`Parallel`):

* ``serial``: one item after another in this process (no pickling).
* ``processes``: a :class:`concurrent.futures.ProcessPoolExecutor` of ``workers`` processes
  started with ``spawn``. Each worker is single-threaded (``OMP_NUM_THREADS=1`` and the like,
  :data:`SINGLE_THREAD_ENV`, set before anything heavy is imported) and gets ``shared`` once,
  through its initialiser; ``fn`` and the items must be picklable.
* ``ray``: Ray tasks of one CPU each. With ``ray_address`` None a local Ray is started with
  ``num_cpus=workers``; with an address (``auto``, ``ray://host:10001``, ...) the existing
  cluster is joined. ``shared`` is put in the object store once (``ray.put``). A Ray already
  initialised in this process is used as it is and left running; one started here is shut
  down at the end. Ray is an optional dependency (``pip install
  'sequential-scene-parsing[ray]'``).

Progress: ``progress(done, total, name)`` (and ``on_result(index, result)``) is called in
this process each time an item finishes. Errors: with ``on_error="raise"`` (benchmarks) the
first failing item stops the map (the items not started are cancelled) with
:class:`ItemError`, which names the item; with ``on_error="collect"`` a failed item's result
is an :class:`ItemFailure` and the others go on.
Log levels of this process (the root logger and those of ``ssp.*``) are set in the workers too.
"""

from __future__ import annotations

import logging
import os
import pickle
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ssp.errors import ArgumentError, SSPError

__all__ = [
    "EXECUTORS",
    "ItemError",
    "ItemFailure",
    "Parallel",
    "SINGLE_THREAD_ENV",
    "done_messages",
    "map_items",
]

log = logging.getLogger(__name__)

EXECUTORS = ("serial", "processes", "ray")
RAY_INSTALL = "pip install 'sequential-scene-parsing[ray]'"

#: Environment of the worker processes (and Ray workers): one thread each for the numerical
#: libraries, so ``workers`` workers use ``workers`` cores.
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


@dataclass(frozen=True)
class Parallel:
    """How :func:`map_items` runs: ``executor`` (one of :data:`EXECUTORS`), ``workers``
    (processes, or the CPUs of a local Ray), ``ray_address`` (None: a local Ray)."""

    executor: str = "serial"
    workers: int = 1
    ray_address: str | None = None

    def __post_init__(self) -> None:
        if self.executor not in EXECUTORS:
            raise ArgumentError(
                f"executor must be one of {', '.join(EXECUTORS)}, got {self.executor!r}"
            )
        if int(self.workers) < 1:
            raise ArgumentError(f"workers must be >= 1, got {self.workers}")
        if self.ray_address is not None and self.executor != "ray":
            raise ArgumentError("a Ray address needs the ray executor")

    @classmethod
    def from_options(
        cls, executor: str | None = None, workers: int = 1, ray_address: str | None = None
    ) -> Parallel:
        """The command-line choice: no executor named means ``serial`` for one worker,
        ``ray`` with an address, else ``processes``."""
        if executor is None:
            executor = "ray" if ray_address else "serial" if workers == 1 else "processes"
        return cls(executor, int(workers), ray_address)

    @property
    def serial(self) -> bool:
        return self.executor == "serial"


@dataclass(frozen=True)
class ItemFailure:
    """A failed item (``on_error="collect"``): its name, the exception's type name, message,
    traceback text, and whether it was one of ssp's typed errors (:class:`SSPError`: bad
    input) rather than a bug."""

    name: str
    error_type: str
    error: str
    traceback: str = ""
    expected: bool = False

    def __str__(self) -> str:
        return f"{self.name}: {self.error_type}: {self.error}"


class ItemError(SSPError):
    """A work item of :func:`map_items` failed; ``failure`` says which and why."""

    def __init__(self, failure: ItemFailure) -> None:
        super().__init__(f"{failure.name} failed: {failure.error_type}: {failure.error}")
        self.failure = failure


# ------------------------------------------------------------------------------ worker side
_WORKER: dict[str, Any] = {}


def _configure_worker(env: dict[str, str], levels: dict[str, int], fmt: str | None) -> None:
    """Single-threaded numerics and this process's log levels, in a worker (idempotent)."""
    os.environ.update(env)
    if _WORKER.get("configured"):
        return
    logging.basicConfig(level=levels.get("", logging.WARNING), format=fmt or logging.BASIC_FORMAT)
    for name, level in levels.items():
        logging.getLogger(name or None).setLevel(level)
    _WORKER["configured"] = True


def _init_process(env: dict[str, str], levels: dict[str, int], fmt, shared: bytes) -> None:
    """Process-pool initialiser: environment first, then the shared value (unpickling it
    imports numpy and the like)."""
    _configure_worker(env, levels, fmt)
    _WORKER["shared"] = pickle.loads(shared)


def _call(fn: Callable, item: Any, shared: Any) -> tuple[bool, Any]:
    """``(True, fn(item, shared))`` or ``(False, (type name, message, traceback, expected))``."""
    try:
        return True, fn(item, shared)
    except Exception as exc:
        return False, _describe(exc)


def _describe(exc: BaseException) -> tuple[str, str, str, bool]:
    tb = "".join(traceback.format_exception(exc))
    return type(exc).__name__, str(exc), tb, isinstance(exc, SSPError)


def _process_task(fn: Callable, item: Any) -> tuple[bool, Any]:
    return _call(fn, item, _WORKER.get("shared"))


def _ray_task(fn, item, shared, env, levels, fmt) -> tuple[bool, Any]:
    _configure_worker(env, levels, fmt)
    return _call(fn, item, shared)


def _log_levels() -> tuple[dict[str, int], str | None]:
    """This process's root level and the explicit levels of the ``ssp`` loggers, and the
    root handler's format."""
    root = logging.getLogger()
    levels = {"": root.level}
    for name, obj in logging.Logger.manager.loggerDict.items():
        if (name == "ssp" or name.startswith("ssp.")) and isinstance(obj, logging.Logger):
            if obj.level != logging.NOTSET:
                levels[name] = obj.level
    fmt = None
    if root.handlers and root.handlers[0].formatter is not None:
        fmt = root.handlers[0].formatter._fmt
    return levels, fmt


# ------------------------------------------------------------------------------ main side
def done_messages(
    progress: Callable[[str], None] | None, parallel: Parallel
) -> Callable[[int, int, str], None] | None:
    """A :func:`map_items` ``progress`` that tells a benchmark's message ``progress`` which
    item finished (``"<name> done (k/n)"``), when the items run in parallel (serially, the
    items report their own steps); None when there is nothing to tell."""
    if progress is None or parallel.serial:
        return None
    return lambda k, total, name: progress(f"{name} done ({k}/{total})")


def map_items(
    fn: Callable[[Any, Any], Any],
    items: Sequence[Any],
    *,
    shared: Any = None,
    parallel: Parallel | None = None,
    names: Sequence[str] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    on_result: Callable[[int, Any], None] | None = None,
    on_error: str = "raise",
) -> list:
    """``[fn(item, shared) for item in items]``, run by ``parallel`` (module docstring).

    Args:
        fn: a module-level function (or a :func:`functools.partial` of one) for the
            ``processes`` and ``ray`` executors; it must not depend on state outside its
            arguments.
        items: the work items (picklable unless serial).
        shared: one read-only value every call gets (e.g. the model library); sent to each
            worker once.
        parallel: the executor (default serial).
        names: one name per item for progress and errors (default ``item <i>``).
        progress: ``progress(done, total, name)`` after each item, in this process.
        on_result: ``on_result(index, result)`` after each item, in this process, in the
            order the items finish (serial: item order).
        on_error: ``"raise"``: :class:`ItemError` for the first failed item; ``"collect"``:
            an :class:`ItemFailure` in its place.

    Raises:
        ItemError: an item failed (``on_error="raise"``).
        ArgumentError: bad options, or the ray executor without Ray installed.
    """
    parallel = parallel if parallel is not None else Parallel()
    if on_error not in ("raise", "collect"):
        raise ArgumentError(f"on_error must be 'raise' or 'collect', got {on_error!r}")
    items = list(items)
    names = [f"item {i}" for i in range(len(items))] if names is None else list(names)
    if len(names) != len(items):
        raise ArgumentError(f"{len(names)} names for {len(items)} items")
    if not items:
        return []
    run = {"serial": _map_serial, "processes": _map_processes, "ray": _map_ray}
    results = _Results(names, progress, on_result, on_error)
    return run[parallel.executor](fn, items, shared, parallel, results)


class _Results:
    """Results by item index, progress and the error policy."""

    def __init__(self, names, progress, on_result, on_error) -> None:
        self.names = names
        self.progress = progress
        self.on_result = on_result
        self.on_error = on_error
        self.values: list[Any] = [None] * len(names)
        self.done = 0

    def finish(self, i: int, outcome: tuple[bool, Any]) -> None:
        ok, value = outcome
        if not ok:
            value = ItemFailure(self.names[i], *value)
            if value.traceback and not value.expected:  # a bug: keep its traceback
                log.error("%s failed:\n%s", self.names[i], value.traceback.rstrip())
            if self.on_error == "raise":
                raise ItemError(value)
        self.values[i] = value
        self.done += 1
        if self.on_result is not None:
            self.on_result(i, value)
        if self.progress is not None:
            self.progress(self.done, len(self.names), self.names[i])


def _map_serial(fn, items, shared, parallel, results: _Results) -> list:
    for i, item in enumerate(items):
        try:
            outcome = (True, fn(item, shared))
        except Exception as exc:
            if results.on_error == "raise":  # the exception chained: traceback with --debug
                raise ItemError(ItemFailure(results.names[i], *_describe(exc))) from exc
            outcome = (False, _describe(exc))
        results.finish(i, outcome)
    return results.values


def _map_processes(fn, items, shared, parallel, results: _Results) -> list:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    levels, fmt = _log_levels()
    names = results.names
    pool = ProcessPoolExecutor(
        max_workers=min(parallel.workers, len(items)),
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_init_process,
        initargs=(SINGLE_THREAD_ENV, levels, fmt, pickle.dumps(shared)),
    )
    try:
        futures = {pool.submit(_process_task, fn, item): i for i, item in enumerate(items)}
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in sorted(finished, key=futures.get):
                i = futures[fut]
                try:
                    outcome = fut.result()
                except BrokenProcessPool as exc:  # a worker died (killed, out of memory)
                    raise ItemError(
                        ItemFailure(names[i], type(exc).__name__, f"a worker process died: {exc}")
                    ) from exc
                except Exception as exc:  # the item or its result could not be pickled
                    outcome = (False, (type(exc).__name__, str(exc), "", False))
                results.finish(i, outcome)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return results.values


def _ray():
    try:
        import ray
    except ImportError as exc:
        raise ArgumentError(
            f"the ray executor needs Ray, which is not installed: {RAY_INSTALL}"
        ) from exc
    return ray


def _map_ray(fn, items, shared, parallel, results: _Results) -> list:
    ray = _ray()
    levels, fmt = _log_levels()
    started = not ray.is_initialized()
    if started:
        env = {"env_vars": dict(SINGLE_THREAD_ENV)}
        if parallel.ray_address is None:
            ray.init(
                num_cpus=parallel.workers,
                include_dashboard=False,
                runtime_env=env,
                log_to_driver=True,
            )
        else:
            ray.init(address=parallel.ray_address, runtime_env=env)
    refs: dict = {}
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
        shared_ref = ray.put(shared)
        refs = {
            task.remote(fn, item, shared_ref, SINGLE_THREAD_ENV, levels, fmt): i
            for i, item in enumerate(items)
        }
        pending = list(refs)
        while pending:
            finished, pending = ray.wait(pending, num_returns=1)
            for ref in finished:
                i = refs[ref]
                try:
                    outcome = ray.get(ref)
                except ray.exceptions.RayError as exc:  # a worker died, a task was lost
                    outcome = (False, (type(exc).__name__, str(exc), "", False))
                try:
                    results.finish(i, outcome)
                except ItemError:
                    for r in pending:
                        ray.cancel(r)
                    raise
    finally:
        if started:
            ray.shutdown()
    return results.values
