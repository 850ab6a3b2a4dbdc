"""Which Doppler and carrier-phase measurements enter the fused graph, computed for the whole trace
without Python loops over epochs.

Doppler: every real slot flagged ``prr_ok`` above the elevation mask, at epochs with a clock
variable (the drift key is tied to it), with the constant-velocity motion model only (the factor
constrains velocity states). Carrier: time-differenced between consecutive epochs ``k - 1`` and
``k`` of the same satellite and signal, both ``adr_ok``, no ``adr_slip`` at ``k``, and only where
the clock chain links ``k`` directly to ``k - 1`` (no receiver clock reset, no motion gap).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import doppler_rows, tdcp_measured
from fusion.trace import Trace, cn0_sigma_factor, count_skip, satellite_counts


#: Fewest time-differenced carrier measurements an epoch pair needs to get any (4 unknowns + 1 check).
MIN_TDCP_SATS = 5


@dataclass
class RawInputs:
    """E epochs, S slots. doppler (E,S) bool slots with a Doppler factor; prr_sigma (E,S) [m/s];
    use_drift: some Doppler is used (its clock chain needs drift states); tdcp_prev (E,S) int: the
    slot of epoch k-1 whose carrier phase is differenced with slot s of epoch k (-1: none);
    tdcp_sigma (E,S) [m]; counts: factors used and measurements left out, by reason; lin_pos (E,3) the
    positions the carrier factors are linearised at (None: the graph's initial positions); prr_bias
    (E,S) [m/s] subtracted from each pseudorange rate (a learned Doppler bias; None: 0)."""

    doppler: np.ndarray
    prr_sigma: np.ndarray
    tdcp_prev: np.ndarray
    tdcp_sigma: np.ndarray
    use_drift: bool = False
    counts: dict = field(default_factory=dict)
    lin_pos: np.ndarray | None = None
    prr_bias: np.ndarray | None = None

    def __post_init__(self):
        if self.prr_bias is None:
            self.prr_bias = np.zeros(self.doppler.shape)

    @property
    def has_tdcp(self) -> bool:
        return bool((self.tdcp_prev >= 0).any())


def cn0_scale(trace: Trace, ref_dbhz: float) -> np.ndarray:
    """(E,S) factor >= 1 on a measurement's sigma for its C/N0 below ``ref_dbhz``: 10^((ref - C/N0) / 20),
    the amplitude-noise scaling of a tracking loop (1 where C/N0 is unknown, <= 0, or ``ref_dbhz`` <= 0)."""
    if trace.cn0 is None or ref_dbhz <= 0:
        return np.ones(trace.mask.shape)
    cn0 = np.asarray(trace.cn0, float)
    return np.where(cn0 > 0, cn0_sigma_factor(cn0, ref_dbhz), 1.0)


def doppler_slots(trace: Trace, above: np.ndarray, has_clock: np.ndarray, cfg: GraphConfig,
                  counts: dict) -> tuple[np.ndarray, np.ndarray]:
    """(E,S) bool Doppler slots used and (E,S) their sigmas [m/s]; above (E,S) bool slots over the
    elevation mask, has_clock (E,) bool epochs with a clock variable."""
    ok = trace.mask & trace.prr_ok
    sigma = np.sqrt((cfg.prr_sigma_scale * trace.prr_sigma * cn0_scale(trace, cfg.prr_cn0_ref_dbhz)) ** 2
                    + cfg.prr_sigma_floor_mps ** 2)
    bad_sigma = ok & ~(np.isfinite(sigma) & (sigma > 0))
    count_skip(counts, "doppler_bad_sigma", bad_sigma)
    # a zero satellite velocity means "unknown" in a Trace: a Doppler factor would then silently
    # read the satellite's motion as the receiver's
    no_sat_vel = ok & ~bad_sigma & ~np.any(trace.sat_vel != 0, axis=-1)
    count_skip(counts, "doppler_without_satellite_velocity", no_sat_vel)
    use = ok & ~bad_sigma & ~no_sat_vel & above & has_clock[:, None]
    if cfg.doppler_min_sats > 0:
        few = satellite_counts(trace.sat_id, use) < cfg.doppler_min_sats
        count_skip(counts, "doppler_few_satellites", use & few[:, None])
        use = use & ~few[:, None]
    if cfg.motion != "cv":
        count_skip(counts, "doppler_without_velocity_states", use)
        use = np.zeros_like(use)
    counts["doppler_factors"] = int(use.sum())
    return use, np.where(use, sigma, 1.0)


def tdcp_pairs(trace: Trace, above: np.ndarray, clock_link: np.ndarray, cfg: GraphConfig,
               counts: dict) -> tuple[np.ndarray, np.ndarray]:
    """(E,S) int slot of epoch k-1 paired with slot s of epoch k (-1: none) and (E,S) sigma [m] of
    the difference. above (E,S) bool; clock_link (E,) int from the clock chain."""
    E, S = trace.mask.shape
    ok = trace.mask & trace.adr_ok & np.isfinite(trace.adr_sigma) & (trace.adr_sigma >= 0)
    count_skip(counts, "carrier_bad_sigma", trace.mask & trace.adr_ok & ~ok)
    prev = np.full((E, S), -1)
    if E < 2:
        return prev, np.ones((E, S))
    ident = trace.sat_id.astype(np.int64) * 64 + trace.signal
    cur_ok = ok[1:] & above[1:] & ~trace.adr_slip[1:]
    same = (ident[1:, :, None] == ident[:-1, None, :]) & ok[:-1, None, :] & above[:-1, None, :]
    found = same.any(axis=2) & cur_ok
    chained = (clock_link[1:] == np.arange(E - 1))[:, None]
    count_skip(counts, "carrier_chain_broken_by_clock", found & ~chained)
    use = found & chained
    # a displacement and a carrier clock change are four unknowns: with fewer than MIN_TDCP_SATS
    # differences an epoch pair's carrier factors would leave them singular (or unchecked by the
    # robust loss), so the pair keeps none; nor with fewer distinct satellites than cfg.tdcp_min_distinct_sats
    few = use.sum(axis=1) < MIN_TDCP_SATS
    if cfg.tdcp_min_distinct_sats > 0:
        few |= satellite_counts(trace.sat_id[1:], use) < cfg.tdcp_min_distinct_sats
    count_skip(counts, "carrier_too_few_satellites", use & few[:, None])
    use &= ~few[:, None]
    prev[1:] = np.where(use, same.argmax(axis=2), -1)
    prev_sigma = np.take_along_axis(trace.adr_sigma[:-1], np.maximum(prev[1:], 0), axis=1)
    sigma = np.ones((E, S))
    sigma[1:] = np.sqrt(trace.adr_sigma[1:] ** 2 + prev_sigma ** 2 + cfg.tdcp_sigma_floor_m ** 2)
    if cfg.tdcp_cn0_ref_dbhz > 0:
        # the weaker end of the pair sets the difference's C/N0 factor (a reflected arc reads low C/N0)
        weak = cn0_scale(trace, cfg.tdcp_cn0_ref_dbhz)
        sigma[1:] *= np.maximum(weak[1:], np.take_along_axis(weak[:-1], np.maximum(prev[1:], 0), axis=1))
    counts["tdcp_factors"] = int(use.sum())
    return prev, np.where(prev >= 0, sigma, 1.0)


def raw_inputs(trace: Trace, el: np.ndarray, elev_mask_deg: float, has_clock: np.ndarray,
               clock_link: np.ndarray, cfg: GraphConfig, use_doppler: bool = True,
               use_carrier: bool = True) -> RawInputs:
    """The Doppler and carrier factors of a trace (none where the trace lacks the fields or the
    options switch them off). el (E,S) elevations [deg] at the initial positions; has_clock (E,)
    bool; clock_link (E,) int (see :class:`fusion.estimate.graph.clock.ClockChain`)."""
    E, S = trace.mask.shape
    above = el >= elev_mask_deg
    counts: dict = {}
    doppler, prr_sigma = np.zeros((E, S), bool), np.ones((E, S))
    if use_doppler and trace.has_doppler:
        doppler, prr_sigma = doppler_slots(trace, above, has_clock, cfg, counts)
    prev, tdcp_sigma = np.full((E, S), -1), np.ones((E, S))
    if use_carrier and trace.has_carrier:
        prev, tdcp_sigma = tdcp_pairs(trace, above, clock_link, cfg, counts)
    return RawInputs(doppler=doppler, prr_sigma=prr_sigma, tdcp_prev=prev, tdcp_sigma=tdcp_sigma,
                     use_drift=bool(doppler.any()), counts=counts)


def carrier_rows(trace: Trace, raw: RawInputs, lin_pos: np.ndarray, kk: np.ndarray, ss: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The linear model of the time-differenced carrier factors at slots (kk, ss) (N,) (each paired with
    ``raw.tdcp_prev``'s slot of epoch kk - 1), linearised at ``lin_pos`` (E,3): ``measured = grad . u + dq``.
    Returns grad (N,3) and measured (N,) [m] (:func:`fusion.estimate.graph.factors.tdcp_measured`)."""
    prev = raw.tdcp_prev[kk, ss]
    measured, grad = tdcp_measured(trace.adr[kk, ss] - trace.adr[kk - 1, prev], trace.sat_pos[kk - 1, prev],
                                   trace.sat_pos[kk, ss], lin_pos[kk - 1], lin_pos[kk])
    return grad, measured


def doppler_rows_at(trace: Trace, raw: RawInputs, rx: np.ndarray, ks: np.ndarray, ss: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The linear model of the Doppler factors at slots (ks, ss) (N,), their bias removed, seen from ``rx``
    (E,3): ``rhs = grad . v + drift``. Returns grad (N,3) and rhs (N,) [m/s]
    (:func:`fusion.estimate.graph.factors.doppler_rows`)."""
    return doppler_rows(trace.prr[ks, ss] - raw.prr_bias[ks, ss], trace.sat_pos[ks, ss], trace.sat_vel[ks, ss],
                        rx[ks])


def relative_distrust(ratio: np.ndarray, knee: float = 1.0) -> np.ndarray:
    """(E,S) each slot's pseudorange sigma ratio (E,S) (over the physical model's; NaN: none) over its epoch's
    median and over ``knee``, never below 1 (1 where NaN)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # epochs without any learned sigma -> NaN
        return np.maximum(1.0, np.nan_to_num(ratio / np.nanmedian(ratio, axis=1, keepdims=True) / knee, nan=1.0))


def carrier_sigma_by_pseudorange(raw: RawInputs, ratio: np.ndarray, power: float, knee: float = 1.0,
                                  min_count: int = 0) -> tuple[np.ndarray, int]:
    """``raw.tdcp_sigma`` (E,S) [m] raised where a satellite's pseudorange is trusted less than its epoch's others.

    ratio (E,S): each slot's pseudorange sigma over the physical model's (the learned head's multiplier; NaN
    where the slot has none). A reflected signal's carrier follows the reflected path, whose length changes as
    the car turns or the street changes, and nothing in the carrier itself shows it; its pseudorange carries the
    same reflection metres long, which the head reads. :func:`relative_distrust` (``knee``: a code's multipath, a
    little above its epoch's median, leaves the carrier alone), the larger of the pair's two ends, to ``power``,
    multiplies the difference's sigma, at epochs with at least ``min_count`` carrier differences (with fewer, the
    carrier left after the distrust no longer holds the track's shape).
    Returns the sigmas and how many differences had their sigma at least doubled."""
    tdcp = raw.tdcp_prev >= 0
    if power <= 0 or not tdcp.any():
        return raw.tdcp_sigma, 0
    rel = relative_distrust(ratio, knee)
    worse = rel.copy()
    worse[1:] = np.maximum(rel[1:], np.take_along_axis(rel[:-1], np.maximum(raw.tdcp_prev[1:], 0), axis=1))
    enough = tdcp.sum(axis=1, keepdims=True) >= min_count
    f = np.where(tdcp & enough, worse ** power, 1.0)
    return raw.tdcp_sigma * f, int((f >= 2.0).sum())


def doppler_sigma_by_pseudorange(raw: RawInputs, ratio: np.ndarray, power: float, knee: float = 1.0
                                  ) -> tuple[np.ndarray, int]:
    """``raw.prr_sigma`` (E,S) [m/s] x :func:`relative_distrust` ** ``power`` on the Doppler slots: a reflected
    signal's Doppler is the reflected path's rate. Returns the sigmas and how many were at least doubled."""
    if power <= 0 or not raw.doppler.any():
        return raw.prr_sigma, 0
    f = np.where(raw.doppler, relative_distrust(ratio, knee) ** power, 1.0)
    return raw.prr_sigma * f, int((f >= 2.0).sum())
