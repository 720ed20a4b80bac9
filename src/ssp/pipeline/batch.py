"""``ssp run`` over many inputs: one :func:`ssp.pipeline.run.run` per input, in parallel.

Each input ``IN`` gets its own output folder ``OUT/<IN's folder name>/`` holding the files of a
single run (``docs/formats.md``); the runs are independent (:mod:`ssp.pipeline.executor` maps
them), so each one's files are those it would write alone. One input that cannot be run at all
(a missing folder, no frames) is reported in its place and the others go on; bad frames are
handled inside each run as usual. An input whose worker process dies (killed, out of memory)
fails alone, named, with how to resume it; a stop (Ctrl-C, SIGTERM) interrupts every running
input, each resumable (:mod:`ssp.pipeline.executor`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

from ssp.config import SSPConfig
from ssp.errors import ArgumentError
from ssp.pipeline.executor import ItemFailure, Parallel, map_items
from ssp.pipeline.manifest import check_out_dir
from ssp.pipeline.run import run
from ssp.pipeline.summary import RunSummary

__all__ = ["input_out_dirs", "run_inputs"]


def input_out_dirs(inputs: Sequence[str | Path], out_dir: str | Path) -> list[Path]:
    """``OUT/<name>`` per input, ``name`` the input folder's name.

    Raises:
        ArgumentError: two inputs share a folder name (their outputs would collide).
    """
    names = [Path(p).resolve().name for p in inputs]
    seen: dict[str, str] = {}
    for p, name in zip(inputs, names, strict=True):
        if name in seen:
            raise ArgumentError(
                f"inputs {seen[name]} and {p} have the same folder name {name!r}: their "
                "outputs would share one folder; rename one, or run them separately"
            )
        seen[name] = str(p)
    return [Path(out_dir) / name for name in names]


def _run_input(item: tuple[str, str], library: Mapping, **options: Any) -> RunSummary:
    """One input's run (a work item of :func:`run_inputs`): ``item`` is (input, output)."""
    src, out = item
    return run(src, library, out, **options)


def run_inputs(
    inputs: Sequence[str | Path],
    library: Mapping,
    out_dir: str | Path,
    config: SSPConfig | None = None,
    *,
    parallel: Parallel | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    **options: Any,
) -> list[RunSummary | ItemFailure]:
    """:func:`ssp.pipeline.run.run` of every input into ``out_dir/<input name>``, in input order.

    Args:
        inputs: input folders (clouds or BOP scenes), with distinct folder names.
        library: the object library (sent once to each worker).
        out_dir: the parent of the runs' output folders.
        config: ssp's settings.
        parallel: how the runs are spread (:mod:`ssp.pipeline.executor`; default serial).
        overwrite: clear earlier runs' files in the output folders first.
        progress: ``progress(done, total, input)`` after each input.
        options: the other keyword arguments of :func:`ssp.pipeline.run.run` (``hypotheses``,
            ``classes``, ``method``, ``models``, ...), the same for every input.

    Returns:
        Per input its :class:`RunSummary`, or an :class:`ItemFailure` when it could not be run.

    Raises:
        ArgumentError: inputs with the same folder name, or an output folder that holds
            something else (checked for every input before any run starts).
    """
    outs = input_out_dirs(inputs, out_dir)
    for out in outs:
        check_out_dir(out, overwrite)
    work = partial(
        _run_input,
        config=config if config is not None else SSPConfig(),
        overwrite=overwrite,
        **options,
    )
    results = map_items(
        work,
        [(str(src), str(out)) for src, out in zip(inputs, outs, strict=True)],
        shared=library,
        parallel=parallel,
        names=[str(p) for p in inputs],
        progress=progress,
        on_error="collect",
    )
    for k, (res, out) in enumerate(zip(results, outs, strict=True)):
        if isinstance(res, ItemFailure) and res.error_type == "WorkerDied":
            results[k] = replace(res, error=f"{res.error}; resume it with: ssp run --resume {out}")
    return results
