"""Per-satellite context the network reads beside (residual, line of sight): what a satellite's
measurement looked like before this epoch and what the phone said about it.

All of it comes from the measurements and the WLS solution of the same trace (no truth):

- ``pr_sigma``: the phone's reported pseudorange uncertainty [m] (``rawPrUncM``);
- ``cn0``: C/N0 [dB-Hz] where the source has it (0 = unknown);
- ``dres``: change of the satellite's WLS post-fit residual since the previous epoch [m] (a jump is
  what multipath or a reflection appearing looks like), with ``prev_ok`` saying it exists;
- ``arc_s``: seconds since the satellite (this signal) was first seen in its current unbroken arc
  (newly acquired signals are the noisy ones);
- ``pr_sigma_ok``: ``pr_sigma`` is the receiver's own report (RINEX reports none: its reader models it
  from C/N0);
- ``signal``: the slot's index into :data:`fusion.trace.SIGNALS`;
- ``isb``: the inter-system bias of the slot's signal against the reference signal (GPS L1 where present)
  [m], one value per signal and trace, from the plain WLS's residuals: subtracted from the pseudorange
  before the network and its least squares see it, so that every signal's slots take the clock as the
  reference's (0 for GSDC derived files, whose ``isrbM`` already removes it);
- ``cmd``: code minus Doppler [m], the pseudorange change since the previous epoch minus the Doppler
  integrated over the step (receiver clock drift and motion cancel; multipath and reflections do not),
  with ``cmd_ok`` where both epochs have a Doppler;
- ``adr_has``, ``adr_ok``, ``adr_slip``: the trace carries carrier phase for the slot; it is valid; it
  slipped or reset since the previous epoch;
- ``rel_sin``, ``rel_cos``, ``heading_ok``: the satellite's azimuth relative to the direction of travel
  (sine and cosine) where the receiver is moving (:func:`travel_heading`). Streets run along the direction
  of travel, so a low satellite across it is the one buildings block or reflect; the line of sight alone
  does not say which way the street runs.

A slot's "previous epoch" is the epoch before it in the trace, if no more than :data:`MAX_STEP_S`
earlier, with the same satellite and signal, neither epoch's WLS failed, and no clock reset between.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.errors import GnssfuseError
from fusion.estimate.wls import WlsResult
from fusion.geometry import ecef2ned_vec, elevation_azimuth, line_of_sight
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.trace import Trace

#: Longest step between epochs [s] that still counts as "the previous epoch" (1 Hz logs: 1 s).
MAX_STEP_S = 1.5
#: Arc ages are capped here [s]: beyond ten minutes an arc is simply "old".
MAX_ARC_S = 600.0
#: The per-slot context arrays, in a fixed order.
CONTEXT_KEYS = ("pr_sigma", "cn0", "dres", "prev_ok", "arc_s", "pr_sigma_ok", "signal", "isb", "cmd", "cmd_ok",
                "adr_has", "adr_ok", "adr_slip", "rel_sin", "rel_cos", "heading_ok")


@dataclass
class SlotContext:
    """(E,S) arrays aligned with a trace's slots (padded slots: pr_sigma 1, the rest 0)."""

    pr_sigma: np.ndarray
    cn0: np.ndarray
    dres: np.ndarray
    prev_ok: np.ndarray
    arc_s: np.ndarray
    pr_sigma_ok: np.ndarray
    signal: np.ndarray
    isb: np.ndarray
    cmd: np.ndarray
    cmd_ok: np.ndarray
    adr_has: np.ndarray
    adr_ok: np.ndarray
    adr_slip: np.ndarray
    rel_sin: np.ndarray
    rel_cos: np.ndarray
    heading_ok: np.ndarray

    def as_dict(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in CONTEXT_KEYS}


def _slot_keys(trace: Trace) -> np.ndarray:
    """(E,S) int64 key of each real slot (satellite and signal), -1 on padding."""
    key = trace.sat_id.astype(np.int64) * 64 + trace.signal.astype(np.int64)
    return np.where(trace.mask, key, -1)


