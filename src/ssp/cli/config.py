"""``ssp dump-config``."""

from __future__ import annotations

from pathlib import Path

import typer

from ssp.cli.common import ConfigOption, console, friendly, load_config
from ssp.errors import ConfigError

__all__ = ["dump_config_cmd"]


@friendly
def dump_config_cmd(
    config: Path | None = ConfigOption,
    out: Path | None = typer.Option(None, "--out", "-o", help="Write to this file."),
) -> None:
    """Print the effective configuration as YAML (defaults, or --config merged over them)."""
    from ssp.config import dump_config
    from ssp.io._files import atomic_write_text

    text = dump_config(load_config(config))
    if out is None:
        print(text, end="")
        return
    try:
        atomic_write_text(out, text)
    except OSError as exc:
        raise ConfigError(f"cannot write {out}: {exc}") from exc
    console.print(f"wrote {out}")
