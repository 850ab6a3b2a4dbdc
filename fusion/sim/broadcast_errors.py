"""What a single-frequency receiver's pseudoranges keep after the broadcast corrections: slowly varying range
errors that no residual of one epoch can see.

A phone corrects each pseudorange with the broadcast orbit and clock and the broadcast ionosphere (Klobuchar) and
a troposphere model. What remains is metres that change over tens of minutes, not noise:

- the broadcast orbit and clock error along the line of sight (the signal-in-space range error, SISRE), a
  first-order Gauss-Markov process per satellite with :data:`SISRE_TAU_S`; its size per constellation is the order
  of the published global averages (Montenbruck et al. 2018, "Multi-GNSS signal-in-space range error assessment",
  Adv. Space Res. 61(12): GPS about 0.6 m, GLONASS about 1.8 m, Galileo 0.3 m, BeiDou 1 m);
- the ionosphere the broadcast model misses (it removes about half of the delay): a share of the slant delay
  drawn once per trace, with a smaller spread per satellite for the model's spatial misfit, scaled by
  (f_L1 / f)^2 per signal; it delays the code and advances the carrier;
- the troposphere a model misses: a few per cent of the slant delay, once per trace.

The simulator writes pseudoranges already corrected (its iono / tropo columns cancel exactly), so without this
the only errors of a simulated trace are noise, multipath and reflections: a track tied by carrier phase is then
right to decimetres, where a phone's sits a metre or more off for minutes (``experiments/results/
carrier_calibration.md``). Off by default (``SimConfig.broadcast_errors``); the sizes were set a priori, not tuned.
"""
from __future__ import annotations

import numpy as np

from fusion.io.raw import SIGNAL_CARRIER_HZ
from fusion.trace import SIGNALS

#: 1-sigma SISRE [m] per Android constellationType (sat_id // 1000): GPS, GLONASS, QZSS, BeiDou, Galileo.
SISRE_M = {1: 0.6, 3: 1.8, 4: 0.6, 5: 1.0, 6: 0.3}
#: correlation time of the SISRE [s]: ephemerides are fitted over hours and replaced every one to four hours
SISRE_TAU_S = 3600.0
#: 1-sigma share of the slant ionospheric delay the broadcast model leaves, per trace and per satellite
IONO_SHARE, IONO_SAT_SHARE = 0.3, 0.1
#: 1-sigma share of the slant tropospheric delay a model leaves, per trace
TROPO_SHARE = 0.05

_L1_HZ = SIGNAL_CARRIER_HZ["GPS_L1"]
#: (f_L1 / f)^2 per index of fusion.trace.SIGNALS: the ionosphere's delay on each signal relative to L1
IONO_SCALE = np.array([(_L1_HZ / SIGNAL_CARRIER_HZ.get(s, _L1_HZ)) ** 2 for s in SIGNALS])


def gauss_markov(t_s: np.ndarray, seg_start: np.ndarray, n: int, sigma: np.ndarray, tau_s: float,
                 rng: np.random.Generator) -> np.ndarray:
    """(E, n) stationary first-order Gauss-Markov processes with 1-sigma ``sigma`` (n,) and correlation time
    ``tau_s``, sampled at times t_s (E,) [s], started afresh (from the stationary distribution) at every
    ``seg_start`` (E,) bool (the first epoch is always a start).

    x_k = a_k x_(k-1) + sqrt(1 - a_k^2) w_k with a_k = exp(-dt_k / tau) is, within a segment,
    x_k = A_k * sum_(j<=k) c_j w_j / A_j with A_k the product of the a's so far: running sums instead of a loop over
    the epochs (A_k = exp(-(t_k - t_start) / tau) stays far above underflow for any drive: a day is e^-24)."""
    E = t_s.shape[0]
    w = rng.standard_normal((E, n)) * sigma
    start = np.asarray(seg_start, bool).copy()
    start[:1] = True
    seg = np.cumsum(start) - 1
    since = t_s - t_s[np.flatnonzero(start)][seg]                     # seconds since the segment's start
    a = np.exp(-np.maximum(np.diff(t_s, prepend=t_s[:1]), 0.0) / tau_s)
    c = np.where(start, 1.0, np.sqrt(1.0 - a * a))                      # a start is a stationary draw
    A = np.exp(-since / tau_s)
    run = np.cumsum(c[:, None] * w / A[:, None], axis=0)
    run -= np.vstack([np.zeros((1, n)), run[:-1]])[np.flatnonzero(start)][seg]      # restart per segment
    return A[:, None] * run


def broadcast_range_errors(t_ms: np.ndarray, seg_start: np.ndarray, sat_id: np.ndarray, signal: np.ndarray,
                           mask: np.ndarray, iono: np.ndarray, tropo: np.ndarray, rng: np.random.Generator
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The code and carrier range errors [m] (each (E,K), 0 off ``mask``) the broadcast corrections leave.

    t_ms (E,), seg_start (E,) bool (trace starts); sat_id (E,K) ``1000 * constellationType + svid``; signal (E,K)
    index into SIGNALS; mask (E,K) bool; iono, tropo (E,K) slant delays [m] at L1 (the simulator's model).
    A satellite's SISRE is one process over its whole trace, shared by its signals. The code carries
    SISRE + ionosphere + troposphere residuals, the carrier SISRE - ionosphere + troposphere."""
    E, K = mask.shape
    ids, col = np.unique(np.where(mask, sat_id, 0), return_inverse=True)
    col = col.reshape(E, K)
    sigma = np.array([SISRE_M.get(int(i) // 1000, 1.0) for i in ids])
    sisre = np.take_along_axis(gauss_markov(t_ms * 1e-3, seg_start, ids.size, sigma, SISRE_TAU_S, rng), col, axis=1)
    trace_of = np.cumsum(seg_start) - 1
    n_traces = int(trace_of[-1]) + 1 if E else 0
    share = rng.normal(0.0, IONO_SHARE, n_traces)[trace_of][:, None] \
        + rng.normal(0.0, IONO_SAT_SHARE, (n_traces, ids.size))[trace_of[:, None], col]
    iono_res = share * iono * IONO_SCALE[signal]
    tropo_res = rng.normal(0.0, TROPO_SHARE, n_traces)[trace_of][:, None] * tropo
    code = np.where(mask, sisre + iono_res + tropo_res, 0.0)
    carrier = np.where(mask, sisre - iono_res + tropo_res, 0.0)
    return code, carrier
