"""Satellite states for measurement rows of any constellation: broadcast navigation (Keplerian
or GLONASS records) or precise SP3 orbits with CLK / SP3 clocks.

Every function takes flat (N,) rows: ``sat_id`` (``1000 * constellationType + svid``), ``signal``
(index into :data:`fusion.trace.SIGNALS`), GPS time ``t_ms + dt_s``; returns ``pos`` (N, 3),
``vel`` (N, 3), ``clock_s`` (N,) (satellite clock offset for *that signal*: relativistic term
included, group delay removed), ``clock_drift`` (N,) [s/s] and ``ok`` (N,) bool (False where no
ephemeris covers the time; the other outputs are zero there).
"""
from __future__ import annotations

import numpy as np

from fusion.io.rinex_nav import Navigation
from fusion.nav.glonass import glonass_state, select_glonass
from fusion.nav.orbits import sat_state, select_ephemeris
from fusion.trace import SIGNALS

#: Signals on the L5 / E5a carrier, whose group delay is ``tgd_l5`` rather than the L1 ``tgd``.
L5_SIGNALS = np.array([s in ("GPS_L5", "GAL_E5A", "QZS_J5") for s in SIGNALS])


def _empty(n: int) -> dict[str, np.ndarray]:
    return {"pos": np.zeros((n, 3)), "vel": np.zeros((n, 3)), "clock_s": np.zeros(n),
            "clock_drift": np.zeros(n), "ok": np.zeros(n, bool)}


def _put(out: dict[str, np.ndarray], rows: np.ndarray, st: dict[str, np.ndarray]) -> None:
    for k in ("pos", "vel", "clock_s", "clock_drift"):
        out[k][rows] = st[k]
    out["ok"][rows] = True


def broadcast_states(nav: Navigation, sat_id: np.ndarray, signal: np.ndarray, t_ms: np.ndarray,
                     dt_s: np.ndarray) -> dict[str, np.ndarray]:
    """States from broadcast records (see module docstring for shapes)."""
    sat_id, t_ms = np.asarray(sat_id, np.int64), np.asarray(t_ms, np.int64)
    dt_s = np.broadcast_to(np.asarray(dt_s, float), sat_id.shape)
    out = _empty(sat_id.size)
    glo = sat_id // 1000 == 3
    rows = np.flatnonzero(~glo)
    idx = select_ephemeris(nav.kepler, sat_id[rows], t_ms[rows], by_sat_id=True)
    rows, idx = rows[idx >= 0], idx[idx >= 0]
    if rows.size:
        st = sat_state(nav.kepler, idx, t_ms[rows], dt_s[rows])
        l5 = L5_SIGNALS[np.asarray(signal)[rows]]
        p = nav.kepler.params
        # sat_state removes the L1-class group delay; L5-class signals take theirs instead.
        st["clock_s"] = st["clock_s"] + np.where(l5, p["tgd"][idx] - p["tgd_l5"][idx], 0.0)
        _put(out, rows, st)
    rows = np.flatnonzero(glo)
    idx = select_glonass(nav.glonass, sat_id[rows], t_ms[rows])
    rows, idx = rows[idx >= 0], idx[idx >= 0]
    if rows.size:
        _put(out, rows, glonass_state(nav.glonass, idx, t_ms[rows], dt_s[rows]))
    return out
