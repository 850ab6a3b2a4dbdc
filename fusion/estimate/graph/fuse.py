"""Smooth a whole trace in the fused factor graph, built once and solved once: pseudoranges (+ Doppler
and carrier where the trace has them) + motion + clock, and optionally what a learned model hands the
graph (:class:`~fusion.estimate.graph.priors.LearnedGraphInputs`); the ``fused-nodnn`` mode.

The ``fused`` mode (the network's one pass as the learned inputs) lives in :mod:`learned.modes`:
``fusion`` never imports ``learned``. The graph is solved in batch (Gauss-Newton, Levenberg-Marquardt where a step fails), or, with
``GraphConfig.incremental``, epoch by epoch with ISAM2 on the same factors.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.errors import GeometryError, GnssfuseError
from fusion.estimate.graph.batch import BatchSolution, solve_batch
from fusion.estimate.graph.bridged_check import check_bridged
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.incremental import solve_incremental
from fusion.estimate.graph.inputs import (EpochInputs, doppler_epochs, initial_positions, prepare_inputs,
                                         pseudorange_gap)
from fusion.estimate.graph.priors import (LearnedGraphInputs, PriorProvider, SlotNoiseProvider,
                                          learned_from_providers)
from fusion.estimate.graph.raw_inputs import MIN_TDCP_SATS, RawInputs
from fusion.estimate.graph.series import where_solved
from fusion.estimate.graph.solve_errors import check_determined
from fusion.estimate.variance_factor import calibrate_graph
from fusion.estimate.wls import WlsResult
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace


def solve_graph(trace: Trace, wls: WlsResult, opts: RunOptions, cfg: GraphConfig,
                learned: LearnedGraphInputs | None = None, on_undetermined: str = "drop",
                want_cov: bool = True, start: BatchSolution | None = None, keep_values: bool = False) -> ModeResult:
    """One build and one solve of the graph.

    on_undetermined: "drop" (epochs nothing can determine are left unsolved and counted in
    ``info["epochs_undetermined"]``) or "raise" (:class:`GeometryError` naming the first one).
    start: a previous batch solve of the trace (``info["batch_solution"]``, kept with ``keep_values``;
    see :func:`learned_guess_and_start`), which the batch solver starts from (and returns as it is where the
    graph and the settings are the same, which the ``fused`` mode's looser first solve never is:
    :func:`~fusion.estimate.graph.batch.solve_batch`). None: the WLS-derived values.
    """
    if on_undetermined not in ("drop", "raise"):
        raise GnssfuseError(f"on_undetermined must be 'drop' or 'raise', got {on_undetermined!r}")
    inp = prepare_inputs(trace, wls, cfg, opts.elev_mask_deg, learned)
    if on_undetermined == "raise":
        check_determined(trace, inp)
    E = trace.n_epochs
    if not inp.keep.any():
        pos, valid, cov, info = np.full((E, 3), np.nan), np.zeros(E, bool), None, {}
    elif cfg.incremental:
        pos, valid, cov, info, inp = incremental_or_retry(trace, wls, opts, cfg, learned, inp, want_cov)
    else:
        pos, valid, cov, info = solve_batch(trace, inp, cfg, want_cov, start)
    info.update(inp.dropped)
    if not keep_values:
        info.pop("batch_solution", None)   # GTSAM objects stay out of results that travel between processes
    if learned is not None and learned.info:
        info.update(learned.info)
    info["priors_used"] = int((inp.prior_ok & inp.keep).sum())
    info["unsolved"] = int((~valid).sum())
    info.update(bridged_epochs(trace, inp, valid))
    info["pr_noise"] = (inp.sel, inp.sigma, inp.pr_bias)     # for fusion.estimate.variance_factor
    info["carrier_linked"] = carrier_linked(inp.raw, E)       # experiments/carrier_calibration.py
    return ModeResult(pos=pos, valid=valid, cov=cov, info=info)


#: The carrier clocks' prior sigma [m] of the incremental smoother's retry (:func:`incremental_or_retry`).
RETRY_CARRIER_CLOCK_PRIOR_M = 20.0


def incremental_or_retry(trace: Trace, wls: WlsResult, opts: RunOptions, cfg: GraphConfig,
                         learned: LearnedGraphInputs | None, inp: EpochInputs, want_cov: bool = True):
    """:func:`solve_incremental`'s (pos, valid, cov, info) and the inputs it solved. Where ISAM2's undamped step finds
    the system singular and the graph holds carrier phase, the trace is solved once more with carrier pairs counted
    by distinct satellites (``GraphConfig.tdcp_min_distinct_sats`` = ``MIN_TDCP_SATS``) and a loose prior on each
    carrier clock (``carrier_clock_prior_m`` = ``RETRY_CARRIER_CLOCK_PRIOR_M``; ``info["incremental_retried"]``):
    a dual-frequency phone's three or four satellites repeat their directions, which the batch solver's damped
    step settles (simulated GPS L1 + L5 phones in deep streets), and an epoch whose differences the robust loss
    switched off holds its carrier clock by nothing (the Pixel5 RINEX test trace with SP3/CLK). Both from the start
    would cost that trace with broadcast GPS 3-14 % in this mode (``GraphConfig``'s comments)."""
    try:
        return (*solve_incremental(trace, inp, cfg, want_cov), inp)
    except GeometryError:
        if inp.raw is None or not inp.raw.has_tdcp or cfg.tdcp_min_distinct_sats >= MIN_TDCP_SATS:
            raise
    cfg = replace(cfg, tdcp_min_distinct_sats=MIN_TDCP_SATS,
                  carrier_clock_prior_m=cfg.carrier_clock_prior_m or RETRY_CARRIER_CLOCK_PRIOR_M)
    inp = prepare_inputs(trace, wls, cfg, opts.elev_mask_deg, learned)
    pos, valid, cov, info = solve_incremental(trace, inp, cfg, want_cov)
    return pos, valid, cov, {**info, "incremental_retried": 1}, inp


def carrier_linked(raw: RawInputs | None, n_epochs: int) -> np.ndarray:
    """(E,) bool: epochs that time-differenced carrier phase ties to the epoch before or after."""
    linked = np.zeros(n_epochs, bool)
    if raw is not None and raw.has_tdcp:
        to_prev = (raw.tdcp_prev >= 0).any(axis=1)
        linked = to_prev | np.r_[to_prev[1:], False]
    return linked


def bridged_epochs(trace: Trace, inp: EpochInputs, valid: np.ndarray) -> dict:
    """Solved epochs that fewer than 4 satellites' pseudoranges and no prior determine (the motion model carries
    them from their neighbours): ``bridged`` (E,) bool, their count and the longest such stretch [s]
    (:func:`bridge_flags`), so that a drift through an outage is flagged rather than passed off as a fix; and
    ``bridged_without_doppler`` (E,) bool those where no Doppler measures the velocity either; and
    ``doppler_epochs`` (E,) bool every epoch whose velocity Doppler measures (where estimates.csv writes it)."""
    bridged, doppler = valid & pseudorange_gap(inp), doppler_epochs(inp)
    return {**bridge_flags(trace, bridged), "bridged_without_doppler": bridged & ~doppler, "doppler_epochs": doppler}


def bridge_flags(trace: Trace, bridged: np.ndarray) -> dict:
    """``bridged`` (E,) bool as the flags: itself, its count (``epochs_bridged``) and the longest stretch of it
    (``longest_bridge_s``), from the last epoch before it to the first after it [s]."""
    t = trace.t_ms.astype(float) / 1000.0
    edges = np.diff(np.r_[0, bridged.astype(int), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    before, after = np.maximum(starts - 1, 0), np.minimum(ends + 1, len(t) - 1)
    longest = float(np.max(t[after] - t[before], initial=0.0))
    return {"bridged": bridged, "epochs_bridged": int(bridged.sum()), "longest_bridge_s": longest}


def fuse(trace: Trace, wls: WlsResult, opts: RunOptions | None = None, provider: PriorProvider | None = None,
         cfg: GraphConfig | None = None, on_undetermined: str = "drop", want_cov: bool = True,
         slot_noise: SlotNoiseProvider | None = None, learned: LearnedGraphInputs | None = None,
         start: BatchSolution | None = None) -> ModeResult:
    """Smooth a whole trace in a factor graph.

    trace: the measurements; wls: the shared ``WlsResult`` (initial positions, clocks, used slots).
    learned: a learned model's priors and per-measurement noise for the trace (one pass), or None.
    provider / slot_noise: the same from callables (a position-prior provider and a per-slot pseudorange
    sigma/bias provider), each asked once at the WLS positions; not with ``learned``.
    cfg: the graph's settings (None: ``opts.graph``). on_undetermined, start: see :func:`solve_graph`.
    Returns a ModeResult with pos (E,3) ECEF, valid (E,), cov (E,3,3) ECEF marginals (batch only;
    None in incremental mode) and info counts.
    """
    opts = opts or RunOptions()
    cfg = cfg or opts.graph
    if learned is not None and (provider is not None or slot_noise is not None):
        raise GnssfuseError("fuse: give the learned inputs or the providers, not both")
    if learned is None:
        at, _ = initial_positions(trace, wls, trace.t_ms.astype(float) / 1000.0)
        learned = learned_from_providers(trace, provider, slot_noise, at)
    return solve_graph(trace, wls, opts, cfg, learned, on_undetermined, want_cov, start)


def learned_guess(trace: Trace, wls: WlsResult, opts: RunOptions) -> np.ndarray:
    """(E,3) positions at which a learned model is asked (``opts.graph.prior_at``): the graph without
    anything learned ("graph"; its online estimates in incremental mode, so it stays causal), or the
    WLS track ("wls"); the WLS track (interpolated where it failed) wherever the first has a gap."""
    return learned_guess_and_start(trace, wls, opts)[0]


def learned_guess_and_start(trace: Trace, wls: WlsResult, opts: RunOptions
                            ) -> tuple[np.ndarray, BatchSolution | None]:
    """:func:`learned_guess`'s positions (E,3), and the solve of the graph without anything learned
    (a :class:`~fusion.estimate.graph.batch.BatchSolution`; None with ``prior_at="wls"`` or in
    incremental mode) as the ``start`` of the solve with the learned inputs: that solve starts next to
    its optimum (the learned inputs move it by metres at most) and patches its graph. The first solve stops
    at ``GraphConfig.guess_rel_tol``: the guess needs decimetres, and the second solve carries on to
    ``lm_rel_tol`` from where it stopped."""
    at, start, _ = learned_guess_start_solved(trace, wls, opts)
    return at, start


def learned_guess_start_solved(trace: Trace, wls: WlsResult, opts: RunOptions
                               ) -> tuple[np.ndarray, BatchSolution | None, np.ndarray | None]:
    """:func:`learned_guess_and_start`, and (E,) bool the epochs the graph without anything learned solved
    (None with ``prior_at="wls"``): elsewhere the guess is the WLS track interpolated across the gap."""
    at, _ = initial_positions(trace, wls, trace.t_ms.astype(float) / 1000.0)
    if opts.graph.prior_at == "wls":
        return at, None, None
    if opts.graph.prior_at != "graph":
        raise GnssfuseError(f"GraphConfig.prior_at must be 'graph' or 'wls', got {opts.graph.prior_at!r}")
    loose = replace(opts.graph, lm_rel_tol=opts.graph.guess_rel_tol)
    first = solve_graph(trace, wls, opts, loose, None, want_cov=False, keep_values=True)
    pos = first.info.get("online_pos", first.pos) if opts.graph.incremental else first.pos
    return where_solved(pos, at), first.info.get("batch_solution"), np.asarray(first.valid, bool)


def calibrated(result: ModeResult, trace: Trace, mode: str, opts: RunOptions, wls: WlsResult) -> ModeResult:
    """A graph mode's ``result`` with its sigmas calibrated (:func:`~fusion.estimate.variance_factor.calibrate_graph`)
    and those of its bridged epochs with Doppler checked (:func:`~fusion.estimate.graph.bridged_check.check_bridged`):
    the one finish both graph modes share."""
    return check_bridged(calibrate_graph(result, trace, mode, opts, wls), trace, wls, opts)


def estimate_fused_nodnn(trace: Trace, wls: WlsResult, opts: RunOptions) -> ModeResult:
    """The ``fused-nodnn`` mode: the graph without anything learned."""
    return calibrated(fuse(trace, wls, opts), trace, "fused-nodnn", opts, wls)
