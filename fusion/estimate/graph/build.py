"""Assemble the fused graph from the named factor builders, one builder per factor kind for the whole
trace at once.

Per epoch ``k``: a position ``x(k)``; a clock ``c(k)`` with one robust pseudorange factor per selected
satellite (GPS L1, or the first signal present, is the reference clock; every other signal gets an
inter-system bias state per motion component, introduced with a zero-mean prior at its first use);
a clock random walk to the previous clocked epoch; the position prior where there is one; and the
motion model's link to ``k - 1``. Where the trace carries them: a robust Doppler factor per satellite
on the velocity and a clock-drift state ``d(k)`` (the clock chain then carries the drift, itself a
random walk), and a robust time-differenced carrier-phase factor per satellite tracked without a slip
since ``k - 1``, on a displacement state ``u(k) = x(k) - x(k-1)``.

Every factor and initial value is tagged with the epoch that introduces it, and links point backwards
only, so the same pieces make the batch graph (all at once) and feed the incremental smoother (epoch
by epoch). The exact linear process factors share one zero linearisation point (:func:`zero_point`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import (clock_drift_factor_ccd, clock_factor_cc, displacement_factor_xxu,
                                           doppler_drift_factor_jd, doppler_factor_vcd, drift_prior_factor_cd,
                                           drift_walk_factor_cdcd,
                                           isb_prior_factor_i, position_prior_factor_x, prior_noise_model,
                                           pseudorange_factor_xc, pseudorange_factor_xci, scalar_robust_models,
                                           tdcp_factor_linearised, zero_point)
from fusion.estimate.graph.inputs import EpochInputs, doppler_drift_epochs, motion_only
from fusion.estimate.graph.keys import (DRIFT_HORIZON_S, carrier_clock_key, clock_key, disp_key, doppler_drift_key,
                                        drift_key, isb_key, pos_key, vel_key)
from fusion.estimate.graph.motion import motion_model
from fusion.estimate.graph.raw_inputs import carrier_rows
from fusion.estimate.graph.series import where_solved
from fusion.geometry import C_LIGHT
from fusion.trace import Trace

#: u(k) = x(k) - x(k-1) is a definition, held to 3 mm per axis (below the carrier factors' 2 cm floor);
#: 0.1 and 1 mm made ISAM2's Cholesky report indeterminant systems on simulated traces with Doppler
#: (too stiff next to the other factors' weights); 3 and 10 mm gave the same accuracy
DISPLACEMENT_SIGMA_M = 3e-3


@dataclass
class GraphPieces:
    """A whole trace's factors and initial values, each tagged with the epoch that introduces it.

    factors (F,) with factor_epoch (F,); points: (epoch, key, (3,) value); doubles: (epoch, key, value);
    value_sets: (epoch, gtsam.Values) for values of other types.
    """

    factors: list = field(default_factory=list)
    factor_epoch: list = field(default_factory=list)
    points: list = field(default_factory=list)
    doubles: list = field(default_factory=list)
    value_sets: list = field(default_factory=list)
    carrier: slice | None = None       # where add_carriers put its measurement factors in ``factors``
    pseudorange: slice | None = None   # where add_pseudoranges put its factors
    #: positions in ``factors`` of factors linearised as rank-deficient HessianFactors (the four-key drift
    #: walk), which the marginals add as information (:mod:`fusion.estimate.graph.marginals`)
    dense: list = field(default_factory=list)

    def add(self, epochs, factors) -> None:
        """Factors (a list) introduced at ``epochs`` (one epoch each, or one int for all)."""
        factors = list(factors)
        self.factors += factors
        self.factor_epoch += [int(epochs)] * len(factors) if np.isscalar(epochs) else [int(k) for k in epochs]

    def graph(self, upto: slice | None = None) -> gtsam.NonlinearFactorGraph:
        """All factors (or those at positions ``upto`` of :meth:`by_epoch`'s order) as one graph."""
        g = gtsam.NonlinearFactorGraph()
        for f in self.factors if upto is None else self.factors[upto]:
            g.add(f)
        return g

    def values(self) -> gtsam.Values:
        """All initial values."""
        vals = gtsam.Values()
        for _, key, v in self.points:
            vals.insert(key, v)
        for _, key, v in self.doubles:
            vals.insert(key, c=v)          # the keyword picks GTSAM's scalar overload at once
        for _, vs in self.value_sets:
            vals.insert(vs)
        return vals

    def by_epoch(self) -> tuple[np.ndarray, list[gtsam.NonlinearFactorGraph], list[gtsam.Values]]:
        """Epochs (N,) in order, with each one's factor graph and values (for an incremental smoother)."""
        fe = np.asarray(self.factor_epoch, int)
        epochs = np.unique(np.concatenate([fe, [p[0] for p in self.points], [d[0] for d in self.doubles],
                                           [v[0] for v in self.value_sets]])).astype(int)
        pos = {int(k): i for i, k in enumerate(epochs)}
        graphs = [gtsam.NonlinearFactorGraph() for _ in epochs]
        vals = [gtsam.Values() for _ in epochs]
        for f, k in zip(self.factors, fe):
            graphs[pos[int(k)]].add(f)
        for k, key, v in self.points:
            vals[pos[k]].insert(key, v)
        for k, key, v in self.doubles:
            vals[pos[k]].insert(key, c=v)
        for k, vs in self.value_sets:
            vals[pos[k]].insert(vs)
        return epochs, graphs, vals


def uses_doppler(inp: EpochInputs) -> bool:
    """Whether the graph uses some Doppler (which measures the velocity and the clock's drift)."""
    return inp.raw is not None and inp.raw.use_drift


def drift_clock_rw(inp: EpochInputs, cfg: GraphConfig) -> float:
    """The clock's random walk [m per sqrt(s)] beside a drift state: tighter where Doppler measures the drift."""
    return cfg.drift_clock_rw_m if uses_doppler(inp) else cfg.drift_clock_rw_no_doppler_m


def level_sigma(inp: EpochInputs, cfg: GraphConfig) -> float:
    """The prior's sigma on each epoch's vertical velocity [m/s] (0: none): its own where Doppler is used."""
    return cfg.cv_level_sigma_mps if uses_doppler(inp) else cfg.cv_level_sigma_no_doppler_mps


def clocked_epochs(inp: EpochInputs, epochs: np.ndarray) -> np.ndarray:
    """The kept epochs with a clock variable (at least one selected pseudorange)."""
    return epochs[inp.sel[epochs].any(axis=1)]


def add_positions(p: GraphPieces, inp: EpochInputs, epochs: np.ndarray) -> None:
    """x(k) at the initial positions."""
    p.points += [(int(k), pos_key(int(k)), inp.init_pos[k]) for k in epochs]


def add_clocks(p: GraphPieces, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> None:
    """c(k) (and d(k), see :func:`drift_key`) at every clocked epoch; each inter-system bias where its
    group is first used in a component (value and zero-mean prior)."""
    ks = clocked_epochs(inp, epochs)
    clock_s = inp.init_clock_m[ks] / C_LIGHT
    p.doubles += [(int(k), clock_key(int(k)), float(c)) for k, c in zip(ks, clock_s)]
    if inp.use_drift:
        d = clock_s + inp.clock_drift_mps[ks] * DRIFT_HORIZON_S / C_LIGHT
        p.doubles += [(int(k), drift_key(int(k)), float(v)) for k, v in zip(ks, d)]
        own = doppler_drift_epochs(inp)[ks]
        p.doubles += [(int(k), doppler_drift_key(int(k)), float(v)) for k, v in zip(ks[own], d[own])]
    if inp.isb.new is None:
        return
    new_k, new_g = np.nonzero(inp.isb.new[ks])
    for k, g in zip(ks[new_k], new_g):           # a handful: one per signal group and component
        comp = int(inp.comp[k])
        p.doubles.append((int(k), isb_key(comp, int(g)), float(-inp.isb.init_m[g])))
        p.add(k, [isb_prior_factor_i(comp, int(g), cfg.isb_sigma_m)])


def add_pseudoranges(p: GraphPieces, trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> None:
    """A robust pseudorange factor per selected slot of the kept epochs."""
    first = len(p.factors)
    p.add(*pseudorange_factors(trace, inp, cfg, epochs))
    p.pseudorange = slice(first, len(p.factors))


def pseudorange_factors(trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray
                        ) -> tuple[np.ndarray, list]:
    """The robust pseudorange factors of the selected slots of ``epochs`` (K,), in (epoch, slot) order,
    and the epoch of each."""
    keep = np.zeros(trace.n_epochs, bool)
    keep[epochs] = True
    ks, ss = np.nonzero(inp.sel & keep[:, None])
    pr = trace.pr[ks, ss] - inp.pr_bias[ks, ss]
    sigma, grp, comp = inp.sigma[ks, ss], inp.isb.group[ks, ss], inp.comp[ks]
    sat = trace.sat_pos[ks, ss]
    models = np.empty(ks.size, object)
    for kind, k, at in inp.pr_losses:
        rows = np.flatnonzero(at[ks])
        models[rows] = scalar_robust_models(kind, k, sigma[rows])
    return ks, [pseudorange_factor_xc(k, r, sat[i], models[i]) if g < 0 else
                pseudorange_factor_xci(k, c, g, r, sat[i], models[i])
                for i, (k, r, g, c) in enumerate(zip(ks.tolist(), pr.tolist(), grp.tolist(), comp.tolist()))]


def add_clock_links(p: GraphPieces, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray, lin: gtsam.Values) -> None:
    """The clock random walk from the previous clocked epoch (none across a reset). With drift states the
    clock follows the drift and the drift walks; a chain start gets a loose drift prior."""
    ks = clocked_epochs(inp, epochs)
    js = inp.clock_link[ks]
    if not inp.use_drift:
        linked = js >= 0
        p.add(ks[linked], [clock_factor_cc(int(j), int(k), inp.clock_mean_m[k], inp.clock_sigma_m[k])
                           for j, k in zip(js[linked], ks[linked])])
        return
    starts = ks[js < 0]
    p.add(starts, [drift_prior_factor_cd(int(k), float(inp.clock_drift_mps[k]), cfg.drift_start_sigma_mps, lin)
                   for k in starts])
    linked = js >= 0
    ks, js = ks[linked], js[linked]
    root, rw = np.sqrt(np.maximum(inp.clock_span_s[ks], 1e-3)), drift_clock_rw(inp, cfg)
    p.add(ks, [clock_drift_factor_ccd(int(j), int(k), float(inp.clock_span_s[k]), rw * r, lin)
               for j, k, r in zip(js, ks, root)])
    first = len(p.factors)
    p.add(ks, [drift_walk_factor_cdcd(int(j), int(k), cfg.drift_rw_mps * r, lin) for j, k, r in zip(js, ks, root)])
    p.dense += range(first, len(p.factors))


def add_dopplers(p: GraphPieces, trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray,
                 lin: gtsam.Values) -> None:
    """A robust Doppler factor per used slot (on v(k), c(k), d(k); or on the drift the Doppler sees, j(k), tied
    to d(k) by the epoch's white jump, :attr:`EpochInputs.doppler_jump_mps`)."""
    keep = np.zeros(trace.n_epochs, bool)
    keep[epochs] = True
    ks, ss = np.nonzero(inp.raw.doppler & keep[:, None])
    prr = trace.prr[ks, ss] - inp.raw.prr_bias[ks, ss]
    models = scalar_robust_models(cfg.robust, cfg.rate_robust_k, inp.raw.prr_sigma[ks, ss])
    sat_pos, sat_vel, rx = trace.sat_pos[ks, ss], trace.sat_vel[ks, ss], inp.init_pos[ks]
    own = doppler_drift_epochs(inp) & keep
    p.add(ks, [doppler_factor_vcd(k, r, sat_pos[i], sat_vel[i], rx[i], models[i],
                                  doppler_drift_key(k) if own[k] else None)
               for i, (k, r) in enumerate(zip(ks.tolist(), prr.tolist()))])
    js = np.flatnonzero(own)
    p.add(js, [doppler_drift_factor_jd(int(k), inp.doppler_jump_mps, lin) for k in js])


def add_carriers(p: GraphPieces, trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray,
                 lin: gtsam.Values) -> None:
    """Robust time-differenced carrier factors from epoch ``k - 1`` to ``k`` on the displacement u(k),
    with u(k), its definition and the carrier clocks q(k-1), q(k) [m] where some satellite kept its chain."""
    raw = inp.raw
    keep = np.zeros(trace.n_epochs, bool)
    keep[epochs] = True
    has = (raw.tdcp_prev >= 0).any(axis=1) & keep
    ks = np.flatnonzero(has)
    lin_pos = inp.init_pos if raw.lin_pos is None else raw.lin_pos
    p.points += [(int(k), disp_key(int(k)), inp.init_pos[k] - inp.init_pos[k - 1]) for k in ks]
    p.add(ks, [displacement_factor_xxu(int(k), DISPLACEMENT_SIGMA_M, lin) for k in ks])
    # carrier clocks [m] are known up to a constant per chain, which a prior at the chain start fixes
    p.doubles += [(int(k), carrier_clock_key(int(k)), float(inp.init_clock_m[k])) for k in ks]
    starts = ks[~has[ks - 1]]
    p.doubles += [(int(k), carrier_clock_key(int(k) - 1), float(inp.init_clock_m[k - 1])) for k in starts]
    unit = gtsam.noiseModel.Isotropic.Sigma(1, 1.0)
    p.add(starts, [gtsam.PriorFactorDouble(carrier_clock_key(int(k) - 1), float(inp.init_clock_m[k - 1]), unit)
                   for k in starts])
    if cfg.carrier_clock_prior_m > 0:
        # where the robust loss has all but switched off an epoch's carrier differences, nothing else holds its
        # carrier clock, and ISAM2's undamped step finds the system singular: a loose prior at the code clock
        loose = gtsam.noiseModel.Isotropic.Sigma(1, cfg.carrier_clock_prior_m)
        p.add(ks, [gtsam.PriorFactorDouble(carrier_clock_key(int(k)), float(inp.init_clock_m[k]), loose)
                   for k in ks])
    first = len(p.factors)
    p.add(*carrier_factors(trace, inp, cfg, has, lin_pos))
    p.carrier = slice(first, len(p.factors))


def carrier_factors(trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray, lin_pos: np.ndarray
                    ) -> tuple[np.ndarray, list]:
    """The time-differenced carrier factors of the epochs ``epochs`` (E,) bool, linearised at ``lin_pos``
    (E,3), and the epoch of each."""
    raw = inp.raw
    kk, ss = np.nonzero((raw.tdcp_prev >= 0) & epochs[:, None])
    sat_k = trace.sat_pos[kk, ss]
    _, measured = carrier_rows(trace, raw, lin_pos, kk, ss)
    models = scalar_robust_models(cfg.robust, cfg.rate_robust_k, raw.tdcp_sigma[kk, ss])
    guess_k = lin_pos[kk]
    return kk, [tdcp_factor_linearised(k, m, sat_k[i], guess_k[i], models[i])
                for i, (k, m) in enumerate(zip(kk.tolist(), measured.tolist()))]


def add_priors(p: GraphPieces, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> None:
    """The position prior where there is one."""
    p.add(*prior_factors(inp, cfg, epochs))


def prior_factors(inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> tuple[np.ndarray, list]:
    """The position prior factors of ``epochs`` (K,) that have one, and the epoch of each."""
    ks = epochs[inp.prior_ok[epochs]]
    return ks, [position_prior_factor_x(int(k), inp.prior_mean[k],
                                        prior_noise_model(inp.prior_cov[k], cfg.prior_robust, cfg.prior_robust_k))
                for k in ks]


def add_motion(p: GraphPieces, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray, lin: gtsam.Values) -> None:
    """The motion model's variables and its link from ``k - 1`` (or a component start) at every kept epoch."""
    motion = motion_model(inp.init_pos, inp.init_vel, inp.dt, cfg, motion_only(inp), level_sigma(inp, cfg))
    if cfg.motion == "cv":
        p.points += [(int(k), vel_key(int(k)), inp.init_vel[k]) for k in epochs]
    for k in epochs:
        k = int(k)
        p.add(k, motion.link_factors(k, lin) if (k > 0 and inp.pos_link[k]) else motion.start_factors(k))
        p.add(k, motion.level_factors(k, lin))


def add_odometry(p: GraphPieces, inp: EpochInputs) -> None:
    """The odometry steps (:mod:`fusion.estimate.graph.odometry`), the heading state with the first."""
    odo = inp.odometry
    if odo is None or not len(odo.factors):
        return
    p.add(odo.epoch, odo.factors)
    p.value_sets.append((int(odo.epoch[0]), odo.values))


def linearisation_point(inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> gtsam.Values:
    """Zeros at every key an exact linear factor of this graph touches: positions and velocities (the
    constant-velocity link), positions and displacements (carrier), clocks and drifts (the drift chain).
    The shared linearisation point of :mod:`fusion.estimate.graph.factors`' linear factors; keys no linear
    factor uses are left out (each insert is a Python call: half the incremental build on a GPS-only trace)."""
    ks = [int(k) for k in epochs]
    points = (pos_key, vel_key) if cfg.motion == "cv" else ()
    if inp.raw is not None and inp.raw.has_tdcp:
        points = (pos_key, vel_key, disp_key) if points else (pos_key, disp_key)
    lin = zero_point([f(k) for k in ks for f in points])
    if inp.use_drift:
        lin.insert(zero_point([f(k) for k in ks for f in (clock_key, drift_key)], "double"))
        lin.insert(zero_point([doppler_drift_key(int(k)) for k in epochs[doppler_drift_epochs(inp)[epochs]]], "double"))
    return lin


def graph_pieces(trace: Trace, inp: EpochInputs, cfg: GraphConfig) -> GraphPieces:
    """Every factor and initial value of the kept epochs (``inp.keep``), built kind by kind."""
    epochs = np.flatnonzero(inp.keep)
    p = GraphPieces()
    lin = linearisation_point(inp, cfg, epochs)
    add_positions(p, inp, epochs)
    add_clocks(p, inp, cfg, epochs)
    add_pseudoranges(p, trace, inp, cfg, epochs)
    add_clock_links(p, inp, cfg, epochs, lin)
    if inp.raw is not None:
        add_dopplers(p, trace, inp, cfg, epochs, lin)
        if inp.raw.has_tdcp:               # a trace may have Doppler but no carrier phase at all
            add_carriers(p, trace, inp, cfg, epochs, lin)
    add_priors(p, inp, cfg, epochs)
    add_motion(p, inp, cfg, epochs, lin)
    add_odometry(p, inp)
    return p


def build_graph(trace: Trace, inp: EpochInputs, cfg: GraphConfig
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray]:
    """The whole-trace graph over the epochs in ``inp.keep``; returns (graph, initial values, epochs)."""
    p = graph_pieces(trace, inp, cfg)
    return p.graph(), p.values(), np.flatnonzero(inp.keep)


def relinearise_carriers(graph: gtsam.NonlinearFactorGraph, p: GraphPieces, trace: Trace, inp: EpochInputs,
                         cfg: GraphConfig, pos: np.ndarray) -> None:
    """Replace ``graph``'s carrier factors (built from ``p``) by the same ones linearised at ``pos`` (E,3)
    (NaN rows: where they were)."""
    if p.carrier is None or p.carrier.start == p.carrier.stop:
        return
    raw = inp.raw
    old = inp.init_pos if raw.lin_pos is None else raw.lin_pos
    lin = where_solved(pos, old)
    has = np.zeros(trace.n_epochs, bool)
    has[np.asarray(p.factor_epoch[p.carrier], int)] = True
    _, factors = carrier_factors(trace, inp, cfg, has, lin)
    for i, f in zip(range(p.carrier.start, p.carrier.stop), factors):
        graph.replace(i, f)
