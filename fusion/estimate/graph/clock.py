"""The receiver clock chain: which epoch's clock each clock is tied to, the expected change along
each link, and where the chain must break (receiver clock resets).

The expected change follows the clock drift seen in the WLS clock series (a robust rolling median
of its rate). Resets come from the loader (``Trace.clock_reset``) or from the WLS clock stepping far
from that drift between consecutive solved epochs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.series import interp_rows, rolling_nanmedian


@dataclass
class ClockChain:
    """E epochs. link (E,) int: index of the epoch whose clock k's clock is tied to (-1: none);
    change_m (E,): expected clock change along that link [m]; sigma_m (E,) its 1-sigma [m];
    n_resets: receiver clock jumps found (a jump seen across several epochs counts once);
    drift_mps (E,): the WLS clock drift [m/s] (starting values of drift states); span_s (E,) the
    time along each link [s]."""

    link: np.ndarray
    change_m: np.ndarray
    sigma_m: np.ndarray
    n_resets: int
    drift_mps: np.ndarray | None = None
    span_s: np.ndarray | None = None


def wls_clock_drift(t: np.ndarray, wls_clock: np.ndarray, pos_link: np.ndarray, window: int) -> np.ndarray:
    """(E,) clock drift [m/s] from the WLS clock series (E,) (NaN where unsolved), robust to single
    bad epochs: rolling median of the rate, interpolated where unknown (0 with no rate at all)."""
    E = t.shape[0]
    rate = np.full(E, np.nan)
    rate[1:] = np.diff(wls_clock) / np.maximum(np.diff(t), 1e-3)
    rate = np.where(pos_link, rate, np.nan)
    drift = rolling_nanmedian(rate, window)
    if not np.isfinite(drift).any():
        return np.zeros(E)
    return np.nan_to_num(interp_rows(t, drift[:, None], np.isfinite(drift))[:, 0])


def find_resets(t: np.ndarray, wls_clock: np.ndarray, drift: np.ndarray, flagged: np.ndarray,
                jump_m: float) -> np.ndarray:
    """(E,) bool epochs where the clock may have jumped: ``flagged`` by the loader, or a WLS clock
    step between consecutive solved epochs more than ``jump_m`` off the drift. A step seen across
    WLS-failed epochs may have happened at any of them, so every epoch from the one after the last
    solved clock up to the detection is marked."""
    reset = np.asarray(flagged, bool).copy()
    solved = np.flatnonzero(np.isfinite(wls_clock))
    if len(solved) > 1:
        a, b = solved[:-1], solved[1:]
        big = np.abs(wls_clock[b] - wls_clock[a] - drift[b] * (t[b] - t[a])) > jump_m
        for lo, hi in zip(a[big] + 1, b[big] + 1):   # a handful of jumps per trace
            reset[lo:hi] = True
    return reset


def clock_chain(t: np.ndarray, wls_clock: np.ndarray, has_clock: np.ndarray, pos_link: np.ndarray,
                flagged: np.ndarray, cfg: GraphConfig) -> ClockChain:
    """Tie each epoch's clock to the previous epoch that has one, unless a reset or a motion-chain
    break lies between them.

    t (E,) [s]; wls_clock (E,) [m] NaN where WLS failed; has_clock (E,) bool epochs with a clock
    variable (>= 1 pseudorange); pos_link (E,) bool motion link to the previous epoch; flagged (E,)
    bool loader-flagged resets.
    """
    E = t.shape[0]
    idx = np.arange(E)
    last_clock = np.maximum.accumulate(np.where(has_clock, idx, -1))
    prev_clock = np.concatenate([[-1], last_clock[:-1]])            # latest clock epoch before k
    drift = wls_clock_drift(t, wls_clock, pos_link, cfg.drift_window)
    reset = find_resets(t, wls_clock, drift, flagged, cfg.clock_jump_m)
    # any reset (or chain break) in (prev_clock, k] breaks the clock link
    breaks = np.cumsum(reset | ~pos_link)
    safe_prev = np.maximum(prev_clock, 0)
    span = t - t[safe_prev]
    link = np.where(has_clock & (prev_clock >= 0) & (breaks == breaks[safe_prev]), prev_clock, -1)
    sigma = cfg.clock_sigma_m + cfg.clock_rw_m * np.sqrt(np.maximum(span, 0.0))
    n_resets = int((reset & ~np.r_[False, reset[:-1]]).sum())
    return ClockChain(link=link, change_m=drift * span, sigma_m=sigma, n_resets=n_resets, drift_mps=drift,
                      span_s=np.maximum(span, 0.0))
