"""Reported sigmas that follow the environment: the a-posteriori variance factor of a solution's
pseudoranges in a sliding window of epochs, applied to a mode's position covariance.

A least-squares covariance ``(H^T W H)^-1`` is only as right as the a-priori sigmas in ``W``. The
textbook check is the variance factor ``sigma0^2 = sum(w r^2) / dof`` of the residuals ``r`` at the
solution: ~1 when the model holds, above 1 where the sigmas are too small (multipath, NLOS, a phone
whose reported uncertainty is optimistic). Here it is computed without truth for any position track:

- per epoch, the residuals of the pseudoranges at the track's position, the receiver clock (and one
  offset per signal, as the inter-system biases do) fitted by weighted mean; ``dof = n - offsets``;
- whitened squared residuals clipped at :data:`CLIP_SIGMAS` sigmas, so a lone gross outlier (which the
  robust solvers already down-weight) does not set the scale of a whole window;
- summed over a centred window of ``window_s`` seconds: ``F_k = sum chi2 / sum dof``, so the factor
  follows a drive from open sky into a street canyon.

The track is the mode's own solution with its own pseudorange noise (``factor_from="own"``) or the shared
WLS solution with the physical sigma model (``"wls"``: the textbook WLS variance factor, one measure of the
environment for every mode); which one serves a mode best was chosen with the rest of the settings.

:func:`calibrate_cov` then reports ``a * F^b * (C + snapshot * S) + diag(floor^2)`` per NED axis, where
``C`` is the mode's own covariance and ``S`` the one-epoch least-squares covariance at its positions
(:func:`snapshot_var`): a smoother's marginals shrink as if every epoch's errors were independent, but
multipath is correlated over many seconds, so a share of the one-epoch variance survives the averaging.
``a`` (a per-axis level), ``b`` (how strongly the covariance follows the factor; the textbook value is 1),
the window, the snapshot share and the per-axis floors (unmodelled error a residual cannot see) are tuned per
mode, leave-drives-out, on the twelve GSDC 2021 training drives and smartLoc only (:data:`DEFAULTS`;
``experiments/sigma_calibration.py``, ``experiments/results/sigma_calibration.md``). Positions never change:
only covariances. ``RunOptions.sigma_calibration`` (``--raw-sigmas``) switches it off.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fusion.estimate.graph.series import where_solved
from fusion.geometry import ecef2ned_cov, ecef2ned_vec, elevation_azimuth, line_of_sight, ned2ecef_cov
from fusion.trace import Trace

#: whitened residuals beyond this many sigmas count as this many (a gross outlier is the robust
#: solvers' business; it must not set the scale of a window)
CLIP_SIGMAS = 10.0


@dataclass(frozen=True)
class SigmaCalibration:
    """How one mode's covariance follows the variance factor: ``a * F^b * C + diag(floor_m^2)`` in NED.

    a (3,) per-axis level, b the exponent on the windowed variance factor F, floor_m (3,) [m] per axis,
    window_s the window's full length [s], min_dof the degrees of freedom a window needs (else F = the
    trace's own factor), snapshot the share of the one-epoch least-squares variance added before scaling
    (:func:`snapshot_var`: what time-correlated errors leave after a smoother's averaging), factor_from
    whose residuals make F: "own" (the mode's pseudoranges at its own positions, with its own noise) or
    "wls" (the shared WLS solution's: one measure of the environment for every mode); disagreement the share
    of the windowed mean squared difference, per NED axis, between a learned mode's positions and its answer
    without anything learned, added last (:func:`disagreement_var`): for ``dnn`` the WLS it corrected (robust
    unless ``--wls-plain``), for ``fused`` the same graph solved without the network (the unlearned modes have
    none)."""

    a: tuple[float, float, float] = (1.0, 1.0, 1.0)
    b: float = 1.0
    floor_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    window_s: float = 60.0
    min_dof: float = 10.0
    snapshot: float = 0.0
    factor_from: str = "own"
    disagreement: float = 0.0


def fitted_positions(mode: str, info: dict) -> bool:
    """Whether a mode's positions are one-epoch least-squares fits to the pseudoranges (:func:`whitened_residuals`'
    ``fitted``): wls, and dnn where the network's output is its learned-weight least squares (not the paper's
    correction added to WLS)."""
    return mode == "wls" or (mode == "dnn" and info.get("output") == "wls")


#: Per-mode settings, tuned leave-drives-out on the twelve GSDC 2021 training drives and smartLoc
#: (``experiments/results/sigma_calibration.md``). ``dnn`` / ``fused`` act on top of the checkpoint's own
#: (pooled, unseen-drive) calibration.
DEFAULTS: dict[str, SigmaCalibration] = {
    "wls": SigmaCalibration(a=(1.0615, 1.0661, 1.18), b=1.5, window_s=15.0, snapshot=0.3),
    "dnn": SigmaCalibration(a=(1.7678, 1.642, 2.2151), b=1.5, floor_m=(1.0, 1.0, 0.0), window_s=15.0,
                            snapshot=0.3),
    "fused-nodnn": SigmaCalibration(a=(1.1312, 1.4488, 1.32), b=1.5, floor_m=(0.0, 0.0, 2.0), window_s=15.0,
                                    snapshot=0.3, factor_from="wls"),
    "fused": SigmaCalibration(a=(0.7789, 0.7913, 1.1364), b=1.5, floor_m=(1.0, 1.0, 0.0), window_s=300.0,
                              snapshot=0.3, disagreement=1.0),
}

#: Per-mode settings at the epochs carrier phase ties to a neighbour (``info["carrier_linked"]``), where a mode has
#: one: its track there is right in shape to centimetres, and what remains is the slowly varying error the broadcast
#: corrections leave (about a metre), which no residual sees: a floor, little of the factor's scaling, and no share of
#: the disagreement. Tuned leave-traces-out on held-out simulated city traces with carrier phase and those errors
#: (``experiments/carrier_calibration.py``; one level for north and east): held out, 45 -> 32 of 60 trace-axes outside
#: 0.55-0.80, though 14 are now too confident (7 before). On the Pixel5 RINEX test trace (reported, not tuned on)
#: ``fused`` went 0.93 / 0.98 / 0.80 -> 0.70 / 0.76 / 0.69 within 1 sigma with broadcast GPS, 0.71 / 0.97 / 0.73 ->
#: 0.39 / 0.91 / 0.61 with SP3/CLK (a 1.2 m north offset under the floor). ``fused-nodnn``'s own setting gained
#: nothing there (``experiments/results/carrier_calibration.md``).
CARRIER_DEFAULTS: dict[str, SigmaCalibration] = {
    "fused": SigmaCalibration(a=(0.0399, 0.0399, 1.7549), b=1.5, floor_m=(1.0, 1.0, 0.0), window_s=15.0,
                              snapshot=0.3, factor_from="wls"),
}


def sigma_model(trace: Trace, pos: np.ndarray, elev_mask_deg: float, zenith_m: float = 1.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """The physical pseudorange model at ``pos`` (E,3) ECEF: slots above the mask (E,S) bool and their
    sigmas sqrt(pr_sigma^2 + (zenith_m / sin el)^2) (E,S) [m] (the graph's default model)."""
    at = where_solved(pos, 0.0)
    _, los = line_of_sight(trace.sat_pos, at)
    el, _ = elevation_azimuth(los, at)
    sel = trace.mask & (el >= elev_mask_deg) & np.isfinite(pos).all(axis=1)[:, None]
    sin_el = np.sin(np.radians(np.clip(el, 5.0, 90.0)))
    return sel, np.sqrt(np.nan_to_num(trace.pr_sigma, nan=0.0) ** 2 + (zenith_m / sin_el) ** 2)


def whitened_residuals(trace: Trace, pos: np.ndarray, sel: np.ndarray, sigma: np.ndarray,
                       bias: np.ndarray | None = None, fitted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Whitened pseudorange residuals at ``pos`` (E,3) with each epoch's clock and per-signal offsets
    fitted (weighted mean), and each epoch's degrees of freedom.

    sel (E,S) slots used; sigma (E,S) [m]; bias (E,S) [m] subtracted from pr (or None); fitted: ``pos`` was
    solved from these pseudoranges epoch by epoch (WLS), so an epoch without a slot to spare beyond its position
    and offsets (4 satellites of one signal) has zero residuals that say nothing about the noise: its dof is 0.
    Returns z (E,S) (NaN off ``sel``) and dof (E,) = used slots - signals present (0 where that is negative).
    The fitted epochs' dof keep the three their positions took: the calibration's level absorbs them, and
    counted out (the textbook factor) the leave-fold-out tuning fitted worse on every mode
    (experiments/results/sigma_calibration.md)."""
    ok = sel & np.isfinite(pos).all(axis=1)[:, None] & (sigma > 0) & np.isfinite(trace.pr)
    rng, _ = line_of_sight(trace.sat_pos, np.where(np.isfinite(pos), pos, 0.0))
    r = trace.pr - (0.0 if bias is None else np.nan_to_num(bias)) - rng
    w = np.where(ok, 1.0 / np.where(sigma > 0, sigma, 1.0) ** 2, 0.0)
    r = np.where(ok, r, 0.0)
    groups = np.unique(trace.signal[ok]) if ok.any() else np.zeros(0, trace.signal.dtype)
    onehot = trace.signal[..., None] == groups                  # (E,S,G)
    sw = np.einsum("es,esg->eg", w, onehot)
    offset = np.einsum("es,esg->eg", w * r, onehot) / np.where(sw > 0, sw, 1.0)
    r = r - np.einsum("eg,esg->es", offset, onehot)
    z = np.where(ok, r * np.sqrt(w), np.nan)
    dof = np.maximum(ok.sum(axis=1) - (sw > 0).sum(axis=1), 0)
    if fitted:
        dof = np.where(dof > 3, dof, 0)
    return z, dof


def snapshot_var(trace: Trace, pos: np.ndarray, sel: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(E,3) NED variances [m^2] of a one-epoch least-squares position at ``pos`` (E,3) from the slots
    ``sel`` (E,S) with sigmas ``sigma`` (E,S), a clock offset per signal estimated alongside: what an epoch's
    own geometry allows, before any averaging over time (NaN where the epoch cannot be solved)."""
    ok = sel & np.isfinite(pos).all(axis=1)[:, None] & (sigma > 0)
    at = np.where(np.isfinite(pos), pos, 0.0)
    _, los = line_of_sight(trace.sat_pos, at)
    groups = np.unique(trace.signal[ok]) if ok.any() else np.zeros(1, trace.signal.dtype)
    H = np.concatenate([-los, (trace.signal[..., None] == groups).astype(float)], axis=2)   # (E,S,3+G)
    w = np.where(ok, 1.0 / np.where(sigma > 0, sigma, 1.0) ** 2, 0.0)
    N = np.einsum("esi,es,esj->eij", H, w, H)
    absent = np.einsum("esg,es->eg", H[..., 3:], ok.astype(float)) == 0
    N[:, 3:, 3:] += np.einsum("eg,gh->egh", absent.astype(float), np.eye(len(groups)))  # decouple absent groups
    solvable = ok.sum(axis=1) >= 3 + (~absent).sum(axis=1)
    out = np.full((trace.n_epochs, 3), np.nan)
    if solvable.any():
        good = solvable.copy()
        good[solvable] = well_conditioned(N[solvable], 1e12)
        cov = np.linalg.inv(N[good])[:, :3, :3]
        out[good] = np.diagonal(ecef2ned_cov(cov, at[good]), axis1=1, axis2=2)
    return out


def well_conditioned(N: np.ndarray, limit: float) -> np.ndarray:
    """(K,) bool ``np.linalg.cond(N) < limit`` for symmetric positive semi-definite N (K, n, n).

    Eigenvalues in (0, trace] give ``cond <= trace^n / det``: where that bound is below the limit with a
    thousandfold margin (against the rounding of the determinant) the epoch is settled without its SVD,
    which leaves the SVD to the few near-singular epochs (a WLS trace: none of ~2000).
    """
    n = N.shape[-1]
    det = np.linalg.det(N) if N.shape[0] else np.zeros(0)
    sure = (det > 0) & (np.trace(N, axis1=1, axis2=2) ** n < 1e-3 * limit * det)
    out = sure.copy()
    if not sure.all():
        out[~sure] = np.linalg.cond(N[~sure]) < limit
    return out


def epoch_chi2(z: np.ndarray, clip: float = CLIP_SIGMAS) -> np.ndarray:
    """(E,) sum over each epoch's slots of min(z^2, clip^2) from whitened residuals z (E,S) (NaN: unused)."""
    return np.nansum(np.minimum(z ** 2, clip ** 2), axis=1)


def centred_sums(t_s: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Sums of ``x`` (E, ...) over the epochs within +-window_s/2 of each epoch (t_s (E,) ascending [s]), by
    running sums: O(E) whatever the spacing of the epochs."""
    x = np.asarray(x, float)
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    lo = np.searchsorted(t_s, t_s - window_s / 2, side="left")
    hi = np.searchsorted(t_s, t_s + window_s / 2, side="right")
    return c[hi] - c[lo]


def windowed_factor(t_s: np.ndarray, chi2: np.ndarray, dof: np.ndarray, window_s: float,
                    min_dof: float = 10.0) -> np.ndarray:
    """(E,) variance factor per epoch: sum of chi2 / sum of dof over epochs within +-window_s/2 of it.

    t_s (E,) ascending times [s]; chi2, dof (E,). A window with fewer than ``min_dof`` degrees of
    freedom takes the whole trace's factor; a trace without any takes 1."""
    chi2 = np.where(dof > 0, chi2, 0.0)
    wc, wd = centred_sums(t_s, np.c_[chi2, dof], window_s).T
    total_c, total_d = float(np.sum(chi2)), float(np.sum(dof))
    whole = total_c / total_d if total_d >= min_dof else 1.0
    return np.where(wd >= min_dof, wc / np.maximum(wd, 1e-12), whole)


def track_factor(trace: Trace, pos: np.ndarray, sel: np.ndarray, sigma: np.ndarray,
                 bias: np.ndarray | None, window_s: float, min_dof: float = 10.0, fitted: bool = False) -> np.ndarray:
    """(E,) windowed variance factor of a position track ``pos`` (E,3) (NaN rows: not solved; ``fitted`` as
    in :func:`whitened_residuals`)."""
    z, dof = whitened_residuals(trace, pos, sel, sigma, bias, fitted)
    return windowed_factor(trace.t_ms.astype(float) / 1000.0, epoch_chi2(z), dof, window_s, min_dof)


def calibrate_cov(cov_ecef: np.ndarray, pos: np.ndarray, factor: np.ndarray, cal: SigmaCalibration,
                  snap_var: np.ndarray | None = None, dis_var: np.ndarray | None = None) -> np.ndarray:
    """``a * F^b * (C + snapshot * diag(snap_var)) + diag(floor^2) + disagreement * diag(dis_var)`` per NED axis
    at ``pos`` (E,3): cov_ecef (E,3,3) [m^2], factor (E,), snap_var (E,3) NED [m^2] (:func:`snapshot_var`),
    dis_var (E,3) NED [m^2] (:func:`disagreement_var`; either NaN or None: 0). Rows with a NaN position or
    covariance are returned as they were."""
    cov = np.array(cov_ecef, float, copy=True)
    ok = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(pos).all(axis=1) & np.isfinite(factor)
    if not ok.any():
        return cov
    ned = ecef2ned_cov(cov[ok], pos[ok])
    if snap_var is not None and cal.snapshot > 0:
        # errors that are correlated over time (multipath) do not average out in a smoother: a share of
        # the one-epoch variance stays, whatever the marginal says
        ned = ned + cal.snapshot * np.nan_to_num(snap_var[ok])[:, :, None] * np.eye(3)
    s = np.sqrt(np.asarray(cal.a, float)[None, :] * np.maximum(factor[ok], 1e-6)[:, None] ** cal.b)   # (N,3)
    ned = ned * s[:, :, None] * s[:, None, :] + np.eye(3) * np.asarray(cal.floor_m, float) ** 2
    if dis_var is not None and cal.disagreement > 0:
        # not scaled by the factor: where the learned inputs moved the solution, the truth is no closer to
        # either answer than they are to each other, whatever the residuals say
        ned = ned + cal.disagreement * np.nan_to_num(dis_var[ok])[:, :, None] * np.eye(3)
    cov[ok] = ned2ecef_cov(ned, pos[ok])
    return cov


def disagreement_var(t_s: np.ndarray, pos: np.ndarray, ref: np.ndarray, window_s: float) -> np.ndarray:
    """(E,3) NED mean squared difference [m^2] between positions ``pos`` (E,3) ECEF and ``ref`` (E,3) ECEF
    over a centred window of ``window_s`` seconds (times ``t_s`` (E,) ascending; rows where either is NaN
    count in no window; an epoch whose window holds none gets 0)."""
    ok = np.isfinite(pos).all(axis=1) & np.isfinite(ref).all(axis=1)
    sq = np.zeros((len(t_s), 4))
    if ok.any():
        sq[ok, :3] = ecef2ned_vec(pos[ok] - ref[ok], pos[ok]) ** 2
    sq[:, 3] = ok
    s = centred_sums(t_s, sq, window_s)
    return s[:, :3] / np.maximum(s[:, 3], 1.0)[:, None]


def wls_track(trace: Trace, wls, elev_mask_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shared WLS solution as (pos (E,3), slots (E,S), sigmas (E,S)) for :func:`track_factor`: its
    positions (NaN where not solved), the slots it kept and the physical sigma model."""
    pos = np.where(np.asarray(wls.valid, bool)[:, None], wls.pos, np.nan)
    sel, sigma = sigma_model(trace, pos, elev_mask_deg)
    return pos, sel & np.asarray(wls.used, bool), sigma


def solved_positions(result) -> np.ndarray:
    """(E,3) a result's positions, NaN where it did not solve the epoch."""
    return np.where(np.asarray(result.valid, bool)[:, None], result.pos, np.nan)


def calibrate_result(result, trace: Trace, mode: str, sel: np.ndarray, sigma: np.ndarray,
                     bias: np.ndarray | None = None, cal: SigmaCalibration | None = None,
                     wls: tuple | None = None, unlearned: np.ndarray | None = None, snap: np.ndarray | None = None):
    """A mode's :class:`~fusion.run_types.ModeResult` with its covariance calibrated in place (positions
    untouched) and the factor's median in ``info["variance_factor_p50"]``.

    sel, sigma, bias (E,S): the mode's own pseudorange slots, sigmas and biases (its snapshot covariance,
    and its factor where ``cal.factor_from == "own"``); wls: :func:`wls_track` (the factor where
    ``cal.factor_from == "wls"``); cal: :data:`DEFAULTS` of ``mode`` unless given; unlearned (E,3) ECEF: the
    mode's answer without the network (dnn: the WLS it corrected; fused: the same graph solved without the
    learned inputs), for its :func:`disagreement_var` (None: no such term); snap (E,3): :func:`snapshot_var` at
    the result's positions with ``sel`` and ``sigma`` where the caller has it (None: computed if ``cal`` needs it).
    A result without a covariance is returned as it is."""
    if result.cov is None or not np.asarray(result.valid).any():
        return result
    cal = cal or DEFAULTS[mode]
    pos = solved_positions(result)
    if cal.factor_from == "wls" and wls is not None:
        f = track_factor(trace, wls[0], wls[1], wls[2], None, cal.window_s, cal.min_dof, fitted=True)
    else:
        f = track_factor(trace, pos, sel, sigma, bias, cal.window_s, cal.min_dof,
                         fitted=fitted_positions(mode, result.info))
    if cal.snapshot > 0 and snap is None:
        snap = snapshot_var(trace, pos, sel, sigma)
    dis = None
    if cal.disagreement > 0 and unlearned is not None:
        dis = disagreement_var(trace.t_ms.astype(float) / 1000.0, pos, unlearned, cal.window_s)
    result.cov = calibrate_cov(result.cov, pos, f, cal, snap, dis)
    result.info["variance_factor_p50"] = float(np.median(f[np.asarray(result.valid, bool)]))
    return result


def calibrate_snapshot(result, trace: Trace, mode: str, opts, wls, used: np.ndarray | None = None):
    """``wls`` / ``dnn``: :func:`calibrate_result` with the physical sigma model at the mode's own positions
    (``used`` (E,S): the slots the solver kept, e.g. WLS after fault exclusion), the shared WLS solution
    ``wls`` and, for ``dnn``, the WLS positions it corrected (``info["unlearned_pos"]``, (E,3)), when
    ``opts.sigma_calibration``."""
    if not getattr(opts, "sigma_calibration", False) or result.cov is None:
        return result
    sel, sigma = sigma_model(trace, solved_positions(result), opts.elev_mask_deg)
    cal = DEFAULTS[mode]
    track = wls_track(trace, wls, opts.elev_mask_deg) if cal.factor_from == "wls" else None   # else unused
    return calibrate_result(result, trace, mode, sel if used is None else sel & used, sigma, cal=cal, wls=track,
                            unlearned=result.info.get("unlearned_pos"))


def calibrate_graph(result, trace: Trace, mode: str, opts, wls):
    """Graph modes: :func:`calibrate_result` with the graph's own pseudorange noise (``info["pr_noise"]``:
    slots, sigmas, biases, each (E,S), left there by the solve), the shared WLS solution ``wls`` and, for
    ``fused``, its solve without anything learned (``info["unlearned_pos"]``, (E,3)), when
    ``opts.sigma_calibration``; at the epochs carrier phase ties (``info["carrier_linked"]``) the mode's
    :data:`CARRIER_DEFAULTS` where it has one and ``opts.carrier_sigma_calibration`` (their count in
    ``info["carrier_calibrated"]``)."""
    noise = result.info.get("pr_noise")
    if not getattr(opts, "sigma_calibration", False) or noise is None or result.cov is None:
        return result
    track = wls_track(trace, wls, opts.elev_mask_deg)
    linked = np.asarray(result.info.get("carrier_linked", np.zeros(trace.n_epochs, bool)), bool) \
        & np.asarray(result.valid, bool)
    carrier, snap = None, None
    if getattr(opts, "carrier_sigma_calibration", True) and mode in CARRIER_DEFAULTS and linked.any():
        # both settings take the same one-epoch variances: computed once
        snap = snapshot_var(trace, solved_positions(result), *noise[:2])
        carrier = replace(result, cov=result.cov.copy(), info=dict(result.info))
        carrier = calibrate_result(carrier, trace, mode, *noise, cal=CARRIER_DEFAULTS[mode], wls=track,
                                   unlearned=result.info.get("unlearned_pos"), snap=snap).cov
    result = calibrate_result(result, trace, mode, *noise, wls=track, unlearned=result.info.get("unlearned_pos"),
                              snap=snap)
    if carrier is not None:
        result.cov = np.where(linked[:, None, None], carrier, result.cov)
        result.info["carrier_calibrated"] = int(linked.sum())
    return scale_bridged(result, opts.graph.bridged_sigma_scale, opts.graph.bridged_sigma_scale_down)


def scale_bridged(result, scale_h: float, scale_down: float):
    """The result with the covariance of its bridged epochs without Doppler (``info["bridged_without_doppler"]``
    (E,) bool: fewer than 4 satellites, no prior, no Doppler) scaled by ``scale_h`` on the north and east axes
    and ``scale_down`` on the down axis (their squares on the variances), in place: there the velocity is the
    motion model's alone, no residual says how wrong that model is, and the variance factor cannot see it
    (GraphConfig.bridged_sigma_scale, bridged_sigma_scale_down)."""
    bridged = result.info.get("bridged_without_doppler")
    if result.cov is None or (scale_h, scale_down) == (1.0, 1.0) or not isinstance(bridged, np.ndarray) \
            or not bridged.any():
        return result
    result.cov = result.cov.copy()
    d = np.array([scale_h, scale_h, scale_down])
    ned = ecef2ned_cov(result.cov[bridged], result.pos[bridged]) * d[:, None] * d[None, :]
    result.cov[bridged] = ned2ecef_cov(ned, result.pos[bridged])
    return result
