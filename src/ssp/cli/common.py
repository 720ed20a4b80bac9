"""What the ``ssp`` commands share: the consoles, the error handling (:func:`friendly`), the
options several commands take, loading the settings and the models, the progress bar, and
stopping a long command on a signal.

Where the output is not a terminal (a log file, a pipe, CI), nothing is transient: the
progress bar and the spinner of ``console.status`` become one plain line per step (per
``every`` steps for long inputs) with the step's seconds (:class:`PlainProgress`,
:class:`PlainStatus`), and the consoles never wrap a line or cut a table (:data:`LOG_WIDTH`).
Repeated warnings are summarised by kind (:func:`warning_digest`, :func:`log_digest`)."""

from __future__ import annotations

import logging
import math
import re
import signal
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console, ConsoleDimensions
from rich.markup import escape

__all__ = [
    "masks_arg",
    "CacheOption",
    "ConfigOption",
    "ExecutorOption",
    "ExperimentOption",
    "FramesOption",
    "JsonOption",
    "LOG_WIDTH",
    "ModelsArg",
    "PlainProgress",
    "PlainStatus",
    "ModelsOption",
    "ProcessesOption",
    "RayAddressOption",
    "StagesOption",
    "StrideOption",
    "WorkersOption",
    "console",
    "err_console",
    "check_experiment",
    "experiment_library",
    "friendly",
    "get_parallel",
    "load_config",
    "load_library",
    "load_library_config",
    "log_digest",
    "print_warnings",
    "progress_bar",
    "restore_signals",
    "state",
    "stop_on_sigterm",
    "stopped",
    "warning_digest",
    "warning_kind",
]

#: Width of a console that is not a terminal (a log file, a pipe): rich wraps nothing and cuts
#: no table there (a terminal's width would cut them at 80 columns).
LOG_WIDTH = 10_000


def _interactive(c: Console) -> bool:
    """Whether ``c`` can show a live bar or spinner: a terminal (now) that rich found
    interactive (not TERM=dumb)."""
    return bool(c.is_interactive and c.is_terminal)


class _Console(Console):
    """A rich console that, when not a terminal, wraps nothing (:data:`LOG_WIDTH`) and turns
    ``status`` into plain lines (:class:`PlainStatus`)."""

    @property
    def size(self) -> ConsoleDimensions:
        dims = super().size
        if self._width is None and not self.is_terminal:
            return ConsoleDimensions(LOG_WIDTH, dims.height)
        return dims

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        Console.size.fset(self, new_size)  # type: ignore[attr-defined]

    def status(self, status: Any, **kwargs: Any) -> Any:  # type: ignore[override]
        if _interactive(self):
            return _DrawnStatus(self, status)
        return PlainStatus(status)


class _DrawnStatus:
    """``console.status`` on a terminal without rich's refresh thread: the spinner and its text
    are redrawn at each :meth:`update` by the calling thread. A process that runs no other
    thread can fork the search's lanes (``ssp.lanes`` forks no process that runs another
    thread: a child could hang on a lock that thread holds)."""

    def __init__(self, console: Console, status: Any) -> None:
        from rich.live import Live
        from rich.spinner import Spinner

        self._spinner = Spinner("dots", text=status)
        self._live = Live(self._spinner, console=console, transient=True, auto_refresh=False)

    def __enter__(self) -> _DrawnStatus:
        self._live.__enter__()
        self._live.refresh()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._live.__exit__(*exc)

    def update(self, status: Any = None, **_: Any) -> None:
        if status is not None:
            self._spinner.update(text=status)
        self._live.refresh()

    def start(self) -> None:
        self._live.start()

    def stop(self) -> None:
        self._live.stop()


console = _Console()
err_console = _Console(stderr=True)
#: ``debug``: --debug given (tracebacks instead of one-line errors); ``stop``: a stop was
#: asked for by a signal (:func:`stop_on_sigterm`).
state: dict[str, bool] = {"debug": False}

