"""Everything the factor loop needs, per epoch, computed for the whole trace without Python loops
over epochs: initial values, satellite selection and sigmas, motion and clock chains, priors, and
which epochs the graph can determine at all."""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.clock import clock_chain
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.consistency import raise_pseudorange_sigmas, raise_raw_sigmas
from fusion.estimate.graph.drift_noise import doppler_jump, drift_change
from fusion.estimate.graph.isb import IsbInputs, isb_inputs
from fusion.estimate.graph.odometry import OdometryFactors, odometry_factors
from fusion.estimate.graph.priors import LearnedGraphInputs, Priors, clean_priors
from fusion.estimate.graph.raw_inputs import (RawInputs, carrier_sigma_by_pseudorange, doppler_sigma_by_pseudorange,
                                              raw_inputs)
from fusion.estimate.graph.series import interp_rows
from fusion.estimate.wls import WlsResult
from fusion.geometry import elevation_azimuth, line_of_sight
from fusion.trace import Trace, satellite_counts


@dataclass
class EpochInputs:
    """Everything the factor loop needs, precomputed without Python loops.

    E epochs, S slots.
    init_pos (E,3), init_clock_m (E,) (NaN where no satellite), init_vel (E,3) ECEF [m/s] initial
    velocities (central differences of init_pos within a motion component, 0 for isolated epochs),
    sel (E,S) bool satellites used, sigma (E,S) [m], dt (E,) [s] time since the previous epoch
    (0 for the first), pos_link (E,) bool (epoch k linked by motion to k-1), clock_link (E,) int
    (index of the epoch whose clock k's clock is chained to, -1 for none), clock_mean_m (E,) the
    expected clock change along that link, clock_sigma_m (E,), prior_mean (E,3), prior_cov (E,3,3),
    prior_ok (E,) bool, keep (E,) bool (epoch in a determinable component), comp (E,) component id,
    dropped: counts by reason; isb: the inter-system bias states (:class:`IsbInputs`);
    pr_bias (E,S) [m] subtracted from each pseudorange (a slot-noise provider's bias, else 0); n_sats (E,) int
    the satellites among the selected slots (two frequencies of one satellite count once); raw: the
    Doppler and carrier factors (:class:`RawInputs`); clock_drift_mps (E,) starting drift [m/s] and
    clock_span_s (E,) [s] along each clock link (for drift states); use_drift: the clock chain has drift
    states (GraphConfig.clock_drift_states); doppler_jump_mps: the white jump of the drift each epoch's
    Doppler sees beyond the clock's walk [m/s] (0: none, the Doppler sees the drift state itself;
    :mod:`fusion.estimate.graph.drift_noise`); pr_losses: the pseudorange factors' robust losses, scales
    and the epochs of each (:func:`pseudorange_losses`).
    """

    init_pos: np.ndarray
    init_clock_m: np.ndarray
    init_vel: np.ndarray
    sel: np.ndarray
    sigma: np.ndarray
    dt: np.ndarray
    pos_link: np.ndarray
    clock_link: np.ndarray
    clock_mean_m: np.ndarray
    clock_sigma_m: np.ndarray
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    prior_ok: np.ndarray
    keep: np.ndarray
    comp: np.ndarray
    dropped: dict
    isb: IsbInputs
    pr_bias: np.ndarray
    n_sats: np.ndarray
    pr_losses: list[tuple[str, float, np.ndarray]]
    raw: RawInputs | None = None
    clock_drift_mps: np.ndarray | None = None
    clock_span_s: np.ndarray | None = None
    odometry: OdometryFactors | None = None
    use_drift: bool = False
    doppler_jump_mps: float = 0.0


def doppler_drift_epochs(inp: EpochInputs) -> np.ndarray:
    """(E,) bool kept epochs whose Doppler sees a drift of its own (:attr:`EpochInputs.doppler_jump_mps` > 0)."""
    if inp.raw is None or inp.doppler_jump_mps <= 0:
        return np.zeros(inp.keep.shape, bool)
    return (inp.raw.doppler & inp.keep[:, None]).any(axis=1)


