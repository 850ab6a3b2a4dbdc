"""Factor-graph building blocks for the fused modes: settings, per-epoch inputs, GTSAM factors.

The graph has, per epoch ``k``:

- ``x(k)``: receiver position, ``Point3`` ECEF [m];
- ``b(k)``: receiver clock bias in *seconds* (GTSAM's ``PseudorangeFactor`` multiplies it by c;
  our code carries the clock in metres and converts only here), created only for epochs with at
  least one pseudorange;
- ``v(k)``: velocity ECEF [m/s], only with ``motion="cv"``;
- ``i(16 * comp + g)``: inter-system bias [m] of signal group ``g`` (every signal other than the
  reference, GPS L1 when present) in motion component ``comp`` (a window without gaps), only with
  ``isb="window"`` and only for groups that occur. Such a signal's pseudorange is modelled as
  range + c*b(k) + ISB through GTSAM's C++ ``DifferentialPseudorangeFactor``, whose correction
  variable enters as ``pr = range + c*b - corr``: the key holds ``-ISB``.

Factors: one robust ``PseudorangeFactor`` per selected satellite, an optional
``PriorFactorPoint3`` from a *position prior provider* (the learned correction), motion factors
between consecutive epochs, and a clock random walk (``BetweenFactorDouble``) whose mean follows
the clock drift seen in the WLS clock series.

Sagnac: GTSAM 4.3's ``PseudorangeFactor`` already adds the Earth-rotation range term
``OMEGA_E / c * (x_sat * y_rx - y_sat * x_rx)`` to the geometric range (checked against
:func:`fusion.geometry.line_of_sight` in ``tests/test_graph.py``), which is the first-order form of
:func:`fusion.geometry.sagnac_rotate`. Satellite positions are therefore passed at transmit time,
unrotated: rotating them as well would apply the correction twice.

Everything except the final factor construction is vectorised over epochs and satellites; the
factor loop is inherent to GTSAM's Python API (one object per factor) and costs a few µs each.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.geometry import C_LIGHT, elevation_azimuth, line_of_sight, ned_rotation
from fusion.trace import Trace

#: ``provider(trace, init_pos (E,3), valid (E,)) -> (mean_ecef (E,3), cov_ecef (E,3,3), valid (E,))``
PriorProvider = Callable[[Trace, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def X(k: int) -> int:
    """Key of the position at epoch ``k``."""
    return gtsam.symbol("x", k)


def B(k: int) -> int:
    """Key of the receiver clock (seconds) at epoch ``k``."""
    return gtsam.symbol("b", k)


def V(k: int) -> int:
    """Key of the velocity at epoch ``k`` (constant-velocity motion only)."""
    return gtsam.symbol("v", k)


#: signal groups per component are packed into one key index: 16 > len(SIGNALS)
ISB_STRIDE = 16


def I(comp: int, group: int) -> int:
    """Key of the (negated) inter-system bias [m] of signal ``group`` in motion component ``comp``."""
    return gtsam.symbol("i", ISB_STRIDE * comp + group)


@dataclass
class GraphConfig:
    """Noise and robustness settings. Defaults were tuned on the training traces only
    (2020-05-14-US-MTV-1, 2020-06-05-US-MTV-1, 2020-09-04-US-SF-2); ``benchmarks/bench_graph.py
    --part tune [--weights CKPT]`` reprints both tables.

    Graph (fused-nodnn, mean GSDC score over the three training traces, one change at a time from
    the round-1 defaults, 3.975 m): pr_sigma_zenith_m 1.5 -> 1.0 (3.927), robust_k 1 -> 2 (3.913),
    cv_accel_v 0.5 -> 0.2 (3.907); together 3.846 m. No other single change in ``GRAPH_GRID`` helped
    (huber, pr_sigma_scale 0.5/2, cv_accel_h 0.5/2, cv_pos_sigma 0.2/1, clock_rw 2/20, motion rw: 3.93-4.75).

    Learned prior, round 3 (weights trained on a 75% WLS-based / 25% paper-box guess mix with
    per-axis variance calibration; tuned on 2020-09-04-US-SF-2 with a leave-one-out model: the
    recipe of ``learned/weights/TRAINING.md`` (same data, options and seed) trained without
    2020-09-04-US-SF-2; ``bench_graph.py --part prior --weights CKPT``). There:
    wls h p50 5.17 / p95 13.83 / score 9.50 m; fused-nodnn 2.80 / 5.98 / 4.39; the network alone
    asked at the graph solution 4.61 / 10.97 / 7.79, at WLS 4.62 / 12.25 / 8.43. The network output
    is computed once per guess and reused for every row. GSDC score [m] (h p95 in brackets):

    ========= ======= ============ ============ ============ ============ ============ ============
    prior at          graph                                  wls
    --------- ------- -------------------------------------- --------------------------------------
    cov scale floor m none         huber(1)     cauchy(1)    none         huber(1)     cauchy(1)
    ========= ======= ============ ============ ============ ============ ============ ============
    1         0       4.58 (6.35)  4.46 (6.13)  4.35 (5.94)  4.64 (6.52)  4.51 (6.26)  4.42 (6.08)
    1         2       4.54 (6.26)  4.45 (6.09)  4.36 (5.92)  4.58 (6.37)  4.53 (6.30)  4.41 (6.06)
    2         0       4.50 (6.21)  4.42 (6.05)  4.38 (5.97)  4.51 (6.25)  4.43 (6.08)  4.42 (6.07)
    2         2       4.45 (6.10)  4.45 (6.11)  4.39 (5.98)  4.48 (6.19)  4.42 (6.07)  4.42 (6.06)
    4         0       4.44 (6.10)  4.40 (6.01)  4.40 (6.00)  4.47 (6.18)  4.42 (6.06)  4.42 (6.04)
    4         2       4.45 (6.10)  4.40 (6.01)  4.41 (6.01)  4.45 (6.14)  4.42 (6.07)  4.43 (6.06)
    16        0       4.40 (6.01)  4.40 (6.01)  4.37 (5.95)  4.40 (6.00)  4.40 (6.00)  4.38 (5.96)
    16        2       4.40 (6.01)  4.40 (6.01)  4.37 (5.95)  4.40 (6.00)  4.40 (6.00)  4.38 (5.96)
    ========= ======= ============ ============ ============ ============ ============ ============

    Asking the network at the no-prior graph solution still beats asking it at WLS (in every row
    but one), although it was trained around WLS guesses: the better guess gives the better
    correction. With the calibrated variances the cauchy(1) loss no longer needs inflation:
    chosen graph / 1 / 2 m / cauchy(1), 4.36 m, 0.01 m from the best row (floor 0), kept for
    safety against over-confident outputs on unseen data. The gain over fused-nodnn on this
    held-out trace is small (0.03 m score, p95 5.98 -> 5.92); without the robust loss the prior
    still costs up to 0.19 m. Round 2 (older box-only weights, their recipe likewise trained
    without 2020-09-04-US-SF-2): best 16 / 2 m / cauchy(1) at 4.42, prior never beat fused-nodnn
    (4.39).
        """

    # Pseudorange sigma [m]: sqrt((pr_sigma_scale * pr_sigma)^2 + (pr_sigma_zenith_m / sin(el))^2).
    pr_sigma_scale: float = 1.0
    pr_sigma_zenith_m: float = 1.0
    robust: str = "cauchy"             # "huber", "cauchy" or "none"
    robust_k: float = 2.0              # scale on the whitened residual
    # Motion: "rw" = zero-mean position random walk; "cv" = velocity states, constant velocity.
    motion: str = "cv"
    # rw: per-axis position step sigma per second [m/s] (horizontal / vertical, NED at the epoch).
    rw_sigma_h_mps: float = 10.0
    rw_sigma_v_mps: float = 2.0
    # cv: velocity random walk [m/s per sqrt(s)] horizontal / vertical; position process noise
    # [m per sqrt(s)] on p_k = p_{k-1} + v_{k-1} dt.
    cv_accel_h: float = 1.0
    cv_accel_v: float = 0.2
    cv_pos_sigma_m: float = 0.5
    max_gap_s: float = 10.0            # motion chain broken beyond this epoch gap
    # Clock random walk around the WLS-derived drift: sigma = clock_sigma_m + clock_rw_m * sqrt(dt).
    clock_sigma_m: float = 2.0
    clock_rw_m: float = 5.0
    clock_jump_m: float = 1000.0       # WLS clock step beyond drift larger than this = clock reset
    drift_window: int = 5              # epochs each side for the robust WLS clock-drift estimate
    # Learned prior: covariance used = prior_cov_scale * cov + prior_sigma_floor_m^2 * I.
    # Where the provider is asked: "graph" = at the solution of the same graph without the prior
    # (a better guess than WLS, around which the network was trained: on a held-out training trace
    # this beat asking at WLS, see the table above); "wls" = at the WLS positions (one solve
    # instead of two).
    # Incremental mode uses the no-prior smoother's *online* estimates, so it stays causal.
    prior_at: str = "graph"
    prior_cov_scale: float = 1.0
    prior_sigma_floor_m: float = 2.0
    # robust loss on the prior's Mahalanobis distance (in sigmas), so that a wrong network output
    # cannot drag the solution: "huber", "cauchy", "none"
    prior_robust: str = "cauchy"
    prior_robust_k: float = 1.0
    # Batch solver: LM stops when the cost improves by less than this fraction (1e-6 took 2-4x the
    # iterations for < 1 cm change on the training traces).
    lm_rel_tol: float = 1e-4
    lm_max_iter: int = 50
    # Incremental (ISAM2): relinearisation threshold and extra update() calls after the last epoch.
    isam_relin_threshold: float = 0.05
    isam_settle: int = 2
    # relinearisation checked every 5th update: 2.5x faster than every update, same accuracy on the
    # training traces
    isam_relin_skip: int = 5
    # ISAM2 stops back-substitution below this change. GTSAM has one threshold for all variables,
    # so it is applied in clock units (isam_wildfire_m / c seconds), i.e. effectively full
    # propagation for positions (see benchmarks/bench_graph.py for the ms/epoch this costs).
    isam_wildfire_m: float = 0.001
    # Inter-system biases: "window" = one constant bias per non-reference signal (GLONASS G1,
    # Galileo E1, BeiDou B1I, ... vs GPS L1) per motion component; "none" = one clock for all.
    # The zero-mean prior sigma was chosen a priori, not tuned: the derived files' isrbM already
    # removes the bulk of the bias, the residue is metres, and 10 m leaves it free while keeping a
    # group seen by a single satellite determinable. GPS-only traces get no bias states at all.
    isb: str = "window"
    isb_sigma_m: float = 10.0


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
    dropped: counts by reason.
    isb_group (E,S) int: signal group of each slot (-1 = reference clock or ``isb="none"``);
    isb_new (E,G) bool: epoch k is the first in its component to use group g (its bias key and
    prior are introduced there); isb_init_m (G,) initial bias per group;
    isb_groups: the SIGNALS index of each group.
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
    isb_group: np.ndarray
    isb_new: np.ndarray | None = None
    isb_init_m: np.ndarray | None = None
    isb_groups: tuple = ()


# ---------------------------------------------------------------------------- vectorised inputs
def _interp_rows(t: np.ndarray, rows: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Fill rows where ``ok`` is False by linear interpolation in time (ends held constant)."""
    out = rows.copy()
    if ok.all():
        return out
    for j in range(rows.shape[1]):  # 3 columns, not epochs
        out[~ok, j] = np.interp(t[~ok], t[ok], rows[ok, j])
    return out


