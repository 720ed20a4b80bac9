"""``ssp demo``: the built-in demos (a synthetic sequence against the baselines, or the
physics-only foundation demo)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from ssp.cli.common import ConfigOption, console, friendly, load_config
from ssp.cli.experiments import print_table1

__all__ = ["demo"]


@friendly
def demo(
    out: Path = typer.Option(Path("ssp-demo"), "--out", "-o", help="Output folder."),
    config: Path | None = ConfigOption,
    foundation: bool = typer.Option(
        False, "--foundation", help="The physics-only foundation demo instead."
    ),
) -> None:
    """Run the built-in demo: a short synthetic block structure parsed frame by frame by ssp and
    by its baselines; prints the comparison and writes OUT/report.html (about 30 s)."""
    if foundation:
        _foundation_demo(out, config)
        return
    from ssp.eval.sequence_demo import run_sequence_demo

    with console.status("ssp demo") as status:  # a line per frame in a log (PlainStatus)
        result = run_sequence_demo(out, load_config(config), progress=status.update)
    print_table1(result)
    console.print(f"{result['seconds']:.0f} s; open [bold]{Path(out) / 'report.html'}[/]")
    if result.get("recording"):
        console.print(f"3D recording of ssp's run: [bold]ssp view {result['recording']}[/]")
    else:
        from ssp.viz.record import INSTALL_HINT

        console.print(f"no 3D recording (rerun is not installed: {INSTALL_HINT})")


def _foundation_demo(out: Path, config: Path | None) -> None:
    """The physics-only demo: a cube tower, the built-in tools dropped, a block relaxed."""
    from ssp.eval.demo import run_foundation_demo

    with console.status("running the foundation demo (about 10 s)"):
        r = run_foundation_demo(out, load_config(config))
    t, tl, rx = r["tower"], r["tools"], r["relaxation"]
    table = Table(title="ssp foundation demo")
    table.add_column("experiment")
    table.add_column("result")
    table.add_row(
        "10-cube tower, 2 s dynamic",
        f"max drift {t['max_drift_mm']:.4f} mm, max penetration {t['max_penetration_mm']:.3f} mm,"
        f" {t['us_per_step']:.0f} us/step",
    )
    table.add_row(
        f"{tl['objects']} built-in tools dropped 2 cm",
        f"max penetration {tl['max_penetration_mm']:.3f} mm, residual acceleration "
        f"{tl['max_residual_acceleration_m_s2']:.3f} m/s^2, {tl['us_per_step']:.0f} us/step",
    )
    table.add_row(
        "block hypothesis 6 mm above a cube, tilted 4 deg",
        f"quasi-static relaxation ({rx['steps']} steps): height change "
        f"{rx['block_height_change_mm']:.2f} mm, tilt {rx['block_tilt_after_deg']:.2f} deg, "
        f"acceleration from rest {rx['accel_from_rest_before_m_s2']:.2f} -> "
        f"{rx['accel_from_rest_after_m_s2']:.3f} m/s^2",
    )
    console.print(table)
    for f in r["files"]:
        console.print(f"wrote [bold]{f}[/]")
