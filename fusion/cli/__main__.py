"""``python -m armfusion.fusion.cli``: the same entry point as the ``armfusion`` script."""

from armfusion.fusion.cli.main import app

app()