def pseudorange_gap(inp: EpochInputs) -> np.ndarray:
    """(E,) bool epochs whose position neither 4 satellites' pseudoranges nor a prior fixes."""
    return (inp.n_sats < 4) & ~inp.prior_ok


def doppler_epochs(inp: EpochInputs) -> np.ndarray:
    """(E,) bool epochs with a Doppler factor (their velocity is measured)."""
    return inp.raw.doppler.any(axis=1) if inp.raw is not None else np.zeros(len(inp.dt), bool)


def motion_only(inp: EpochInputs) -> np.ndarray:
    """(E,) bool epochs whose velocity random walk takes GraphConfig.bridged_accel_scale: fewer than 4
    pseudoranges (not satellites), no prior and no Doppler. The scale was chosen on single-frequency logs,
    where the two counts agree; on the held-out simulated city traces with two frequencies thinned to 3
    satellites, giving it to every :func:`pseudorange_gap` epoch without Doppler cost 5.1 % on average, 7 of 12
    traces worse (experiments/results/dual_frequency_bridges.md): a second frequency's pseudoranges still steer."""
    return (inp.sel.sum(axis=1) < 4) & ~inp.prior_ok & ~doppler_epochs(inp)


def initial_positions(trace: Trace, wls: WlsResult, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E,3) WLS positions, interpolated in time where WLS failed, and (E,) bool where WLS solved."""
    wls_ok = np.asarray(wls.valid, bool) & np.isfinite(wls.pos).all(axis=1)
    if not wls_ok.any():
        raise GeometryError(f"{trace.name}: WLS solved no epoch, so the graph has no initial position")
    return interp_rows(t, np.asarray(wls.pos, float), wls_ok), wls_ok


def learned_priors(trace: Trace, learned: LearnedGraphInputs | None, cfg: GraphConfig) -> tuple[Priors, int]:
    """The learned position priors cleaned by :func:`clean_priors` (none without them), and the count the
    model offered but the rule rejected (non-finite or not positive definite)."""
    E = trace.n_epochs
    if learned is None or not learned.has_prior:
        none = np.zeros(E, bool)
        return Priors(np.zeros((E, 3)), np.tile(np.eye(3), (E, 1, 1)), none, none, none), 0
    mean, cov, valid = (np.asarray(a, dtype) for a, dtype in ((learned.prior_mean, float), (learned.prior_cov, float),
                                                                (learned.prior_ok, bool)))
    if mean.shape != (E, 3) or cov.shape != (E, 3, 3) or valid.shape != (E,):
        raise GeometryError(f"{trace.name}: learned prior shapes {mean.shape}, {cov.shape}, {valid.shape}; "
                            f"expected {(E, 3)}, {(E, 3, 3)}, {(E,)}")
    pri = clean_priors(mean, cov, valid, cfg.prior_cov_scale, cfg.prior_sigma_floor_m,
                       what="GraphConfig: prior_cov_scale / prior_sigma_floor_m")
    return pri, int((valid & ~(pri.finite & pri.spd)).sum())


def select_satellites(trace: Trace, wls: WlsResult, wls_ok: np.ndarray, init_pos: np.ndarray,
                      cfg: GraphConfig, elev_mask_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slots used, their pseudorange sigmas [m] and residuals pr - range at the initial position
    (NaN where not used), each (E,S). Where WLS solved, its choice of satellites is trusted (it may
    have excluded outliers); elsewhere the elevation mask alone decides."""
    rng, los = line_of_sight(trace.sat_pos, init_pos)
    el, _ = elevation_azimuth(los, init_pos)
    sel = trace.mask & (el >= elev_mask_deg)
    if getattr(wls, "used", None) is not None:
        sel &= np.where(wls_ok[:, None], np.asarray(wls.used, bool), True)
    sin_el = np.sin(np.radians(np.clip(el, 5.0, 90.0)))
    sigma = np.sqrt((cfg.pr_sigma_scale * trace.pr_sigma) ** 2 + (cfg.pr_sigma_zenith_m / sin_el) ** 2)
    return sel, sigma, np.where(sel, trace.pr - rng, np.nan)


