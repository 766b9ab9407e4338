"""``python -m fusion.cli``: the same entry point as the ``armfusion`` script."""

from fusion.cli.main import app

app()
