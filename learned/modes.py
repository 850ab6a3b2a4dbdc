"""The ``dnn`` and ``fused`` pipeline modes: the trained network wired into fusion's estimators.

``fusion``'s mode registry names these functions by string (``"learned.modes:estimate_dnn"``), so the
CLI imports torch only when one of them runs.
"""
from __future__ import annotations

import numpy as np

from fusion.estimate.graph.fuse import fuse, learned_guess
from fusion.estimate.graph.priors import LearnedGraphInputs, PriorProvider
from fusion.estimate.wls import WlsResult
from fusion.geometry import ecef2ned_cov, ned2ecef_cov
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace
from learned.infer import Corrector


def estimate_dnn(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """Pipeline mode ``dnn``: WLS position as the guess, ``opts.dnn_passes`` corrections (features
    recomputed at each corrected position). Epochs with invalid WLS or < 4 satellites: not solved."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    pos, valid = np.asarray(wls.pos, float), np.asarray(wls.valid, bool)
    cov, too_few, trust = None, 0, np.full(trace.n_epochs, np.nan)
    for _ in range(max(1, int(opts.dnn_passes))):
        c = corrector.predict(trace, pos, valid, elev_mask_deg=opts.elev_mask_deg, output=opts.dnn_output)
        too_few += c.n_too_few
        pos, valid, cov, trust = c.mean_ecef, c.valid, c.cov_ecef, c.trust
    info = {"passes": int(max(1, opts.dnn_passes)), "unsolved": int((~valid).sum()),
            "unsolved_wls": int((~np.asarray(wls.valid, bool)).sum()), "too_few_sats": too_few,
            "output": opts.dnn_output or corrector.output, "weights": str(corrector.path),
            "guard_shrunk": int((trust[valid] < 1).sum()), "guard_off": int((trust[valid] == 0).sum())}
    return ModeResult(pos=pos, valid=valid, cov=cov, info=info)


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


def learned_provider(opts: RunOptions, corrector: Corrector | None = None) -> PriorProvider:
    """The checkpoint's corrector as a prior provider, under the run's elevation mask (as ``dnn``),
    applied ``opts.dnn_passes`` times."""
    corrector = corrector or Corrector.load(opts.weights, device=opts.device)
    return iterated(corrector.provider(opts.elev_mask_deg), int(opts.dnn_passes))


def graph_inputs(corrector: Corrector, trace: Trace, wls: WlsResult, opts: RunOptions) -> LearnedGraphInputs:
    """One network pass at :func:`learned_guess`: the position prior and the per-satellite sigmas and biases
    the graph uses (``opts.learned_prior`` / ``opts.learned_sigmas`` switch each off), and the guard's counts."""
    at = learned_guess(trace, wls, opts)
    c = corrector.predict(trace, at, trace.n_sats >= 1, elev_mask_deg=opts.elev_mask_deg)
    ok = c.valid
    info = {"guard_shrunk": int((c.trust[ok] < 1).sum()), "guard_off": int((c.trust[ok] == 0).sum()),
            "network_epochs": int(ok.sum())}
    out = LearnedGraphInputs(info=info)
    if opts.learned_prior:
        out.prior_mean, out.prior_cov, out.prior_ok = c.mean_ecef, c.cov_ecef, c.valid
    if opts.learned_sigmas:
        out.pr_sigma, out.pr_bias = c.sigma, c.bias
    return out


def estimate_fused(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """The ``fused`` mode: pseudoranges weighted by the per-satellite head + the learned position prior
    + motion, from one network pass; ``opts.learned_prior`` / ``opts.learned_sigmas`` switch each part off."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    res = fuse(trace, wls, opts, learned=graph_inputs(corrector, trace, wls, opts))
    if res.cov is not None and res.valid.any():
        # the graph's marginals, scaled per NED axis as measured on unseen drives (ones if not calibrated)
        ok = res.valid
        v = np.sqrt(corrector.var_scale["unseen_fused"])
        ned = ecef2ned_cov(res.cov[ok], res.pos[ok]) * np.outer(v, v)
        res.cov = res.cov.copy()
        res.cov[ok] = ned2ecef_cov(ned, res.pos[ok])
    return res
