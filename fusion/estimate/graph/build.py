"""Assemble the fused graph, epoch by epoch, from the named factor builders.

Per epoch ``k``: a position ``x(k)``; a clock ``c(k)`` with one robust pseudorange factor per selected
satellite (GPS L1, or the first signal present, is the reference clock; every other signal gets an
inter-system bias state per motion component, introduced with a zero-mean prior at its first use);
a clock random walk to the previous clocked epoch; the position prior where the provider gave one;
and the motion model's link to ``k - 1``. Links point backwards only, so the same per-epoch factors
feed the batch graph and the incremental smoother.
"""
from __future__ import annotations

import gtsam
import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import (clock_factor_cc, isb_prior_factor_i, position_prior_factor_x,
                                           prior_noise_model, pseudorange_factor_xc, pseudorange_factor_xci,
                                           robust_model)
from fusion.estimate.graph.inputs import EpochInputs
from fusion.estimate.graph.keys import clock_key, isb_key, pos_key
from fusion.estimate.graph.motion import motion_model
from fusion.geometry import C_LIGHT
from fusion.trace import Trace


def pseudorange_factors(k: int, trace: Trace, inp: EpochInputs, cfg: GraphConfig) -> list:
    """Robust pseudorange factors of every selected satellite of epoch ``k``."""
    out = []
    comp, grp = int(inp.comp[k]), inp.isb.group[k]
    for s in np.flatnonzero(inp.sel[k]):          # ~10 satellites
        model = robust_model(cfg.robust, cfg.robust_k, gtsam.noiseModel.Isotropic.Sigma(1, float(inp.sigma[k, s])))
        pr = trace.pr[k, s] - inp.pr_bias[k, s]
        if grp[s] < 0:
            out.append(pseudorange_factor_xc(k, pr, trace.sat_pos[k, s], model))
        else:
            out.append(pseudorange_factor_xci(k, comp, int(grp[s]), pr, trace.sat_pos[k, s], model))
    return out


def clock_and_bias(k: int, inp: EpochInputs, cfg: GraphConfig, values: gtsam.Values) -> list:
    """Epoch ``k``'s clock variable and the inter-system biases first used here (values and priors)."""
    values.insert(clock_key(k), float(inp.init_clock_m[k] / C_LIGHT))
    out = []
    if inp.isb.new is not None:
        comp = int(inp.comp[k])
        for g in np.flatnonzero(inp.isb.new[k]):
            values.insert(isb_key(comp, int(g)), float(-inp.isb.init_m[g]))
            out.append(isb_prior_factor_i(comp, int(g), cfg.isb_sigma_m))
    return out


def clock_link(k: int, inp: EpochInputs) -> list:
    """The clock random walk from the previous clocked epoch to ``k`` (none across a reset)."""
    j = int(inp.clock_link[k])
    return [clock_factor_cc(j, k, inp.clock_mean_m[k], inp.clock_sigma_m[k])] if j >= 0 else []


def epoch_factors(k: int, trace: Trace, inp: EpochInputs, motion, cfg: GraphConfig
                  ) -> tuple[list, gtsam.Values]:
    """Factors and initial values introduced by epoch ``k``; ``motion`` from
    :func:`fusion.estimate.graph.motion.motion_model`."""
    factors: list = []
    values = gtsam.Values()
    values.insert(pos_key(k), inp.init_pos[k])
    if inp.sel[k].any():
        factors += clock_and_bias(k, inp, cfg, values)
        factors += pseudorange_factors(k, trace, inp, cfg)
        factors += clock_link(k, inp)
    if inp.prior_ok[k]:
        model = prior_noise_model(inp.prior_cov[k], cfg.prior_robust, cfg.prior_robust_k)
        factors.append(position_prior_factor_x(k, inp.prior_mean[k], model))
    motion.add_values(k, values)
    factors += motion.link_factors(k) if (k > 0 and inp.pos_link[k]) else motion.start_factors(k)
    return factors, values


def trace_motion(inp: EpochInputs, cfg: GraphConfig):
    """The motion model of ``cfg`` for this trace's epochs."""
    return motion_model(inp.init_pos, inp.init_vel, inp.dt, cfg)


def build_graph(trace: Trace, inp: EpochInputs, cfg: GraphConfig
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray]:
    """The whole-trace graph over the epochs in ``inp.keep``; returns (graph, initial values, epochs)."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    motion = trace_motion(inp, cfg)
    epochs = np.flatnonzero(inp.keep)
    for k in epochs:
        factors, vals = epoch_factors(int(k), trace, inp, motion, cfg)
        for f in factors:
            graph.add(f)
        values.insert(vals)
    return graph, values, epochs
