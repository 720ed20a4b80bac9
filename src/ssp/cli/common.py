"""What the ``ssp`` commands share: the consoles, the error handling (:func:`friendly`), the
options several commands take, loading the settings and the models, the progress bar, and
stopping a long command on a signal."""

from __future__ import annotations

import signal
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

__all__ = [
    "CacheOption",
    "ConfigOption",
    "ExecutorOption",
    "ExperimentOption",
    "FramesOption",
    "JsonOption",
    "ModelsArg",
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
    "progress_bar",
    "restore_signals",
    "state",
    "stop_on_sigterm",
    "stopped",
]

console = Console()
err_console = Console(stderr=True)
#: ``debug``: --debug given (tracebacks instead of one-line errors); ``stop``: a stop was
#: asked for by a signal (:func:`stop_on_sigterm`).
state: dict[str, bool] = {"debug": False}

F = TypeVar("F", bound=Callable[..., Any])


def friendly(fn: F) -> F:
    """Turn ssp's typed errors and file-system errors (a folder that cannot be written, a full
    disk) into a one-line message and exit code 1; Ctrl-C into exit code 130. Tracebacks with
    --debug; any other exception is a bug and keeps its traceback."""

    @wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from ssp.errors import SSPError

        try:
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
    with progress_bar() as progress:
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


def progress_bar():
    """A transient progress bar on stderr."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        console=err_console,
        transient=True,
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
