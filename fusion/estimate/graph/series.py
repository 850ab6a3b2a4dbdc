"""Helpers over per-epoch time series: fill gaps by interpolation or from another series, robust rolling
medians."""
from __future__ import annotations

import warnings

import numpy as np


def interp_rows(t: np.ndarray, rows: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Fill rows (E,k) where ``ok`` (E,) is False by linear interpolation in ``t`` (E,) (ends held
    constant)."""
    out = rows.copy()
    if ok.all():
        return out
    for j in range(rows.shape[1]):  # k columns, not epochs
        out[~ok, j] = np.interp(t[~ok], t[ok], rows[ok, j])
    return out


def where_solved(pos: np.ndarray, other) -> np.ndarray:
    """``pos`` (E,3) where its row is finite, else ``other`` ((E,3) or a scalar): an unsolved epoch takes the
    fallback."""
    return np.where(np.isfinite(pos).all(axis=1)[:, None], pos, other)


def rolling_nanmedian(x: np.ndarray, w: int) -> np.ndarray:
    """Median of x (E,) over a centred window of 2w+1 samples, ignoring NaN (all-NaN -> NaN)."""
    pad = np.concatenate([np.full(w, np.nan), x, np.full(w, np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * w + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows -> NaN, on purpose
        return np.nanmedian(win, axis=1)
