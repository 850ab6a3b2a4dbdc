"""The ``dnn`` and ``fused`` pipeline modes: the trained network wired into fusion's estimators.

``fusion``'s mode registry names these functions by string (``"learned.modes:estimate_dnn"``). Neither
imports torch: the network runs in numpy (:mod:`learned.npnet`), asked once per run.
"""
from __future__ import annotations

import numpy as np

from fusion.estimate.graph.fuse import fuse, learned_guess, learned_guess_and_start
from fusion.estimate.graph.priors import LearnedGraphInputs, PriorProvider
from fusion.estimate.wls import WlsResult
from fusion.geometry import ecef2ned_cov, ned2ecef_cov
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace
from learned.infer import Corrector


def estimate_dnn(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """Pipeline mode ``dnn``: one network pass at the WLS positions (learned-weight least squares or the
    paper's correction, ``opts.dnn_output``). Epochs with invalid WLS or < 4 satellites: not solved.
    ``opts.dnn_passes`` > 1 re-asks the network at its own output (features recomputed each pass)."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    pos, valid = np.asarray(wls.pos, float), np.asarray(wls.valid, bool)
    cov, too_few, c = None, 0, None
    for _ in range(max(1, int(opts.dnn_passes))):
        c = corrector.predict(trace, pos, valid, elev_mask_deg=opts.elev_mask_deg, output=opts.dnn_output)
        too_few += c.n_too_few
        pos, valid, cov = c.mean_ecef, c.valid, c.cov_ecef
    info = {"passes": int(max(1, opts.dnn_passes)), "unsolved": int((~valid).sum()),
            "unsolved_wls": int((~np.asarray(wls.valid, bool)).sum()), "too_few_sats": too_few,
            "output": opts.dnn_output or corrector.output, "weights": str(corrector.path),
            "guard_shrunk": c.info["epochs_guard_shrunk"], "guard_off": c.info["epochs_guard_off"],
            # flat, so that metrics.json (which keeps scalar info) and the report carry them
            **{f"learned_{k}": v for k, v in c.info.items()}}
    return ModeResult(pos=pos, valid=valid, cov=cov, info=info)


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
                 at: np.ndarray | None = None) -> LearnedGraphInputs:
    """The network's one pass at :func:`learned_guess` under the run's elevation mask: the position prior
    and the per-measurement sigmas and biases the graph uses (``opts.learned_prior`` /
    ``opts.learned_sigmas`` switch each off), and what the guard did (info keys ``learned_*``).
    at: (E,3) that guess if already made."""
    at = learned_guess(trace, wls, opts) if at is None else at
    out = corrector.graph_inputs(trace, at, trace.n_sats >= 1, elev_mask_deg=opts.elev_mask_deg)
    out.info = {f"learned_{k}": v for k, v in (out.info or {}).items()}
    if not opts.learned_prior:
        out.prior_mean = out.prior_cov = out.prior_ok = None
    if not opts.learned_sigmas:
        out.pr_sigma = out.pr_bias = out.prr_sigma = out.prr_bias = None
    return out


def estimate_fused(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """The ``fused`` mode: pseudoranges weighted by the per-satellite head + the learned position prior
    + motion, from one network pass; ``opts.learned_prior`` / ``opts.learned_sigmas`` switch each part off."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    at, start = learned_guess_and_start(trace, wls, opts)
    # the solve with the learned inputs starts from the first solve's solution (one network pass)
    res = fuse(trace, wls, opts, learned=graph_inputs(corrector, trace, wls, opts, at), start=start)
    if res.cov is not None and res.valid.any():
        # the graph's marginals, scaled per NED axis as measured on unseen drives (ones if not calibrated)
        ok = res.valid
        v = np.sqrt(corrector.var_scale["unseen_fused"])
        ned = ecef2ned_cov(res.cov[ok], res.pos[ok]) * np.outer(v, v)
        res.cov = res.cov.copy()
        res.cov[ok] = ned2ecef_cov(ned, res.pos[ok])
    return res
