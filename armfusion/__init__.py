"""armfusion: a robot arm's absolute joint angles from gravity, with relative encoders.

The layers install under this one namespace (``armfusion.sensors`` → ``armfusion.models`` →
``armfusion.fusion``), so an unrelated top-level ``models`` or ``sensors`` package in the same
environment is left alone. The names a user's code calls first are importable from here::

    import armfusion

    arm = armfusion.load_arm("wmra")
    rec, truth = armfusion.simulate(arm, "static-poses", seed=1)
    tracker, start = armfusion.start_from_recording(arm, rec)
    run = tracker.run(rec)

They are loaded on first use, so ``import armfusion`` stays cheap (the compiled kernels are
imported only by what needs them).
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# name → the module that defines it (one definition each; this is an index, not a copy)
_API = {
    "load_arm": "armfusion.fusion.configfile",
    "read_recording": "armfusion.sensors.recording",
    "write_recording": "armfusion.sensors.recording",
    "simulate": "armfusion.models.simulator",
    "solve_still": "armfusion.fusion.startup.solve",
    "start_from_recording": "armfusion.fusion.tracking.tracker",
    "StartOptions": "armfusion.fusion.tracking.tracker",
    "Tracker": "armfusion.fusion.tracking.tracker",
    "identify": "armfusion.fusion.identification.identify",
    "diagnose": "armfusion.fusion.workbench.diagnose",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name not in _API:
        raise AttributeError(f"module 'armfusion' has no attribute {name!r}")
    value = getattr(importlib.import_module(_API[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