def learned_slot_noise(trace: Trace, got_sigma: np.ndarray | None, got_bias: np.ndarray | None, sel: np.ndarray,
                       sigma: np.ndarray, level: str = "absolute") -> tuple[np.ndarray, np.ndarray, int]:
    """The learned sigma (E,S) where it is finite and positive on a selected slot, else the model's
    ``sigma`` (``level`` "relative": rescaled per epoch to the median of ``sigma``, see GraphConfig); the
    learned bias (E,S) there, else 0; and how many selected slots it set. None: the model's alone."""
    if got_sigma is None:
        return sigma, np.zeros_like(sigma), 0
    if level not in ("absolute", "relative"):
        raise GeometryError(f"GraphConfig.slot_noise_level must be 'absolute' or 'relative', got {level!r}")
    got_sigma = np.asarray(got_sigma, float)
    got_bias = np.zeros_like(got_sigma) if got_bias is None else np.asarray(got_bias, float)
    if got_sigma.shape != sigma.shape or got_bias.shape != sigma.shape:
        raise GeometryError(f"{trace.name}: learned pseudorange sigma / bias shapes {got_sigma.shape} / "
                            f"{got_bias.shape}, expected {sigma.shape}")
    use = sel & np.isfinite(got_sigma) & (got_sigma > 0) & np.isfinite(got_bias)
    if level == "relative":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)      # epochs the model skipped -> NaN
            ratio = np.nanmedian(np.where(use, sigma, np.nan), 1) / np.nanmedian(np.where(use, got_sigma, np.nan), 1)
        got_sigma = got_sigma * np.nan_to_num(ratio, nan=1.0)[:, None]
    return np.where(use, got_sigma, sigma), np.where(use, got_bias, 0.0), int(use.sum())


def pseudorange_losses(cfg: GraphConfig, learned_sigmas: bool, n_sats: np.ndarray
                       ) -> list[tuple[str, float, np.ndarray]]:
    """The pseudorange factors' robust losses: (kind, scale [sigmas], epochs (E,) bool) that partition the
    epochs. At epochs of at least ``robust_min_sats`` satellites (n_sats (E,)), ``learned_robust``
    where some pseudorange of the graph has a learned sigma and ``unlearned_robust`` where none has (a network
    whose guard handed every measurement to the physical model builds the graph without it); ``robust`` at the
    others (GraphConfig)."""
    enough = n_sats >= cfg.robust_min_sats
    kind, k = (cfg.learned_robust, cfg.learned_robust_k) if learned_sigmas else (cfg.unlearned_robust,
                                                                                 cfg.unlearned_robust_k)
    return [(kind, k, enough), (cfg.robust, cfg.robust_k, ~enough)]


def drift_states(raw: RawInputs | None, mode: str) -> bool:
    """Whether the clock chain gets drift states: always, or where some Doppler is used (``mode``
    "always" / "doppler", GraphConfig.clock_drift_states)."""
    if mode not in ("always", "doppler"):
        raise GeometryError(f"GraphConfig.clock_drift_states must be 'always' or 'doppler', got {mode!r}")
    return mode == "always" or (raw is not None and raw.use_drift)


