"""Satellite states from precise products: SP3 orbits (Lagrange interpolation) and clocks from a
RINEX clock file where it covers the time, else from the SP3 file's own clock column.

Conventions and what is left out (all at the metre / nanosecond level that broadcast data has
anyway): SP3 positions are the satellite's centre of mass, not its antenna phase centre (no
PCO applied, up to ~1-2 m along the radial for some satellites); precise clocks refer to the
ionosphere-free code combination, so single-frequency pseudoranges need the broadcast group
delay (TGD / BGD) - taken from the broadcast navigation when given, else left out (a few ns);
the relativistic periodic term, excluded from precise clocks by convention, is added
(``-2 r.v / c^2``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.errors import DataError
from fusion.geometry import C_LIGHT
from fusion.io.clk import PreciseClocks
from fusion.io.sp3 import Sp3Orbits
from fusion.nav.sat_states import group_delay, select_record

#: Lagrange interpolation uses this many SP3 samples around the query (order 9 over 5-min samples
#: is at the millimetre level for GNSS orbits).
N_LAGRANGE = 10
_LETTER_CTYPE = {"G": 1, "R": 3, "J": 4, "C": 5, "E": 6}
_SVID_OFFSET = {"J": 192}


@dataclass
class PreciseOrbits:
    """An SP3 file (positions, clocks) and optionally a finer clock file."""

    sp3: Sp3Orbits
    clk: PreciseClocks | None = None

    def systems(self) -> set[str]:
        return {str(s)[0] for s in self.sp3.sats if str(s)[0] in _LETTER_CTYPE}


def sat_ids(names: np.ndarray) -> np.ndarray:
    """SP3 / CLK names (``"G01"``, ``"J02"``) -> (N,) sat_id (-1 for systems we do not model)."""
    out = np.full(len(names), -1, np.int64)
    for k, n in enumerate(names):
        n = str(n)
        if n[0] in _LETTER_CTYPE and n[1:].strip().isdigit():
            out[k] = _LETTER_CTYPE[n[0]] * 1000 + int(n[1:]) + _SVID_OFFSET.get(n[0], 0)
    return out


def _columns(names: np.ndarray, sat_id: np.ndarray) -> np.ndarray:
    """(N,) column of each row's satellite in a product with satellites ``names``, -1 if absent."""
    ids = sat_ids(names)
    order = np.argsort(ids)
    pos = np.clip(np.searchsorted(ids[order], sat_id), 0, ids.size - 1)
    col = order[pos]
    return np.where(ids[col] == sat_id, col, -1)


#: A Lagrange window's samples may lie at most this far apart [s], or this many times the file's usual spacing
#: where that is wider (a regular 30-min file). Holes across a 5-min CODE file's own samples cost 1 cm at 30 min,
#: 0.4 m at 60 min and 350 m at 150 min (an hours-long hole put the Pixel5 kilometres off;
#: experiments/results/precise_holes.md).
MAX_STEP_S = 1800.0
MAX_GAP_SPACINGS = 1.5


