"""Accuracy metrics: errors in the truth's local NED frame, summary statistics, CDFs.

Rows that cannot be scored (no estimate, or no truth for that epoch) are NaN in the error arrays;
:func:`summarize` excludes and counts them (``n_excluded``) rather than dropping them silently.
"""
from __future__ import annotations

import numpy as np

from fusion.errors import DataError
from fusion.geometry import ecef2ned_cov, ecef2ned_vec
from fusion.run_types import ModeResult
from fusion.trace import Trace


def ned_errors(est_ecef: np.ndarray, truth_ecef: np.ndarray) -> np.ndarray:
    """Estimate minus truth, rotated into the NED frame at the truth.

    est_ecef, truth_ecef: (E, 3) ECEF [m], NaN rows allowed. Returns (E, 3) [north, east, down] [m],
    NaN where either row is not finite.
    """
    est = np.asarray(est_ecef, float)
    truth = np.asarray(truth_ecef, float)
    if est.shape != truth.shape or est.ndim != 2 or est.shape[1] != 3:
        raise DataError(f"ned_errors needs two (E, 3) arrays, got {est.shape} and {truth.shape}")
    out = np.full(est.shape, np.nan)
    ok = np.isfinite(est).all(1) & np.isfinite(truth).all(1)
    if ok.any():
        out[ok] = ecef2ned_vec(est[ok] - truth[ok], truth[ok])
    return out


def horizontal(err_ned: np.ndarray) -> np.ndarray:
    """(E,) horizontal error magnitude [m] from (E, 3) NED errors (NaN rows stay NaN)."""
    return np.hypot(err_ned[:, 0], err_ned[:, 1])


def summarize(err_ned: np.ndarray) -> dict:
    """Summary of (E, 3) NED errors [m].

    Returns a dict with
    - ``mae_n/e/d``: mean absolute error per axis;
    - ``std_n/e/d``: standard deviation of the absolute error per axis (the paper's "MAE +- std");
    - ``h_p50``, ``h_p95``: 50th / 95th percentile of the horizontal error (numpy linear
      interpolation);
    - ``gsdc_score``: mean of ``h_p50`` and ``h_p95`` (the GSDC 2021 per-phone score);
    - ``n``: epochs scored; ``n_excluded``: rows with any NaN (no estimate or no truth).
    With no scorable row every statistic is NaN and ``n`` is 0.
    """
    err = np.asarray(err_ned, float)
    if err.ndim != 2 or err.shape[1] != 3:
        raise DataError(f"summarize needs (E, 3) NED errors, got shape {err.shape}")
    ok = np.isfinite(err).all(1)
    e = np.abs(err[ok])
    out: dict = {"n": int(ok.sum()), "n_excluded": int((~ok).sum())}
    if not ok.any():
        nan = float("nan")
        out.update({k: nan for k in ("mae_n", "mae_e", "mae_d", "std_n", "std_e", "std_d",
                                     "h_p50", "h_p95", "gsdc_score")})
        return out
    for i, ax in enumerate("ned"):
        out[f"mae_{ax}"] = float(e[:, i].mean())
        out[f"std_{ax}"] = float(e[:, i].std())
    h = horizontal(err[ok])
    p50, p95 = np.percentile(h, [50, 95])
    out.update(h_p50=float(p50), h_p95=float(p95), gsdc_score=float((p50 + p95) / 2))
    return out


def cdf(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Empirical CDF of the finite entries of ``values``: (sorted values, fraction <= value)."""
    v = np.asarray(values, float).ravel()
    v = np.sort(v[np.isfinite(v)])
    return v, np.arange(1, v.size + 1) / max(v.size, 1)


def format_summary(s: dict) -> str:
    """One-line human-readable form of :func:`summarize`'s dict."""
    return (f"n={s['n']} (excl {s['n_excluded']})  MAE N/E/D {s['mae_n']:.2f}/{s['mae_e']:.2f}/"
            f"{s['mae_d']:.2f} m  h p50 {s['h_p50']:.2f}  p95 {s['h_p95']:.2f}  "
            f"GSDC {s['gsdc_score']:.2f} m")


def trace_errors(trace: Trace, result: ModeResult) -> np.ndarray | None:
    """(E, 3) NED error [m] of a mode's estimates w.r.t. the truth (NaN rows where the epoch is
    unsolved or has no truth), or None when the trace has no truth. Truth is used here only."""
    if not trace.has_truth:
        return None
    est = np.where(result.valid[:, None], result.pos, np.nan)
    return ned_errors(est, trace.truth)


def sigma_ratios(err_ned: np.ndarray, pos: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,3) |error| / 1 sigma per NED axis of the N rows without a NaN. err_ned (E,3) [m], pos (E,3) ECEF,
    cov (E,3,3) ECEF [m^2]."""
    ok = np.isfinite(err_ned).all(1) & np.isfinite(pos).all(1) & np.isfinite(cov).all((1, 2))
    var = np.diagonal(ecef2ned_cov(cov[ok], pos[ok]), axis1=1, axis2=2)
    return np.abs(err_ned[ok]) / np.sqrt(np.maximum(var, 1e-12))


def within_sigma(err_ned: np.ndarray, pos: np.ndarray, cov: np.ndarray) -> dict:
    """Calibration of a covariance: the share of |error| within 1 and 2 sigma per NED axis.

    err_ned (E,3) [m], pos (E,3) ECEF, cov (E,3,3) ECEF [m^2]; rows with a NaN are left out. Returns
    ``within1sigma_n/e/d``, ``within2sigma_n/e/d`` (a Gaussian: 0.683 / 0.954) and ``n_cov`` (rows used)."""
    z = sigma_ratios(err_ned, pos, cov)
    out: dict = {"n_cov": len(z)}
    if not len(z):
        return out
    for i, ax in enumerate("ned"):
        out[f"within1sigma_{ax}"] = float((z[:, i] <= 1).mean())
        out[f"within2sigma_{ax}"] = float((z[:, i] <= 2).mean())
    return out


def mode_metrics(trace: Trace, result: ModeResult) -> dict | None:
    """Accuracy against truth (None when the trace has none): ``summarize(trace_errors(...))``, and for a
    mode with a covariance its calibration per axis (:func:`within_sigma`): judged per trace and axis,
    not only pooled."""
    err = trace_errors(trace, result)
    if err is None:
        return None
    out = summarize(err)
    if result.cov is not None:
        out.update(within_sigma(err, np.where(result.valid[:, None], result.pos, np.nan), np.asarray(result.cov, float)))
    return out


def format_table(rows: dict[str, dict | None]) -> str:
    """Plain-text accuracy table, one row per mode (``rows``: mode -> :func:`summarize` dict or None)."""
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

