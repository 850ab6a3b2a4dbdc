"""The receiver clock drift as the log's own Doppler shows it, for graphs with Doppler.

The graph ties each epoch's clock drift to the previous one by a random walk (``GraphConfig.drift_rw_mps``)
and each clock to the previous clock plus the drift times the interval. A phone's drift, as its Doppler
measures it, can jump far more from one epoch to the next: on the Pixel5 RINEX log it changes by 0.69 m/s per
sqrt(s) while its Dopplers agree with each other to centimetres per second
(``experiments/canyon_doppler_cause.py``), and the jumps do not add up (the clock itself does not wander
that fast). Where an epoch has few Dopplers, a drift that cannot follow the jump pushes it into the velocity,
and the track runs off; a drift walk loose enough to follow it lets the drift wander where few satellites
leave it undetermined.

So the jump gets a variable of its own: each epoch's Doppler sees the drift plus a white jump of that epoch
(:func:`fusion.estimate.graph.keys.doppler_drift_key`, tied to the drift by
:func:`fusion.estimate.graph.factors.doppler_drift_factor_jd`), and the clock integrates the drift without it.
Its size comes from the log: a least-squares fit of velocity and drift to each epoch's Dopplers (at least
``MIN_DOPPLERS``, at the initial positions) gives the drift and its variance; the robust spread of the change
between consecutive fits, per sqrt(s), less the part the fits' own noise explains, is the drift's change
(:func:`drift_change`); what the configured walk leaves of it is the jump (:func:`doppler_jump`). Nothing is
tuned: a log whose drift is as steady as the configured walk keeps the graph it had.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.consistency import doppler_system, mad_sigma, weighted_lsq
from fusion.trace import Trace

if TYPE_CHECKING:
    from fusion.estimate.graph.inputs import EpochInputs

#: Dopplers an epoch needs for its drift to count (four unknowns and two spare)
MIN_DOPPLERS = 6
#: consecutive pairs of such epochs a trace needs for an estimate
MIN_PAIRS = 30
#: epochs count whose fit knows the drift to this (1 sigma) [m/s] or better: where a street leaves only high
#: satellites the drift and the vertical velocity are hard to tell apart, and such an epoch's drift says
#: nothing of the clock (twice the default walk, GraphConfig.drift_rw_mps, so that a jump beyond it shows
#: above the fits' noise)
KNOWN_SD_MPS = 0.4


def epoch_drifts(trace: Trace, inp: EpochInputs) -> tuple[np.ndarray, np.ndarray]:
    """(E,) each kept epoch's clock drift [m/s] from a weighted least-squares fit of velocity and drift to its
    Doppler factors (``inp.raw``, at least ``MIN_DOPPLERS``), and (E,) its variance [(m/s)^2] scaled by the
    fit's residuals where they exceed its sigmas (a-posteriori variance factor, floored at 1): NaN elsewhere.
    Least squares, not a robust fit: a reflected path's Doppler left in raises the variance with the residuals,
    where a robust fit would set it aside, report a small variance and still leave part of it in the drift.
    Epochs whose Dopplers span fewer directions (two frequencies of few satellites) get a huge variance, and
    :func:`drift_change` leaves them out."""
    G, b, use = doppler_system(trace, inp)
    enough = use.sum(axis=1) >= MIN_DOPPLERS
    use &= enough[:, None]
    A = np.where(use[..., None], np.concatenate([G, np.ones(use.shape + (1,))], axis=2), 0.0)
    w = np.where(use, 1.0 / inp.raw.prr_sigma ** 2, 0.0)
    x, cov = weighted_lsq(A, np.where(use, b, 0.0), w)
    r = b - (A @ x[..., None])[..., 0]
    s0 = np.maximum((w * r * r).sum(axis=1) / np.maximum(use.sum(axis=1) - 4, 1), 1.0)
    return np.where(enough, x[:, 3], np.nan), np.where(enough, cov[:, 3, 3] * s0, np.nan)


def drift_change(trace: Trace, inp: EpochInputs) -> float | None:
    """The drift's change from one epoch to the next [m/s per sqrt(s)] beyond what the one-epoch fits' noise
    explains, from consecutive epochs of one motion chain and no clock reset whose fits know
    the drift to ``KNOWN_SD_MPS``; None where fewer than ``MIN_PAIRS`` such pairs exist."""
    if inp.raw is None or not inp.raw.doppler.any():
        return None
    drift, var = epoch_drifts(trace, inp)
    drift = np.where(var <= KNOWN_SD_MPS ** 2, drift, np.nan)
    dt = np.diff(trace.t_ms / 1000.0)
    pair = np.isfinite(drift[1:]) & np.isfinite(drift[:-1]) & inp.pos_link[1:] & (dt > 0) & ~trace.clock_reset[1:]
    if pair.sum() < MIN_PAIRS:
        return None
    root = np.sqrt(dt[pair])
    change = (drift[1:] - drift[:-1])[pair] / root
    spread = mad_sigma(change)
    noise = np.median((var[1:] + var[:-1])[pair] / dt[pair])
    return float(np.sqrt(max(spread ** 2 - noise, 0.0)))


def doppler_jump(change: float | None, cfg: GraphConfig, interval_s: float = 1.0) -> float:
    """The white jump [m/s] of the drift each epoch's Doppler sees beyond the clock's walk, from the log's drift
    ``change`` [m/s per sqrt(s)] (:func:`drift_change`) between epochs ``interval_s`` apart: what of
    ``change^2 = drift_rw_mps^2 + 2 jump^2 / interval_s`` the configured walk leaves (a white jump shows twice
    in a difference, and the change is per sqrt(s)); 0 where the walk explains it all or nothing is known."""
    if change is None:
        return 0.0
    return float(np.sqrt(max(change ** 2 - cfg.drift_rw_mps ** 2, 0.0) * interval_s / 2.0))