def _lagrange(t_ms: np.ndarray, t_ref: np.ndarray, values: np.ndarray, col: np.ndarray,
              t_q: np.ndarray) -> np.ndarray:
    """Interpolate (T, N, k) ``values`` of column ``col`` (Q,) at times ``t_q`` (Q,) [s since
    t_ms[0]] with :data:`N_LAGRANGE` samples; NaN where any sample is missing, the file has fewer, the
    window holds a hole (:data:`MAX_STEP_S`) or the time is outside."""
    T = t_ms.size
    if T < N_LAGRANGE:
        return np.full((t_q.size, values.shape[-1]), np.nan)
    start = np.clip(np.searchsorted(t_ref, t_q) - N_LAGRANGE // 2, 0, T - N_LAGRANGE)
    win = start[:, None] + np.arange(N_LAGRANGE)[None, :]                    # (Q, n)
    vw = values[win, col[:, None]]                                           # (Q, n, k)
    out = np.einsum("qn,qnk->qk", _lagrange_weights(t_ref, start, N_LAGRANGE, t_q), vw)
    steps = np.diff(t_ref)
    widest = max(MAX_STEP_S, MAX_GAP_SPACINGS * float(np.median(steps)))
    ok = (t_q >= t_ref[0]) & (t_q <= t_ref[-1]) & (_widest_step(steps, start) <= widest)
    return np.where(ok[:, None], out, np.nan)


def _widest_step(steps: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(Q,) the widest of the N_LAGRANGE - 1 steps (T-1,) between the samples of each window from ``start`` (Q,)."""
    return steps[start[:, None] + np.arange(N_LAGRANGE - 1)[None, :]].max(axis=1)


def _lagrange_weights(t_ref: np.ndarray, start: np.ndarray, n: int, t_q: np.ndarray) -> np.ndarray:
    """(Q, n) Lagrange basis weights prod_{m != j} (t_q - t_m) / (t_j - t_m) of the n samples from each
    ``start`` (Q,). The numerators are prefix times suffix products (exact at a sample time, where a
    full product over (t_q - t_j) would divide by zero); the denominators depend on the window alone,
    so they are computed once per distinct window (a day of 5-min SP3 has < 300) instead of per query."""
    diff = t_q[:, None] - t_ref[start[:, None] + np.arange(n)]               # (Q, n)
    ones = np.ones((len(t_q), 1))
    prefix = np.cumprod(np.hstack([ones, diff[:, :-1]]), axis=1)
    suffix = np.cumprod(np.hstack([ones, diff[:, :0:-1]]), axis=1)[:, ::-1]
    starts, which = np.unique(start, return_inverse=True)
    tw = t_ref[starts[:, None] + np.arange(n)]                               # (W, n)
    gap = tw[:, :, None] - tw[:, None, :]
    gap[:, np.arange(n), np.arange(n)] = 1.0
    return prefix * suffix / np.prod(gap, axis=2)[which]


def precise_states(prec: PreciseOrbits, sat_id: np.ndarray, signal: np.ndarray, t_ms: np.ndarray,
                   dt_s: np.ndarray, nav=None) -> dict[str, np.ndarray]:
    """States from SP3 (+ CLK); same shapes and outputs as
    :func:`fusion.nav.sat_states.broadcast_states`. ``nav``: optional broadcast
    :class:`~fusion.io.rinex_nav.Navigation` for the group delays."""
    sp3 = prec.sp3
    if sp3.clock is None:
        raise DataError(f"{sp3.source}: SP3 orbits were read without clocks")
    sat_id, t_ms = np.asarray(sat_id, np.int64), np.asarray(t_ms, np.int64)
    dt_s = np.broadcast_to(np.asarray(dt_s, float), sat_id.shape)
    col = _columns(sp3.sats, sat_id)
    t0 = sp3.t_ms[0]
    t_ref = (sp3.t_ms - t0) * 1e-3
    t_q = (t_ms - t0) * 1e-3 + dt_s
    c = np.maximum(col, 0)
    pos = _lagrange(sp3.t_ms, t_ref, sp3.pos, c, t_q)
    vel = (_lagrange(sp3.t_ms, t_ref, sp3.pos, c, t_q + 0.5) - _lagrange(sp3.t_ms, t_ref, sp3.pos, c, t_q - 0.5))
    clock, drift = _clock(prec, sat_id, t_ms, dt_s, c, t_q)
    clock = clock - 2.0 * np.sum(pos * vel, axis=1) / C_LIGHT**2 - _group_delay(nav, sat_id, signal, t_ms)
    ok = (col >= 0) & np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1) & np.isfinite(clock)
    z = lambda a: np.where(ok.reshape(ok.shape + (1,) * (a.ndim - 1)), a, 0.0)  # noqa: E731
    return {"pos": z(pos), "vel": z(vel), "clock_s": z(clock), "clock_drift": z(drift), "ok": ok}


def _clock(prec: PreciseOrbits, sat_id, t_ms, dt_s, sp3_col, t_q) -> tuple[np.ndarray, np.ndarray]:
    """(N,) clock [s] and drift [s/s]: linear interpolation in the CLK file where it covers the
    time, else in the SP3 clock column."""
    sp3 = prec.sp3
    clock, drift = _linear(sp3.t_ms, sp3.clock, sp3_col, t_ms, dt_s)
    if prec.clk is not None:
        ccol = _columns(prec.clk.sats, sat_id)
        c2, d2 = _linear(prec.clk.t_ms, prec.clk.bias, np.maximum(ccol, 0), t_ms, dt_s)
        use = (ccol >= 0) & np.isfinite(c2)
        clock, drift = np.where(use, c2, clock), np.where(use, d2, drift)
    return clock, drift


def _linear(t_ref_ms: np.ndarray, values: np.ndarray, col: np.ndarray, t_ms: np.ndarray, dt_s: np.ndarray):
    """Linear interpolation of (T, N) ``values`` at column ``col`` (Q,); NaN outside or missing."""
    t_q = (t_ms - t_ref_ms[0]) * 1e-3 + dt_s
    t_ref = (t_ref_ms - t_ref_ms[0]) * 1e-3
    hi = np.clip(np.searchsorted(t_ref, t_q), 1, max(t_ref.size - 1, 1))
    lo = hi - 1
    span = t_ref[hi] - t_ref[lo]
    v0, v1 = values[lo, col], values[hi, col]
    slope = (v1 - v0) / np.where(span > 0, span, np.nan)
    val = v0 + slope * (t_q - t_ref[lo])
    inside = (t_q >= t_ref[0]) & (t_q <= t_ref[-1])
    return np.where(inside, val, np.nan), np.where(inside, slope, np.nan)


def _group_delay(nav, sat_id: np.ndarray, signal: np.ndarray, t_ms: np.ndarray) -> np.ndarray:
    """(N,) broadcast group delay [s] of each row's signal (0 without navigation or record)."""
    out = np.zeros(sat_id.shape)
    if nav is None or len(nav.kepler) == 0:
        return out
    idx = select_record(nav.kepler, np.asarray(sat_id, np.int64), np.asarray(signal), np.asarray(t_ms, np.int64))
    ok = idx >= 0
    out[ok] = group_delay(nav.kepler, idx[ok], np.asarray(signal)[ok])
    return out
