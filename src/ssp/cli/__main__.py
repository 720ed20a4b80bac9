"""``python -m ssp.cli``: the ``ssp`` command line."""

from ssp.cli import app

app()