F = TypeVar("F", bound=Callable[..., Any])


def friendly(fn: F) -> F:
    """Turn ssp's typed errors and file-system errors (a folder that cannot be written, a full
    disk) into a one-line message and exit code 1; Ctrl-C into exit code 130. Tracebacks with
    --debug; any other exception is a bug and keeps its traceback. Repeated log warnings are
    capped and counted at the end (:func:`log_digest`)."""

    @wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from ssp.errors import SSPError

        try:
            with log_digest():
                return fn(*args, **kwargs)
        except (SSPError, OSError) as exc:
            if state["debug"]:
                raise
            err_console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            if state["debug"]:
                raise
            err_console.print("[bold red]interrupted[/]")
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


# ------------------------------------------------------------------------------ options
ConfigOption = typer.Option(None, "--config", "-c", help="YAML config file (partial is fine).")
CacheOption = typer.Option(
    None, "--cache", help="Hull cache folder (default: $SSP_CACHE_DIR, else ~/.cache/ssp)."
)
ModelsArg = typer.Argument(None, help="Model folder (default: the built-in models).")
JsonOption = typer.Option(False, "--json", help="Machine-readable output.")
ExperimentOption = typer.Option(
    "structure", "--experiment", "-e", help="isolated (tools apart) or structure (blocks built up)."
)
ModelsOption = typer.Option(
    None, "--models", "-m", help="Model folder (default: the built-in models)."
)
StagesOption = typer.Option(5, min=1, help="Static scenes per sequence.")
FramesOption = typer.Option(4, min=1, help="Repeated frames of each static scene.")
StrideOption = typer.Option(1, min=1, help="Render every n-th pixel (1: 640 x 480).")
ExecutorOption = typer.Option(
    None,
    "--executor",
    help=(
        "serial, processes or ray: how independent sequences / trials run (default: serial "
        "for --workers 1, else processes). Results are those of the serial run."
    ),
    show_default=False,
)
WorkersOption = typer.Option(
    1, "--workers", "-j", min=1, help="Worker processes (or CPUs of a local Ray), one core each."
)
ProcessesOption = typer.Option(
    None,
    "--processes",
    min=1,
    max=64,
    help="Processes per frame (search.processes and perception.processes, Linux): an object's "
    "candidates simulated at once, and the segments' hypotheses estimated at once; the results "
    "are the same for any number. 2 on a 2-core machine.",
    show_default=False,
)
RayAddressOption = typer.Option(
    None,
    "--ray-address",
    help="Join this Ray cluster (e.g. auto, ray://host:10001) instead of a local Ray.",
    show_default=False,
)


# ------------------------------------------------------------------------------ loading
def load_config(path: Path | None):
    """The settings of ``--config`` (defaults when not given)."""
    from ssp.config import SSPConfig
    from ssp.config import load_config as load

    return load(path) if path else SSPConfig()


def load_library_config(config: Path | None, cache: Path | None):
    """The library settings of ``--config``, with the ``--cache`` folder when given."""
    cfg = load_config(config).library
    return cfg if cache is None else cfg.model_copy(update={"cache_dir": cache})


def load_library(models: Path | None, config: Path | None, cache: Path | None = None):
    """The built-in library, or the model folder ``models``, with a progress bar.

    Models of the folder that cannot be built are skipped, each with its reason printed."""
    from ssp.library import ObjectLibrary
    from ssp.library.properties import read_folder

    cfg = load_library_config(config, cache)
    if models is None:
        return ObjectLibrary.builtin(cfg)
    # no lines in a log: the models load before every command, --json ones too
    with progress_bar(lines=False) as progress:
        task = progress.add_task(f"loading {models}", total=len(read_folder(models)))
        lib = ObjectLibrary.from_folder(
            models,
            cfg,
            progress=lambda name: progress.update(task, advance=1),
            status=lambda text: progress.update(task, description=text[:70]),
            on_error="skip",
        )
    for name, why in lib.skipped.items():
        err_console.print(f"[yellow]skipped model {name}:[/] {why}")
    return lib


