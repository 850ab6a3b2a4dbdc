"""gnssfuse's GNSS side: traces, estimators (WLS, the factor graph), evaluation, the CLI.

Public API (imported lazily, so ``import fusion.trace`` stays light)::

    from fusion import load_trace, run_modes, RunOptions
"""
from __future__ import annotations

import importlib

_PUBLIC = {
    "load_trace": "fusion.prepare.load", "find_traces": "fusion.prepare.load",
    "run_modes": "fusion.modes", "MODES": "fusion.modes",
    "RunOptions": "fusion.run_types", "ModeResult": "fusion.run_types",
    "Trace": "fusion.trace", "SIGNALS": "fusion.trace",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'fusion' has no attribute {name!r}")
