"""The ``dnn`` and ``fused`` pipeline modes: the trained network wired into fusion's estimators.

``fusion``'s mode registry names these functions by string (``"learned.modes:estimate_dnn"``), so the
CLI imports torch only when one of them runs.
"""
from __future__ import annotations

import numpy as np

from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.priors import PriorProvider
from fusion.estimate.wls import WlsResult
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace
from learned.infer import Corrector


def estimate_dnn(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """Pipeline mode ``dnn``: WLS position as the guess, ``opts.dnn_passes`` corrections (features
    recomputed at each corrected position). Epochs with invalid WLS or < 4 satellites: not solved."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    pos, valid = np.asarray(wls.pos, float), np.asarray(wls.valid, bool)
    cov, too_few = None, 0
    for _ in range(max(1, int(opts.dnn_passes))):
        c = corrector.predict(trace, pos, valid, elev_mask_deg=opts.elev_mask_deg)
        too_few += c.n_too_few
        pos, valid, cov = c.mean_ecef, c.valid, c.cov_ecef
    info = {"passes": int(max(1, opts.dnn_passes)), "unsolved": int((~valid).sum()),
            "unsolved_wls": int((~np.asarray(wls.valid, bool)).sum()), "too_few_sats": too_few,
            "weights": str(corrector.path)}
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


def learned_provider(opts: RunOptions) -> PriorProvider:
    """The checkpoint's corrector as a prior provider, under the run's elevation mask (as ``dnn``),
    applied ``opts.dnn_passes`` times."""
    corrector = Corrector.load(opts.weights, device=opts.device)
    return iterated(corrector.provider(opts.elev_mask_deg), int(opts.dnn_passes))


def estimate_fused(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """The ``fused`` mode: pseudoranges + learned position prior + motion (the paper's correction
    inside a graph)."""
    return fuse(trace, wls, opts, provider=learned_provider(opts))
