"""Smooth a whole trace in the fused factor graph: pseudoranges + motion + clock, and optionally a
position prior per epoch from a *prior provider*; the ``fused-nodnn`` mode.

The ``fused`` mode (the learned correction as the provider) lives in :mod:`learned.modes`: ``fusion``
never imports ``learned``. Any provider ``provider(trace, init_pos (E,3), valid (E,)) ->
(mean_ecef (E,3), cov_ecef (E,3,3), valid (E,))`` can be passed to :func:`fuse`. The graph is solved
in batch with Levenberg-Marquardt, or, with ``RunOptions.incremental``, epoch by epoch with ISAM2 on
the same factors.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.errors import GnssfuseError
from fusion.estimate.graph.batch import solve_batch
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.incremental import solve_incremental
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.priors import PriorProvider, SlotNoiseProvider
from fusion.estimate.graph.solve_errors import check_determined
from fusion.estimate.wls import WlsResult
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace


def solve_graph(trace: Trace, wls: WlsResult, opts: RunOptions, cfg: GraphConfig,
                provider: PriorProvider | None = None, prior_guess: np.ndarray | None = None,
                on_undetermined: str = "drop", want_cov: bool = True,
                slot_noise: SlotNoiseProvider | None = None) -> ModeResult:
    """One solve of the graph, the providers asked at ``prior_guess`` (E,3) (None: the WLS track).

    on_undetermined: "drop" (epochs nothing can determine are left unsolved and counted in
    ``info["epochs_undetermined"]``) or "raise" (:class:`GeometryError` naming the first one).
    """
    if on_undetermined not in ("drop", "raise"):
        raise GnssfuseError(f"on_undetermined must be 'drop' or 'raise', got {on_undetermined!r}")
    inp = prepare_inputs(trace, wls, cfg, opts.elev_mask_deg, provider, prior_guess=prior_guess,
                         slot_noise=slot_noise, use_doppler=opts.use_doppler, use_carrier=opts.use_carrier,
                         use_odometry=opts.use_odometry)
    if inp.raw is not None and inp.raw.has_tdcp:
        inp.raw.lin_pos = carrier_linearisation(trace, wls, inp.init_pos, opts, cfg, provider, prior_guess,
                                                slot_noise)
    if on_undetermined == "raise":
        check_determined(trace, inp)
    E = trace.n_epochs
    if not inp.keep.any():
        pos, valid, cov, info = np.full((E, 3), np.nan), np.zeros(E, bool), None, {}
    elif opts.incremental:
        pos, valid, cov, info = solve_incremental(trace, inp, cfg)
    else:
        pos, valid, cov, info = solve_batch(trace, inp, cfg, want_cov)
    info.update(inp.dropped)
    info["priors_used"] = int((inp.prior_ok & inp.keep).sum())
    info["unsolved"] = int((~valid).sum())
    return ModeResult(pos=pos, valid=valid, cov=cov, info=info)


def carrier_linearisation(trace: Trace, wls: WlsResult, init_pos: np.ndarray, opts: RunOptions, cfg: GraphConfig,
                          provider: PriorProvider | None, guess: np.ndarray | None,
                          slot_noise: SlotNoiseProvider | None = None) -> np.ndarray:
    """(E,3) positions at which the carrier factors are linearised (``cfg.tdcp_linearize_at``): the
    same graph solved without carrier ("graph"; online estimates in incremental mode, so it stays
    causal), or ``init_pos`` (E,3) ("initial"); ``init_pos`` wherever the first solve left a gap."""
    if cfg.tdcp_linearize_at == "initial":
        return init_pos
    if cfg.tdcp_linearize_at != "graph":
        raise GnssfuseError(f"tdcp_linearize_at must be 'graph' or 'initial', got {cfg.tdcp_linearize_at!r}")
    first = solve_graph(trace, wls, replace(opts, use_carrier=False), cfg, provider, guess, want_cov=False,
                        slot_noise=slot_noise)
    pos = first.info.get("online_pos", first.pos) if opts.incremental else first.pos
    return np.where(np.isfinite(pos).all(axis=1)[:, None], pos, init_pos)


def prior_guess(trace: Trace, wls: WlsResult, opts: RunOptions, cfg: GraphConfig) -> np.ndarray | None:
    """Where the provider is asked (``cfg.prior_at``): the no-prior graph's solution ("graph"; its
    online estimates in incremental mode, so it stays causal) or None for the WLS track ("wls")."""
    if cfg.prior_at == "wls":
        return None
    if cfg.prior_at != "graph":
        raise GnssfuseError(f"prior_at must be 'graph' or 'wls', got {cfg.prior_at!r}")
    first = solve_graph(trace, wls, opts, cfg, want_cov=False)
    # a no-prior graph with nothing determinable solves no epoch and has no online estimates:
    # its all-NaN positions then make the provider fall back to the initial positions
    return first.info.get("online_pos", first.pos) if opts.incremental else first.pos


def fuse(trace: Trace, wls: WlsResult, opts: RunOptions | None = None, provider: PriorProvider | None = None,
         cfg: GraphConfig | None = None, on_undetermined: str = "drop", want_cov: bool = True,
         slot_noise: SlotNoiseProvider | None = None) -> ModeResult:
    """Smooth a whole trace in a factor graph.

    trace: the measurements; wls: the shared ``WlsResult`` (initial positions, clocks, used slots).
    provider: position prior provider, or None for the graph without a prior.
    slot_noise: per-slot pseudorange sigma/bias provider, or None for the config's sigma model.
    on_undetermined: see :func:`solve_graph`.
    Returns a ModeResult with pos (E,3) ECEF, valid (E,), cov (E,3,3) ECEF marginals (batch only;
    None in incremental mode) and info counts.
    """
    opts, cfg = opts or RunOptions(), cfg or GraphConfig()
    learned = provider is not None or slot_noise is not None
    guess = prior_guess(trace, wls, opts, cfg) if learned else None
    return solve_graph(trace, wls, opts, cfg, provider, guess, on_undetermined, want_cov, slot_noise)


def estimate_fused_nodnn(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """The ``fused-nodnn`` mode: the graph without a prior, pseudoranges + motion only."""
    return fuse(trace, wls, opts, provider=None)
