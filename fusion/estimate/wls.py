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
   :func:`solve_wls` and of the pipeline): RAIM-style fault detection and exclusion - a chi-square
   test on the weighted residuals, then the smallest set of satellites (at most ``max_exclusions``,
   never below 5 left) whose removal passes it excluded; an epoch no allowed exclusion repairs is
   kept, ``flagged``, and solved with Huber weights so that the fault it holds pulls less. With epoch
   times (``t_ms``), the flagged epochs and those left with at most
   :data:`NEIGHBOUR_CHECK_MAX_SATS` satellites (a test of little power) are first checked against
   the position predicted from the settled epochs around them (:mod:`fusion.estimate.neighbour_fde`). ``robust="huber"``: iteratively reweighted least
   squares with Huber weights ``min(1, huber_k / |z|)`` on the standardised residuals ``z``.
   ``robust=False``: the paper's plain WLS.
5. Three-satellite epochs (with ``t_ms``): solved for position alone with the receiver clock
   interpolated from the valid epochs around them (:mod:`fusion.estimate.clock_bridge`); flagged in
   ``clock_predicted``, or left unsolved as ``three_sats_no_clock``.

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
An epoch is ``valid`` only when it had >= 4 satellites after the mask, a well-conditioned normal
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
from fusion.estimate.lsq import gauss_newton, ill_conditioned, normal_equations
from fusion.estimate.neighbour_fde import exclude_by_neighbours
from fusion.estimate.raim import exclude_faults, huber_irls, variance_factor
from fusion.geometry import ecef2geodetic, elevation_azimuth, line_of_sight
from fusion.run_types import ModeResult
from fusion.trace import count_skip

#: goGPS default a-priori code standard deviation (``STD_CODE``) [m].
SIGMA0_M = 3.0
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
_WEIGHTINGS = ("elevation", "uncertainty", "none")


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

    def __post_init__(self) -> None:
        E = self.valid.shape[0]
        if self.n_excluded is None:
            self.n_excluded = np.zeros(E, np.int64)
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
def solve_wls(trace, *, x0: np.ndarray | None = None, elev_mask_deg: float = 10.0,
              weighting: str = "elevation", robust: bool | str = "exclude", max_iter: int = 10,
              **kwargs) -> WlsResult:
    """WLS over every epoch of a :class:`fusion.trace.Trace` (see :func:`solve_wls_arrays`), with
    fault detection and exclusion by default (``robust=False`` / ``"none"``: the plain baseline) and
    three-satellite epochs solved with the clock interpolated from their neighbours. The fault test's
    variance is calibrated on the trace (``test_scale="trace"``, :func:`fusion.estimate.raim.variance_factor`).

    x0: optional (E, 3) ECEF starting positions (NaN rows fall back to the coarse start); it is
    a *starting point* only - the result does not depend on it when Gauss-Newton converges.
    """
    kwargs.setdefault("test_scale", "trace")
    return solve_wls_arrays(trace.sat_pos, trace.pr, trace.mask, trace.pr_sigma, x0,
                            elev_mask_deg=elev_mask_deg, weighting=weighting, robust=robust,
                            max_iter=max_iter, t_ms=trace.t_ms, clock_reset=trace.clock_reset, **kwargs)


