"""The ``dnn`` and ``fused`` pipeline modes: the trained network wired into fusion's estimators.

``fusion``'s mode registry names these functions by string (``"learned.modes:estimate_dnn"``). Neither
imports torch: the network runs in numpy (:mod:`learned.npnet`), asked once per run (``fused``: its
pseudorange sigmas once more, :func:`sigmas_again`).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.estimate.graph.batch import BatchSolution
from fusion.estimate.graph.fuse import (bridge_flags, calibrated, fuse, learned_guess, learned_guess_start_solved,
                                       solve_graph)
from fusion.estimate.graph.priors import LearnedGraphInputs, PriorProvider
from fusion.estimate.graph.series import where_solved
from fusion.estimate.neighbour_fde import GATE, PRED_SIGMA_M, gross_outliers
from fusion.estimate.variance_factor import calibrate_snapshot, sigma_model, track_factor
from fusion.estimate.wls import NEIGHBOUR_CHECK_MAX_SATS, TRACE_DEFAULTS, WlsResult, solve_wls_arrays
from fusion.geometry import ecef2ned_cov, ecef2ned_vec, ned2ecef_cov
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace, satellite_counts
from learned.infer import Corrector

#: Furthest settled neighbour the fault screen predicts from [ms]: runs of weak epochs (five or six
#: satellites) last seconds; a gross fault (> 80 m) stands out of a five-second interpolation.
SCREEN_GAP_MS = 5000
#: Rounds of the fault screen (each repairs the weak epochs next to those repaired before).
SCREEN_ROUNDS = 3
#: An epoch is screened when its fix lies farther than this from its neighbours' prediction [m], and counts
#: as repaired when its re-solved fix lies within it: the neighbour check's gate on a prediction error
#: (4 x 10 m, :mod:`fusion.estimate.neighbour_fde`).
PREDICTION_GATE_M = GATE * PRED_SIGMA_M
#: Largest 3-D position sigma [m] (the WLS's a-posteriori covariance) of an epoch that predicts for the
#: screen: 1.5 x the prediction's assumed 10 m, for the vertical. Chosen on smartLoc (GPS only: in a canyon
#: predictions from imprecise neighbours moved good fixes by tens of metres) and the fault injection.
SETTLED_SIGMA_M = 15.0


def estimate_dnn(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """Pipeline mode ``dnn``: one network pass at the WLS positions (learned-weight least squares or the
    paper's correction, ``opts.dnn_output``). Epochs with invalid WLS or < 4 satellites: not solved.
    ``opts.dnn_passes`` > 1 re-asks the network at its own output (features recomputed each pass).
    The measurements the robust WLS excluded as faults do not reach the network (a +200 m fault would
    otherwise pull its learned-weight solution: ``experiments/robust_wls.py --dnn``)."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    pos, valid = np.asarray(wls.pos, float), np.asarray(wls.valid, bool)
    cov, too_few, c = None, 0, None
    drop, pos = fault_screen(trace, wls, opts)
    guess = np.where(valid[:, None], pos, np.nan)
    for _ in range(max(1, int(opts.dnn_passes))):
        c = corrector.predict(trace, pos, valid, elev_mask_deg=opts.elev_mask_deg, output=opts.dnn_output,
                              drop=drop)
        too_few += c.n_too_few
        pos, valid, cov = c.mean_ecef, c.valid, c.cov_ecef
    info = {"passes": int(max(1, opts.dnn_passes)), "unsolved": int((~valid).sum()),
            "unsolved_wls": int((~np.asarray(wls.valid, bool)).sum()), "too_few_sats": too_few,
            "output": opts.dnn_output or corrector.output, "weights": str(corrector.path),
            "guard_shrunk": c.info["epochs_guard_shrunk"], "guard_off": c.info["epochs_guard_off"],
            "meas_fault_screened": int(np.sum(drop)),
            # flat, so that metrics.json (which keeps scalar info) and the report carry them
            **{f"learned_{k}": v for k, v in c.info.items()},
            **learned_move(pos, guess, valid),
            "unlearned_pos": guess}       # what the network corrected: the WLS (its sigma calibration)
    return calibrate_snapshot(ModeResult(pos=pos, valid=valid, cov=cov, info=info), trace, "dnn", opts, wls)


def learned_move(pos: np.ndarray, unlearned: np.ndarray, valid: np.ndarray) -> dict[str, float]:
    """How far the network moved a mode's solution from its answer without it: the median and 95th percentile
    horizontal distance [m] (``learned_move_h_p50_m``, ``learned_move_h_p95_m``; none where no epoch has both).
    pos, unlearned (E,3) ECEF; valid (E,) bool."""
    ok = np.asarray(valid, bool) & np.isfinite(pos).all(axis=1) & np.isfinite(unlearned).all(axis=1)
    if not ok.any():
        return {}
    h = np.linalg.norm(ecef2ned_vec(pos[ok] - unlearned[ok], pos[ok])[:, :2], axis=1)
    return {"learned_move_h_p50_m": float(np.median(h)), "learned_move_h_p95_m": float(np.percentile(h, 95))}


def fault_screen(trace: Trace, wls: WlsResult, opts: RunOptions) -> tuple[np.ndarray, np.ndarray]:
    """The measurements the ``dnn`` mode's network must not see, and its guess.

    Those the robust WLS excluded as faults, except on the epochs whose test has little power (flagged,
    or at most :data:`fusion.estimate.wls.NEIGHBOUR_CHECK_MAX_SATS` satellites) and whose fix lies more
    than :data:`PREDICTION_GATE_M` from the position precise neighbours (3-D sigma at most
    :data:`SETTLED_SIGMA_M`) predict: there, those deviating grossly (more than the WLS's
    ``exclude_above_m``) from the prediction (:func:`fusion.estimate.neighbour_fde.gross_outliers`), provided
    the epoch re-solved without them (:func:`screened_guess`) is back within :data:`PREDICTION_GATE_M` of
    it. Epochs so repaired predict for the next round (:data:`SCREEN_ROUNDS`): runs of weak epochs are
    repaired from both ends. Returns (drop (E,S) bool, guess (E,3) ECEF).
    """
    drop, pos = np.asarray(wls.excluded, bool), np.asarray(wls.pos, float)
    gross = TRACE_DEFAULTS.exclude_above_m
    valid = np.asarray(wls.valid, bool)
    # --wls-plain: the paper's baseline keeps every measurement, and so does its learned snapshot
    if not opts.wls_robust or not np.isfinite(gross) or not valid.any():
        return drop, pos
    above = trace.mask & (np.asarray(wls.elev_deg) >= opts.elev_mask_deg) & valid[:, None]
    weak = valid & (np.asarray(wls.flagged, bool) | (wls.n_used <= NEIGHBOUR_CHECK_MAX_SATS))
    # predictions only from epochs as precise as the prediction is assumed to be (their own covariance,
    # a-posteriori scaled): in a street canyon the neighbours are tens of metres off themselves
    sigma = np.sqrt(np.trace(np.nan_to_num(np.asarray(wls.cov)[:, :3, :3], nan=np.inf), axis1=1, axis2=2))
    settled = valid & ~weak & ~np.asarray(wls.clock_predicted, bool) & (sigma <= SETTLED_SIGMA_M)
    for _ in range(SCREEN_ROUNDS):
        far, decided, pred = gross_outliers(trace.t_ms, trace.sat_pos, trace.pr, pos, weak, settled, above, gross,
                                            off_m=PREDICTION_GATE_M, max_gap_ms=SCREEN_GAP_MS)
        changed = decided & (far != drop).any(1)
        new = screened_guess(trace, pos, changed, np.where(changed[:, None], far, drop), opts)
        # kept only where it repairs the epoch: the fix without them is back at its neighbours' prediction
        # (in a street canyon the neighbours share the multipath, and a re-solve is no better)
        repaired = changed & (np.linalg.norm(new - pred, axis=1) <= PREDICTION_GATE_M)
        if not repaired.any():
            break
        drop = np.where(repaired[:, None], far, drop)
        pos = np.where(repaired[:, None], new, pos)
        settled, weak = settled | repaired, weak & ~repaired
    return drop, pos


def screened_guess(trace: Trace, pos: np.ndarray, epochs: np.ndarray, drop: np.ndarray, opts: RunOptions) -> np.ndarray:
    """(E,3) ``pos`` with the ``epochs`` (E,) re-solved (plain WLS from ``pos``) without the measurements in
    ``drop`` (E,S): a gross fault the WLS fit absorbed displaces its position, and the network reads its
    inputs at the guess."""
    idx = np.flatnonzero(epochs)
    if idx.size == 0:
        return pos
    again = solve_wls_arrays(trace.sat_pos[idx], trace.pr[idx], trace.mask[idx] & ~drop[idx], trace.pr_sigma[idx],
                             pos[idx], elev_mask_deg=opts.elev_mask_deg, weighting=opts.wls_weighting)
    pos = pos.copy()
    pos[idx[again.valid]] = again.pos[again.valid]
    return pos


def iterated(provider: PriorProvider, passes: int) -> PriorProvider:
    """Apply a provider ``passes`` times, each pass starting from the previous pass's mean (kept for
    callers composing their own providers; the modes ask the network once)."""
    if passes <= 1:
        return provider

    def run(trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
        pos, ok = init_pos, valid
        for _ in range(passes):
            mean, cov, ok = provider(trace, pos, ok)
            pos = np.where(np.asarray(ok)[:, None], mean, init_pos)
        return mean, cov, ok
    return run


def graph_inputs(corrector: Corrector, trace: Trace, wls: WlsResult, opts: RunOptions,
                 at: np.ndarray | None = None, sigma_power: float | np.ndarray | None = None) -> LearnedGraphInputs:
    """The network's one pass at :func:`learned_guess` under the run's elevation mask: the position prior
    and the per-measurement sigmas and biases the graph uses (``opts.learned_prior`` /
    ``opts.learned_sigmas`` / ``opts.learned_bias`` / ``opts.learned_doppler`` switch each off), and what the guard
    did (info keys ``learned_*``).
    at: (E,3) that guess if already made; sigma_power: the head's power, a number or per epoch (E,1)
    (:func:`sigma_power_by_factor`; None: ``GraphConfig.learned_sigma_power``)."""
    at = learned_guess(trace, wls, opts) if at is None else at
    out = corrector.graph_inputs(trace, at, trace.n_sats >= 1, elev_mask_deg=opts.elev_mask_deg,
                                 sigma_power=opts.graph.learned_sigma_power if sigma_power is None else sigma_power)
    out.info = {f"learned_{k}": v for k, v in (out.info or {}).items()}
    if not opts.learned_prior:
        out.prior_mean = out.prior_cov = out.prior_ok = None
    if not opts.learned_sigmas:
        out.pr_sigma = out.pr_bias = None
    if not opts.learned_bias:
        out.pr_bias = None                      # the graph then subtracts nothing from the pseudoranges
    if not opts.learned_doppler:
        out.doppler_noise = None
    return out


def sigmas_again(corrector: Corrector, trace: Trace, wls: WlsResult, opts: RunOptions,
                 learned: LearnedGraphInputs, at: np.ndarray, start: BatchSolution | None,
                 sigma_power: float | np.ndarray | None = None) -> tuple[LearnedGraphInputs, BatchSolution | None]:
    """``learned`` with its pseudorange sigmas asked again at the graph's own answer with them, each of
    ``GraphConfig.learned_sigma_passes`` - 1 times, and the last of those solves (the final solve's start).

    The first pass asks the network at the graph without anything learned (``at`` (E,3) ECEF): in a canyon
    that guess is metres off, and the residuals the head reads there carry the guess's error beside each
    satellite's own. A solve with its sigmas, to the full tolerance (stopped at ``guess_rel_tol`` it left
    smartLoc at 25.65 against 25.10 m), is the better guess for the next pass. Only the sigmas are taken
    again: the position prior and the biases stay the first pass's, since a guess already moved by them
    would have the network move it again (a scratch run asking all three again: GSDC cross-validated 3.689
    against 3.664 m).
    Batch mode only (the incremental smoother asks once, at its online estimates, to stay causal);
    sigma_power as :func:`graph_inputs` takes it."""
    if opts.graph.incremental or learned.pr_sigma is None or opts.graph.learned_sigma_passes <= 1:
        return learned, start
    info = dict(learned.info or {})
    for _ in range(opts.graph.learned_sigma_passes - 1):
        guess = solve_graph(trace, wls, opts, opts.graph, learned, want_cov=False, start=start, keep_values=True)
        again = graph_inputs(corrector, trace, wls, opts, where_solved(guess.pos, at), sigma_power)
        # the guard's measurement counts are the pass whose sigmas the graph takes; its epoch counts the prior's
        info.update({k: v for k, v in (again.info or {}).items() if k.startswith(("learned_meas", "learned_pr_"))})
        learned = replace(learned, pr_sigma=again.pr_sigma, info=info)
        start = guess.info.get("batch_solution", start)
    info["learned_sigma_passes"] = opts.graph.learned_sigma_passes
    return learned, start


def residual_factor(trace: Trace, at: np.ndarray, opts: RunOptions) -> np.ndarray | None:
    """(E,) the windowed a-posteriori variance factor F of the physical model's pseudorange residuals at ``at``
    (E,3) ECEF, the graph without anything learned (window ``GraphConfig.prior_factor_window_s``); None in
    incremental mode, whose smoother stays causal (the centred window reads epochs ahead), and where neither the
    prior's widening nor the sigmas' power ramp reads it.
    Unsolved rows of ``at`` (NaN) have no residuals: their window's factor, or the trace's, stands for them."""
    g = opts.graph
    if g.incremental or (g.prior_factor_power == 0 and g.learned_sigma_power_high == g.learned_sigma_power):
        return None
    sel, sigma = sigma_model(trace, at, opts.elev_mask_deg)
    return track_factor(trace, at, sel, sigma, None, g.prior_factor_window_s)


def sigma_power_by_factor(F: np.ndarray | None, opts: RunOptions) -> float | np.ndarray:
    """The learned sigmas' power per epoch (E,1): ``learned_sigma_power`` where the residuals fit their model
    (F <= 1), rising with log F to ``learned_sigma_power_high`` at F >= ``learned_sigma_power_f_high``
    (``GraphConfig``: why and how chosen); the plain number without F (incremental mode) or a ramp."""
    g = opts.graph
    if F is None or g.learned_sigma_power_high == g.learned_sigma_power:
        return g.learned_sigma_power
    t = np.clip(np.log(np.maximum(F, 1.0)) / np.log(g.learned_sigma_power_f_high), 0.0, 1.0)
    return (g.learned_sigma_power + (g.learned_sigma_power_high - g.learned_sigma_power) * t)[:, None]


def power_where_redundant(power: float | np.ndarray, trace: Trace, at: np.ndarray, opts: RunOptions
                          ) -> tuple[float | np.ndarray, int | None]:
    """The learned sigmas' ``power`` (a number or (E,1)) set to 0, the physical model's sigma, at the epochs where
    fewer than ``GraphConfig.learned_sigma_min_sats`` distinct satellites are above the mask at ``at`` (E,3) ECEF,
    and the count of such epochs (None: the rule is off, ``learned_sigma_min_sats`` 0 as shipped). The head
    judges each satellite against the others, and four leave little to judge by; but on every tuning log where
    the rule acts it costs, and only a test trace gains (experiments/results/few_satellite_sigmas.md)."""
    n_min = opts.graph.learned_sigma_min_sats
    if n_min <= 0:
        return power, None
    sel, _ = sigma_model(trace, at, opts.elev_mask_deg)
    few = satellite_counts(trace.sat_id, sel) < n_min
    if not few.any():
        return power, 0
    per_epoch = np.broadcast_to(np.asarray(power, float).reshape(-1, 1), (trace.n_epochs, 1))
    return np.where(few[:, None], 0.0, per_epoch), int(few.sum())


def prior_by_factor(learned: LearnedGraphInputs, F: np.ndarray | None, opts: RunOptions) -> LearnedGraphInputs:
    """``learned`` with its prior covariance (E,3,3) x ``max(1, F / ref) ** power`` per epoch, F (E,) from
    :func:`residual_factor` (``GraphConfig.prior_factor_*``: why and how chosen).
    Info: the factor's median (``learned_prior_factor_p50``) and the epochs whose prior it widened
    (``learned_prior_widened``). Batch mode only (F None: incremental)."""
    g = opts.graph
    if F is None or learned.prior_cov is None or g.prior_factor_power == 0:
        return learned
    k = np.maximum(1.0, F / g.prior_factor_ref) ** g.prior_factor_power
    info = dict(learned.info or {}, learned_prior_factor_p50=float(np.median(F)),
                learned_prior_widened=int(np.sum(np.asarray(learned.prior_ok, bool) & (k > 1))))
    return replace(learned, prior_cov=learned.prior_cov * k[:, None, None], info=info)


def prior_where_determined(learned: LearnedGraphInputs, solved: np.ndarray | None) -> LearnedGraphInputs:
    """``learned`` without its position prior at the epochs the graph without anything learned could not solve
    (``solved`` (E,) bool; None: keep all): there too few satellites remain, the network was asked at the WLS
    track interpolated across the gap, and its prior alone would place the epoch: on held-out simulated GPS-only
    deep streets 11-255 m off at the median (5.7 km on one trace without Doppler) where the rest holds 2-4 m
    (experiments/results/prior_undetermined.md). Such epochs stay unsolved, as in ``fused-nodnn``, and are counted
    (``learned_prior_withheld``)."""
    if solved is None or learned.prior_ok is None:
        return learned
    withheld = np.asarray(learned.prior_ok, bool) & ~solved
    info = dict(learned.info or {}, learned_prior_withheld=int(withheld.sum()))
    return replace(learned, prior_ok=np.asarray(learned.prior_ok, bool) & solved, info=info)


def estimate_fused(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """The ``fused`` mode: pseudoranges weighted by the per-satellite head (its power rising where the residuals
    exceed their model, :func:`sigma_power_by_factor`) + the learned position prior (widened there,
    :func:`prior_by_factor`; withheld where the graph without it cannot place the epoch,
    :func:`prior_where_determined`) + motion, from one network pass (and its sigmas from a second,
    :func:`sigmas_again`); ``opts.learned_prior`` / ``opts.learned_sigmas`` switch each part off. Epochs of fewer
    than 4 satellites are flagged bridged whether the prior holds them or not (:func:`flag_few_satellites`)."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    at, start, solved = learned_guess_start_solved(trace, wls, opts)
    F = residual_factor(trace, at, opts)
    power, few = power_where_redundant(sigma_power_by_factor(F, opts), trace, at, opts)
    learned = prior_by_factor(graph_inputs(corrector, trace, wls, opts, at, power), F, opts)
    if few is not None:
        learned.info = dict(learned.info or {}, learned_epochs_few_satellites=few)
    learned = prior_where_determined(learned, solved)
    learned, start = sigmas_again(corrector, trace, wls, opts, learned, at, start, power)
    # the solve with the learned inputs starts from the last solve's solution
    res = fuse(trace, wls, opts, learned=learned, start=start)
    if opts.graph.prior_at == "graph":
        res.info["unlearned_pos"] = at          # the first solve: nothing learned (its sigma calibration)
        res.info.update(learned_move(res.pos, at, res.valid))
    if res.cov is not None and res.valid.any():
        # the graph's marginals, scaled per NED axis as measured on unseen drives (ones if not calibrated)
        ok = res.valid
        v = np.sqrt(corrector.var_scale["unseen_fused"])
        ned = ecef2ned_cov(res.cov[ok], res.pos[ok]) * np.outer(v, v)
        res.cov = res.cov.copy()
        res.cov[ok] = ned2ecef_cov(ned, res.pos[ok])
    return flag_few_satellites(calibrated(res, trace, "fused", opts, wls), trace)


def flag_few_satellites(res: ModeResult, trace: Trace) -> ModeResult:
    """``res`` with every solved epoch of fewer than 4 selected satellites flagged bridged (``bridge_flags``), the
    network's prior there or not: the network reads those same few pseudoranges, so the prior adds no satellite,
    and the graph's own flag (no prior) would leave ``fused`` flagging none of what ``fused-nodnn`` flags. Only
    the flags: the sigmas the graph's flag widened stay as they were (``fused``'s held 0.61-0.82 of the errors
    within 1 sigma per axis at such epochs on held-out simulated GPS-only deep streets,
    experiments/results/prior_undetermined.md)."""
    sel = (res.info.get("pr_noise") or (None,))[0]
    if sel is not None:
        res.info.update(bridge_flags(trace, res.valid & (satellite_counts(trace.sat_id, sel) < 4)))
    return res