def initial_clocks(wls: WlsResult, wls_ok: np.ndarray, resid: np.ndarray) -> np.ndarray:
    """(E,) clock [m]: WLS where solved, else the median residual at the initial position; NaN for
    epochs without a selected satellite. resid (E,S) NaN where not selected."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # epochs without satellites -> NaN
        med = np.nanmedian(resid, axis=1)
    clock = np.where(wls_ok, np.asarray(wls.clock_m, float), med)
    return np.where(np.isfinite(resid).any(axis=1), clock, np.nan)


def motion_links(t: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """dt (E,) [s] since the previous epoch (0 first), pos_link (E,) bool tied to the previous epoch
    (no gap over ``max_gap_s``), comp (E,) motion component id."""
    dt = np.concatenate([[0.0], np.diff(t)])
    pos_link = np.concatenate([[False], dt[1:] <= max_gap_s])
    return dt, pos_link, np.cumsum(~pos_link) - 1


def initial_velocities(init_pos: np.ndarray, dt: np.ndarray, pos_link: np.ndarray) -> np.ndarray:
    """(E,3) ECEF [m/s]: central differences of the initial track within motion components (one-sided
    at component ends, 0 for isolated epochs)."""
    E = init_pos.shape[0]
    if E < 2:
        return np.zeros((E, 3))
    fwd = np.diff(init_pos, axis=0) / np.maximum(dt[1:], 1e-3)[:, None]
    fwd = np.where(pos_link[1:, None], fwd, np.nan)
    nan_row = np.full((1, 3), np.nan)
    both = np.stack([np.vstack([fwd, nan_row]), np.vstack([nan_row, fwd])])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # isolated epochs -> 0 velocity
        return np.nan_to_num(np.nanmean(both, axis=0))


def determinable(comp: np.ndarray, n_sats: np.ndarray, prior_ok: np.ndarray) -> np.ndarray:
    """(E,) bool epochs in a motion component with an anchor (an epoch with >= 4 satellites'
    pseudoranges, :func:`satellite_counts`, or a prior); the clocks are then fixed by their pseudoranges.
    The graph drops the others."""
    anchor = (n_sats >= 4) | prior_ok
    comp_ok = np.bincount(comp, weights=anchor.astype(float), minlength=comp.max() + 1) > 0
    return comp_ok[comp]


def trace_raw_inputs(trace: Trace, init_pos: np.ndarray, elev_mask_deg: float, has_clock: np.ndarray,
                     clock_link: np.ndarray, cfg: GraphConfig, use_doppler: bool, use_carrier: bool
                     ) -> RawInputs | None:
    """The trace's Doppler / carrier factors (None when it has neither or both are switched off);
    init_pos (E,3) fixes the elevations, has_clock (E,) bool, clock_link (E,) int."""
    if not ((use_doppler and trace.has_doppler) or (use_carrier and trace.has_carrier)):
        return None
    el, _ = elevation_azimuth(line_of_sight(trace.sat_pos, init_pos)[1], init_pos)
    return raw_inputs(trace, el, elev_mask_deg, has_clock, clock_link, cfg, use_doppler, use_carrier)


def distrust_raw(trace: Trace, inp: EpochInputs, learned_sigma: np.ndarray, physical: np.ndarray,
                 cfg: GraphConfig) -> None:
    """Raise ``inp.raw``'s carrier (and Doppler) sigmas in place where the head distrusts the satellite's
    pseudorange (``GraphConfig.learned_carrier_*``, ``learned_doppler_power``), counted in ``inp.dropped``.
    learned_sigma, physical (E,S) [m]: the head's pseudorange sigmas and the physical model's."""
    if cfg.learned_carrier_power <= 0 and cfg.learned_doppler_power <= 0:
        return
    # every slot the head judged, the ones the graph's selection left out (gross residuals) too
    ratio = np.where(trace.mask & (physical > 0), learned_sigma / physical, np.nan)
    if cfg.learned_carrier_power > 0:
        inp.raw.tdcp_sigma, inp.dropped["learned_carrier_sigmas_raised"] = carrier_sigma_by_pseudorange(
            inp.raw, ratio, cfg.learned_carrier_power, cfg.learned_carrier_knee, cfg.learned_carrier_min_count)
    if cfg.learned_doppler_power > 0:
        inp.raw.prr_sigma, inp.dropped["learned_doppler_sigmas_raised"] = doppler_sigma_by_pseudorange(
            inp.raw, ratio, cfg.learned_doppler_power, cfg.learned_carrier_knee)


def prepare_inputs(trace: Trace, wls: WlsResult, cfg: GraphConfig, elev_mask_deg: float = 10.0,
                   learned: LearnedGraphInputs | None = None) -> EpochInputs:
    """Initial values, satellite selection, sigmas, chain links and priors for every epoch.

    learned: the learned model's priors and per-measurement noise for the whole trace (None: the
    config's physical models alone). ``cfg.use_doppler`` / ``cfg.use_carrier`` add the trace's Doppler /
    carrier factors where it has them, ``cfg.use_odometry`` its odometry steps
    (:mod:`fusion.estimate.graph.odometry`). Raises :class:`GeometryError` when no epoch has any usable
    initial position.
    """
    t = trace.t_ms.astype(float) / 1000.0
    init_pos, wls_ok = initial_positions(trace, wls, t)
    pri, n_rejected = learned_priors(trace, learned, cfg)
    sel, sigma, resid = select_satellites(trace, wls, wls_ok, init_pos, cfg, elev_mask_deg)
    physical = sigma
    sigma, pr_bias, n_learned = learned_slot_noise(trace, None if learned is None else learned.pr_sigma,
                                                   None if learned is None else learned.pr_bias, sel, sigma,
                                                   cfg.slot_noise_level)
    init_clock = initial_clocks(wls, wls_ok, resid)
    dt, pos_link, comp = motion_links(t, cfg.max_gap_s)
    wls_clock = np.where(wls_ok, np.asarray(wls.clock_m, float), np.nan)
    chain = clock_chain(t, wls_clock, sel.any(axis=1), pos_link, trace.clock_reset, cfg)
    n_sats = satellite_counts(trace.sat_id, sel)
    keep = determinable(comp, n_sats, pri.ok)
    dropped = {"clock_resets": chain.n_resets, "epochs_undetermined": int((~keep).sum())}
    if learned is not None and learned.has_prior:
        dropped = {"prior_rejected": n_rejected, **dropped}
    if learned is not None and learned.pr_sigma is not None:
        dropped = {"learned_sigmas": n_learned, **dropped}
    inp = EpochInputs(init_pos=init_pos, init_clock_m=init_clock,
                      init_vel=initial_velocities(init_pos, dt, pos_link), sel=sel, sigma=sigma, dt=dt,
                      pos_link=pos_link, clock_link=chain.link, clock_mean_m=chain.change_m,
                      clock_sigma_m=chain.sigma_m, prior_mean=pri.mean, prior_cov=pri.cov, prior_ok=pri.ok,
                      keep=keep, comp=comp, dropped=dropped,
                      isb=isb_inputs(trace, sel, comp, init_clock, resid, cfg), pr_bias=pr_bias, n_sats=n_sats,
                      pr_losses=pseudorange_losses(cfg, n_learned > 0, n_sats),
                      raw=trace_raw_inputs(trace, init_pos, elev_mask_deg, sel.any(axis=1), chain.link, cfg,
                                           cfg.use_doppler, cfg.use_carrier),
                      clock_drift_mps=chain.drift_mps, clock_span_s=chain.span_s)
    inp.use_drift = drift_states(inp.raw, cfg.clock_drift_states)
    if inp.raw is not None:
        inp.dropped.update(inp.raw.counts)
        if learned is not None and learned.doppler_noise is not None and inp.raw.doppler.any():
            inp.dropped.update({f"learned_{k}": v for k, v in learned.doppler_noise(trace, inp).items()})
        if n_learned:
            distrust_raw(trace, inp, np.asarray(learned.pr_sigma, float), physical, cfg)
        inp.dropped.update(raise_raw_sigmas(trace, inp, cfg.doppler_check_window_s, cfg.carrier_check_window_s))
        if cfg.doppler_jump_from_log and inp.use_drift and inp.raw.doppler.any():
            change, linked = drift_change(trace, inp), dt[pos_link]
            inp.doppler_jump_mps = doppler_jump(change, cfg, float(np.median(linked)) if linked.size else 1.0)
            # None: the log has too few epochs whose drift is well known to tell (not: a steady clock)
            inp.dropped["doppler_drift_jump_mps"] = None if change is None else round(inp.doppler_jump_mps, 3)
    inp.dropped.update(raise_pseudorange_sigmas(trace, inp, cfg.pseudorange_check_window_s))
    if cfg.use_odometry:
        inp.odometry = odometry_factors(trace, init_pos, wls_ok, pos_link, comp, keep, cfg)
        inp.dropped.update(inp.odometry.counts if inp.odometry is not None else {"odometry_steps": 0})
    return inp