def solve_wls_arrays(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                     sigma: np.ndarray | None = None, x0: np.ndarray | None = None, *,
                     elev_mask_deg: float = 10.0, weighting: str = "elevation",
                     robust: bool | str = False, max_iter: int = 10, max_cond: float = 1e7,
                     max_exclusions: int = 3, huber_k: float = 1.5, sigma0: float = SIGMA0_M,
                     cov_scale: str = "posterior", tol_m: float = 1e-4, t_ms: np.ndarray | None = None,
                     clock_reset: np.ndarray | None = None, test_scale: float | str = 1.0) -> WlsResult:
    """Batched WLS on raw padded arrays (the engine behind :func:`solve_wls`).

    sat_pos:     (E, S, 3) transmit-time satellite ECEF [m].
    pr:          (E, S)    corrected pseudoranges [m].
    mask:        (E, S)    bool, real slots.
    sigma:       (E, S)    1-sigma pseudorange uncertainty [m]; needed only for ``"uncertainty"``.
    x0:          (E, 3)    optional starting positions (NaN rows -> coarse start).
    t_ms:        (E,)      epoch times; with it, three-satellite epochs are solved with the clock
                           interpolated from neighbouring valid epochs (:mod:`fusion.estimate.clock_bridge`).
    clock_reset: (E,)      bool, known clock jumps (no clock is interpolated across one).
    test_scale:  variance factor of the a-priori sigmas for the fault test: a number, or ``"trace"``
                 to estimate it from this batch's residuals (then epochs are no longer independent).

    Real slots with non-finite inputs (or a non-positive sigma under ``"uncertainty"``) are not
    used and are counted in ``dropped``; wrong shapes or option values raise :class:`DataError`.
    """
    sat_pos, pr, mask, sigma, x0 = _check_inputs(sat_pos, pr, mask, sigma, x0, weighting)
    robust_mode = _robust_mode(robust)
    _check_options(cov_scale, max_iter, max_exclusions)
    dropped: dict[str, int] = {}
    sat_pos, pr, real = _usable_slots(sat_pos, pr, mask, sigma, weighting, dropped)
    E = pr.shape[0]
    status = np.where(real.sum(1) < 4, FEW_SATS, OK).astype(np.int8)
    n_iter = np.zeros(E, np.int64)
    x, used, el, w_prior = _coarse_and_mask(sat_pos, pr, real, x0, status, elev_mask_deg, weighting,
                                            sigma, sigma0, max_iter, max_cond, n_iter, dropped)
    # fine stage: weighted, to the step tolerance
    alive = status == OK
    x, conv, bad, runaway = gauss_newton(sat_pos, pr, w_prior, x, alive, max_iter, tol_m, max_cond, n_iter)
    eligible = alive & conv & ~bad & ~runaway
    flagged, n_excluded = np.zeros(E, bool), np.zeros(E, np.int64)
    w_fit = w_prior
    if robust_mode == "exclude":
        kw = dict(max_exclusions=max_exclusions, max_iter=max_iter, tol=tol_m, max_cond=max_cond, n_iter=n_iter)
        x, used, conv, bad, runaway, w_fit, flagged, n_excluded = _exclude(
            sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, test_scale, kw, dropped, t_ms)
        if flagged.any():
            x, conv, bad, runaway, w_fit = huber_irls(sat_pos, pr, used, w_prior, x, flagged, conv, bad,
                                                      runaway, huber_k, max_iter, tol_m, max_cond, n_iter)
    elif robust_mode == "huber":
        x, conv, bad, runaway, w_fit = huber_irls(sat_pos, pr, used, w_prior, x, eligible, conv, bad,
                                                  runaway, huber_k, max_iter, tol_m, max_cond, n_iter)
    res = _finish(sat_pos, pr, real, used, w_fit, x, el, status, alive, conv, bad, runaway, n_iter,
                  max_cond, cov_scale, dropped)
    res.flagged = flagged & res.valid
    res.n_excluded = n_excluded
    if t_ms is not None:
        _bridge_three_sat_epochs(res, sat_pos, pr, real, np.asarray(t_ms), clock_reset, elev_mask_deg,
                                 weighting, sigma, sigma0, max_iter, tol_m)
    return res


# ------------------------------------------------------------------------------------- the stages
def _exclude(sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, test_scale, kw, dropped, t_ms):
    """Snapshot fault detection and exclusion (:func:`_fde`), then, with epoch times, the epochs it
    could not decide identified from their neighbours (:mod:`fusion.estimate.neighbour_fde`).
    Returns :func:`fusion.estimate.raim.exclude_faults`'s tuple."""
    above_mask = used
    (x, used, conv, bad, runaway, w_fit, flagged, n_excl), scale = _fde(
        sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, test_scale, kw, dropped)
    settled = eligible & ~flagged & conv & ~bad & ~runaway
    # the undecided epochs, and those whose test has little power (one or two redundant satellites)
    weak = flagged | (settled & (used.sum(1) <= NEIGHBOUR_CHECK_MAX_SATS))
    if t_ms is None or not weak.any():
        return x, used, conv, bad, runaway, w_fit, flagged, n_excl
    x, used, conv, bad, runaway, repaired, n_excl = exclude_by_neighbours(
        sat_pos, pr, above_mask, used, w_prior, x, weak, settled & ~weak, np.asarray(t_ms), conv, bad,
        runaway, n_excl, scale=scale, dropped=dropped, **kw)
    return x, used, conv, bad, runaway, np.where(used, w_prior, 0.0), flagged & ~repaired, n_excl


