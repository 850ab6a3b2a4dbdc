"""One pipeline, several estimators, identical inputs: the mode registry.

A *mode* is a function ``estimate(trace, wls, opts) -> ModeResult``. WLS is solved once per
trace and handed to every mode, so ``wls``, ``dnn``, ``fused`` and ``fused-nodnn`` are compared
on the same measurements and the same initial positions. The registry names each mode by a
``"module:function"`` string and imports it only when asked for: ``fusion`` never imports
``learned`` (the ``dnn`` and ``fused`` modes live there), and ``gnssfuse run --mode wls`` never
imports torch or GTSAM.
"""
from __future__ import annotations

import importlib
from typing import Callable

import numpy as np

from fusion.errors import GnssfuseError, ModeUnavailableError
from fusion.estimate.wls import WlsResult, solve_wls
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace

#: mode name -> "module:function". Adding a mode is one line here.
MODES: dict[str, str] = {
    "wls": "fusion.estimate.wls:estimate_wls",
    "dnn": "learned.modes:estimate_dnn",
    "fused": "learned.modes:estimate_fused",
    "fused-nodnn": "fusion.estimate.graph.fuse:estimate_fused_nodnn",
}


def get_mode(name: str) -> Callable[..., ModeResult]:
    """The estimator of mode ``name``; :class:`GnssfuseError` when unknown, :class:`ModeUnavailableError`
    when its module or function cannot be imported."""
    if name not in MODES:
        raise GnssfuseError(f"unknown mode {name!r}; choose from {', '.join(MODES)}")
    module, func = MODES[name].split(":")
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise ModeUnavailableError(f"mode {name!r} is unavailable: cannot import {module} ({exc})") from exc
    if not hasattr(mod, func):
        raise ModeUnavailableError(f"mode {name!r} is unavailable: {module} has no {func}()")
    return getattr(mod, func)


def solve_initial(trace: Trace, opts: RunOptions) -> WlsResult:
    """The WLS solution every mode starts from."""
    return solve_wls(trace, elev_mask_deg=opts.elev_mask_deg, weighting=opts.wls_weighting,
                     robust=opts.wls_robust)


def run_modes(trace: Trace, modes: list[str] | tuple[str, ...], opts: RunOptions | None = None,
              wls: WlsResult | None = None) -> dict[str, ModeResult]:
    """Run each mode on the same trace and the same WLS solution."""
    opts = opts or RunOptions()
    funcs = {m: get_mode(m) for m in modes}  # fail on a bad mode name before any work
    wls = solve_initial(trace, opts) if wls is None else wls
    return {m: _finite(f(trace, wls, opts)) for m, f in funcs.items()}


def _finite(result: ModeResult) -> ModeResult:
    """``result`` with an epoch whose position is not finite counted unsolved (a network with NaN weights answers
    NaN), so that the epochs said solved are the rows estimates.csv writes."""
    result.valid = np.asarray(result.valid, bool) & np.isfinite(result.pos).all(axis=1)
    return result
