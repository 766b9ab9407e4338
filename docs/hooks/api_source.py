"""mkdocs hook: lets mkdocstrings read the installed layout (``armfusion.fusion`` …) from the
source folders.

The layers' folders sit at the repository's top (fusion/, models/, sensors/) and install
below ``armfusion`` by a package-dir mapping, which griffe (mkdocstrings' reader) does not
follow. Before the build this hook lays out, in a temporary folder, ``armfusion/`` as it is
installed (its ``__init__.py`` and one symbolic link per layer) and points the Python handler
there; nothing is imported and nothing is written into the working tree.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from mkdocs.plugins import event_priority

LAYERS = ("fusion", "models", "sensors")


@event_priority(100)  # before mkdocstrings reads its handlers' options
def on_config(config):
    root = Path(config.config_file_path).resolve().parent
    staged = Path(tempfile.mkdtemp(prefix="armfusion-api-"))
    atexit.register(shutil.rmtree, staged, ignore_errors=True)
    package = staged / "armfusion"
    package.mkdir()
    (package / "__init__.py").symlink_to(root / "armfusion" / "__init__.py")
    for layer in LAYERS:
        (package / layer).symlink_to(root / layer, target_is_directory=True)
    handlers = config.plugins["mkdocstrings"].config.handlers
    handlers.setdefault("python", {})["paths"] = [str(staged)]
    return config
