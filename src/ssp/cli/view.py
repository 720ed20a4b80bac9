"""``ssp view``: open a 3D recording in the rerun viewer (:mod:`ssp.viz.record`)."""

from __future__ import annotations

from pathlib import Path

import typer

from ssp.cli.common import console, friendly

__all__ = ["view"]


@friendly
def view(
    recording: Path = typer.Argument(..., help="A recording (.rrd) written by --record."),
    web: bool = typer.Option(
        False, "--web", help="Serve it to a browser instead (no display needed here)."
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="Print the viewer command instead of running it."
    ),
) -> None:
    """Open a 3D recording of a run (ssp run --record, ssp demo) in the rerun viewer."""
    from ssp.viz.record import prepare_view, view_command
    from ssp.viz.record import view as open_viewer

    if dry_run:
        cmd = " ".join(view_command(recording, web=web))
        console.print(cmd, highlight=False, markup=False, soft_wrap=True)
        return
    cmd = prepare_view(recording, web=web)
    if web:
        console.print(
            f"serving {recording} to a browser ({' '.join(cmd)}); open the address it prints "
            "(by default http://localhost:9090). Ctrl-C stops it.",
            highlight=False,
        )
    else:
        console.print(f"opening {recording} in the rerun viewer", highlight=False)
    open_viewer(recording, web=web)