def _fde(sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, test_scale, kw, dropped):
    """Fault detection and exclusion (:func:`fusion.estimate.raim.exclude_faults`). With
    ``test_scale="trace"`` a first pass at the a-priori variance gives the residuals of the epochs
    it settled, whose robust variance factor (:func:`fusion.estimate.raim.variance_factor`) sets the
    test of the second, final pass; a factor of 1 keeps the first pass. Returns
    (:func:`fusion.estimate.raim.exclude_faults`'s tuple, the variance factor of the test)."""
    scale = 1.0 if test_scale == "trace" else float(test_scale)
    first = exclude_faults(sat_pos, pr, used, w_prior, x.copy(), eligible, conv, bad.copy(), runaway.copy(),
                           dropped=dropped if test_scale != "trace" else {}, scale=scale, **kw)
    if test_scale != "trace":
        return first, scale
    x1, used1, _, bad1, run1, w1, flagged1, _ = first
    settled = eligible & ~flagged1 & ~bad1 & ~run1
    scale = variance_factor(sat_pos, pr, w1, x1, used1, settled)
    if scale == 1.0:
        count_skip(dropped, "outlier", first[-1])
        return first, scale
    return exclude_faults(sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, dropped=dropped,
                          scale=scale, **kw), scale


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


def _coarse_and_mask(sat_pos, pr, real, x0, status, elev_mask_deg, weighting, sigma, sigma0, max_iter,
                     max_cond, n_iter, dropped):
    """Coarse fix (all satellites, unit weights), then the elevation mask and a-priori weights.

    ``status`` (E,) is updated in place. Returns x (E,4), used (E,S), elevations (E,S) [deg] and
    weights (E,S). 100 m is ample for the coarse stage: elevations only need km accuracy, and one
    Gauss-Newton step from 100 m off lands within ~1e-6 m.
    """
    x = _start_state(sat_pos, pr, real, x0)
    alive = status == OK
    x, _, _, runaway = gauss_newton(sat_pos, pr, real.astype(float), x, alive, max(max_iter, 10), 100.0,
                                    max_cond, n_iter)
    # An ill-conditioned coarse stage may still recover once weights and mask change: the fine
    # stage decides about degeneracy.
    status[alive & runaway] = DIVERGED
    alive = status == OK
    el = _elevations(sat_pos, x[:, :3], real & alive[:, None])
    used = real & (el >= elev_mask_deg)
    count_skip(dropped, "below_mask", real & ~used & alive[:, None])
    status[alive & (used.sum(1) < 4)] = FEW_SATS_AFTER_MASK
    used &= (status == OK)[:, None]
    w_prior = np.where(used, 1.0 / _sigmas(weighting, el, sigma, sigma0) ** 2, 0.0)
    return x, used, el, w_prior


def _elevations(sat_pos, pos, where):
    """(E,S) elevation [deg] of each satellite seen from pos (E,3); 0 outside ``where`` (E,S)."""
    _, los = line_of_sight(sat_pos, pos)
    el, _ = elevation_azimuth(los, pos)
    return np.where(where, el, 0.0)


def _finish(sat_pos, pr, real, used, w_fit, x, el, status, alive, conv, bad, runaway, n_iter, max_cond,
            cov_scale, dropped) -> WlsResult:
    """Final evaluation at the solution: residuals, conditioning, plausibility, covariance."""
    N, _, r, _ = normal_equations(sat_pos, pr, w_fit, x)
    bad = bad | (alive & ill_conditioned(N, max_cond))
    status[alive & bad] = DEGENERATE
    status[(status == OK) & (runaway | ~_plausible(x))] = DIVERGED
    status[(status == OK) & ~conv] = NOT_CONVERGED
    valid = status == OK
    cov = np.full((x.shape[0], 4, 4), np.nan)
    if valid.any():
        n = used[valid].sum(1)
        chi2 = np.sum(w_fit[valid] * r[valid] ** 2, axis=1)
        f = np.ones(n.shape)
        if cov_scale == "posterior":
            red = n > 4
            f[red] = np.maximum(1.0, chi2[red] / (n[red] - 4))
        cov[valid] = f[:, None, None] * np.linalg.inv(N[valid])
    used = used & valid[:, None]
    return WlsResult(
        pos=np.where(valid[:, None], x[:, :3], np.nan), clock_m=np.where(valid, x[:, 3], np.nan), cov=cov,
        valid=valid, converged=conv, used=used, n_used=used.sum(1),
        resid=np.where(real & valid[:, None], r, 0.0), elev_deg=el, status=status, n_iter=n_iter,
        reasons=_reasons(status), dropped=dropped)


