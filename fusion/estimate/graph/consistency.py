"""Doppler and carrier sigmas held to what the measurements themselves show: a robust scale of each kind's
residuals in its own one-epoch fit, over a sliding window, raises sigmas that are too small.

A phone's Doppler sigma is a tracking-loop figure (often a constant) that knows nothing of multipath or a
reflected path's Doppler, and a time-differenced carrier's sigma knows nothing of multipath change or an
unflagged slip. Given too much weight, such measurements steer the velocities and displacements, and the
graph does worse with them than with pseudoranges alone (seen on city phone logs). Each kind can be checked
without truth and without a solve: at every epoch its measurements share four unknowns, ``b = g . x + c``
(``g`` the line-of-sight gradient; Doppler: the velocity and the clock drift; carrier: the displacement and
the carrier-clock change), so with more than four satellites the epoch's residuals show how noisy the kind
is against its stated sigma:

- per epoch, a Cauchy IRLS fit (``ROBUST_K`` times the epoch's own robust scale), then least squares on what
  it kept (within ``REJECT`` scales), so that a few gross errors, which the graph's robust losses already
  handle, neither steer the fit nor set the scale;
- the residuals ``r`` standardised by their sigma and their leverage ``h`` in the weighted fit,
  ``r / (sigma sqrt(1 - h))``, of epochs with at least ``MIN_REDUNDANCY`` spare measurements;
- their scale ``1.4826 * median|.|`` (the median absolute deviation) pooled over a centred window of epochs
  (the trace's where a window has too few), floored at 1: a sigma is only ever raised, never trusted beyond
  what the file states.

The graph multiplies the kind's sigmas at each epoch by this scale (the robust loss keeps its ``k`` in
sigmas, as an M-estimator with an estimated scale does). :func:`doppler_scale` and :func:`carrier_scale`
give it for a trace's Doppler and carrier factors; which kinds the graph checks is
``GraphConfig.doppler_check_window_s`` / ``carrier_check_window_s`` (why the carrier's is off:
``experiments/results/raw_sigma_check.md``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fusion.estimate.graph.raw_inputs import carrier_rows, doppler_rows_at
from fusion.geometry import line_of_sight
from fusion.trace import Trace

if TYPE_CHECKING:
    from fusion.estimate.graph.inputs import EpochInputs

#: Cauchy width of the one-epoch fits, in units of the epoch's robust scale
ROBUST_K = 2.0
#: measurements beyond this many robust scales are left out of the one-epoch fits' last, least-squares pass
REJECT = 4.0
#: Cauchy-weighted passes of the one-epoch fits (after a least-squares start)
ROBUST_PASSES = 3
#: spare measurements (beyond the four unknowns) an epoch needs to say anything about its kind's noise
MIN_REDUNDANCY = 2
#: MAD to sigma for Gaussian errors
MAD_TO_SIGMA = 1.4826


def row_medians(x: np.ndarray) -> np.ndarray:
    """(R,) the median of each row of x (R,C), ignoring NaN (all-NaN rows: NaN); one sort, no per-row loop."""
    srt = np.sort(x, axis=1)                     # NaN sort last
    n = np.isfinite(x).sum(axis=1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[:, None], axis=1)[:, 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[:, None], axis=1)[:, 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def mad_sigma(x: np.ndarray) -> float:
    """``1.4826 * median|x - median(x)|`` of the finite values of x (any shape): a Gaussian's sigma, robustly."""
    x = x[np.isfinite(x)]
    return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x))))


