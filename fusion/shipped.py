"""Where the shipped configs are: the repository's ``config/`` folder, installed as the
data-only package ``armfusion.config``.

``config/`` holds files only (the arm configs ``*.yaml``, the Zenoh configs ``*.json5``
and ``deploy/*.json5``); ``pyproject.toml`` maps it to the package name
``armfusion.config`` (a namespace package: no ``__init__.py``), so a wheel carries it as
package data and the import system finds it wherever the project is installed; an
editable install finds it in the working tree. Run from a checkout that was never
installed (``python -m armfusion.fusion.cli`` with the repository on ``sys.path``), the package is
not importable and the ``config/`` folder beside ``fusion/`` is used instead.

The folder comes from the package's import spec, not from
:func:`importlib.resources.files`: on Python 3.11 that fails on a namespace package of a
setuptools editable install (its search path carries a placeholder entry that is not a
folder, and ``MultiplexedPath`` refuses it with ``NotADirectoryError``).
"""

from __future__ import annotations

from importlib.util import find_spec
from pathlib import Path

PACKAGE = "armfusion.config"
"""The import name of the shipped ``config/`` folder."""

_CHECKOUT_CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"


def shipped_config_dir() -> Path:
    """The folder holding the shipped configs: the first real folder on the package's
    search path (pip installs unpacked), else ``config/`` beside ``fusion/``."""
    spec = find_spec(PACKAGE)
    for entry in (spec.submodule_search_locations or []) if spec is not None else []:
        if Path(entry).is_dir():
            return Path(entry).resolve()
    return _CHECKOUT_CONFIG_DIR


def shipped_config(name: str) -> Path:
    """The shipped file ``name`` (e.g. ``"wmra.yaml"``, ``"deploy/chair.json5"``); it may
    not exist."""
    return shipped_config_dir() / name
