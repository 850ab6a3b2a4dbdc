"""Assemble the fused graph, epoch by epoch, from the named factor builders.

Per epoch ``k``: a position ``x(k)``; a clock ``c(k)`` with one robust pseudorange factor per selected
satellite (GPS L1, or the first signal present, is the reference clock; every other signal gets an
inter-system bias state per motion component, introduced with a zero-mean prior at its first use);
a clock random walk to the previous clocked epoch; the position prior where the provider gave one;
and the motion model's link to ``k - 1``. Where the trace carries them: a robust Doppler factor per
satellite on the velocity and a clock-drift state ``d(k)`` (the clock chain then carries the drift,
itself a random walk), and a robust time-differenced carrier-phase factor per satellite tracked
without a slip since ``k - 1``, on a displacement state ``u(k) = x(k) - x(k-1)``. Links point backwards only, so the same per-epoch factors feed the
batch graph and the incremental smoother.
"""
from __future__ import annotations

import gtsam
import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import (clock_drift_factor_ccd, clock_factor_cc, displacement_factor_xxu,
                                           doppler_factor_vcd, drift_prior_factor_cd, drift_walk_factor_cdcd,
                                           isb_prior_factor_i, position_prior_factor_x, prior_noise_model,
                                           pseudorange_factor_xc, pseudorange_factor_xci, robust_model,
                                           tdcp_factor_uqq)
from fusion.estimate.graph.inputs import EpochInputs
from fusion.estimate.graph.keys import DRIFT_HORIZON_S, carrier_clock_key, clock_key, disp_key, drift_key, isb_key, pos_key
from fusion.estimate.graph.motion import motion_model
from fusion.geometry import C_LIGHT
from fusion.trace import Trace

#: u(k) = x(k) - x(k-1) is a definition, held to 3 mm per axis (below the carrier factors' 2 cm floor);
#: 0.1 and 1 mm made ISAM2's Cholesky report indeterminant systems on simulated traces with Doppler
#: (too stiff next to the other factors' weights); 3 and 10 mm gave the same accuracy
DISPLACEMENT_SIGMA_M = 3e-3


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


def uses_drift(inp: EpochInputs) -> bool:
    """Whether the graph has clock-drift states (it uses some Doppler)."""
    return inp.raw is not None and inp.raw.use_drift


def clock_and_bias(k: int, inp: EpochInputs, cfg: GraphConfig, values: gtsam.Values) -> list:
    """Epoch ``k``'s clock variable (and drift, see :func:`drift_key`) and the inter-system biases first
    used here (values and priors)."""
    clock_s = float(inp.init_clock_m[k] / C_LIGHT)
    values.insert(clock_key(k), clock_s)
    if uses_drift(inp):
        values.insert(drift_key(k), clock_s + float(inp.clock_drift_mps[k]) * DRIFT_HORIZON_S / C_LIGHT)
    out = []
    if inp.isb.new is not None:
        comp = int(inp.comp[k])
        for g in np.flatnonzero(inp.isb.new[k]):
            values.insert(isb_key(comp, int(g)), float(-inp.isb.init_m[g]))
            out.append(isb_prior_factor_i(comp, int(g), cfg.isb_sigma_m))
    return out


def clock_link(k: int, inp: EpochInputs, cfg: GraphConfig) -> list:
    """The clock random walk from the previous clocked epoch to ``k`` (none across a reset). With drift
    states the clock follows the drift and the drift walks; a chain start gets a loose drift prior."""
    j = int(inp.clock_link[k])
    if not uses_drift(inp):
        return [clock_factor_cc(j, k, inp.clock_mean_m[k], inp.clock_sigma_m[k])] if j >= 0 else []
    if j < 0:
        return [drift_prior_factor_cd(k, float(inp.clock_drift_mps[k]), cfg.drift_start_sigma_mps)]
    root_span = float(np.sqrt(max(inp.clock_span_s[k], 1e-3)))
    return [clock_drift_factor_ccd(j, k, float(inp.clock_span_s[k]), cfg.drift_clock_rw_m * root_span),
            drift_walk_factor_cdcd(j, k, cfg.drift_rw_mps * root_span)]


def doppler_factors(k: int, trace: Trace, inp: EpochInputs, cfg: GraphConfig) -> list:
    """Robust Doppler factors of epoch ``k`` (on v(k), c(k), d(k))."""
    raw = inp.raw
    out = []
    for s in np.flatnonzero(raw.doppler[k]):      # ~10 satellites
        model = robust_model(cfg.robust, cfg.robust_k, gtsam.noiseModel.Isotropic.Sigma(1, float(raw.prr_sigma[k, s])))
        out.append(doppler_factor_vcd(k, trace.prr[k, s], trace.sat_pos[k, s], trace.sat_vel[k, s],
                                      inp.init_pos[k], model))
    return out


def tdcp_factors(k: int, trace: Trace, inp: EpochInputs, cfg: GraphConfig, values: gtsam.Values) -> list:
    """Robust time-differenced carrier factors from epoch ``k - 1`` to ``k`` on the displacement u(k)
    (its variable and definition added here when some satellite kept its carrier chain)."""
    raw = inp.raw
    cur = np.flatnonzero(raw.tdcp_prev[k] >= 0)
    if cur.size == 0:
        return []
    lin = inp.init_pos if raw.lin_pos is None else raw.lin_pos
    values.insert(disp_key(k), inp.init_pos[k] - inp.init_pos[k - 1])
    out = [displacement_factor_xxu(k, DISPLACEMENT_SIGMA_M)]
    # carrier clocks [m] are known up to a constant per chain, which a prior at the chain start fixes
    values.insert(carrier_clock_key(k), float(inp.init_clock_m[k]))
    if not (raw.tdcp_prev[k - 1] >= 0).any():
        values.insert(carrier_clock_key(k - 1), float(inp.init_clock_m[k - 1]))
        out.append(gtsam.PriorFactorDouble(carrier_clock_key(k - 1), float(inp.init_clock_m[k - 1]),
                                           gtsam.noiseModel.Isotropic.Sigma(1, 1.0)))
    for s in cur:                                   # ~10 satellites
        p = int(raw.tdcp_prev[k, s])
        model = robust_model(cfg.robust, cfg.robust_k, gtsam.noiseModel.Isotropic.Sigma(1, float(raw.tdcp_sigma[k, s])))
        out.append(tdcp_factor_uqq(k, trace.adr[k, s] - trace.adr[k - 1, p], trace.sat_pos[k - 1, p],
                                   trace.sat_pos[k, s], lin[k - 1], lin[k], model))
    return out


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
        factors += clock_link(k, inp, cfg)
        if inp.raw is not None:
            factors += doppler_factors(k, trace, inp, cfg) + tdcp_factors(k, trace, inp, cfg, values)
    if inp.prior_ok[k]:
        model = prior_noise_model(inp.prior_cov[k], cfg.prior_robust, cfg.prior_robust_k)
        factors.append(position_prior_factor_x(k, inp.prior_mean[k], model))
    if inp.odometry is not None:
        factors += inp.odometry.add_at(k, values)
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
