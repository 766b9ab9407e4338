"""``python -m armfusion``: the same command line as the ``armfusion`` script."""

from armfusion.fusion.cli.main import app

if __name__ == "__main__":
    app()
