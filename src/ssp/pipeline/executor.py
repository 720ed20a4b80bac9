"""Map a function over independent work items: in this process, in worker processes, or on Ray.

:func:`map_items` runs ``fn(item, shared)`` for every item and returns the results **in the
order of the items**, whatever the executor and whatever order the items finish in. The
results equal the serial run's when ``fn`` is a pure function of its arguments: each item
carries everything it depends on (its seed included); nothing is shared between items but the
read-only ``shared`` value.

Executors (:class:`Parallel`):

* ``serial``: one item after another in this process (no pickling).
* ``processes``: ``workers`` processes started with ``spawn``, each sent one item at a time
  through its own pipe. Each worker is single-threaded (``OMP_NUM_THREADS=1`` and the like,
  :data:`SINGLE_THREAD_ENV`, set before anything heavy is imported) and gets ``shared`` once,
  when it starts; ``fn`` and the items must be picklable. A worker that dies (killed, out of
  memory) fails the item it was running only, named, and a new worker goes on with the
  others; when this process stops (Ctrl-C, or SIGTERM made a KeyboardInterrupt as ``ssp``
  does), each worker gets SIGTERM, which interrupts its item as Ctrl-C would (an ``ssp run``
  writes its summary and stays resumable), and the map ends at once.
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
import signal
import time
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
    """A worker process's start: environment first, then the shared value (unpickling it
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


class _Worker:
    """One worker process of :func:`_map_processes` and the pipe to it."""

    def __init__(self, ctx, init: tuple) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, *init))
        self.process.start()
        child.close()
        self.item: int | None = None  # the item it is running

    def death(self) -> str:
        """How the process ended, in words."""
        self.process.join(timeout=5)
        code = self.process.exitcode
        if code is not None and code < 0:
            try:
                return f"killed by {signal.Signals(-code).name}"
            except ValueError:
                return f"killed by signal {-code}"
        return f"exit code {code}" if code is not None else "its pipe closed"


def _map_processes(fn, items, shared, parallel, results: _Results) -> list:
    """The ``processes`` executor: ``workers`` spawned processes, each fed one item at a time
    through its own pipe, so the item a worker runs is always known: a worker that dies
    (killed, out of memory) fails that item only (the others go on; a new worker takes its
    place), and a stop of this process (Ctrl-C, SIGTERM made KeyboardInterrupt) is passed on
    to the workers, which interrupt their items (:func:`_stop_workers`)."""
    import multiprocessing
    from multiprocessing.connection import wait

    levels, fmt = _log_levels()
    ctx = multiprocessing.get_context("spawn")
    init = (SINGLE_THREAD_ENV, levels, fmt, pickle.dumps(shared))
    todo = list(range(len(items)))[::-1]  # popped from the end: item order
    workers = [_Worker(ctx, init) for _ in range(min(parallel.workers, len(items)))]
    finished = False
    try:
        while todo or any(w.item is not None for w in workers):
            for k, w in enumerate(workers):
                if w.item is None and todo and not w.process.is_alive():  # died idle
                    w.conn.close()
                    workers[k] = w = _Worker(ctx, init)
                while w.item is None and todo:
                    i = todo.pop()
                    try:
                        w.conn.send((fn, items[i]))
                    except Exception as exc:  # the item or fn cannot be pickled
                        results.finish(i, (False, (type(exc).__name__, str(exc), "", False)))
                        continue
                    w.item = i
            busy = [w for w in workers if w.item is not None]
            if not busy:
                continue
            wait([w.conn for w in busy] + [w.process.sentinel for w in busy])
            for w in busy:
                outcome = None
                if w.conn.poll():
                    try:
                        outcome = w.conn.recv()
                    except (EOFError, OSError):
                        outcome = None
                elif w.process.is_alive():
                    continue
                i, w.item = w.item, None
                if outcome is None:  # it died while running item i: that item fails alone
                    how = w.death()
                    msg = f"the worker process running it died ({how}); the other items go on"
                    log.error("%s: %s", results.names[i], msg)
                    workers[workers.index(w)] = _Worker(ctx, init) if todo else w
                    outcome = (False, ("WorkerDied", msg, "", False))
                results.finish(i, outcome)
        finished = True
    finally:
        _stop_workers(workers, graceful=finished)
    return results.values


def _stop_workers(workers: list[_Worker], graceful: bool, timeout: float = 60.0) -> None:
    """End the workers: ``graceful`` (all items done), ask each to exit; else (this process is
    stopping: an interrupt, a failed item with ``on_error="raise"``) send each SIGTERM, which
    interrupts the item it runs as Ctrl-C would (a run writes its summary and stays
    resumable), and wait up to ``timeout`` s before killing what is left."""
    for w in workers:
        if not w.process.is_alive():
            continue
        if graceful:
            try:
                w.conn.send(None)
            except OSError:
                w.process.terminate()
        else:
            w.process.terminate()
    deadline = time.monotonic() + timeout
    try:
        for w in workers:
            w.process.join(timeout=max(0.0, deadline - time.monotonic()))
    except KeyboardInterrupt:  # asked again to stop: do not wait
        pass
    finally:
        for w in workers:
            if w.process.is_alive():
                w.process.kill()
                w.process.join(timeout=5)
            w.conn.close()


def _worker_main(conn, env, levels, fmt, shared: bytes) -> None:
    """A worker of :func:`_map_processes`: run the items it is sent, one at a time, and send
    back each :func:`_call` outcome; None or a closed pipe ends it. SIGINT is ignored (a
    Ctrl-C reaches the whole process group: the main process decides, and passes it on as
    SIGTERM); SIGTERM interrupts the running item (KeyboardInterrupt) and ends the worker."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    _init_process(env, levels, fmt, shared)
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError, SystemExit):
            return
        if msg is None:
            return
        fn, item = msg
        _WORKER["busy"] = True
        try:
            outcome = _call(fn, item, _WORKER.get("shared"))
        except (KeyboardInterrupt, SystemExit):
            return  # stopped: nobody waits for its result
        finally:
            _WORKER["busy"] = False
        try:
            conn.send(outcome)
        except (OSError, SystemExit):
            return
        except Exception as exc:  # the result cannot be pickled
            conn.send((False, (type(exc).__name__, f"its result cannot be sent back: {exc}",
                               "", False)))  # fmt: skip


def _on_sigterm(signum, frame) -> None:
    """A worker's SIGTERM: interrupt the item it runs, or end it when it waits for one."""
    if _WORKER.get("busy"):
        raise KeyboardInterrupt
    raise SystemExit(0)


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