def _reasons(status: np.ndarray) -> dict[str, int]:
    counts = {STATUS_NAMES[k]: int(np.sum(status == k)) for k in range(1, len(STATUS_NAMES))}
    return {k: v for k, v in counts.items() if v}


def _bridge_three_sat_epochs(res: WlsResult, sat_pos, pr, real, t_ms, clock_reset, elev_mask_deg, weighting,
                             sigma, sigma0, max_iter, tol) -> None:
    """Solve (in place) epochs left with exactly three satellites above the mask, the clock
    interpolated from the valid epochs around them (:mod:`fusion.estimate.clock_bridge`)."""
    few = np.flatnonzero(np.isin(res.status, (FEW_SATS, FEW_SATS_AFTER_MASK)) & (real.sum(1) >= 3))
    good = np.flatnonzero(res.valid)
    if few.size == 0 or good.size == 0:
        return
    near = good[np.clip(np.searchsorted(good, few), 1, good.size) - 1]   # a valid neighbour's position
    pos0 = res.pos[near]
    el = _elevations(sat_pos[few], pos0, real[few])
    used = real[few] & (el >= elev_mask_deg)
    few, pos0, el, used = (a[used.sum(1) == 3] for a in (few, pos0, el, used))
    resets = np.zeros(res.n_epochs, bool) if clock_reset is None else np.asarray(clock_reset, bool)
    clock, ok = interpolate_clock(t_ms, res.clock_m, res.valid, resets, few)
    res.status[few[~ok]] = THREE_SATS_NO_CLOCK
    w = np.where(used, 1.0 / _sigmas(weighting, el, sigma[few], sigma0) ** 2, 0.0)
    pos, conv, cov3 = solve_fixed_clock(sat_pos[few], pr[few], w, pos0, np.where(ok, clock, 0.0), max_iter, tol)
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
    res.n_used[e] = 3
    res.elev_deg[e] = el[good_fix]
    res.reasons = _reasons(res.status)


# ------------------------------------------------------------------------------------- helpers
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


def _sigmas(weighting, el_deg, sigma, sigma0):
    """(E, S) a-priori pseudorange sigmas [m] for the chosen weighting."""
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


def _check_options(cov_scale, max_iter, max_exclusions) -> None:
    if cov_scale not in ("posterior", "prior"):
        raise DataError(f"cov_scale must be 'posterior' or 'prior', got {cov_scale!r}")
    if max_iter < 1:
        raise DataError(f"max_iter must be >= 1, got {max_iter}")
    if max_exclusions < 0:
        raise DataError(f"max_exclusions must be >= 0, got {max_exclusions}")


def _robust_mode(robust) -> str:
    if robust is False or robust is None or robust == "none":
        return "none"
    if robust is True or robust == "exclude":
        return "exclude"
    if robust == "huber":
        return "huber"
    raise DataError(f"robust must be False, True, 'exclude' or 'huber', got {robust!r}")


def _check_inputs(sat_pos, pr, mask, sigma, x0, weighting):
    if weighting not in _WEIGHTINGS:
        raise DataError(f"weighting must be one of {_WEIGHTINGS}, got {weighting!r}")
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
    return ModeResult(pos=wls.pos.copy(), valid=wls.valid.copy(), cov=wls.cov[:, :3, :3].copy(),
                      info={"unsolved": int((~wls.valid).sum()),
                            # epochs loaded with < 4 measurements (CLI loads with min_sats=1 so the
                            # fused modes can carry them; WLS solves only 3-satellite ones, below)
                            "lt4_sats": int((trace.n_sats < 4).sum()),
                            **wls_counts(wls)})


def wls_counts(wls: WlsResult) -> dict[str, int]:
    """What the robust WLS did, for a mode's ``info`` (and so the report and metrics.json)."""
    out = {"excluded_measurements": int(wls.dropped.get("outlier", 0)),
           "epochs_with_exclusions": int(np.sum(wls.valid & (wls.n_excluded > 0))),
           "epochs_fault_undecided": int(np.sum(wls.flagged)),
           "epochs_clock_predicted": int(np.sum(wls.clock_predicted))}
    out.update({f"unsolved_{k}": v for k, v in wls.reasons.items()})
    return out
