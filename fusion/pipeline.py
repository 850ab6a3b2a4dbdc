"""One pipeline, several estimators, identical inputs: the ``gnssfuse run`` command.

A *mode* is a function ``estimate(trace, wls, opts) -> ModeResult``. WLS is solved once per
trace and handed to every mode, so ``wls``, ``dnn``, ``fused`` and ``fused-nodnn`` are compared
on the same measurements and the same initial positions. Modes that need torch or GTSAM live in
other modules and are imported only when asked for.
"""
from __future__ import annotations

import argparse
import importlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from fusion.errors import GnssfuseError, ModeUnavailableError
from fusion.geometry import ecef2geodetic
from fusion.trace import SIGNALS, Trace


@dataclass
class RunOptions:
    """Settings shared by every mode of one run."""

    weights: Path | None = None          # DNN checkpoint; None = the weights shipped in learned/weights
    elev_mask_deg: float = 10.0
    device: str = "cpu"
    dnn_passes: int = 1                  # DNN applied iteratively, features recomputed each pass
    incremental: bool = False            # fused modes: ISAM2 / fixed-lag instead of batch LM
    signals: tuple[str, ...] = ("GPS_L1",)
    wls_weighting: str = "elevation"
    wls_robust: bool = False


@dataclass
class ModeResult:
    """Output of one mode on one trace.

    pos:   (E, 3) ECEF [m], NaN rows where the epoch was not solved.
    valid: (E,) bool.
    cov:   (E, 3, 3) ECEF position covariance [m^2], or None when the mode gives none.
    info:  counts and diagnostics for the report (e.g. skipped epochs by reason).
    """

    pos: np.ndarray
    valid: np.ndarray
    cov: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def estimate_wls(trace: Trace, wls, opts: RunOptions) -> ModeResult:
    """The WLS baseline as a mode (WLS is already solved by :func:`run_modes`)."""
    # Copies: every mode receives the same WlsResult, so no mode's output may alias it.
    return ModeResult(pos=wls.pos.copy(), valid=wls.valid.copy(), cov=wls.cov[:, :3, :3].copy(),
                      info={"unsolved": int((~wls.valid).sum()),
                            # epochs loaded with < 4 measurements (CLI loads with min_sats=1 so the
                            # fused modes can carry them; WLS cannot solve them)
                            "lt4_sats": int((trace.n_sats < 4).sum())})