def get_parallel(executor: str | None, workers: int, ray_address: str | None):
    """The :class:`ssp.pipeline.executor.Parallel` of the --executor, --workers, --ray-address
    options."""
    from ssp.errors import ArgumentError
    from ssp.pipeline.executor import Parallel

    try:
        return Parallel.from_options(executor, workers, ray_address)
    except ArgumentError as exc:
        raise typer.BadParameter(str(exc)) from None


def progress_bar(lines: bool = True):
    """A transient progress bar on stderr; where stderr is not a terminal, a
    :class:`PlainProgress` (a plain line per step; none without ``lines``) instead."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
    from rich.table import Column

    if not _interactive(err_console):
        return PlainProgress(quiet=not lines)

    class DrawnProgress(Progress):
        """Redrawn by the calling thread at each update: no refresh thread (see
        :class:`_DrawnStatus`)."""

        def update(self, *args: Any, **kwargs: Any) -> None:
            kwargs.setdefault("refresh", True)
            super().update(*args, **kwargs)

        def advance(self, *args: Any, **kwargs: Any) -> None:
            super().advance(*args, **kwargs)
            self.refresh()

    return DrawnProgress(
        TextColumn(
            "{task.description}",
            table_column=Column(max_width=60, no_wrap=True, overflow="ellipsis"),
        ),
        BarColumn(),
        MofNCompleteColumn(),
        console=err_console,
        transient=True,
        auto_refresh=False,
    )


class _Task:
    def __init__(self, name: str, total: float | None) -> None:
        self.name = self.description = name
        self.total = total
        self.completed = self.printed = 0.0
        self.since = self.said = time.perf_counter()

    def line(self, what: str) -> str:
        of = f"{self.completed:g}" if self.total is None else f"{self.completed:g}/{self.total:g}"
        return f"{self.name} {of}{' ' if self.description == self.name else ': '}{what}"


class PlainProgress:
    """The progress of :func:`progress_bar` where no bar can be shown: a plain line on stderr
    (none when ``quiet``) each time a task advances (``NAME DONE/TOTAL: DESCRIPTION
    (SECONDS s)``, the seconds of that step), or every ``ceil(total / MAX_LINES)`` steps for
    long inputs (then the seconds per step) and at least every :attr:`MAX_QUIET` seconds; a
    new description alone (what a task is doing, e.g. the frame a benchmark starts) is a line
    ``... (+SECONDS s)`` (the seconds since the task's last line) when the last line is at
    least :attr:`DESCRIBE_GAP` seconds old. The same calls as
    :class:`rich.progress.Progress` (``add_task``, ``update``, a context manager)."""

    #: Lines per task at most (but for :attr:`MAX_QUIET` and new descriptions).
    MAX_LINES = 100
    #: Seconds without a line at most, while steps finish.
    MAX_QUIET = 60.0
    #: Seconds since the task's last line before a new description alone is a line.
    DESCRIBE_GAP = 1.0

    def __init__(self, quiet: bool = False) -> None:
        self._tasks: dict[int, _Task] = {}
        self.quiet = quiet

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def add_task(self, description: str, total: float | None = None, **_: Any) -> int:
        task = len(self._tasks)
        self._tasks[task] = _Task(str(description), total)
        return task

    def update(
        self,
        task_id: int,
        *,
        total: float | None = None,
        completed: float | None = None,
        advance: float | None = None,
        description: str | None = None,
        **_: Any,
    ) -> None:
        t = self._tasks[task_id]
        if total is not None:
            t.total = total
        new = description is not None and str(description) != t.description
        if description is not None:
            t.description = str(description)
        done = (t.completed if completed is None else completed) + (advance or 0)
        now = time.perf_counter()
        if done == t.completed:  # a new description alone
            if new and not self.quiet and now - t.said >= self.DESCRIBE_GAP:
                self._say(t, f"{t.description} (+{now - t.said:.2f} s)", now)
            return
        t.completed = done
        if self.quiet:
            return
        if done < t.printed:  # counting again (the next scene of a refine)
            t.printed = 0
        every = math.ceil(t.total / self.MAX_LINES) if t.total else 1
        last = t.total is not None and done >= t.total
        if done - t.printed < every and not last and now - t.since < self.MAX_QUIET:
            return
        steps = done - t.printed
        sec = (now - t.since) / steps if steps > 0 else now - t.since
        t.printed, t.since = done, now
        each = f"{sec:.2f} s" if steps == 1 else f"{sec:.2f} s each, {steps:g} steps"
        what = "" if t.description == t.name else t.description
        self._say(t, f"{what} ({each})" if what else f"({each})", now)

    @staticmethod
    def _say(t: _Task, what: str, now: float) -> None:
        t.said = now
        err_console.print(escape(t.line(what)), highlight=False)


class PlainStatus:
    """``console.status`` where no spinner can be shown: the status, and each update, as a
    plain line on stderr with the seconds since the start."""

    def __init__(self, status: Any) -> None:
        self._t0 = time.perf_counter()
        self._say(status)

    def _say(self, text: Any) -> None:
        dt = time.perf_counter() - self._t0
        err_console.print(escape(f"[{dt:7.1f} s] {text}"), highlight=False)

    def __enter__(self) -> PlainStatus:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def update(self, status: Any = None, **_: Any) -> None:
        if status is not None:
            self._say(status)

    def start(self) -> None:
        return None

    def stop(self) -> None:
        return None


# ------------------------------------------------------------------------------ warnings
_FRAME = re.compile(r"^frame \S+: ")
_SUBJECT = re.compile(r"^[\w.\-]+: (?=\S)")
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def warning_kind(text: str) -> str:
    """The kind of a warning: its text without a leading ``frame N:`` and object id, its
    numbers as ``#`` (``cube_7: would fall (stability term -68.9)`` and ``block_2: would
    fall (stability term -3.1)`` are one kind)."""
    t = _FRAME.sub("", str(text).strip())
    t = _SUBJECT.sub("", t)
    return _NUMBER.sub("#", t)


def warning_digest(items: Iterable[tuple[str, str]]) -> list[tuple[str, list[tuple[str, str]]]]:
    """``(where, warning)`` pairs grouped by :func:`warning_kind`, the most frequent kind
    first (then first seen): ``[(kind, [(where, warning), ...]), ...]``."""
    groups: dict[str, list[tuple[str, str]]] = {}
    for where, text in items:
        groups.setdefault(warning_kind(text), []).append((str(where), str(text)))
    order = {k: n for n, k in enumerate(groups)}
    return sorted(groups.items(), key=lambda kv: (-len(kv[1]), order[kv[0]]))


def print_warnings(
    items: Iterable[tuple[str, str]], *, examples: int = 3, where: str = "frame", full: str = ""
) -> None:
    """The warnings of a run (``(frame, warning)`` pairs): one line each when there are few
    and no kind repeats; else summarised, one line per kind (:func:`warning_digest`): the
    count, the first warning and the first frames it came from (up to ``examples`` other
    texts of the kind below it). ``full``: where every warning is (said in the heading)."""
    items = list(items)
    if not items:
        return
    groups = warning_digest(items)
    if all(len(g) == 1 for _, g in groups) and len(items) <= 2 * examples:
        for w, text in items:
            console.print(f"[yellow]warning[/] {escape(w)}: {escape(text)}", highlight=False)
        return
    n = len(groups)
    heading = f"{len(items)} warnings of {n} kind{'s' if n > 1 else ''}"
    console.print(f"[yellow]{heading}[/]" + (f" (all of them: {escape(full)})" if full else ""))
    for _, group in groups:
        places = list(dict.fromkeys(w for w, _ in group))
        shown = ", ".join(places[:5]) + (f", ... ({len(places)} {where}s)" if places[5:] else "")
        plural = "s" if len(places) > 1 else ""
        console.print(
            f"  [yellow]{len(group)} x[/] {escape(group[0][1])}: {where}{plural} {escape(shown)}",
            highlight=False,
        )
        others = list(dict.fromkeys(text for _, text in group if text != group[0][1]))
        for text in others[:examples]:
            console.print(f"      also: {escape(text)}", highlight=False)
        if len(others) > examples:
            console.print(f"      and {len(others) - examples} other texts of this kind")


class _Digest(logging.Filter):
    """A log filter that lets the first ``examples`` warnings of each kind through and counts
    the rest."""

    def __init__(self, examples: int) -> None:
        super().__init__()
        self.examples = examples
        self.seen: dict[tuple[str, str], list] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        decided = record.__dict__.get("_ssp_digest")
        if decided is not None:  # the same record at another handler
            return decided
        try:
            text = record.getMessage()
        except Exception:  # a bad format: let logging report it
            return True
        entry = self.seen.setdefault((record.name, warning_kind(text)), [0, text])
        entry[0] += 1
        record._ssp_digest = entry[0] <= self.examples
        return record._ssp_digest


@contextmanager
def log_digest(examples: int = 3) -> Iterator[None]:
    """Within it, the log shows the first ``examples`` warnings of each kind (by logger and
    :func:`warning_kind`); at its end, one line per kind with more: how many were not shown."""
    digest = _Digest(examples)
    handlers = list(logging.getLogger().handlers)
    for h in handlers:
        h.addFilter(digest)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(digest)
        for (name, _), (count, text) in digest.seen.items():
            if count > examples:
                err_console.print(
                    escape(
                        f"WARNING {name}: {count - examples} more warnings like "
                        f"{text!r} not shown ({count} in all)"
                    ),
                    highlight=False,
                )


def check_experiment(name: str) -> str:
    """The ``--experiment`` (isolated or structure)."""
    if name not in ("isolated", "structure"):
        raise typer.BadParameter(f"--experiment must be isolated or structure, not {name!r}")
    return name


def experiment_library(
    experiment: str, models: Path | None, config: Path | None, cache: Path | None
):
    """The library of a synthetic experiment; a one-line error when it cannot be run on it."""
    lib = load_library(models, config, cache)
    missing = [c for c in ("cube", "block") if c not in lib]
    if experiment == "structure" and missing:
        from ssp.errors import UnknownObjectError

        raise UnknownObjectError(
            f"--experiment structure builds its scenes of the classes 'cube' and 'block', and "
            f"{models} has no {' or '.join(repr(m) for m in missing)}: use the built-in models "
            "(no --models) or add those models to the folder"
        )
    return lib


# ------------------------------------------------------------------------------ signals
def stop_on_sigterm():
    """Make SIGTERM stop a run like Ctrl-C (a clean 'interrupted' summary and a resume hint),
    and remember either signal: an interrupt raised inside a library that swallows exceptions
    (some catch BaseException) is raised again at the next frame (:func:`stopped`). Returns
    the previous handlers (None when signals cannot be set here)."""
    state["stop"] = False

    def stop(signum, frame):
        state["stop"] = True
        raise KeyboardInterrupt

    try:
        return {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    except ValueError:  # not the main thread
        return None


def restore_signals(previous) -> None:
    """Put back the handlers :func:`stop_on_sigterm` replaced."""
    for sig, handler in (previous or {}).items():
        signal.signal(sig, handler)


def stopped() -> None:
    """KeyboardInterrupt when a stop was asked for (between frames)."""
    if state.get("stop"):
        raise KeyboardInterrupt


def masks_arg(masks: str | None) -> str | None:
    """``--masks``: a detections file as its absolute path (what run.json records, so a
    resume from another folder reads the same file), anything else as given (the run
    checks it)."""
    from ssp.io.bop import MASK_MODES

    if masks is None or masks in MASK_MODES or not Path(masks).expanduser().is_file():
        return masks
    return str(Path(masks).expanduser().resolve())