def _rolling_nanmedian(x: np.ndarray, w: int) -> np.ndarray:
    """Median of x over a centred window of 2w+1 samples, ignoring NaN (all-NaN -> NaN)."""
    pad = np.concatenate([np.full(w, np.nan), x, np.full(w, np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * w + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows -> NaN, on purpose
        return np.nanmedian(win, axis=1)


def _ned_cov_to_ecef(ref: np.ndarray, var_n: np.ndarray, var_e: np.ndarray, var_d: np.ndarray) -> np.ndarray:
    """(E,3,3) ECEF covariances of diagonal NED covariances at ``ref`` (E,3)."""
    R = ned_rotation(ref)                                   # v_ned = R v_ecef
    D = np.stack([var_n, var_e, var_d], axis=-1)            # (E,3)
    return np.einsum("eji,ej,ejk->eik", R, D, R)


#: smallest eigenvalue [m^2] a provider's covariance needs to be used as a prior
PRIOR_MIN_EIG = 1e-6


@dataclass
class Priors:
    """A provider's output made safe for the graph (see :func:`clean_priors`), E epochs.

    mean (E,3) ECEF (0 where not ok); cov (E,3,3) the covariance used (identity where not ok);
    ok (E,) bool usable; finite (E,) bool mean and covariance finite; spd (E,) bool covariance
    positive definite (smallest eigenvalue > ``PRIOR_MIN_EIG``, identity where not finite).
    """

    mean: np.ndarray
    cov: np.ndarray
    ok: np.ndarray
    finite: np.ndarray
    spd: np.ndarray


def clean_priors(mean: np.ndarray, cov: np.ndarray, valid: np.ndarray, scale: float, floor_m: float,
                 what: str = "cov_scale / sigma_floor_m") -> Priors:
    """The one rule turning a provider's (mean (E,3), cov (E,3,3), valid (E,)) into priors.

    A prior is used where the provider said valid, mean and covariance are finite and the
    symmetrised covariance is positive definite; the covariance used is then
    ``scale * cov + floor_m**2 * I`` (inflation: the network's covariance ignores that its errors
    are correlated from epoch to epoch; floor: see the GraphConfig table). ``what`` names the
    options in the error raised when scale <= 0 or floor_m < 0.
    """
    if not (scale > 0 and floor_m >= 0):
        raise GeometryError(f"{what}: the covariance scale must be > 0 and the sigma floor >= 0, got "
                            f"{scale} and {floor_m}")
    mean, cov, valid = np.asarray(mean, float), np.asarray(cov, float), np.asarray(valid, bool)
    finite = np.isfinite(mean).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    cov_safe = np.where(finite[:, None, None], 0.5 * (cov + cov.transpose(0, 2, 1)), np.eye(3))
    # a singular / indefinite covariance from the provider is a defect: reject it before the
    # floor below would hide it
    spd = np.linalg.eigvalsh(cov_safe)[:, 0] > PRIOR_MIN_EIG
    ok = valid & finite & spd
    used = scale * cov_safe + floor_m ** 2 * np.eye(3)
    return Priors(mean=np.where(ok[:, None], mean, 0.0), cov=np.where(ok[:, None, None], used, np.eye(3)),
                  ok=ok, finite=finite, spd=spd)


def prepare_inputs(trace: Trace, wls, cfg: GraphConfig, elev_mask_deg: float = 10.0,
                   provider: PriorProvider | None = None, prior_guess: np.ndarray | None = None) -> EpochInputs:
    """Initial values, satellite selection, sigmas, chain links and priors for every epoch.

    wls: a ``fusion.wls.WlsResult`` (pos (E,3), clock_m (E,), valid (E,), used (E,S)).
    prior_guess: (E,3) positions at which to ask the provider (NaN rows: the initial position);
    None = the initial positions (WLS, interpolated where it failed). ``fusion.graph.fuse`` passes
    the no-prior graph solution under ``prior_at="graph"`` and None under ``prior_at="wls"``.
    Raises :class:`GeometryError` when no epoch has any usable initial position.
    """
    E = trace.n_epochs
    t = trace.t_ms.astype(float) / 1000.0
    wls_ok = np.asarray(wls.valid, bool) & np.isfinite(wls.pos).all(axis=1)
    dropped: dict[str, int] = {}

    # --- initial positions: WLS, interpolated in time where WLS failed
    if not wls_ok.any():
        raise GeometryError(f"{trace.name}: WLS solved no epoch, so the graph has no initial position")
    init_pos = _interp_rows(t, np.asarray(wls.pos, float), wls_ok)

    # --- the learned prior, asked at prior_guess (else at the initial positions every mode sees)
    prior_mean = np.zeros((E, 3))
    prior_cov = np.tile(np.eye(3), (E, 1, 1))
    prior_ok = np.zeros(E, bool)
    if provider is not None:
        ask = trace.n_sats >= 1
        at = init_pos
        if prior_guess is not None:
            at = np.where(np.isfinite(prior_guess).all(axis=1)[:, None], prior_guess, init_pos)
        pm, pc, pv = provider(trace, at, ask)
        pm, pc, pv = np.asarray(pm, float), np.asarray(pc, float), np.asarray(pv, bool)
        if pm.shape != (E, 3) or pc.shape != (E, 3, 3) or pv.shape != (E,):
            raise GeometryError(f"{trace.name}: prior provider returned shapes {pm.shape}, {pc.shape}, "
                                f"{pv.shape}; expected {(E, 3)}, {(E, 3, 3)}, {(E,)}")
        pri = clean_priors(pm, pc, pv, cfg.prior_cov_scale, cfg.prior_sigma_floor_m,
                           what="GraphConfig: prior_cov_scale / prior_sigma_floor_m")
        prior_mean, prior_cov, prior_ok = pri.mean, pri.cov, pri.ok
        dropped["prior_rejected"] = int((pv & ~(pri.finite & pri.spd)).sum())

    # --- satellite selection and sigmas at the initial position
    rng, los = line_of_sight(trace.sat_pos, init_pos)
    el, _ = elevation_azimuth(los, init_pos)
    sel = trace.mask & (el >= elev_mask_deg)
    if getattr(wls, "used", None) is not None:
        # where WLS solved, trust its choice (it may have excluded outliers); elsewhere elevation only
        sel &= np.where(wls_ok[:, None], np.asarray(wls.used, bool), True)
    sin_el = np.sin(np.radians(np.clip(el, 5.0, 90.0)))
    sigma = np.sqrt((cfg.pr_sigma_scale * trace.pr_sigma) ** 2 + (cfg.pr_sigma_zenith_m / sin_el) ** 2)
    n_sel = sel.sum(axis=1)

    # --- clock initial values: WLS where solved, else the median residual at the initial position
    resid = np.where(sel, trace.pr - rng, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # epochs without satellites -> NaN
        med = np.nanmedian(resid, axis=1)
    init_clock = np.where(wls_ok, np.asarray(wls.clock_m, float), med)
    init_clock = np.where(n_sel > 0, init_clock, np.nan)

    # --- motion chain: broken by long gaps
    dt = np.concatenate([[0.0], np.diff(t)])
    pos_link = np.concatenate([[False], dt[1:] <= cfg.max_gap_s])
    comp = np.cumsum(~pos_link) - 1

    # --- velocities for the cv model: central differences of the initial track within components
    init_vel = np.zeros((E, 3))
    if E > 1:
        fwd = np.diff(init_pos, axis=0) / np.maximum(dt[1:], 1e-3)[:, None]
        fwd = np.where(pos_link[1:, None], fwd, np.nan)
        both = np.stack([np.vstack([fwd, np.full((1, 3), np.nan)]), np.vstack([np.full((1, 3), np.nan), fwd])])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # isolated epochs -> 0 velocity
            init_vel = np.nan_to_num(np.nanmean(both, axis=0))

    # --- clock chain: link each clock to the previous epoch that has one, unless reset/gap.
    has_clock = n_sel > 0
    idx = np.arange(E)
    last_clock = np.maximum.accumulate(np.where(has_clock, idx, -1))
    prev_clock = np.concatenate([[-1], last_clock[:-1]])            # latest clock epoch before k
    # drift from the WLS clock series (metres per second), robust to single bad epochs
    cw = np.where(wls_ok, np.asarray(wls.clock_m, float), np.nan)
    rate = np.full(E, np.nan)
    rate[1:] = np.diff(cw) / np.maximum(dt[1:], 1e-3)
    rate = np.where(pos_link, rate, np.nan)
    drift = _rolling_nanmedian(rate, cfg.drift_window)
    drift = np.nan_to_num(_interp_rows(t, drift[:, None], np.isfinite(drift))[:, 0]) if np.isfinite(drift).any() \
        else np.zeros(E)
    # resets: flagged by the loader, or the WLS clock stepping far from the drift between consecutive
    # WLS-solved epochs. A step seen across WLS-failed epochs may have happened at any of them, so
    # every epoch from the one after the last solved clock up to the detection is marked.
    reset = np.asarray(trace.clock_reset, bool).copy()
    solved = np.flatnonzero(np.isfinite(cw))
    if len(solved) > 1:
        a, b = solved[:-1], solved[1:]
        big = np.abs(cw[b] - cw[a] - drift[b] * (t[b] - t[a])) > cfg.clock_jump_m
        for lo, hi in zip(a[big] + 1, b[big] + 1):
            reset[lo:hi] = True
    # any reset (or chain break) in (prev_clock, k] breaks the clock link
    breaks = np.cumsum(reset | ~pos_link)
    safe_prev = np.maximum(prev_clock, 0)
    span = t - t[safe_prev]
    clock_link = np.where(has_clock & (prev_clock >= 0) & (breaks == breaks[safe_prev]), prev_clock, -1)
    clock_mean = drift * span
    clock_sig = cfg.clock_sigma_m + cfg.clock_rw_m * np.sqrt(np.maximum(span, 0.0))
    # one jump seen across n WLS-failed epochs marks n epochs but is one reset
    dropped["clock_resets"] = int((reset & ~np.r_[False, reset[:-1]]).sum())

    # --- determinability: a motion component needs an anchor (an epoch with >= 4 pseudoranges or a
    # prior); the clocks are then fixed by their pseudoranges. Others are dropped and counted.
    anchor = (n_sel >= 4) | prior_ok
    comp_ok = np.bincount(comp, weights=anchor.astype(float), minlength=comp.max() + 1) > 0
    keep = comp_ok[comp]
    dropped["epochs_undetermined"] = int((~keep).sum())
    inp = EpochInputs(init_pos=init_pos, init_clock_m=init_clock, init_vel=init_vel, sel=sel, sigma=sigma,
                      dt=dt, pos_link=pos_link, clock_link=clock_link, clock_mean_m=clock_mean,
                      clock_sigma_m=clock_sig, prior_mean=prior_mean, prior_cov=prior_cov,
                      prior_ok=prior_ok, keep=keep, comp=comp, dropped=dropped,
                      isb_group=np.full(trace.mask.shape, -1, np.int64))
    _isb_inputs(trace, inp, resid, cfg)
    return inp


def _isb_inputs(trace: Trace, inp: EpochInputs, resid: np.ndarray, cfg: GraphConfig) -> None:
    """Signal groups, first-use epochs and initial values of the inter-system biases (in place;
    ``inp.isb_group`` comes in all -1).

    resid (E,S): pseudorange minus range at the initial position (NaN where not selected).
    """
    E = inp.sel.shape[0]
    if cfg.isb == "none":
        return
    if cfg.isb != "window":
        raise GeometryError(f"unknown isb model {cfg.isb!r}; choose window or none")
    if not cfg.isb_sigma_m > 0:
        raise GeometryError(f"GraphConfig: isb_sigma_m must be > 0, got {cfg.isb_sigma_m}")
    sig = np.asarray(trace.signal, np.int64)
    present = np.unique(sig[inp.sel])
    if present.size <= 1:
        return                                   # one signal: its clock is the receiver clock
    ref = 0 if 0 in present else int(present[0])   # SIGNALS[0] = GPS_L1
    groups = tuple(int(g) for g in present if g != ref)
    new = np.zeros((E, len(groups)), bool)
    init = np.zeros(len(groups))
    # bias residue per satellite: pseudorange residual minus the epoch's (reference) clock
    d = resid - inp.init_clock_m[:, None]
    starts = np.r_[0, np.flatnonzero(np.diff(inp.comp)) + 1]
    for g, sg in enumerate(groups):              # a handful of signal groups, not epochs
        in_g = inp.sel & (sig == sg)
        inp.isb_group[in_g] = g
        used = in_g.any(axis=1)
        # first epoch of each component using this group: use count since the component start is 1
        cnt = np.cumsum(used)
        before = np.concatenate([[0], cnt[:-1]])[starts]
        new[:, g] = used & (cnt - before[inp.comp] == 1)
        # one trace-wide starting value (the factors are linear in the bias, so LM needs no better)
        init[g] = np.nan_to_num(np.nanmedian(np.where(in_g, d, np.nan)))
    inp.isb_new, inp.isb_init_m, inp.isb_groups = new, init, groups


# ---------------------------------------------------------------------------- factors
def robust_model(kind: str, k: float, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """``base`` wrapped in a robust loss. GTSAM applies the M-estimator to the norm of the
    *whitened* error, i.e. to the Mahalanobis distance for a full-covariance ``base`` (checked in
    ``tests/test_graph.py``), so ``k`` is in sigmas whatever the covariance."""
    if kind == "none":
        return base
    if kind == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(k)
    elif kind == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    else:
        raise GeometryError(f"unknown robust loss {kind!r}; choose huber, cauchy or none")
    return gtsam.noiseModel.Robust.Create(est, base)


def prior_noise_model(cov: np.ndarray, robust: str = "none", robust_k: float = 1.0) -> gtsam.noiseModel.Base:
    """Noise model of one position prior: Gaussian with ``cov`` (3,3) (already cleaned by
    :func:`clean_priors`), wrapped in ``robust`` ("huber", "cauchy", "none") at ``robust_k`` sigmas."""
    return robust_model(robust, robust_k, gtsam.noiseModel.Gaussian.Covariance(cov))


def _robust(cfg: GraphConfig, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    return robust_model(cfg.robust, cfg.robust_k, base)


def pseudorange_factor(key_x: int, key_b: int, pr_m: float, sat_pos: np.ndarray, sigma_m: float,
                       cfg: GraphConfig) -> gtsam.PseudorangeFactor:
    """One robust pseudorange factor; ``sat_pos`` at transmit time (GTSAM adds the Sagnac term)."""
    return gtsam.PseudorangeFactor(key_x, key_b, float(pr_m), sat_pos, 0.0,
                                   _robust(cfg, gtsam.noiseModel.Isotropic.Sigma(1, float(sigma_m))))


class MotionNoise:
    """Per-epoch motion covariances, computed once for the whole trace (vectorised)."""

    def __init__(self, inp: EpochInputs, cfg: GraphConfig):
        dt = np.maximum(inp.dt, 1e-3)
        if cfg.motion == "rw":
            var_h, var_v = (cfg.rw_sigma_h_mps * dt) ** 2, (cfg.rw_sigma_v_mps * dt) ** 2
            self.cov = _ned_cov_to_ecef(inp.init_pos, var_h, var_h, var_v)
        elif cfg.motion == "cv":
            # velocity random walk; position follows p_k = p_{k-1} + v_{k-1} dt with small noise
            var_h, var_v = cfg.cv_accel_h ** 2 * dt, cfg.cv_accel_v ** 2 * dt
            self.vel_cov = _ned_cov_to_ecef(inp.init_pos, var_h, var_h, var_v)
            self.pos_sqrt_info = 1.0 / (cfg.cv_pos_sigma_m * np.sqrt(dt))
        else:
            raise GeometryError(f"unknown motion model {cfg.motion!r}; choose rw or cv")


def motion_factors(k: int, inp: EpochInputs, noise: MotionNoise, cfg: GraphConfig) -> list:
    """Factors tying epoch k to k-1 (caller checks ``inp.pos_link[k]``)."""
    if cfg.motion == "rw":
        return [gtsam.BetweenFactorPoint3(X(k - 1), X(k), np.zeros(3),
                                          gtsam.noiseModel.Gaussian.Covariance(noise.cov[k]))]
    # p_k - p_{k-1} - dt v_{k-1} = 0 is linear, so a whitened JacobianFactor wrapped for the
    # nonlinear graph is exact and runs in C++ (a Python CustomFactor would be far slower). With
    # an all-zero linearisation point its error is exactly A x - b.
    w = noise.pos_sqrt_info[k]
    I3 = np.eye(3)
    jf = gtsam.JacobianFactor(X(k), w * I3, X(k - 1), -w * I3, V(k - 1), -w * inp.dt[k] * I3,
                              np.zeros(3), gtsam.noiseModel.Unit.Create(3))
    lin = gtsam.Values()
    for key in (X(k), X(k - 1), V(k - 1)):
        lin.insert(key, _ZERO3)
    return [gtsam.LinearContainerFactor(jf, lin),
            gtsam.BetweenFactorPoint3(V(k - 1), V(k), np.zeros(3),
                                      gtsam.noiseModel.Gaussian.Covariance(noise.vel_cov[k]))]


_ZERO3 = np.zeros(3)


def epoch_factors(k: int, trace: Trace, inp: EpochInputs, noise: MotionNoise, cfg: GraphConfig,
                  use_prior: bool) -> tuple[list, gtsam.Values]:
    """Factors and initial values introduced by epoch ``k`` (links point backwards only, so the
    same function feeds the batch graph and the incremental smoother)."""
    factors: list = []
    vals = gtsam.Values()
    vals.insert(X(k), inp.init_pos[k])
    c_sel = np.flatnonzero(inp.sel[k])
    if c_sel.size:
        vals.insert(B(k), float(inp.init_clock_m[k] / C_LIGHT))
        grp = inp.isb_group[k]
        comp = int(inp.comp[k])
        if inp.isb_new is not None:
            for g in np.flatnonzero(inp.isb_new[k]):   # bias first used here: value + prior
                key = I(comp, int(g))
                vals.insert(key, float(-inp.isb_init_m[g]))
                factors.append(gtsam.PriorFactorDouble(key, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, float(cfg.isb_sigma_m))))
        for s in c_sel:
            if grp[s] < 0:
                factors.append(pseudorange_factor(X(k), B(k), trace.pr[k, s], trace.sat_pos[k, s],
                                                  inp.sigma[k, s], cfg))
            else:
                factors.append(gtsam.DifferentialPseudorangeFactor(
                    X(k), B(k), I(comp, int(grp[s])), float(trace.pr[k, s]), trace.sat_pos[k, s], 0.0,
                    _robust(cfg, gtsam.noiseModel.Isotropic.Sigma(1, float(inp.sigma[k, s])))))
        j = int(inp.clock_link[k])
        if j >= 0:
            factors.append(gtsam.BetweenFactorDouble(
                B(j), B(k), float(inp.clock_mean_m[k] / C_LIGHT),
                gtsam.noiseModel.Isotropic.Sigma(1, float(inp.clock_sigma_m[k] / C_LIGHT))))
    if use_prior and inp.prior_ok[k]:
        model = prior_noise_model(inp.prior_cov[k], cfg.prior_robust, cfg.prior_robust_k)
        factors.append(gtsam.PriorFactorPoint3(X(k), inp.prior_mean[k], model))
    if cfg.motion == "cv":
        vals.insert(V(k), inp.init_vel[k])
    if k > 0 and inp.pos_link[k]:
        factors.extend(motion_factors(k, inp, noise, cfg))
    elif cfg.motion == "cv":
        # a component's first velocity is otherwise free when the component has a single epoch
        factors.append(gtsam.PriorFactorPoint3(V(k), inp.init_vel[k], gtsam.noiseModel.Isotropic.Sigma(3, 50.0)))
    return factors, vals