#: mode name -> "module:function". Adding a mode is one line here.
MODES: dict[str, str] = {
    "wls": "fusion.pipeline:estimate_wls",
    "dnn": "learned.infer:estimate_dnn",
    "fused": "fusion.graph:estimate_fused",
    "fused-nodnn": "fusion.graph:estimate_fused_nodnn",
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


def solve_initial(trace: Trace, opts: RunOptions):
    """The WLS solution every mode starts from."""
    from fusion.wls import solve_wls

    return solve_wls(trace, elev_mask_deg=opts.elev_mask_deg, weighting=opts.wls_weighting,
                     robust=opts.wls_robust)


def run_modes(trace: Trace, modes: list[str] | tuple[str, ...], opts: RunOptions | None = None,
              wls=None) -> dict[str, ModeResult]:
    """Run each mode on the same trace and the same WLS solution."""
    opts = opts or RunOptions()
    funcs = {m: get_mode(m) for m in modes}  # fail on a bad mode name before any work
    wls = solve_initial(trace, opts) if wls is None else wls
    return {m: f(trace, wls, opts) for m, f in funcs.items()}


# ---------------------------------------------------------------------------- outputs
ESTIMATE_COLUMNS = ["gps_millis", "lat_deg", "lon_deg", "height_m", "x_m", "y_m", "z_m"]


def estimates_frame(trace: Trace, result: ModeResult) -> pd.DataFrame:
    """One row per solved epoch, in the CLI contract's columns."""
    ok = result.valid & np.isfinite(result.pos).all(axis=1)
    pos = result.pos[ok]
    llh = ecef2geodetic(pos) if len(pos) else np.zeros((0, 3))
    cols = (trace.t_ms[ok], llh[:, 0], llh[:, 1], llh[:, 2], pos[:, 0], pos[:, 1], pos[:, 2])
    return pd.DataFrame(dict(zip(ESTIMATE_COLUMNS, cols, strict=True)))


def trace_errors(trace: Trace, result: ModeResult) -> np.ndarray | None:
    """(E, 3) NED error [m] of a mode's estimates w.r.t. the truth (NaN rows where the epoch is
    unsolved or has no truth), or None when the trace has no truth. Truth is used here only."""
    if not trace.has_truth:
        return None
    from fusion.metrics import ned_errors

    est = np.where(result.valid[:, None], result.pos, np.nan)
    return ned_errors(est, trace.truth)


def mode_metrics(trace: Trace, result: ModeResult) -> dict | None:
    """Accuracy against truth (None when the trace has none): ``summarize(trace_errors(...))``."""
    err = trace_errors(trace, result)
    if err is None:
        return None
    from fusion.metrics import summarize

    return summarize(err)


def format_table(rows: dict[str, dict | None]) -> str:
    """Plain-text accuracy table, one row per mode."""
    head = f"{'mode':<12} {'MAE N':>14} {'MAE E':>14} {'MAE D':>14} {'h p50':>7} {'h p95':>7} {'score':>7} {'n':>6}"
    lines = [head, "-" * len(head)]
    for mode, m in rows.items():
        if m is None:
            lines.append(f"{mode:<12} (no truth: metrics unavailable)")
            continue
        axes = [f"{m[f'mae_{a}']:6.2f}±{m[f'std_{a}']:<6.2f}" for a in "ned"]
        lines.append(f"{mode:<12} {axes[0]:>14} {axes[1]:>14} {axes[2]:>14} "
                     f"{m['h_p50']:7.2f} {m['h_p95']:7.2f} {m['gsdc_score']:7.2f} {m['n']:6d}")
    return "\n".join(lines)


def write_outputs(out_dir: Path, trace: Trace, mode: str, result: ModeResult) -> dict:
    """Write estimates.csv (+ metrics.json when truth exists); return the metrics record."""
    out_dir.mkdir(parents=True, exist_ok=True)
    estimates_frame(trace, result).to_csv(out_dir / "estimates.csv", index=False, float_format="%.10g")
    record = {
        "trace": trace.name, "mode": mode, "epochs_total": trace.n_epochs,
        "epochs_solved": int(result.valid.sum()), "skipped": dict(trace.skipped),
        "info": {k: v for k, v in result.info.items() if isinstance(v, (int, float, str, bool))},
        "metrics": mode_metrics(trace, result),
    }
    if record["metrics"] is not None:
        (out_dir / "metrics.json").write_text(json.dumps(record, indent=2))
    return record


# ---------------------------------------------------------------------------- CLI
def add_run_options(p: argparse.ArgumentParser) -> None:
    """Options shared by ``gnssfuse run`` and ``gnssfuse evaluate`` (read by :func:`options_from_args`)."""
    p.add_argument("--weights", type=Path, default=None, help="DNN checkpoint (default: shipped weights)")
    p.add_argument("--signals", default="GPS_L1",
                   help=f"comma-separated, from {','.join(SIGNALS)} (2023 spellings such as GPS_L1_CA "
                        "too), or all")
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg]")
    p.add_argument("--dnn-passes", type=int, default=1, help="apply the DNN iteratively this many times")
    p.add_argument("--incremental", action="store_true", help="fused modes: incremental smoother instead of batch")
    p.add_argument("--robust-wls", action="store_true", help="WLS with outlier exclusion")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-truth-height-fix", action="store_true",
                   help="keep GSDC 2021 truth heights as published (~63 m too high)")


def build_parser(prog: str = "gnssfuse run") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Solve one trace in one mode and write estimates.csv.")
    p.add_argument("trace_dir", type=Path, help="a <collection>/<phone> folder (GSDC 2021 derived or 2022/23 device_gnss)")
    p.add_argument("--mode", default="wls", choices=list(MODES))
    p.add_argument("--out", type=Path, required=True, help="output folder")
    add_run_options(p)
    return p


def options_from_args(args: argparse.Namespace) -> RunOptions:
    from fusion.io_gsdc import resolve_signals

    # The loader's vocabulary: our names, GSDC 2023 spellings (GPS_L1_CA, ...) or "all".
    names = [s.strip() for s in args.signals.split(",") if s.strip()]
    signals = tuple(SIGNALS[i] for i in resolve_signals(names))
    if args.dnn_passes < 1:
        raise GnssfuseError("--dnn-passes must be >= 1")
    return RunOptions(weights=args.weights, elev_mask_deg=args.elev_mask, device=args.device,
                      dnn_passes=args.dnn_passes, incremental=args.incremental, signals=signals,
                      wls_robust=args.robust_wls)


def main(argv: list[str], prog: str = "gnssfuse run") -> int:
    from fusion.io_gsdc import load_trace

    args = build_parser(prog).parse_args(argv)
    opts = options_from_args(args)
    # min_sats=1: keep epochs with 1-3 satellites; WLS/dnn leave them unsolved (counted in info),
    # the fused modes carry them with the prior and the motion model
    trace = load_trace(args.trace_dir, signals=opts.signals, fix_truth_height=not args.no_truth_height_fix,
                       min_sats=1)
    result = run_modes(trace, [args.mode], opts)[args.mode]
    record = write_outputs(args.out, trace, args.mode, result)
    print(f"{trace.name}: {record['epochs_solved']}/{trace.n_epochs} epochs solved in mode {args.mode}"
          + (f"; skipped while loading: {record['skipped']}" if record["skipped"] else ""))
    print(format_table({args.mode: record["metrics"]}))
    print(f"wrote {args.out / 'estimates.csv'}" + (" and metrics.json" if record["metrics"] else ""))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
