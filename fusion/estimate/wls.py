"""Batched weighted least-squares (WLS) snapshot positioning: every epoch of a trace at once.

Unknowns per epoch: receiver ECEF position (x, y, z) and receiver clock ``c*dt`` [m]. The model is

    pr[e, s] = |R(omega_e * tau) sat_pos[e, s] - x[e]| + clock[e]  (+ noise)

with the Sagnac rotation done by :func:`fusion.geometry.line_of_sight`. Each epoch is a snapshot:
no clock or weight carries from one epoch to the next, so receiver clock jumps cannot leak between
epochs (the neighbours' *positions* serve only to identify faults, step 4, and their clocks only to
bridge three-satellite epochs, step 5). Gauss-Newton runs on the padded (E, S) arrays; the only Python
loop is over iterations, and converged / failed epochs drop out of the active set.

Procedure
---------
1. Coarse stage: start at ``x0`` where given, else at the Earth's surface under the mean direction
   of the epoch's satellites (a few hundred km off at most), clock = mean(pr - range). Iterate
   unweighted, with *all* satellites (no elevation is known yet), until the step is below 100 m.
2. Elevation mask: elevations are computed once at the coarse position; satellites below
   ``elev_mask_deg`` are dropped. Weights are fixed from these elevations (the elevation of a
   20,000 km distant satellite does not move measurably with a metre-level position change).
3. Fine stage: weighted Gauss-Newton to a 0.1 mm step, at most ``max_iter`` iterations.
4. Robust stage (:mod:`fusion.estimate.raim`). ``robust="exclude"`` (``True``; the default of
   :func:`solve_wls` and of the pipeline): first, an epoch left with a residual above 1 km (a
   millisecond-ambiguous pseudorange) loses its largest one and is re-solved, one at a time
   (:func:`fusion.estimate.raim.exclude_gross`: the test below linearises at a fit such a fault pulls
   tens of kilometres off); then RAIM-style fault detection and exclusion - a chi-square
   test on the weighted residuals, then the smallest set of satellites (at most ``max_exclusions``,
   never below 5 left) whose removal passes it excluded; an epoch no allowed exclusion repairs is
   kept, ``flagged``, and solved with Huber weights so that the fault it holds pulls less. An
   exclusion whose removed residuals are all moderate (below ``exclude_above_m``, 80 m in
   :data:`TRACE_DEFAULTS`) is undone and the epoch flagged and down-weighted the same way: in a street
   canyon multipath spreads tens of metres over many satellites, and a satellite's geometry is worth
   more down-weighted than lost (``experiments/results/robust_wls.md``). With epoch
   times (``t_ms``), the flagged epochs (with ``neighbour_weak``, also those that passed with at most
   :data:`NEIGHBOUR_CHECK_MAX_SATS` satellites, a test of little power: off in :data:`TRACE_DEFAULTS`,
   in a street canyon the neighbours share the multipath) are first checked against the position
   predicted from the settled epochs around them (:mod:`fusion.estimate.neighbour_fde`). In the Huber
   stage of the flagged epochs (``irls_reported``) each a-priori sigma is raised by the measurement's
   reported sigma over the epoch's median (:func:`reported_sigma_factor`: C/N0 says which satellite is
   reflected where elevation cannot), and the threshold scaled by the test's variance factor
   (``irls_scale="trace"``). ``robust="huber"``: iteratively reweighted least
   squares with Huber weights ``min(1, huber_k / |z|)`` on the standardised residuals ``z``.
   ``robust=False``: the paper's plain WLS.
5. Three-satellite epochs (with ``t_ms``): solved for position alone with the receiver clock
   interpolated from the valid epochs around them (:mod:`fusion.estimate.clock_bridge`); flagged in
   ``clock_predicted``, or left unsolved as ``three_sats_no_clock``.

State and settings
------------------
The options are one frozen :class:`fusion.estimate.wls_state.WlsSettings` (``solve_wls`` and
``solve_wls_arrays`` also take its fields as keywords); every stage takes the fit so far, a
:class:`fusion.estimate.wls_state.FitState` (positions, clocks, used slots, weights, convergence flags),
and returns the next one.

Weighting (``weighting=``)
--------------------------
- ``"elevation"`` (default): goGPS's elevation weighting. goGPS builds its code co-factor matrix with
  ``q = 1 / sin(el)^2`` (``cofactor_matrix_SA.m``, ``weights == 1``: "elevation"; goGPS 1.0 keeps it
  as ``W_MODE`` "sin^2"), i.e. ``sigma = SIGMA0_M / sin(el)`` with goGPS's default code std
  ``SIGMA0_M = 3 m`` (``STD_CODE``). goGPS 1.0's own ``W_MODE`` default is uniform weights; the paper
  states it used goGPS's elevation-based weights with a 10 degree mask, which is what we reproduce.
- ``"uncertainty"``: ``sigma = pr_sigma`` (the phone's ``rawPrUncM``).
- ``"none"``: ``sigma = SIGMA0_M`` for every satellite (unweighted).

Covariance
----------
``cov = f * (H^T W H)^-1`` with ``W = diag(1 / sigma^2)`` (a-priori sigmas in metres; under
``robust="huber"`` the final down-weighted ones) and
``f = max(1, v^T W v / (n - 4))``, the a-posteriori variance factor when there is redundancy,
floored at 1 so the reported uncertainty is never more optimistic than the a-priori model
(``cov_scale="prior"`` uses ``f = 1``). ``f = 1`` when n = 4 (no redundancy to estimate it from).

Failure reporting
-----------------
An epoch is ``valid`` only when it had >= 4 satellites after the mask (satellites, not signals: given
``sat_id``, two frequencies of one satellite count once), a well-conditioned normal
matrix (condition number of the unit-diagonal scaled normal matrix <= ``max_cond``; catches
coplanar and cone geometries), a converged fine stage, and a
plausible result (finite, ellipsoidal height within [-2 km, 100 km]). ``status`` holds a code per
epoch (:data:`STATUS_NAMES`) and ``reasons`` counts the epochs per failure reason, so a caller can
report "12 epochs: few_sats" instead of silently losing them. Invalid epochs get NaN position, clock
and covariance; the batch never raises for a bad epoch. Epochs are independent of each other except
for the robust stage's calibrated test and neighbour check (step 4) and step 5.

All satellites share one receiver clock: the loaders' corrected pseudoranges already remove the
inter-signal range bias (``isrbM``), so one clock serves every constellation in the trace.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fusion.errors import DataError
from fusion.estimate.clock_bridge import interpolate_clock, solve_fixed_clock
from fusion.estimate.lsq import ill_conditioned, normal_equations
from fusion.estimate.neighbour_fde import exclude_by_neighbours
from fusion.estimate.raim import exclude_faults, exclude_gross, huber_irls, identify_faults, variance_factor
from fusion.estimate.variance_factor import calibrate_snapshot
from fusion.estimate.wls_state import SIGMA0_M, FitState, WlsSettings  # noqa: F401 (SIGMA0_M: public here too)
from fusion.geometry import ecef2geodetic, elevation_azimuth, line_of_sight
from fusion.run_types import ModeResult
from fusion.trace import count_skip, satellite_counts

#: Epochs with at most this many satellites after exclusion are also checked against their neighbours:
#: with one or two redundant measurements the chi-square test misses many gross faults.
NEIGHBOUR_CHECK_MAX_SATS = 6
#: Mean Earth radius used for the coarse start [m].
_R_EARTH = 6_371_000.0
#: Plausible ellipsoidal heights of a phone (a car, a walker, an aircraft) [m].
_H_MIN, _H_MAX = -2_000.0, 100_000.0

#: Per-epoch status codes (``WlsResult.status``); 0 is the only valid one.
STATUS_NAMES: tuple[str, ...] = (
    "ok", "few_sats", "few_sats_after_mask", "degenerate", "diverged", "not_converged",
    "three_sats_no_clock",
)
(OK, FEW_SATS, FEW_SATS_AFTER_MASK, DEGENERATE, DIVERGED, NOT_CONVERGED,
 THREE_SATS_NO_CLOCK) = range(len(STATUS_NAMES))


@dataclass
class WlsResult:
    """Per-epoch WLS solution. ``E`` epochs, ``S`` satellite slots.

    pos:       (E, 3)    ECEF position [m], NaN where not valid.
    clock_m:   (E,)      receiver clock c*dt [m], NaN where not valid.
    cov:       (E, 4, 4) covariance of [x, y, z, clock] in ECEF [m^2], NaN where not valid.
    valid:     (E,)      bool, solution usable (see module docstring).
    converged: (E,)      bool, the fine stage reached its step tolerance.
    used:      (E, S)    bool, slots in the final fit (mask & above elevation & not excluded).
    n_used:    (E,)      int, ``used.sum(1)``.
    resid:     (E, S)    pr - range - clock at the solution for every real slot (used or not);
                         0 on padding and on invalid epochs.
    elev_deg:  (E, S)    elevation at the coarse position [deg]; 0 on padding and on epochs
                         that failed before the mask stage (few_sats, coarse divergence).
    status:    (E,)      int8 code into :data:`STATUS_NAMES`.
    n_iter:    (E,)      int, Gauss-Newton iterations spent (all stages).
    reasons:   epoch counts per failure status name (only non-zero ones).
    dropped:   slot counts by reason: ``nonfinite_input``, ``bad_sigma``, ``below_mask``,
               ``outlier`` (excluded by fault detection).
    flagged:   (E,) bool, valid epochs whose fault test still fails after the exclusions it was
               allowed (too few satellites or the cap reached): the test cannot decide.
    clock_predicted: (E,) bool, three-satellite epochs solved with an interpolated clock.
    n_excluded: (E,) int, measurements excluded by fault detection.
    excluded:  (E, S) bool, the slots fault detection excluded (above the mask, not used) on valid epochs.
    """

    pos: np.ndarray
    clock_m: np.ndarray
    cov: np.ndarray
    valid: np.ndarray
    converged: np.ndarray
    used: np.ndarray
    n_used: np.ndarray
    resid: np.ndarray
    elev_deg: np.ndarray
    status: np.ndarray
    n_iter: np.ndarray
    reasons: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    flagged: np.ndarray | None = None
    clock_predicted: np.ndarray | None = None
    n_excluded: np.ndarray | None = None
    excluded: np.ndarray | None = None

    def __post_init__(self) -> None:
        E = self.valid.shape[0]
        if self.n_excluded is None:
            self.n_excluded = np.zeros(E, np.int64)
        if self.excluded is None:
            self.excluded = np.zeros(self.used.shape, bool)
        if self.flagged is None:
            self.flagged = np.zeros(E, bool)
        if self.clock_predicted is None:
            self.clock_predicted = np.zeros(E, bool)

    @property
    def n_epochs(self) -> int:
        return int(self.valid.shape[0])

    def summary(self) -> str:
        """One line for logs: 'WLS 1995/1998 valid; few_sats: 3'."""
        parts = [f"WLS {int(self.valid.sum())}/{self.n_epochs} valid"]
        parts += [f"{k}: {v}" for k, v in self.reasons.items()]
        return "; ".join(parts)


# ---------------------------------------------------------------------------------------- public API
#: What :func:`solve_wls` (and so every mode) runs unless told otherwise: fault exclusion, its test
#: calibrated on the trace, and only residuals over 80 m excluded - smaller ones are down-weighted
#: (Huber, :func:`fusion.estimate.raim.costly_exclusions`) instead, with each measurement's a-priori sigma
#: raised by its reported sigma (C/N0) over the epoch's median and the threshold scaled by the trace's
#: variance factor; the neighbour check reopens only the undecided epochs. Exclusion guard chosen
#: leave-one-drive-out on the twelve GSDC training drives, the rest on half the drives and smartLoc
#: (``experiments/robust_wls.py --tune``).
TRACE_DEFAULTS = WlsSettings(robust="exclude", test_scale="trace", exclude_above_m=80.0, max_dop_growth=1.0,
                             neighbour_weak=False, irls_reported=True, irls_scale="trace", huber_k=2.0)


def solve_wls(trace, settings: WlsSettings | None = None, *, x0: np.ndarray | None = None,
              **options) -> WlsResult:
    """WLS over every epoch of a :class:`fusion.trace.Trace` (see :func:`solve_wls_arrays`), with
    fault detection and exclusion by default (``robust=False`` / ``"none"``: the plain baseline) and
    three-satellite epochs solved with the clock interpolated from their neighbours. The fault test's
    variance is calibrated on the trace (``test_scale="trace"``, :func:`fusion.estimate.raim.variance_factor`).

    settings: defaults to :data:`TRACE_DEFAULTS`; ``options`` (any :class:`WlsSettings` field, e.g.
    ``robust=False``, ``elev_mask_deg=5.0``) change it.
    x0: optional (E, 3) ECEF starting positions (NaN rows fall back to the coarse start); it is
    a *starting point* only - the result does not depend on it when Gauss-Newton converges.
    """
    settings = (TRACE_DEFAULTS if settings is None else settings).replace(**options)
    return solve_wls_arrays(trace.sat_pos, trace.pr, trace.mask, trace.pr_sigma, x0, settings=settings,
                            t_ms=trace.t_ms, clock_reset=trace.clock_reset, sat_id=trace.sat_id)


def solve_wls_arrays(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, sigma: np.ndarray | None = None,
                     x0: np.ndarray | None = None, *, settings: WlsSettings | None = None,
                     t_ms: np.ndarray | None = None, clock_reset: np.ndarray | None = None,
                     sat_id: np.ndarray | None = None, **options) -> WlsResult:
    """Batched WLS on raw padded arrays (the engine behind :func:`solve_wls`).

    sat_pos:     (E, S, 3) transmit-time satellite ECEF [m].
    pr:          (E, S)    corrected pseudoranges [m].
    mask:        (E, S)    bool, real slots.
    sigma:       (E, S)    1-sigma pseudorange uncertainty [m]; needed only for ``"uncertainty"``.
    x0:          (E, 3)    optional starting positions (NaN rows -> coarse start).
    settings:    :class:`WlsSettings` (default: plain WLS, ``WlsSettings()``); ``options`` (its field
                 names) change it.
    t_ms:        (E,)      epoch times; with it, three-satellite epochs are solved with the clock
                           interpolated from neighbouring valid epochs (:mod:`fusion.estimate.clock_bridge`).
    clock_reset: (E,)      bool, known clock jumps (no clock is interpolated across one).
    sat_id:      (E, S)    int, the satellite of each slot: "four satellites" and "three" count satellites,
                           not slots (a second frequency adds no direction). None: each slot its own.

    Real slots with non-finite inputs (or a non-positive sigma under ``"uncertainty"``) are not
    used and are counted in ``dropped``; wrong shapes or option values raise :class:`DataError`.
    """
    cfg = (WlsSettings() if settings is None else settings).replace(**options)
    sat_pos, pr, mask, sigma, x0 = _check_inputs(sat_pos, pr, mask, sigma, x0, cfg.weighting)
    dropped: dict[str, int] = {}
    sat_pos, pr, real = _usable_slots(sat_pos, pr, mask, sigma, cfg.weighting, dropped)
    ids = _satellite_ids(sat_id, real.shape)
    status = np.where(satellite_counts(ids, real) < 4, FEW_SATS, OK).astype(np.int8)
    fit, el = _coarse_and_mask(_start_fit(sat_pos, pr, real, x0, dropped), status, sigma, cfg, ids)
    # fine stage: weighted, to the step tolerance
    alive = status == OK
    fit = fit.solve(alive, fit.w_prior, cfg.max_iter, cfg.tol_m, cfg.max_cond)
    eligible = alive & fit.conv & ~fit.bad & ~fit.runaway
    if cfg.robust == "exclude":
        fit, gross = exclude_gross(fit, eligible, cfg)
        fit, scale = _exclude(fit, eligible, cfg, t_ms)
        fit = fit.replace(n_excluded=fit.n_excluded + gross.sum(1))
        if fit.flagged.any():
            fit = huber_irls(fit, fit.flagged, cfg, scale=scale,
                             sigma_factor=reported_sigma_factor(sigma, fit.used) if cfg.irls_reported else None)
    elif cfg.robust == "huber":
        fit = huber_irls(fit, eligible, cfg)
    res = _finish(fit, el, status, alive, cfg)
    if t_ms is not None:
        _bridge_three_sat_epochs(res, fit, sigma, np.asarray(t_ms), clock_reset, cfg, ids)
    return res


def _satellite_ids(sat_id: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """(E,S) the satellite of each slot for :func:`fusion.trace.satellite_counts`; without ``sat_id``, zeros:
    each slot a satellite of its own."""
    if sat_id is None:
        return np.zeros(shape, np.int64)
    if np.shape(sat_id) != shape:
        raise DataError(f"sat_id must be {shape} like pr, got {np.shape(sat_id)}")
    return np.asarray(sat_id)


# ------------------------------------------------------------------------------------- the stages
def _exclude(fit: FitState, eligible: np.ndarray, cfg: WlsSettings, t_ms) -> tuple[FitState, float]:
    """Snapshot fault detection and exclusion (:func:`_fde`), then, with epoch times, the epochs it
    could not decide identified from their neighbours (:mod:`fusion.estimate.neighbour_fde`).
    Returns (the fit, the test's variance factor)."""
    above_mask = fit.used
    fit, scale = _fde(fit, eligible, cfg)
    settled = eligible & ~fit.flagged & fit.conv & ~fit.bad & ~fit.runaway
    # the undecided epochs, and those whose test has little power (one or two redundant satellites)
    weak = fit.flagged | (settled & (fit.used.sum(1) <= NEIGHBOUR_CHECK_MAX_SATS))
    targets = weak if cfg.neighbour_weak else fit.flagged
    if t_ms is None or not targets.any():
        return fit, scale
    fit, repaired = exclude_by_neighbours(fit, above_mask, targets, settled & ~weak, np.asarray(t_ms), cfg, scale)
    return fit.replace(w_fit=fit.weights, flagged=fit.flagged & ~repaired), scale


def _fde(fit: FitState, eligible: np.ndarray, cfg: WlsSettings) -> tuple[FitState, float]:
    """Fault detection and exclusion (:func:`fusion.estimate.raim.exclude_faults`). With
    ``test_scale="trace"`` a first pass at the a-priori variance gives the residuals of the epochs
    it settled, whose robust variance factor (:func:`fusion.estimate.raim.variance_factor`) sets the
    test of the second, final pass (the first pass is kept when the factor is 1 and no exclusion guard
    is set). Returns (the fit after exclusion, the variance factor of the test)."""
    if cfg.test_scale != "trace":
        scale = float(cfg.test_scale)
        return exclude_faults(fit, eligible, cfg, scale=scale), scale
    # The trial pass counts its exclusions apart: only the pass that is kept adds them to the fit's.
    # It runs without the exclusion guard: the factor measures the trace's noise, and the epochs whose
    # moderate faults the guard would keep (down-weighted, flagged) are most of what it must see.
    unguarded = cfg.replace(exclude_above_m=float("inf"))
    trial = identify_faults(fit, eligible, unguarded, scale=1.0)
    first = exclude_faults(fit.replace(dropped={}), eligible, unguarded, scale=1.0, identified=trial)
    settled = eligible & ~first.flagged & ~first.bad & ~first.runaway
    scale = variance_factor(first.sat_pos, first.pr, first.w_fit, first.x, first.used, settled)
    if scale == 1.0 and cfg == unguarded:
        count_skip(fit.dropped, "outlier", first.n_excluded)
        return first.replace(dropped=fit.dropped), scale
    # the guard does not enter the identification: at the same scale the trial's serves again
    return exclude_faults(fit, eligible, cfg, scale=scale, identified=trial if scale == 1.0 else None), scale


def _usable_slots(sat_pos, pr, mask, sigma, weighting, dropped):
    """Real slots with finite inputs (and a usable sigma under "uncertainty"), counted when not.

    Returns sat_pos (E,S,3) and pr (E,S) with harmless finite filler on unusable slots, and real (E,S).
    """
    finite = np.isfinite(pr) & np.isfinite(sat_pos).all(-1)
    count_skip(dropped, "nonfinite_input", mask & ~finite)
    real = mask & finite
    if weighting == "uncertainty":
        good_sigma = np.isfinite(sigma) & (sigma > 0)
        count_skip(dropped, "bad_sigma", real & ~good_sigma)
        real &= good_sigma
    # Padding gets harmless finite values so the vectorised maths never meets NaN.
    return np.where(real[..., None], sat_pos, 0.0), np.where(real, pr, 0.0), real


def _start_fit(sat_pos, pr, real, x0, dropped) -> FitState:
    """The fit before any stage: every usable slot used at unit weight, from :func:`_start_state`."""
    E = pr.shape[0]
    w = real.astype(float)
    return FitState(sat_pos=sat_pos, pr=pr, real=real, w_prior=w, used=real, x=_start_state(sat_pos, pr, real, x0),
                    w_fit=w, conv=np.zeros(E, bool), bad=np.zeros(E, bool), runaway=np.zeros(E, bool),
                    flagged=np.zeros(E, bool), n_excluded=np.zeros(E, np.int64), n_iter=np.zeros(E, np.int64),
                    dropped=dropped)


def _coarse_and_mask(fit: FitState, status: np.ndarray, sigma: np.ndarray,
                     cfg: WlsSettings, ids: np.ndarray) -> tuple[FitState, np.ndarray]:
    """Coarse fix (all satellites, unit weights), then the elevation mask and a-priori weights.

    ``status`` (E,) is updated in place; ``ids`` (E,S) each slot's satellite (:func:`_satellite_ids`).
    Returns the fit at the coarse state with ``used``, ``w_prior``
    and ``w_fit`` set by the mask and weighting (and fresh ``conv`` / ``bad`` / ``runaway``), and the
    elevations (E,S) [deg]. 100 m is ample for the coarse stage: elevations only need km accuracy, and
    one Gauss-Newton step from 100 m off lands within ~1e-6 m.
    """
    alive = status == OK
    coarse = fit.solve(alive, fit.w_prior, max(cfg.max_iter, 10), 100.0, cfg.max_cond)
    # An ill-conditioned coarse stage may still recover once weights and mask change: the fine
    # stage decides about degeneracy.
    status[alive & coarse.runaway] = DIVERGED
    alive = status == OK
    real = fit.real
    el = _elevations(fit.sat_pos, coarse.x[:, :3], real & alive[:, None])
    used = real & (el >= cfg.elev_mask_deg)
    count_skip(fit.dropped, "below_mask", real & ~used & alive[:, None])
    status[alive & (satellite_counts(ids, used) < 4)] = FEW_SATS_AFTER_MASK
    used &= (status == OK)[:, None]
    w_prior = np.where(used, 1.0 / _sigmas(cfg, el, sigma) ** 2, 0.0)
    return fit.replace(x=coarse.x, used=used, w_prior=w_prior, w_fit=w_prior), el


def _elevations(sat_pos, pos, where):
    """(E,S) elevation [deg] of each satellite seen from pos (E,3); 0 outside ``where`` (E,S)."""
    _, los = line_of_sight(sat_pos, pos)
    el, _ = elevation_azimuth(los, pos)
    return np.where(where, el, 0.0)


def _finish(fit: FitState, el: np.ndarray, status: np.ndarray, alive: np.ndarray, cfg: WlsSettings) -> WlsResult:
    """Final evaluation at the solution: residuals, conditioning, plausibility, covariance.

    el: (E,S) elevations [deg]; status: (E,) codes, updated in place; alive: (E,) epochs that reached
    the fine stage."""
    x, used, w_fit = fit.x, fit.used, fit.w_fit
    N, _, r, _ = normal_equations(fit.sat_pos, fit.pr, w_fit, x)
    bad = fit.bad | (alive & ill_conditioned(N, cfg.max_cond))
    status[alive & bad] = DEGENERATE
    status[(status == OK) & (fit.runaway | ~_plausible(x))] = DIVERGED
    status[(status == OK) & ~fit.conv] = NOT_CONVERGED
    valid = status == OK
    cov = np.full((x.shape[0], 4, 4), np.nan)
    if valid.any():
        n = used[valid].sum(1)
        chi2 = np.sum(w_fit[valid] * r[valid] ** 2, axis=1)
        f = np.ones(n.shape)
        if cfg.cov_scale == "posterior":
            red = n > 4
            f[red] = np.maximum(1.0, chi2[red] / (n[red] - 4))
        cov[valid] = f[:, None, None] * np.linalg.inv(N[valid])
    used = used & valid[:, None]
    return WlsResult(
        pos=np.where(valid[:, None], x[:, :3], np.nan), clock_m=np.where(valid, x[:, 3], np.nan), cov=cov,
        valid=valid, converged=fit.conv, used=used, n_used=used.sum(1),
        resid=np.where(fit.real & valid[:, None], r, 0.0), elev_deg=el, status=status, n_iter=fit.n_iter,
        reasons=_reasons(status), dropped=fit.dropped, flagged=fit.flagged & valid, n_excluded=fit.n_excluded,
        excluded=fit.real & (el >= cfg.elev_mask_deg) & ~used & valid[:, None])


def _reasons(status: np.ndarray) -> dict[str, int]:
    counts = {STATUS_NAMES[k]: int(np.sum(status == k)) for k in range(1, len(STATUS_NAMES))}
    return {k: v for k, v in counts.items() if v}


def _bridge_three_sat_epochs(res: WlsResult, fit: FitState, sigma: np.ndarray, t_ms: np.ndarray, clock_reset,
                             cfg: WlsSettings, ids: np.ndarray) -> None:
    """Solve (in place) epochs left with exactly three satellites above the mask (any number of signals each),
    the clock interpolated from the valid epochs around them (:mod:`fusion.estimate.clock_bridge`).
    sigma: (E,S) the input sigmas; t_ms: (E,); clock_reset: (E,) bool or None; ids (E,S) each slot's
    satellite."""
    real = fit.real
    few = np.flatnonzero(np.isin(res.status, (FEW_SATS, FEW_SATS_AFTER_MASK)) & (satellite_counts(ids, real) >= 3))
    good = np.flatnonzero(res.valid)
    if few.size == 0 or good.size == 0:
        return
    near = good[np.clip(np.searchsorted(good, few), 1, good.size) - 1]   # a valid neighbour's position
    pos0 = res.pos[near]
    el = _elevations(fit.sat_pos[few], pos0, real[few])
    used = real[few] & (el >= cfg.elev_mask_deg)
    few, pos0, el, used = (a[satellite_counts(ids[few], used) == 3] for a in (few, pos0, el, used))
    resets = np.zeros(res.n_epochs, bool) if clock_reset is None else np.asarray(clock_reset, bool)
    clock, ok = interpolate_clock(t_ms, res.clock_m, res.valid, resets, few)
    res.status[few[~ok]] = THREE_SATS_NO_CLOCK
    w = np.where(used, 1.0 / _sigmas(cfg, el, sigma[few]) ** 2, 0.0)
    pos, conv, cov3 = solve_fixed_clock(fit.sat_pos[few], fit.pr[few], w, pos0, np.where(ok, clock, 0.0),
                                        cfg.max_iter, cfg.tol_m)
    good_fix = ok & conv & _plausible(np.concatenate([pos, clock[:, None]], axis=1))
    e = few[good_fix]
    res.status[e] = OK
    res.valid[e] = True
    res.converged[e] = True          # the fixed-clock fit converged (good_fix includes conv)
    res.clock_predicted[e] = True
    res.pos[e], res.clock_m[e] = pos[good_fix], clock[good_fix]
    res.cov[e] = np.nan
    res.cov[e, :3, :3] = cov3[good_fix]
    res.used[e] = used[good_fix]
    res.n_used[e] = used[good_fix].sum(1)
    res.elev_deg[e] = el[good_fix]
    res.reasons = _reasons(res.status)


# ------------------------------------------------------------------------------------- helpers
def reported_sigma_factor(sigma: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(E, S) factor >= 1 on a slot's a-priori sigma: its reported pseudorange sigma (the receiver's own,
    or the C/N0 model where the file reports none) over the median of the epoch's ``used`` slots.
    sigma, used: (E, S). A weak signal (low C/N0: reflected, diffracted) counts as the noisier one,
    which the elevation model alone cannot see in a street canyon."""
    s = np.where(used & np.isfinite(sigma) & (sigma > 0), sigma, np.nan)
    has = np.isfinite(s).any(1)
    med = np.ones(s.shape[0])
    med[has] = np.nanmedian(s[has], axis=1)
    return np.where(np.isfinite(s), np.maximum(1.0, s / med[:, None]), 1.0)


def _start_state(sat_pos, pr, real, x0):
    """(E, 4) initial [x, y, z, clock]: x0 rows where finite, else the coarse start."""
    cnt = np.maximum(real.sum(1), 1)
    mean = (sat_pos * real[..., None]).sum(1) / cnt[:, None]
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    # Satellites in view cluster above the receiver, so their mean direction points roughly at it.
    coarse = np.where(norm > 0, mean / np.where(norm > 0, norm, 1.0) * _R_EARTH, 0.0)
    pos = coarse
    if x0 is not None:
        pos = np.where(np.isfinite(x0).all(1, keepdims=True), x0, coarse)
    rng, _ = line_of_sight(sat_pos, pos)
    clock = np.sum(np.where(real, pr - rng, 0.0), axis=1) / cnt
    return np.concatenate([pos, clock[:, None]], axis=1)


def _sigmas(cfg: WlsSettings, el_deg, sigma):
    """(E, S) a-priori pseudorange sigmas [m] for ``cfg.weighting``; el_deg, sigma (E, S)."""
    weighting, sigma0 = cfg.weighting, cfg.sigma0
    if weighting == "elevation":
        # Floor at 1 degree so a zero/negative mask cannot produce infinite sigmas.
        return sigma0 / np.sin(np.radians(np.maximum(el_deg, 1.0)))
    if weighting == "uncertainty":
        return np.where(np.isfinite(sigma) & (sigma > 0), sigma, 1.0)
    return np.full(el_deg.shape, float(sigma0))


def _plausible(x):
    """(E,) True where the state is finite and at a height a phone can be."""
    ok = np.isfinite(x).all(1) & (np.linalg.norm(x[:, :3], axis=1) > 1e6)
    out = np.zeros(x.shape[0], bool)
    if ok.any():
        h = ecef2geodetic(x[ok, :3])[:, 2]
        out[ok] = (h > _H_MIN) & (h < _H_MAX)
    return out


def _check_inputs(sat_pos, pr, mask, sigma, x0, weighting):
    pr = np.asarray(pr, float)
    if pr.ndim != 2:
        raise DataError(f"pr must be (E, S), got shape {pr.shape}")
    E, S = pr.shape
    sat_pos = np.asarray(sat_pos, float)
    mask = np.asarray(mask)
    if sat_pos.shape != (E, S, 3):
        raise DataError(f"sat_pos has shape {sat_pos.shape}, expected {(E, S, 3)}")
    if mask.shape != (E, S) or mask.dtype != bool:
        raise DataError(f"mask must be bool {(E, S)}, got {mask.dtype} {mask.shape}")
    if sigma is None:
        if weighting == "uncertainty":
            raise DataError("weighting='uncertainty' needs sigma (pseudorange uncertainties)")
        sigma = np.ones((E, S))
    sigma = np.asarray(sigma, float)
    if sigma.shape != (E, S):
        raise DataError(f"sigma has shape {sigma.shape}, expected {(E, S)}")
    if x0 is not None:
        x0 = np.asarray(x0, float)
        if x0.shape == (3,):
            x0 = np.broadcast_to(x0, (E, 3))
        if x0.shape != (E, 3):
            raise DataError(f"x0 has shape {x0.shape}, expected {(E, 3)}")
    return sat_pos, pr, mask, sigma, x0


def estimate_wls(trace, wls: WlsResult, opts) -> ModeResult:
    """The WLS baseline as a mode (WLS is already solved by :func:`fusion.modes.run_modes`)."""
    # Copies: every mode receives the same WlsResult, so no mode's output may alias it.
    res = ModeResult(pos=wls.pos.copy(), valid=wls.valid.copy(), cov=wls.cov[:, :3, :3].copy(),
                     info={"unsolved": int((~wls.valid).sum()),
                           # epochs loaded with < 4 satellites (CLI loads with min_sats=1 so the
                           # fused modes can carry them; WLS solves only 3-satellite ones, below)
                           "lt4_sats": int((satellite_counts(trace.sat_id, trace.mask) < 4).sum()),
                           **wls_counts(wls)})
    return calibrate_snapshot(res, trace, "wls", opts, wls, used=wls.used)


def wls_counts(wls: WlsResult) -> dict[str, int]:
    """What the robust WLS did, for a mode's ``info`` (and so the report and metrics.json)."""
    out = {"excluded_measurements": int(wls.dropped.get("outlier", 0)),
           "epochs_with_exclusions": int(np.sum(wls.valid & (wls.n_excluded > 0))),
           "epochs_fault_undecided": int(np.sum(wls.flagged)),
           "epochs_clock_predicted": int(np.sum(wls.clock_predicted))}
    out.update({f"unsolved_{k}": v for k, v in wls.reasons.items()})
    return out
