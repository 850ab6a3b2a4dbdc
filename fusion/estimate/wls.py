"""Batched weighted least-squares (WLS) snapshot positioning: every epoch of a trace at once.

Unknowns per epoch: receiver ECEF position (x, y, z) and receiver clock ``c*dt`` [m]. The model is

    pr[e, s] = |R(omega_e * tau) sat_pos[e, s] - x[e]| + clock[e]  (+ noise)

with the Sagnac rotation done by :func:`fusion.geometry.line_of_sight`. Each epoch is an independent
snapshot: nothing (clock, position, weights) carries from one epoch to the next, so receiver clock
jumps cannot leak between epochs. Gauss-Newton runs on the padded (E, S) arrays; the only Python
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
4. Optional robust stage (``robust=True`` / ``"exclude"``): while the largest standardised
   residual of an epoch exceeds ``outlier_k`` and at least 5 satellites would remain, drop that
   satellite and re-solve (fault detection and exclusion; with 5 satellites a single fault cannot be
   told apart, hence >= 6 before a drop). ``robust="huber"``: iteratively reweighted least squares
   with Huber weights ``min(1, huber_k / |z|)`` on the standardised residuals ``z``.

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
and covariance; the batch never raises for a bad epoch.

All satellites share one receiver clock: the loaders' corrected pseudoranges already remove the
inter-signal range bias (``isrbM``), so one clock serves every constellation in the trace.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fusion.errors import DataError
from fusion.geometry import ecef2geodetic, elevation_azimuth, line_of_sight
from fusion.run_types import ModeResult
from fusion.trace import count_skip

#: goGPS default a-priori code standard deviation (``STD_CODE``) [m].
SIGMA0_M = 3.0
#: Mean Earth radius used for the coarse start [m].
_R_EARTH = 6_371_000.0
#: Positions farther than this from the Earth's centre mean Gauss-Newton has run away [m].
_R_RUNAWAY = 1.0e8
#: Plausible ellipsoidal heights of a phone (a car, a walker, an aircraft) [m].
_H_MIN, _H_MAX = -2_000.0, 100_000.0

#: Per-epoch status codes (``WlsResult.status``); 0 is the only valid one.
STATUS_NAMES: tuple[str, ...] = (
    "ok", "few_sats", "few_sats_after_mask", "degenerate", "diverged", "not_converged",
)
OK, FEW_SATS, FEW_SATS_AFTER_MASK, DEGENERATE, DIVERGED, NOT_CONVERGED = range(len(STATUS_NAMES))
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
               ``outlier``.
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
              weighting: str = "elevation", robust: bool | str = False, max_iter: int = 10,
              **kwargs) -> WlsResult:
    """WLS over every epoch of a :class:`fusion.trace.Trace` (see :func:`solve_wls_arrays`).

    x0: optional (E, 3) ECEF starting positions (NaN rows fall back to the coarse start); it is
    a *starting point* only - the result does not depend on it when Gauss-Newton converges.
    """
    return solve_wls_arrays(trace.sat_pos, trace.pr, trace.mask, trace.pr_sigma, x0,
                            elev_mask_deg=elev_mask_deg, weighting=weighting, robust=robust,
                            max_iter=max_iter, **kwargs)


def solve_wls_arrays(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                     sigma: np.ndarray | None = None, x0: np.ndarray | None = None, *,
                     elev_mask_deg: float = 10.0, weighting: str = "elevation",
                     robust: bool | str = False, max_iter: int = 10, max_cond: float = 1e7,
                     outlier_k: float = 4.0, huber_k: float = 1.5, sigma0: float = SIGMA0_M,
                     cov_scale: str = "posterior", tol_m: float = 1e-4) -> WlsResult:
    """Batched WLS on raw padded arrays (the engine behind :func:`solve_wls`).

    sat_pos: (E, S, 3) transmit-time satellite ECEF [m].
    pr:      (E, S)    corrected pseudoranges [m].
    mask:    (E, S)    bool, real slots.
    sigma:   (E, S)    1-sigma pseudorange uncertainty [m]; needed only for ``"uncertainty"``.
    x0:      (E, 3)    optional starting positions (NaN rows -> coarse start).

    Real slots with non-finite inputs (or a non-positive sigma under ``"uncertainty"``) are not
    used and are counted in ``dropped``; wrong shapes or option values raise :class:`DataError`.
    """
    sat_pos, pr, mask, sigma, x0 = _check_inputs(sat_pos, pr, mask, sigma, x0, weighting)
    robust_mode = _robust_mode(robust)
    if cov_scale not in ("posterior", "prior"):
        raise DataError(f"cov_scale must be 'posterior' or 'prior', got {cov_scale!r}")
    if max_iter < 1:
        raise DataError(f"max_iter must be >= 1, got {max_iter}")
    E, S = pr.shape
    dropped: dict[str, int] = {}

    # Slots we cannot use at all: counted, never silently.
    finite = np.isfinite(pr) & np.isfinite(sat_pos).all(-1)
    count_skip(dropped, "nonfinite_input", mask & ~finite)
    real = mask & finite
    if weighting == "uncertainty":
        good_sigma = np.isfinite(sigma) & (sigma > 0)
        count_skip(dropped, "bad_sigma", real & ~good_sigma)
        real &= good_sigma
    # Padding gets harmless finite values so the vectorised maths never meets NaN.
    sat_pos = np.where(real[..., None], sat_pos, 0.0)
    pr = np.where(real, pr, 0.0)

    status = np.zeros(E, np.int8)
    status[real.sum(1) < 4] = FEW_SATS
    n_iter = np.zeros(E, np.int64)

    # ---- 1. coarse stage: all satellites, unit weights. 100 m is ample: elevations only need km
    # accuracy, and one Gauss-Newton step from 100 m off lands within ~1e-6 m.
    x = _start_state(sat_pos, pr, real, x0)
    w1 = real.astype(float)
    alive = status == OK
    x, _, bad, runaway = _gauss_newton(sat_pos, pr, w1, x, alive, max(max_iter, 10), 100.0,
                                       max_cond, n_iter)
    status[alive & runaway] = DIVERGED
    # An ill-conditioned coarse stage may still recover once weights and mask change: the fine
    # stage decides about degeneracy.

    # ---- 2. elevation mask and weights, fixed from the coarse position
    alive = status == OK
    _, los = line_of_sight(sat_pos, x[:, :3])
    el, _ = elevation_azimuth(los, x[:, :3])
    el = np.where(real & alive[:, None], el, 0.0)
    used = real & (el >= elev_mask_deg)
    count_skip(dropped, "below_mask", real & ~used & alive[:, None])
    status[alive & (used.sum(1) < 4)] = FEW_SATS_AFTER_MASK
    used &= (status == OK)[:, None]
    sig = _sigmas(weighting, el, sigma, sigma0)
    w_prior = np.where(used, 1.0 / sig**2, 0.0)

    # ---- 3. fine stage
    alive = status == OK
    x, conv, bad, runaway = _gauss_newton(sat_pos, pr, w_prior, x, alive, max_iter, tol_m,
                                          max_cond, n_iter)

    # ---- 4. robust stage
    w_fit = w_prior
    if robust_mode == "exclude":
        x, used, conv, bad, runaway, w_fit = _exclude_outliers(
            sat_pos, pr, used, w_prior, x, alive & conv & ~bad & ~runaway, conv, bad, runaway,
            outlier_k, max_iter, tol_m, max_cond, n_iter, dropped)
    elif robust_mode == "huber":
        x, conv, bad, runaway, w_fit = _huber_irls(
            sat_pos, pr, used, w_prior, x, alive & conv & ~bad & ~runaway, conv, bad, runaway,
            huber_k, max_iter, tol_m, max_cond, n_iter)

    # ---- final evaluation at the solution: residuals, conditioning, covariance, plausibility
    N, b, r, H = _normal_equations(sat_pos, pr, w_fit, x)
    bad |= alive & _ill_conditioned(N, max_cond)
    plausible = _plausible(x)
    status[alive & bad] = DEGENERATE
    status[(status == OK) & (runaway | ~plausible)] = DIVERGED
    status[(status == OK) & ~conv] = NOT_CONVERGED
    valid = status == OK

    cov = np.full((E, 4, 4), np.nan)
    if valid.any():
        Ninv = np.linalg.inv(N[valid])
        n = used[valid].sum(1)
        chi2 = np.sum(w_fit[valid] * r[valid] ** 2, axis=1)
        f = np.ones(n.shape)
        if cov_scale == "posterior":
            red = n > 4
            f[red] = np.maximum(1.0, chi2[red] / (n[red] - 4))
        cov[valid] = f[:, None, None] * Ninv

    pos = np.where(valid[:, None], x[:, :3], np.nan)
    clock = np.where(valid, x[:, 3], np.nan)
    used &= valid[:, None]
    resid = np.where(real & valid[:, None], r, 0.0)
    reasons = {STATUS_NAMES[k]: int(np.sum(status == k)) for k in range(1, len(STATUS_NAMES))}
    return WlsResult(
        pos=pos, clock_m=clock, cov=cov, valid=valid, converged=conv,
        used=used, n_used=used.sum(1), resid=resid, elev_deg=el, status=status, n_iter=n_iter,
        reasons={k: v for k, v in reasons.items() if v}, dropped=dropped,
    )


# ------------------------------------------------------------------------------------- the engine
def _normal_equations(sat_pos, pr, w, x):
    """Linearise at state x (E, 4): returns N (E,4,4), b (E,4), residuals r (E,S), H (E,S,4)."""
    rng, los = line_of_sight(sat_pos, x[:, :3])
    H = np.concatenate([-los, np.ones(los.shape[:-1] + (1,))], axis=-1)
    r = pr - rng - x[:, 3:4]
    Hw = H * w[..., None]
    N = np.matmul(Hw.transpose(0, 2, 1), H)
    b = np.matmul(Hw.transpose(0, 2, 1), r[..., None])[..., 0]
    return N, b, r, H


def _ill_conditioned(N: np.ndarray, max_cond: float) -> np.ndarray:
    """(E,) True where the normal matrix is singular or badly conditioned.

    The test is on the Jacobi-scaled matrix C = D^-1/2 N D^-1/2 (unit diagonal), so it does not
    depend on how the weights are scaled. A cheap determinant screens every epoch: with trace(C) = 4,
    cond(C) <= 4^4 / det(C), so det(C) >= 256 / max_cond proves the epoch fine; only the few
    epochs that fail the screen pay for an eigen-decomposition.
    """
    out = np.ones(N.shape[0], bool)
    d = np.diagonal(N, axis1=1, axis2=2)
    ok = np.isfinite(N).all(axis=(1, 2)) & (d > 0).all(1)
    if not ok.any():
        return out
    s = 1.0 / np.sqrt(d[ok])
    C = N[ok] * s[:, :, None] * s[:, None, :]
    fine = np.linalg.det(C) >= 256.0 / max_cond
    if not fine.all():
        ev = np.linalg.eigvalsh(C[~fine])
        fine[~fine] = ev[:, 0] * max_cond >= ev[:, -1]
    out[ok] = ~fine
    return out


def _gauss_newton(sat_pos, pr, w, x, active, max_iter, tol, max_cond, n_iter):
    """Iterate the epochs in ``active`` until the state step is below ``tol`` [m].

    x: (E, 4) updated in place for active epochs. n_iter: (E,) incremented in place.
    Returns (x, converged, ill_conditioned, runaway), each flag (E,) bool.
    """
    E = x.shape[0]
    active = active.copy()
    conv = np.zeros(E, bool)
    bad = np.zeros(E, bool)
    runaway = np.zeros(E, bool)
    eye = np.eye(4)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        N, b, _, _ = _normal_equations(sat_pos[idx], pr[idx], w[idx], x[idx])
        sing = _ill_conditioned(N, max_cond)
        N[sing] = eye
        b[sing] = 0.0
        dx = np.linalg.solve(N, b[..., None])[..., 0]
        x[idx] += dx
        n_iter[idx] += 1
        step = np.linalg.norm(dx, axis=1)
        lost = ~np.isfinite(x[idx]).all(1) | (np.linalg.norm(x[idx, :3], axis=1) > _R_RUNAWAY)
        done = (step < tol) & ~sing & ~lost
        conv[idx[done]] = True
        bad[idx[sing]] = True
        runaway[idx[lost]] = True
        active[idx[done | sing | lost]] = False
    # A runaway state must not poison later stages with inf / NaN.
    x[runaway] = 0.0
    return x, conv, bad, runaway


def _standardised_residuals(sat_pos, pr, w, x, used):
    """|v| / sqrt(Qv_ii) with Qv = W^-1 - H N^-1 H^T (the residuals' own covariance).

    Unlike |v| * sqrt(w), this accounts for the fit pulling the residual of a faulty satellite
    toward zero. Returns (E, S) with 0 on unused slots.
    """
    N, _, r, H = _normal_equations(sat_pos, pr, w, x)
    safe = np.where(_ill_conditioned(N, 1e12)[:, None, None], np.eye(4), N)
    Ninv = np.linalg.inv(safe)
    hnh = np.einsum("esi,eij,esj->es", H, Ninv, H)
    qv = np.where(used, 1.0 / np.where(used, w, 1.0) - hnh, 1.0)
    z = np.abs(r) / np.sqrt(np.maximum(qv, 1e-12))
    return np.where(used, z, 0.0)


def _exclude_outliers(sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, k, max_iter,
                      tol, max_cond, n_iter, dropped):
    """Fault detection and exclusion, one satellite per epoch per round, all epochs at once."""
    used = used.copy()
    x_cur = x
    for _ in range(used.shape[1]):
        w = np.where(used, w_prior, 0.0)
        z = _standardised_residuals(sat_pos, pr, w, x_cur, used)
        worst = np.argmax(z, axis=1)
        zmax = z[np.arange(z.shape[0]), worst]
        drop = eligible & (zmax > k) & (used.sum(1) >= 6)
        if not drop.any():
            break
        idx = np.flatnonzero(drop)
        used[idx, worst[idx]] = False
        count_skip(dropped, "outlier", idx.size)
        w = np.where(used, w_prior, 0.0)
        x_cur, c2, b2, r2 = _gauss_newton(sat_pos, pr, w, x_cur, drop, max_iter, tol, max_cond,
                                          n_iter)
        conv = np.where(drop, c2, conv)
        bad = bad | (drop & b2)
        runaway = runaway | (drop & r2)
        eligible = eligible & ~(drop & (~c2 | b2 | r2))
    return x_cur, used, conv, bad, runaway, np.where(used, w_prior, 0.0)


def _huber_irls(sat_pos, pr, used, w_prior, x, eligible, conv, bad, runaway, k, max_iter, tol,
                max_cond, n_iter, rounds: int = 8):
    """Iteratively reweighted LS with Huber weights on standardised residuals."""
    w = np.where(used, w_prior, 0.0)
    for _ in range(rounds):
        # Standardise with the a-priori weights: with the current (reduced) ones a down-weighted
        # residual would look small next round and the weights would oscillate.
        z = _standardised_residuals(sat_pos, pr, np.where(used, w_prior, 0.0), x, used)
        w_new = np.where(used, w_prior * np.minimum(1.0, k / np.maximum(z, 1e-12)), 0.0)
        w_new = np.where(eligible[:, None], w_new, w)
        changed = eligible & (np.abs(w_new - w).max(1) > 1e-3 * w_prior.max(1, initial=0))
        w = w_new
        if not changed.any():
            break
        x, c2, b2, r2 = _gauss_newton(sat_pos, pr, w, x, changed, max_iter, tol, max_cond, n_iter)
        conv = np.where(changed, c2, conv)
        bad = bad | (changed & b2)
        runaway = runaway | (changed & r2)
        eligible = eligible & ~(changed & (~c2 | b2 | r2))
    return x, conv, bad, runaway, w


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
                            # fused modes can carry them; WLS cannot solve them)
                            "lt4_sats": int((trace.n_sats < 4).sum())})
