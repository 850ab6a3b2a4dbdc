"""The fused modes: pseudoranges + learned position prior + motion, smoothed in a GTSAM graph.

``estimate_fused`` adds the learned correction (a position prior per epoch, from
``learned.infer.Corrector``) to the graph; ``estimate_fused_nodnn`` is the same graph without it.
Both solve the whole trace in batch with Levenberg-Marquardt, or, with
``RunOptions.incremental``, epoch by epoch with ISAM2 on the same factors. Graph construction is in
:mod:`fusion.graph_build`.

``fusion`` never imports ``learned`` at module level: any *position prior provider*
``provider(trace, init_pos (E,3), valid (E,)) -> (mean_ecef (E,3), cov_ecef (E,3,3), valid (E,))``
can be plugged into :func:`fuse`.
"""
from __future__ import annotations

import re
import time

import gtsam
import numpy as np

from fusion.errors import GeometryError, GnssfuseError, ModeUnavailableError
from fusion.geometry import C_LIGHT
from fusion.graph_build import (ISB_STRIDE, EpochInputs, GraphConfig, I, MotionNoise, PriorProvider, X,
                                epoch_factors, prepare_inputs)
from fusion.pipeline import ModeResult, RunOptions
from fusion.trace import SIGNALS, Trace

__all__ = ["GraphConfig", "fuse", "estimate_fused", "estimate_fused_nodnn", "build_graph",
           "solve_batch", "solve_incremental"]


def _epoch_label(trace: Trace, k: int) -> str:
    return f"{trace.name}: epoch {k} (t_ms={int(trace.t_ms[k])})"


def _geometry_error(trace: Trace, exc: Exception) -> GeometryError:
    """Turn GTSAM's indeterminant-system exception into our error, naming the epoch."""
    msg = str(exc)
    m = re.search(r"Symbol: ([xbv])(\d+)", msg)
    mi = re.search(r"Symbol: i(\d+)", msg)
    if mi:
        idx = int(mi.group(1))
        return GeometryError(f"{trace.name}: the graph cannot determine the inter-system bias of signal group "
                             f"{idx % ISB_STRIDE} in motion component {idx // ISB_STRIDE} (singular system)")
    if m:
        k = int(m.group(2))
        what = {"x": "position", "b": "receiver clock", "v": "velocity"}[m.group(1)]
        return GeometryError(f"{_epoch_label(trace, k)}: the graph cannot determine the {what} "
                             f"(singular system: too few satellites and no prior or motion link)")
    return GeometryError(f"{trace.name}: factor graph solve failed: {msg.splitlines()[0] if msg else exc!r}")


def check_determined(trace: Trace, inp: EpochInputs) -> None:
    """Raise :class:`GeometryError` naming the first epoch nothing can determine."""
    bad = np.flatnonzero(~inp.keep)
    if bad.size:
        k = int(bad[0])
        raise GeometryError(f"{_epoch_label(trace, k)}: {int(inp.sel[k].sum())} usable pseudoranges, no "
                            f"position prior, and no motion link to an epoch with >= 4 satellites or a prior; "
                            f"its position is undetermined")


def isb_estimates(values: gtsam.Values, inp: EpochInputs) -> dict[str, float]:
    """Estimated inter-system biases [m] (pseudorange minus the reference-clock model), keyed
    ``"<signal>@<component>"``, for every bias state in ``values``."""
    out = {}
    if inp.isb_new is None:
        return out
    for g, sg in enumerate(inp.isb_groups):
        for c in np.unique(inp.comp[inp.isb_new[:, g] & inp.keep]):
            key = I(int(c), g)
            if values.exists(key):
                out[f"{SIGNALS[sg]}@{int(c)}"] = -float(values.atDouble(key))   # the key holds -ISB
    return out