def _previous_slot(keys: np.ndarray, linked: np.ndarray) -> np.ndarray:
    """(E,S) index of the same key's slot in epoch k-1 (-1 where absent or epoch k not ``linked``)."""
    E, S = keys.shape
    prev = np.full((E, S), -1, np.int64)
    if E < 2:
        return prev
    # match key (k, s) against row k-1: sort each previous row once, then one searchsorted per row pair
    order = np.argsort(keys[:-1], axis=1, kind="stable")
    sorted_prev = np.take_along_axis(keys[:-1], order, axis=1)
    offset = (np.arange(E - 1) * (2 ** 40))[:, None]          # keys < 2**40: rows never interleave
    flat = (sorted_prev + offset).ravel()
    q = keys[1:] + offset
    pos = np.clip(np.searchsorted(flat, q.ravel()).reshape(q.shape) - np.arange(E - 1)[:, None] * S, 0, S - 1)
    hit = (np.take_along_axis(sorted_prev, pos, axis=1) == keys[1:]) & (keys[1:] >= 0)
    prev[1:] = np.where(hit & linked[1:, None], np.take_along_axis(order, pos, axis=1), -1)
    return prev


def _arc_ages(t_s: np.ndarray, keys: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """(E,S) seconds since each real slot's arc began (an arc: consecutive ``prev`` links)."""
    e, s = np.nonzero(keys >= 0)
    order = np.lexsort((e, keys[e, s]))                 # by satellite key, then epoch
    e, s = e[order], s[order]
    # sorted this way, a linked slot directly follows its previous-epoch slot: runs are arcs
    is_start = prev[e, s] < 0
    first = np.maximum.accumulate(np.where(is_start, np.arange(e.size), 0))
    out = np.zeros(keys.shape)
    out[e, s] = t_s[e] - t_s[e[first]]
    return np.minimum(out, MAX_ARC_S)


def context_wls(trace: Trace, elev_mask_deg: float) -> WlsResult:
    """The WLS solution the context (and the training guesses) are defined on: plain elevation-weighted
    WLS, without fault exclusion, so that a residual the pipeline's robust WLS would exclude still shows
    its jump to the network, and so that training and inference see the same definition whatever the
    pipeline's WLS options."""
    return solve_initial(trace, RunOptions(elev_mask_deg=elev_mask_deg, wls_robust=False))


def slot_context(trace: Trace, wls: WlsResult, elev_mask_deg: float = 10.0, heading: bool = True) -> SlotContext:
    """The context of every slot of ``trace`` (E epochs, S slots) given its WLS solution (``elev_mask_deg``:
    the mask of the reference-signal WLS that measures inter-system biases). ``heading`` False: the relative
    azimuths are left absent (a network that does not read them need not pay for them)."""
    t_s = trace.t_ms.astype(float) / 1000.0
    step_ok = np.r_[False, np.diff(t_s) <= MAX_STEP_S] & ~np.asarray(trace.clock_reset, bool)
    keys = _slot_keys(trace)
    prev = _previous_slot(keys, step_ok)
    arc = _arc_ages(t_s, keys, prev)
    valid = np.asarray(wls.valid, bool)
    resid = np.where(valid[:, None] & trace.mask, wls.resid, np.nan)
    prev_resid = np.full_like(resid, np.nan)
    prev_resid[1:] = np.take_along_axis(resid[:-1], np.maximum(prev[1:], 0), axis=1)
    dres = resid - np.where(prev >= 0, prev_resid, np.nan)
    prev_ok = np.isfinite(dres)
    cn0 = trace.cn0 if trace.cn0 is not None else np.zeros(trace.mask.shape)
    m = trace.mask
    reported = m if trace.pr_sigma_ok is None else m & trace.pr_sigma_ok
    cmd, cmd_ok = code_minus_doppler(trace, prev, t_s)
    has_adr = trace.adr_ok is not None
    if heading:
        rel_sin, rel_cos, heading_ok = relative_azimuth(trace, np.where(valid[:, None], wls.pos, np.nan), t_s)
    else:
        rel_sin, rel_cos, heading_ok = np.zeros(m.shape), np.zeros(m.shape), np.zeros(m.shape[0], bool)
    return SlotContext(pr_sigma=np.where(m, trace.pr_sigma, 1.0), cn0=np.where(m, cn0, 0.0),
                       dres=np.where(prev_ok, dres, 0.0), prev_ok=prev_ok, arc_s=arc, pr_sigma_ok=reported,
                       signal=np.where(m, trace.signal, 0).astype(np.int64),
                       isb=np.where(m, signal_biases(trace, elev_mask_deg), 0.0), cmd=cmd, cmd_ok=cmd_ok,
                       adr_has=m & has_adr, adr_ok=m & (trace.adr_ok if has_adr else False),
                       adr_slip=m & (trace.adr_slip if has_adr else False), rel_sin=np.where(m, rel_sin, 0.0),
                       rel_cos=np.where(m, rel_cos, 0.0), heading_ok=m & heading_ok[:, None])


#: The direction of travel: a straight-line fit to the last HEADING_WINDOW_S seconds of the WLS track
#: (causal, so a filter running epoch by epoch sees the same), trusted at HEADING_MIN_SPEED_MPS and above
#: (a WLS track's metres of noise over the window turn a slower heading to noise).
HEADING_WINDOW_S = 6.0
HEADING_MIN_SPEED_MPS = 3.0
HEADING_MIN_POINTS = 3


def travel_heading(t_s: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E,) heading [rad, from north towards east, in each epoch's own local frame] of a track ``pos`` (E,3)
    ECEF (NaN rows: no fix) at ascending times ``t_s`` (E,) [s], and (E,) bool where it is trusted: a
    least-squares velocity over the trailing :data:`HEADING_WINDOW_S` of valid fixes, at least
    :data:`HEADING_MIN_POINTS` of them, moving at :data:`HEADING_MIN_SPEED_MPS` or faster. Nothing later
    than an epoch enters its heading."""
    E = t_s.shape[0]
    ok = np.isfinite(pos).all(axis=1)
    if ok.sum() < HEADING_MIN_POINTS:
        return np.zeros(E), np.zeros(E, bool)
    # offsets from the first fix keep the running sums small; the fit is in ECEF, turned into each epoch's
    # north and east afterwards, so a long drive's changing north does not bend its early headings
    first = np.argmax(ok)
    d = np.where(ok[:, None], pos - pos[first], 0.0)
    tt = np.where(ok, t_s - t_s[first], 0.0)
    w = ok.astype(float)
    cols = np.column_stack([w, tt, tt * tt, d, tt[:, None] * d])                       # (E,9)
    cum = np.vstack([np.zeros(cols.shape[1]), np.cumsum(cols, axis=0)])
    # running sums give every epoch's trailing window in O(E), whatever the spacing of the epochs
    start = np.searchsorted(t_s, t_s - HEADING_WINDOW_S, side="left")
    win = cum[1:] - cum[start]
    n, st, stt, sd, std = win[:, 0], win[:, 1], win[:, 2], win[:, 3:6], win[:, 6:9]
    den = n * stt - st * st
    good = ok & (n >= HEADING_MIN_POINTS) & (den > 1e-9 * np.maximum(n * n, 1.0))
    vel = np.where(good[:, None], (n[:, None] * std - st[:, None] * sd) / np.where(good, den, 1.0)[:, None], 0.0)
    ned = np.zeros((E, 3))
    if good.any():
        ned[good] = ecef2ned_vec(vel[good], pos[good])
    moving = good & (np.hypot(ned[:, 0], ned[:, 1]) >= HEADING_MIN_SPEED_MPS)
    return np.arctan2(ned[:, 1], ned[:, 0]), moving


def relative_azimuth(trace: Trace, pos: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E,S) sine and cosine of each slot's azimuth minus the direction of travel (:func:`travel_heading`
    of the track ``pos`` (E,3) ECEF, NaN rows without a fix, at ascending times ``t_s`` (E,) [s]), both in the
    epoch's own local frame, and (E,) bool where the heading is trusted (the sine and cosine are 0 elsewhere)."""
    heading, moving = travel_heading(t_s, pos)
    E, S = trace.mask.shape
    if not moving.any():
        return np.zeros((E, S)), np.zeros((E, S)), moving
    at = np.where(moving[:, None], pos, pos[moving][0])
    _, los = line_of_sight(trace.sat_pos, at)
    _, az = elevation_azimuth(los, at)
    rel = np.radians(az) - heading[:, None]
    keep = moving[:, None] & trace.mask
    return np.where(keep, np.sin(rel), 0.0), np.where(keep, np.cos(rel), 0.0), moving


def signal_biases(trace: Trace, elev_mask_deg: float = 10.0) -> np.ndarray:
    """(E,S) inter-system bias [m] of each slot's signal against the reference signal (GPS L1 where
    present, else the most used one): the trace-wide median of the slot's residual at the reference
    signal's own WLS position minus the median residual of the epoch's reference slots (a WLS with one
    clock for every signal would move its positions to absorb part of the bias)."""
    sig = np.asarray(trace.signal, np.int64)
    present, counts = np.unique(sig[trace.mask], return_counts=True)
    out = np.zeros(sig.shape)
    if present.size <= 1:
        return out                                  # one signal: its clock is the receiver clock
    ref = 0 if 0 in present else int(present[np.argmax(counts)])
    own = trace.select_slots(sig == ref)
    try:
        w = solve_initial(own, RunOptions(elev_mask_deg=elev_mask_deg, wls_robust=False))
    except GnssfuseError:
        return out                                  # the reference alone solves nothing: no estimate
    pos = np.where(np.asarray(w.valid, bool)[:, None], w.pos, np.nan)
    rng, _ = line_of_sight(trace.sat_pos, np.nan_to_num(pos))
    raw = np.where(trace.mask & np.isfinite(pos).all(1)[:, None], trace.pr - rng, np.nan)
    ref_raw = np.where(sig == ref, raw, np.nan)
    have = np.isfinite(ref_raw).any(1)
    clock = np.full(sig.shape[0], np.nan)
    clock[have] = np.nanmedian(ref_raw[have], axis=1)      # epochs without a reference slot: no estimate
    for g in present[present != ref]:               # a handful of signals, not epochs
        d = np.where(sig == g, raw - clock[:, None], np.nan)
        out[trace.mask & (sig == g)] = np.nanmedian(d) if np.isfinite(d).any() else 0.0
    return out


def code_minus_doppler(trace: Trace, prev: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E,S) pseudorange change since the previous epoch minus the mean Doppler range rate times the step
    [m], and (E,S) bool where it exists (both epochs with a Doppler; ``prev`` from :func:`_previous_slot`)."""
    E, S = trace.mask.shape
    if trace.prr_ok is None or E < 2:
        return np.zeros((E, S)), np.zeros((E, S), bool)
    p = np.maximum(prev, 0)
    ok = np.zeros((E, S), bool)
    ok[1:] = (prev[1:] >= 0) & trace.prr_ok[1:] & np.take_along_axis(trace.prr_ok[:-1], p[1:], axis=1)
    cmd = np.zeros((E, S))
    dt = np.diff(t_s)[:, None]
    dpr = trace.pr[1:] - np.take_along_axis(trace.pr[:-1], p[1:], axis=1)
    rate = 0.5 * (trace.prr[1:] + np.take_along_axis(trace.prr[:-1], p[1:], axis=1))
    cmd[1:] = np.where(ok[1:], dpr - rate * dt, 0.0)
    return cmd, ok & trace.mask
