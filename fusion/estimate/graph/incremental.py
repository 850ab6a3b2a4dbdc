"""Epoch by epoch: ISAM2 on the same factors as the batch graph (what a real-time user would run)."""
from __future__ import annotations

import time
from dataclasses import replace

import gtsam
import numpy as np

from fusion.estimate.graph.batch import marginals_at, read_velocities
from fusion.estimate.graph.build import graph_pieces
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.inputs import EpochInputs
from fusion.estimate.graph.isb import isb_estimates
from fusion.estimate.graph.keys import pos_key
from fusion.estimate.graph.solve_errors import geometry_error
from fusion.geometry import C_LIGHT
from fusion.trace import Trace


def isam2(cfg: GraphConfig, carrier: bool = False) -> gtsam.ISAM2:
    """An ISAM2 smoother with per-variable relinearisation thresholds; ``carrier``: the graph holds carrier
    phase (the finer thresholds of a centimetre-level solution)."""
    relin, wildfire = ((cfg.isam_carrier_relin_threshold, cfg.isam_carrier_wildfire_m) if carrier
                       else (cfg.isam_relin_threshold, cfg.isam_wildfire_m))
    params = gtsam.ISAM2Params()
    # The clock is in seconds: scalar thresholds meant for metres would never relinearise it or
    # propagate its updates (0.001 s = 300 km), so thresholds are per variable type, in their units.
    thr = gtsam.ISAM2ThresholdMap()
    for sym, dim, scale in (("x", 3, 1.0), ("v", 3, 1.0), ("c", 1, 1.0 / C_LIGHT), ("d", 1, 1.0 / C_LIGHT),
                            ("j", 1, 1.0 / C_LIGHT), ("u", 3, 1.0), ("q", 1, 1.0), ("i", 1, 1.0),
                            ("h", 2, 0.01)):  # h: odometry heading [rad, rad/s]
        thr.insert((sym, np.full(dim, relin * scale)))
    params.setRelinearizeThreshold(thr)
    params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(wildfire))
    params.relinearizeSkip = cfg.isam_relin_skip
    params.enablePartialRelinearizationCheck = cfg.isam_partial_relin_check
    return gtsam.ISAM2(params)


def feed_epochs(isam: gtsam.ISAM2, trace: Trace, inp: EpochInputs, cfg: GraphConfig) -> np.ndarray:
    """Update ``isam`` epoch by epoch; returns (E,3) each epoch's estimate right after its own update (NaN for
    epochs never added).

    Epochs of a motion component are held back until the component has an anchor, because ISAM2 cannot take an
    undetermined update: an epoch with >= 4 satellites, or a prior at an epoch without pseudoranges (so without a
    clock). A prior at an epoch of 1-3 satellites fixes the position but leaves the clock and (with Doppler of
    fewer than 4 satellites) the velocity and drift to the epochs after it, and ISAM2's Gauss-Newton step, unlike
    the batch solver's damped one, finds that singular (``fused`` on dual-frequency phones in deep streets). A
    component without an anchor is never added."""
    epochs, graphs, values = graph_pieces(trace, inp, cfg).by_epoch()
    anchor = (inp.n_sats >= 4) | (inp.prior_ok & ~inp.sel.any(axis=1))
    online = np.full((trace.n_epochs, 3), np.nan)
    pending_f, pending_v, pending_k = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
    anchored = False
    for k, g, v in zip(epochs, graphs, values):
        k = int(k)
        if not inp.pos_link[k]:
            anchored, pending_k = False, []     # a new motion component starts here; an unanchored one is left out
        if pending_k:
            pending_f.push_back(g)
            pending_v.insert(v)
        else:
            pending_f, pending_v = g, v
        pending_k.append(k)
        anchored |= bool(anchor[k])
        if anchored:
            isam.update(pending_f, pending_v)
            for j in pending_k:
                online[j] = isam.calculateEstimatePoint3(pos_key(j))
            pending_k = []
    return online


def solve_incremental(trace: Trace, inp: EpochInputs, cfg: GraphConfig, want_cov: bool = True
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """ISAM2, one epoch at a time, with the same factors as the batch graph.

    ``pos`` is the final smoothed estimate; ``info["online_pos"]`` (E,3) holds each epoch's estimate
    right after its own update. ``cov`` (``want_cov``): the smoothed position marginals at the final estimate,
    from the batch solver's one recursion over the same graph (not ISAM2's Bayes tree, whose per-epoch
    queries cost more than the solve), with the velocity's as ``info["vel_cov"]``; None where the graph is
    singular at the estimate (``incremental_no_marginals``).
    """
    E = trace.n_epochs
    isam = isam2(cfg, carrier=inp.raw is not None and inp.raw.has_tdcp)
    t0 = time.perf_counter()
    try:
        online = feed_epochs(isam, trace, inp, cfg)
        for _ in range(cfg.isam_settle):        # let relinearisation settle
            isam.update()
        est = isam.calculateEstimate()
    except RuntimeError as exc:
        raise geometry_error(trace, exc) from None
    elapsed = time.perf_counter() - t0
    pos = np.full((E, 3), np.nan)
    added = inp.keep & np.isfinite(online).all(axis=1)
    for k in np.flatnonzero(added):
        pos[k] = est.atPoint3(pos_key(int(k)))
    valid = added & np.isfinite(pos).all(axis=1)
    n = max(int(inp.keep.sum()), 1)
    info = {"online_pos": online, "incremental_s": elapsed, "incremental_unanchored": int((inp.keep & ~added).sum()),
            "ms_per_epoch": 1000.0 * elapsed / n, "isb_m": isb_estimates(est, inp),
            "vel": read_velocities(est, np.flatnonzero(added), E)}
    cov, t1 = None, time.perf_counter()
    if want_cov:
        try:      # a component left out is whole (feed_epochs): the rest is the graph ISAM2 solved
            cov, info["vel_cov"] = marginals_at(trace, replace(inp, keep=added), cfg, est)
        except RuntimeError:
            info["incremental_no_marginals"] = 1
        info["cov_s"] = time.perf_counter() - t1
    return pos, valid, cov, info