def build_graph(trace: Trace, inp: EpochInputs, cfg: GraphConfig, use_prior: bool
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray]:
    """The whole-trace graph over the epochs in ``inp.keep``; returns (graph, initial values, epochs)."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = MotionNoise(inp, cfg)
    epochs = np.flatnonzero(inp.keep)
    for k in epochs:
        factors, vals = epoch_factors(int(k), trace, inp, noise, cfg, use_prior)
        for f in factors:
            graph.add(f)
        values.insert(vals)
    return graph, values, epochs


def solve_batch(trace: Trace, inp: EpochInputs, cfg: GraphConfig, use_prior: bool, want_cov: bool = True
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """Levenberg-Marquardt over the whole trace. Returns pos (E,3), valid (E,), cov (E,3,3)|None, info."""
    E = trace.n_epochs
    t0 = time.perf_counter()
    graph, values, epochs = build_graph(trace, inp, cfg, use_prior)
    t1 = time.perf_counter()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.lm_max_iter)
    params.setRelativeErrorTol(cfg.lm_rel_tol)
    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        t2 = time.perf_counter()
        pos = np.full((E, 3), np.nan)
        for k in epochs:
            pos[k] = result.atPoint3(X(int(k)))
        cov = None
        if want_cov:
            # marginals also expose a graph singular at the solution (LM's damping hides it)
            marg = gtsam.Marginals(graph, result)
            cov = np.full((E, 3, 3), np.nan)
            for k in epochs:
                cov[k] = marg.marginalCovariance(X(int(k)))
    except RuntimeError as exc:
        raise _geometry_error(trace, exc) from None
    t3 = time.perf_counter()
    valid = np.zeros(E, bool)
    valid[epochs] = np.isfinite(pos[epochs]).all(axis=1)
    info = {"factors": int(graph.size()), "iterations": int(opt.iterations()),
            "final_error": float(opt.error()), "build_s": t1 - t0, "solve_s": t2 - t1, "cov_s": t3 - t2,
            "isb_m": isb_estimates(result, inp)}
    return pos, valid, cov, info


def solve_incremental(trace: Trace, inp: EpochInputs, cfg: GraphConfig, use_prior: bool
                      ) -> tuple[np.ndarray, np.ndarray, None, dict]:
    """ISAM2, one epoch at a time, with the same factors as the batch graph.

    Epochs of a motion component are held back until the component has an anchor (an epoch with
    >= 4 satellites or a prior), because ISAM2 cannot take an undetermined update. ``pos`` is the
    final smoothed estimate; ``info["online_pos"]`` (E,3) holds each epoch's estimate right after its
    own update (what a real-time user would have seen). No covariances (None): per-epoch ISAM2
    marginals cost more than the solve itself.
    """
    E = trace.n_epochs
    params = gtsam.ISAM2Params()
    # The clock is in seconds: scalar thresholds meant for metres would never relinearise it or
    # propagate its updates (0.001 s = 300 km), so thresholds are per variable type, in their units.
    thr = gtsam.ISAM2ThresholdMap()
    for sym, dim, scale in (("x", 3, 1.0), ("v", 3, 1.0), ("b", 1, 1.0 / C_LIGHT), ("i", 1, 1.0)):
        thr.insert((sym, np.full(dim, cfg.isam_relin_threshold * scale)))
    params.setRelinearizeThreshold(thr)
    params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(cfg.isam_wildfire_m / C_LIGHT))
    params.relinearizeSkip = cfg.isam_relin_skip
    isam = gtsam.ISAM2(params)
    noise = MotionNoise(inp, cfg)
    anchor = (inp.sel.sum(axis=1) >= 4) | (inp.prior_ok & use_prior)
    online = np.full((E, 3), np.nan)
    pending_f, pending_v, pending_k = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
    anchored = False
    t0 = time.perf_counter()
    try:
        for k in np.flatnonzero(inp.keep):
            k = int(k)
            if not inp.pos_link[k]:
                anchored = False               # a new motion component starts here
            factors, vals = epoch_factors(k, trace, inp, noise, cfg, use_prior)
            for f in factors:
                pending_f.add(f)
            pending_v.insert(vals)
            pending_k.append(k)
            anchored |= bool(anchor[k])
            if anchored:
                isam.update(pending_f, pending_v)
                for j in pending_k:
                    online[j] = isam.calculateEstimatePoint3(X(j))
                pending_f, pending_v, pending_k = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
        for _ in range(cfg.isam_settle):        # let relinearisation settle
            isam.update()
        est = isam.calculateEstimate()
    except RuntimeError as exc:
        raise _geometry_error(trace, exc) from None
    elapsed = time.perf_counter() - t0
    pos = np.full((E, 3), np.nan)
    for k in np.flatnonzero(inp.keep):
        pos[k] = est.atPoint3(X(int(k)))
    valid = inp.keep & np.isfinite(pos).all(axis=1)
    n = max(int(inp.keep.sum()), 1)
    return pos, valid, None, {"online_pos": online, "incremental_s": elapsed,
                              "ms_per_epoch": 1000.0 * elapsed / n, "isb_m": isb_estimates(est, inp)}


def fuse(trace: Trace, wls, opts: RunOptions | None = None, provider: PriorProvider | None = None,
         cfg: GraphConfig | None = None, on_undetermined: str = "drop", want_cov: bool = True) -> ModeResult:
    """Smooth a whole trace in a factor graph.

    trace: the measurements; wls: the shared ``WlsResult`` (initial positions, clocks, used slots).
    provider: position prior provider, or None for the graph without a learned prior.
    on_undetermined: "drop" (epochs nothing can determine are left unsolved and counted in
    ``info["epochs_undetermined"]``) or "raise" (:class:`GeometryError` naming the first one).
    Returns a ModeResult with pos (E,3) ECEF, valid (E,), cov (E,3,3) ECEF marginals (batch only;
    None in incremental mode) and info counts.
    """
    opts = opts or RunOptions()
    cfg = cfg or GraphConfig()
    if on_undetermined not in ("drop", "raise"):
        raise GnssfuseError(f"on_undetermined must be 'drop' or 'raise', got {on_undetermined!r}")
    guess = None
    if provider is not None and cfg.prior_at == "graph":
        first = fuse(trace, wls, opts, None, cfg, on_undetermined="drop", want_cov=False)
        # a no-prior graph with nothing determinable solves no epoch and has no online estimates:
        # its all-NaN positions then make the provider fall back to the initial positions
        guess = first.info.get("online_pos", first.pos) if opts.incremental else first.pos
    elif provider is not None and cfg.prior_at != "wls":
        raise GnssfuseError(f"prior_at must be 'graph' or 'wls', got {cfg.prior_at!r}")
    inp = prepare_inputs(trace, wls, cfg, opts.elev_mask_deg, provider, prior_guess=guess)
    if on_undetermined == "raise":
        check_determined(trace, inp)
    use_prior = provider is not None
    if not inp.keep.any():
        pos, valid, cov, info = np.full((trace.n_epochs, 3), np.nan), np.zeros(trace.n_epochs, bool), None, {}
    elif opts.incremental:
        pos, valid, cov, info = solve_incremental(trace, inp, cfg, use_prior)
    else:
        pos, valid, cov, info = solve_batch(trace, inp, cfg, use_prior, want_cov)
    info.update(inp.dropped)
    info["priors_used"] = int((inp.prior_ok & inp.keep).sum()) if use_prior else 0
    info["unsolved"] = int((~valid).sum())
    return ModeResult(pos=pos, valid=valid, cov=cov, info=info)


def _learned_provider(opts: RunOptions) -> PriorProvider:
    """The checkpoint's corrector as a prior provider, under the run's elevation mask (as ``dnn``)."""
    try:
        from learned.infer import Corrector
    except ImportError as exc:  # the learned package is optional for every other mode
        raise ModeUnavailableError(f"mode 'fused' needs learned.infer (torch): {exc}") from None
    return Corrector.load(opts.weights, device=opts.device).provider(opts.elev_mask_deg)


def iterated(provider: PriorProvider, passes: int) -> PriorProvider:
    """Apply a provider ``passes`` times, each pass starting from the previous pass's mean
    (features recomputed at the corrected position, as ``dnn_passes`` does for the dnn mode)."""
    if passes <= 1:
        return provider

    def run(trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
        pos, ok = init_pos, valid
        for _ in range(passes):
            mean, cov, ok = provider(trace, pos, ok)
            pos = np.where(np.asarray(ok)[:, None], mean, init_pos)
        return mean, cov, ok
    return run


def estimate_fused(trace: Trace, wls, opts: RunOptions) -> ModeResult:
    """Pseudoranges + learned position prior + motion (the paper's correction inside a graph)."""
    return fuse(trace, wls, opts, provider=iterated(_learned_provider(opts), int(opts.dnn_passes)))


def estimate_fused_nodnn(trace: Trace, wls, opts: RunOptions) -> ModeResult:
    """The same graph without the learned prior: pseudoranges + motion only."""
    return fuse(trace, wls, opts, provider=None)
