"""Satellite states for measurement rows of any constellation: broadcast navigation (Keplerian
or GLONASS records) or precise SP3 orbits with CLK / SP3 clocks.

Every function takes flat (N,) rows: ``sat_id`` (``1000 * constellationType + svid``), ``signal``
(index into :data:`fusion.trace.SIGNALS`), GPS time ``t_ms + dt_s``; returns ``pos`` (N, 3),
``vel`` (N, 3), ``clock_s`` (N,) (satellite clock offset for *that signal*: relativistic term
included, group delay removed), ``clock_drift`` (N,) [s/s] and ``ok`` (N,) bool (False where no
ephemeris covers the time; the other outputs are zero there).

Galileo broadcasts two clocks: I/NAV's (for E1 and E5b) and F/NAV's (for E1 and E5a). Each row
takes its signal's own message, and the other one (with the group delay that makes it give the
same signal clock, :func:`fusion.io.rinex_nav.group_delays`) where its own has no record; such
rows are counted in ``skipped`` as ``galileo_<signal>_from_<message>``.
"""
from __future__ import annotations

import numpy as np

from fusion.io.rinex_nav import Navigation
from fusion.nav.glonass import glonass_state, select_glonass
from fusion.nav.orbits import GpsNav, sat_state, select_ephemeris
from fusion.trace import SIGNALS, count_skip

#: Group-delay class of each signal: 0 L1 / E1 / B1I / B1C / G1, 1 L5 / E5a / B2a, 2 L2 / E5b / B2I.
#: BeiDou's D1 / D2 records (all RINEX 3 carries) give group delays for B1I and B2I only: B1C takes B1I's
#: TGD1, B2a none (:func:`fusion.io.rinex_nav.group_delays`); each signal's own bias state in the graph
#: takes the part common to the satellites, a few nanoseconds per satellite stay.
SIGNAL_CLASS = np.array([1 if s in ("GPS_L5", "GAL_E5A", "QZS_J5", "BDS_B2A") else
                         2 if s in ("GPS_L2", "GAL_E5B", "BDS_B2I", "QZS_J2") else 0 for s in SIGNALS])
#: Signals on the L5 / E5a carrier, whose group delay is ``tgd_l5`` rather than the L1 ``tgd``.
L5_SIGNALS = SIGNAL_CLASS == 1
_TGD_KEY = ("tgd", "tgd_l5", "tgd_l2")
_GAL = 6
_MSG_NAME = ("inav", "fnav")


def _empty(n: int) -> dict[str, np.ndarray]:
    return {"pos": np.zeros((n, 3)), "vel": np.zeros((n, 3)), "clock_s": np.zeros(n),
            "clock_drift": np.zeros(n), "ok": np.zeros(n, bool)}


def _put(out: dict[str, np.ndarray], rows: np.ndarray, st: dict[str, np.ndarray]) -> None:
    for k in ("pos", "vel", "clock_s", "clock_drift"):
        out[k][rows] = st[k]
    out["ok"][rows] = True


def select_record(kepler: GpsNav, sat_id: np.ndarray, signal: np.ndarray, t_ms: np.ndarray,
                  skipped: dict[str, int] | None = None) -> np.ndarray:
    """(N,) Keplerian record per row (-1 where none): the nearest valid one of the row's own
    navigation message (Galileo E5a: F/NAV, other Galileo signals: I/NAV), else of the other
    message (counted in ``skipped``). sat_id, signal, t_ms: (N,)."""
    cls = SIGNAL_CLASS[np.asarray(signal, np.int64)]
    gal = np.asarray(sat_id) // 1000 == _GAL
    want = (gal & (cls == 1)).astype(np.int64)
    idx = select_ephemeris(kepler, sat_id, t_ms, by_sat_id=True, msg=want)
    retry = np.flatnonzero(gal & (idx < 0))
    if retry.size:
        other = select_ephemeris(kepler, sat_id[retry], t_ms[retry], by_sat_id=True, msg=1 - want[retry])
        idx[retry] = other
        if skipped is not None:
            sig = np.asarray(signal)[retry]
            for s in np.unique(sig[other >= 0]):
                used = (other >= 0) & (sig == s)
                count_skip(skipped, f"galileo_{SIGNALS[s]}_from_{_MSG_NAME[1 - want[retry][used][0]]}", used)
    return idx


def group_delay(kepler: GpsNav, idx: np.ndarray, signal: np.ndarray) -> np.ndarray:
    """(N,) group delay [s] that the row's signal subtracts from record ``idx``'s clock."""
    cls = SIGNAL_CLASS[np.asarray(signal, np.int64)]
    p = kepler.params
    return np.choose(cls, [p[k][idx] for k in _TGD_KEY])


def broadcast_states(nav: Navigation, sat_id: np.ndarray, signal: np.ndarray, t_ms: np.ndarray,
                     dt_s: np.ndarray, skipped: dict[str, int] | None = None) -> dict[str, np.ndarray]:
    """States from broadcast records (see module docstring for shapes)."""
    sat_id, t_ms = np.asarray(sat_id, np.int64), np.asarray(t_ms, np.int64)
    signal = np.asarray(signal, np.int64)
    dt_s = np.broadcast_to(np.asarray(dt_s, float), sat_id.shape)
    out = _empty(sat_id.size)
    glo = sat_id // 1000 == 3
    rows = np.flatnonzero(~glo)
    idx = select_record(nav.kepler, sat_id[rows], signal[rows], t_ms[rows], skipped)
    rows, idx = rows[idx >= 0], idx[idx >= 0]
    if rows.size:
        st = sat_state(nav.kepler, idx, t_ms[rows], dt_s[rows])
        # sat_state removes the record's L1-class group delay; other signals take theirs instead.
        st["clock_s"] = st["clock_s"] + nav.kepler.params["tgd"][idx] - group_delay(nav.kepler, idx, signal[rows])
        _put(out, rows, st)
    rows = np.flatnonzero(glo)
    idx = select_glonass(nav.glonass, sat_id[rows], t_ms[rows])
    rows, idx = rows[idx >= 0], idx[idx >= 0]
    if rows.size:
        _put(out, rows, glonass_state(nav.glonass, idx, t_ms[rows], dt_s[rows]))
    return out