def weighted_lsq(A: np.ndarray, b: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every epoch's weighted least-squares fit of ``b = A x``: x (E,U) and (A^T W A)^-1 (E,U,U). A (E,S,U),
    b, w (E,S) (weight 0: not used); a 1e-9 ridge keeps epochs with too few rows (or none) invertible."""
    Aw = A * w[..., None]
    N_inv = np.linalg.inv(np.swapaxes(Aw, 1, 2) @ A + 1e-9 * np.eye(A.shape[2]))
    return (N_inv @ (Aw * b[..., None]).sum(axis=1)[..., None])[..., 0], N_inv


def _standardised(A: np.ndarray, b: np.ndarray, sig: np.ndarray, use: np.ndarray, w: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One weighted least-squares pass of every epoch: z (E,S) the residuals / sigma / sqrt(1 - leverage)
    (NaN where not used) and each epoch's robust scale (E,1) of them. A (E,S,4), b, sig, w (E,S), use (E,S)."""
    x, N_inv = weighted_lsq(A, b, w)
    lev = w * ((A @ N_inv) * A).sum(axis=2)
    r = b - (A @ x[..., None])[..., 0]
    z = np.where(use, r / sig / np.sqrt(np.clip(1.0 - lev, 0.05, None)), np.nan)
    return z, np.maximum(MAD_TO_SIGMA * row_medians(np.abs(z)), 1e-6)[:, None]


def epoch_fit(grad: np.ndarray, b: np.ndarray, sigma: np.ndarray, use: np.ndarray,
              groups: np.ndarray | None = None) -> np.ndarray:
    """Standardised residuals of each epoch's robust fit of ``b = grad . x + c`` (one ``c`` per value of
    ``groups`` (E,S) int, e.g. a clock per signal; None: one for all).

    grad (E,S,3), b (E,S), sigma (E,S) > 0 where used, use (E,S) bool. Returns z (E,S): residual / sigma /
    sqrt(1 - leverage) (a fit's residuals are smaller than its errors by that much), NaN where not used or
    where the epoch has fewer than its unknowns + MIN_REDUNDANCY measurements."""
    E, S = b.shape
    if groups is None:
        onehot = np.ones((E, S, 1))
    else:
        onehot = (groups[..., None] == np.unique(groups[use])).astype(float) if use.any() else np.ones((E, S, 1))
    unknowns = 3 + (onehot * use[..., None]).any(axis=1).sum(axis=1)
    use = use & (use.sum(axis=1) >= unknowns + MIN_REDUNDANCY)[:, None]
    A = np.where(use[..., None], np.concatenate([grad, onehot], axis=2), 0.0)
    b = np.where(use, b, 0.0)
    sig = np.where(use, sigma, 1.0)
    w0 = np.where(use, 1.0 / sig ** 2, 0.0)
    z, scale = _standardised(A, b, sig, use, w0)
    for _ in range(ROBUST_PASSES):
        z, scale = _standardised(A, b, sig, use, np.where(use, w0 / (1.0 + (z / (ROBUST_K * scale)) ** 2), 0.0))
    # the last pass is least squares on the measurements the robust fit kept: a down-weighting fit hugs its
    # inliers, and its residuals would understate their spread
    z, _ = _standardised(A, b, sig, use, np.where(use & (np.abs(z) <= REJECT * scale), w0, 0.0))
    return z


def windowed_scale(z: np.ndarray, window: int, min_count: int = 30) -> np.ndarray:
    """(E,) ``1.4826 * median|z|`` over the standardised residuals z (E,S) (NaN: none) of a centred window of
    ``window`` epochs (pooled: a single epoch's handful of residuals gives a biased median), the trace's where
    a window holds fewer than ``min_count``, floored at 1 (1 where nothing is known). The windows are centred
    every ``window // 8`` epochs and interpolated between (a window's median moves little in an eighth of it)."""
    E, S = z.shape
    half = max(window // 2, 0)
    centres = np.unique(np.r_[np.arange(0, E, max(window // 8, 1)), E - 1])
    pad = np.concatenate([np.full((half, S), np.nan), np.abs(z), np.full((half, S), np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half + 1, axis=0)[centres].reshape(len(centres), -1)
    finite = np.isfinite(z)
    overall = np.median(np.abs(z[finite])) if finite.sum() >= min_count else np.nan
    med = np.where(np.isfinite(win).sum(axis=1) >= min_count, row_medians(win), overall)
    out = MAD_TO_SIGMA * np.interp(np.arange(E), centres, med) if np.isfinite(med).all() else np.ones(E)
    return np.maximum(out, 1.0)


def window_epochs(t: np.ndarray, window_s: float) -> int:
    """A window of ``window_s`` seconds in epochs of the times t (E,) [s], by their median interval."""
    dt = np.diff(t)
    step = float(np.median(dt[dt > 0])) if (dt > 0).any() else 1.0
    return int(round(window_s / step))


def kind_scale(grad: np.ndarray, b: np.ndarray, sigma: np.ndarray, use: np.ndarray, t: np.ndarray,
               window_s: float, groups: np.ndarray | None = None) -> np.ndarray:
    """(E,) the factor >= 1 on one measurement kind's sigmas at each epoch (module docstring). grad (E,S,3),
    b (E,S), sigma (E,S), use (E,S) bool, groups (E,S) int or None as :func:`epoch_fit`; t (E,) epoch times
    [s]; window_s the window's full length [s]."""
    return windowed_scale(epoch_fit(grad, b, sigma, use, groups), window_epochs(t, window_s))


def padded_rows(shape: tuple[int, int], ks: np.ndarray, ss: np.ndarray, grad: np.ndarray, b: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """grad (N,3) and b (N,) of the measurements at (ks, ss) laid out as (E,S,3) and (E,S)."""
    G, B = np.zeros(shape + (3,)), np.zeros(shape)
    G[ks, ss], B[ks, ss] = grad, b
    return G, B


def doppler_system(trace: Trace, inp: EpochInputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Doppler factors of the kept epochs as per-epoch linear systems ``b = G . v + drift`` at the initial
    positions: G (E,S,3), b (E,S) (zero where unused) and use (E,S) bool."""
    use = inp.raw.doppler & inp.keep[:, None]
    ks, ss = np.nonzero(use)
    G, B = padded_rows(use.shape, ks, ss, *doppler_rows_at(trace, inp.raw, inp.init_pos, ks, ss))
    return G, B, use


def doppler_fit(trace: Trace, inp: EpochInputs) -> np.ndarray:
    """z (E,S) of :func:`epoch_fit` for the Doppler factors of the kept epochs (velocity and clock drift, at the
    initial positions, with the sigmas ``inp.raw.prr_sigma``); NaN where none."""
    G, B, use = doppler_system(trace, inp)
    return epoch_fit(G, B, inp.raw.prr_sigma, use)


def doppler_scale(trace: Trace, inp: EpochInputs, window_s: float) -> np.ndarray:
    """(E,) the factor on each epoch's Doppler sigmas (``inp.raw.prr_sigma``) from the Doppler factors' own
    one-epoch fits."""
    return windowed_scale(doppler_fit(trace, inp), window_epochs(trace.t_ms / 1000.0, window_s))


def carrier_scale(trace: Trace, inp: EpochInputs, window_s: float) -> np.ndarray:
    """(E,) the factor on each epoch's time-differenced carrier sigmas (``inp.raw.tdcp_sigma``) from the
    carrier factors' own one-epoch fits (displacement and carrier-clock change, at the linearisation point)."""
    raw = inp.raw
    use = (raw.tdcp_prev >= 0) & inp.keep[:, None]
    use[1:] &= inp.keep[:-1, None]
    kk, ss = np.nonzero(use)
    grad, measured = carrier_rows(trace, raw, inp.init_pos if raw.lin_pos is None else raw.lin_pos, kk, ss)
    G, B = padded_rows(use.shape, kk, ss, grad, measured)
    return kind_scale(G, B, raw.tdcp_sigma, use, trace.t_ms / 1000.0, window_s)


def pseudorange_scale(trace: Trace, inp: EpochInputs, window_s: float) -> np.ndarray:
    """(E,) the factor on each epoch's pseudorange sigmas (``inp.sigma``, learned or physical) from the
    pseudoranges' own one-epoch fits (position and a clock per signal, at the initial positions, the
    slot-noise bias removed)."""
    use = inp.sel & inp.keep[:, None] & np.isfinite(trace.pr) & (inp.sigma > 0)
    rng, los = line_of_sight(trace.sat_pos, inp.init_pos)
    b = np.where(use, trace.pr - np.nan_to_num(inp.pr_bias) - rng, 0.0)
    return kind_scale(-los, b, np.where(use, inp.sigma, 1.0), use, trace.t_ms / 1000.0, window_s, trace.signal)


def raise_pseudorange_sigmas(trace: Trace, inp: EpochInputs, window_s: float) -> dict:
    """Multiply ``inp.sigma`` by :func:`pseudorange_scale` (``window_s`` <= 0: not), in place. Returns
    counts for the run's report (pseudoranges whose sigma was raised by more than 5 %)."""
    if window_s <= 0 or not inp.sel.any():
        return {}
    f = pseudorange_scale(trace, inp, window_s)
    inp.sigma = np.where(inp.sel, inp.sigma * f[:, None], inp.sigma)
    return {"pseudorange_sigmas_raised": int((inp.sel & (f[:, None] > 1.05)).sum())}


def raise_raw_sigmas(trace: Trace, inp: EpochInputs, doppler_window_s: float, carrier_window_s: float) -> dict:
    """Multiply ``inp.raw``'s Doppler sigmas by :func:`doppler_scale` (``doppler_window_s`` <= 0: not) and its
    carrier sigmas by :func:`carrier_scale` (``carrier_window_s`` <= 0: not), in place. Returns counts for the
    run's report: the measurements whose sigma was raised (by more than 5 %) per kind."""
    raw, counts = inp.raw, {}
    if raw is None:
        return counts
    if doppler_window_s > 0 and raw.doppler.any():
        f = doppler_scale(trace, inp, doppler_window_s)
        raw.prr_sigma = np.where(raw.doppler, raw.prr_sigma * f[:, None], raw.prr_sigma)
        counts["doppler_sigmas_raised"] = int((raw.doppler & (f[:, None] > 1.05)).sum())
    if carrier_window_s > 0 and raw.has_tdcp:
        tdcp = raw.tdcp_prev >= 0
        f = carrier_scale(trace, inp, carrier_window_s)
        raw.tdcp_sigma = np.where(tdcp, raw.tdcp_sigma * f[:, None], raw.tdcp_sigma)
        counts["carrier_sigmas_raised"] = int((tdcp & (f[:, None] > 1.05)).sum())
    return counts
