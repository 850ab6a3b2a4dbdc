"""The fused graph of :mod:`fusion.estimate.graph.build` as vectorised factor blocks for
:mod:`fusion.estimate.graph.banded_gn`: the same factors, noise models and robust losses, one
:class:`~fusion.estimate.graph.banded_gn.Blocks` per kind for the whole trace.

The state vector holds each epoch's variables together, epochs in time order (position, velocity,
clock, drift, the drift its Doppler sees, displacement, carrier clock), then the trace-wide inter-system
biases. Clocks and drifts
are in metres here (GTSAM's keys hold seconds, :mod:`fusion.estimate.graph.keys`): a cost is the same in
either unit, and metres keep the normal equations at one scale. That both graphs have the same cost at
any values is tested (``tests/estimate/test_banded_gn.py``), kind by kind.

Odometry (a nonlinear heading state) and relinearised carrier factors have no blocks here:
:func:`vector_graph` returns None and the batch solver runs GTSAM's.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.banded_gn import Blocks, System, information_triplets
from fusion.estimate.graph.build import DISPLACEMENT_SIGMA_M, clocked_epochs, drift_clock_rw, level_sigma
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import range_and_gradient
from fusion.estimate.graph.inputs import EpochInputs, doppler_drift_epochs, motion_only
from fusion.estimate.graph.isb import isb_label
from fusion.estimate.graph.marginals import information_marginals
from fusion.estimate.graph.keys import (DRIFT_HORIZON_S, carrier_clock_key, clock_key, disp_key, doppler_drift_key,
                                        drift_key, isb_key, pos_key, vel_key)
from fusion.estimate.graph.motion import START_VEL_SIGMA_MPS, motion_model
from fusion.estimate.graph.raw_inputs import carrier_rows, doppler_rows_at
from fusion.geometry import C_LIGHT
from fusion.trace import Trace

#: per-epoch variables in their order inside an epoch: name, dimension, GTSAM key, GTSAM unit per metre
EPOCH_VARS = (("pos", 3, pos_key, 1.0), ("vel", 3, vel_key, 1.0), ("clk", 1, clock_key, 1.0 / C_LIGHT),
              ("drift", 1, drift_key, 1.0 / C_LIGHT), ("jdrift", 1, doppler_drift_key, 1.0 / C_LIGHT),
              ("disp", 3, disp_key, 1.0), ("qclk", 1, carrier_clock_key, 1.0))
_I3 = np.eye(3)


@dataclass
class Layout:
    """Where each variable sits in the state vector: ``start[name]`` (E,) int, the index of epoch k's
    variable ``name`` of :data:`EPOCH_VARS` (-1: none); ``isb`` {(component, group): index}; N scalars,
    the first ``n_local`` per epoch."""

    start: dict
    isb: dict
    n: int
    n_local: int

    def keys(self) -> list[tuple[int, int, int, float]]:
        """(GTSAM key, index, dimension, GTSAM unit per metre) of every variable."""
        out = []
        for name, dim, key, unit in EPOCH_VARS:
            ks = np.flatnonzero(self.start[name] >= 0)
            out += [(key(int(k)), int(self.start[name][k]), dim, unit) for k in ks]
        out += [(isb_key(c, g), i, 1, 1.0) for (c, g), i in self.isb.items()]
        return out


def epoch_variables(trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> dict:
    """(E,) bool per :data:`EPOCH_VARS` name: which epochs have that variable in the graph."""
    E = trace.n_epochs
    has = {name: np.zeros(E, bool) for name, *_ in EPOCH_VARS}
    has["pos"][epochs] = True
    has["vel"][epochs] = cfg.motion == "cv"
    ks = clocked_epochs(inp, epochs)
    has["clk"][ks] = True
    has["drift"][ks] = inp.use_drift
    has["jdrift"][epochs] = doppler_drift_epochs(inp)[epochs]
    if inp.raw is not None:
        carrier = carrier_epochs(trace, inp)
        has["disp"] = carrier
        has["qclk"] = carrier | np.r_[carrier[1:], False]
    return has


def carrier_epochs(trace: Trace, inp: EpochInputs) -> np.ndarray:
    """(E,) bool kept epochs with a time-differenced carrier factor (as ``build.add_carriers``); none
    where the trace has no carrier phase (``inp.raw.has_tdcp``)."""
    return (inp.raw.tdcp_prev >= 0).any(axis=1) & inp.keep


def make_layout(trace: Trace, inp: EpochInputs, cfg: GraphConfig, epochs: np.ndarray) -> Layout:
    """The state vector's layout (see :class:`Layout`)."""
    has = epoch_variables(trace, inp, cfg, epochs)
    dims = np.array([d for _, d, *_ in EPOCH_VARS])
    size = np.stack([has[name] for name, *_ in EPOCH_VARS], axis=1) * dims        # (E,V)
    first = (np.cumsum(size.ravel()) - size.ravel()).reshape(size.shape)
    start = {name: np.where(size[:, i] > 0, first[:, i], -1) for i, (name, *_) in enumerate(EPOCH_VARS)}
    n_local = int(size.sum())
    isb = {}
    if inp.isb.new is not None:
        ks = clocked_epochs(inp, epochs)
        new_k, new_g = np.nonzero(inp.isb.new[ks])
        for k, g in zip(ks[new_k], new_g):
            isb.setdefault((int(inp.comp[k]), int(g)), n_local + len(isb))
    return Layout(start, isb, n_local + len(isb), n_local)


def initial_state(trace: Trace, inp: EpochInputs, lay: Layout) -> np.ndarray:
    """(N,) the initial values ``build`` gives GTSAM, clocks and drifts in metres."""
    x = np.zeros(lay.n)
    st = lay.start
    _put(x, st["pos"], inp.init_pos)
    _put(x, st["vel"], inp.init_vel)
    _put(x, st["clk"], inp.init_clock_m[:, None])
    if (st["drift"] >= 0).any():
        drift = (inp.init_clock_m + inp.clock_drift_mps * DRIFT_HORIZON_S)[:, None]
        _put(x, st["drift"], drift)
        _put(x, st["jdrift"], drift)
    prev = np.r_[inp.init_pos[:1], inp.init_pos[:-1]]
    _put(x, st["disp"], inp.init_pos - prev)
    _put(x, st["qclk"], inp.init_clock_m[:, None])
    for (_, g), i in lay.isb.items():
        x[i] = -inp.isb.init_m[g]
    return x


def _put(x: np.ndarray, start: np.ndarray, values: np.ndarray) -> None:
    """x[start[k] + j] = values[k, j] where start[k] >= 0; values (E,d)."""
    ks = np.flatnonzero(start >= 0)
    x[start[ks, None] + np.arange(values.shape[1])] = values[ks]


def _cols(start: np.ndarray, ks: np.ndarray, dim: int) -> np.ndarray:
    """(K,dim) state indices of a variable at epochs ``ks``."""
    return start[ks, None] + np.arange(dim)


def scalar_blocks(cols: np.ndarray, coeffs: np.ndarray, rhs: np.ndarray, sigma: np.ndarray | float,
                  robust: str = "none", k: float = 1.0) -> Blocks:
    """Linear scalar factors ``(coeffs . x[cols] - rhs) / sigma``: cols, coeffs (M,n), rhs (M,), sigma (M,) or
    a number."""
    s = np.broadcast_to(np.asarray(sigma, float), rhs.shape)
    return Blocks(cols, (coeffs / s[:, None])[:, None, :], (rhs / s)[:, None], robust, k)


def whitened_blocks(cols: np.ndarray, A: np.ndarray, b: np.ndarray, cov: np.ndarray | None = None,
                    robust: str = "none", k: float = 1.0) -> Blocks:
    """Linear 3-D factors ``A x[cols] - b`` (A (M,3,n), b (M,3)) with covariance ``cov`` (M,3,3) (None:
    already whitened), whitened by the inverse of its Cholesky factor."""
    if cov is not None:
        try:
            W = np.linalg.inv(np.linalg.cholesky(cov))
        except np.linalg.LinAlgError:
            raise GeometryError("a 3-D noise covariance of the graph (motion, prior or odometry) is not positive "
                                "definite: a sigma too small or too large for floating point in its "
                                "settings?") from None
        A, b = W @ A, np.einsum("mij,mj->mi", W, b)
    return Blocks(cols, A, b, robust, k)


def pseudorange_blocks(trace: Trace, inp: EpochInputs, cfg: GraphConfig, lay: Layout) -> list[Blocks]:
    """The robust pseudorange factors: reference-clock slots, then slots with an inter-system bias."""
    ks, ss = np.nonzero(inp.sel & inp.keep[:, None])
    pr = trace.pr[ks, ss] - inp.pr_bias[ks, ss]
    sigma, grp, sat = inp.sigma[ks, ss], inp.isb.group[ks, ss], trace.sat_pos[ks, ss]
    out = []
    for (robust, k, at), isb in itertools.product(inp.pr_losses, (False, True)):
        m = ((grp >= 0) == isb) & at[ks]
        cols = np.concatenate([_cols(lay.start["pos"], ks[m], 3), lay.start["clk"][ks[m], None]], axis=1)
        if isb:
            cols = np.concatenate([cols, isb_index(lay, inp.comp[ks[m]], grp[m])[:, None]], axis=1)
        out.append(Blocks(cols, robust=robust, k=k,
                          model=_pseudorange_model(cols, sat[m], pr[m], sigma[m])))
    return out


def isb_index(lay: Layout, comp: np.ndarray, group: np.ndarray) -> np.ndarray:
    """(M,) state index of the inter-system bias of each (component, group) pair, comp and group (M,) int
    (-1 where the layout has no such bias)."""
    if not lay.isb:
        return np.full(len(comp), -1, np.int64)
    keys = np.array(list(lay.isb), np.int64).reshape(-1, 2)
    table = np.full((keys[:, 0].max() + 1, keys[:, 1].max() + 1), -1, np.int64)
    table[keys[:, 0], keys[:, 1]] = list(lay.isb.values())
    inside = (comp < table.shape[0]) & (group < table.shape[1])
    return np.where(inside, table[np.minimum(comp, table.shape[0] - 1), np.minimum(group, table.shape[1] - 1)], -1)


def _pseudorange_model(cols: np.ndarray, sat: np.ndarray, pr: np.ndarray, sigma: np.ndarray):
    """GTSAM's pseudorange model ``range + Sagnac + clock [- bias] - pr`` over ``sigma``, for M factors
    with variables cols (M,4|5), satellites sat (M,3), pseudoranges pr (M,) and sigmas (M,) [m]."""
    with_bias = cols.shape[1] == 5

    def model(x: np.ndarray, jacobian: bool = True):
        geom, grad = range_and_gradient(sat, x[cols[:, :3]])
        r = geom + x[cols[:, 3]] - pr
        if with_bias:
            r = r - x[cols[:, 4]]
        if not jacobian:
            return (r / sigma)[:, None], None
        parts = [grad, np.ones((len(pr), 1))] + ([-np.ones((len(pr), 1))] if with_bias else [])
        return (r / sigma)[:, None], (np.concatenate(parts, axis=1) / sigma[:, None])[:, None, :]
    return model


def clock_blocks(inp: EpochInputs, cfg: GraphConfig, lay: Layout, epochs: np.ndarray) -> list[Blocks]:
    """The clock chain (and drift states): ``build.add_clock_links`` in metres."""
    ks = clocked_epochs(inp, epochs)
    js = inp.clock_link[ks]
    c, d = lay.start["clk"], lay.start["drift"]
    linked = js >= 0
    if not inp.use_drift:
        k, j = ks[linked], js[linked]
        return [scalar_blocks(np.stack([c[j], c[k]], 1), np.tile([-1.0, 1.0], (len(k), 1)), inp.clock_mean_m[k],
                              inp.clock_sigma_m[k])]
    H, s = DRIFT_HORIZON_S, ks[~linked]
    out = [scalar_blocks(np.stack([d[s], c[s]], 1), np.tile([1.0 / H, -1.0 / H], (len(s), 1)),
                         inp.clock_drift_mps[s], cfg.drift_start_sigma_mps)]
    k, j = ks[linked], js[linked]
    root = np.sqrt(np.maximum(inp.clock_span_s[k], 1e-3))
    a = inp.clock_span_s[k] / H
    out.append(scalar_blocks(np.stack([c[k], c[j], d[j]], 1), np.stack([np.ones_like(a), a - 1.0, -a], 1),
                             np.zeros(len(k)), drift_clock_rw(inp, cfg) * root))
    out.append(scalar_blocks(np.stack([d[k], c[k], d[j], c[j]], 1), np.tile([1.0, -1.0, -1.0, 1.0], (len(k), 1)),
                             np.zeros(len(k)), cfg.drift_rw_mps * root * H))
    return out


def isb_blocks(inp: EpochInputs, cfg: GraphConfig, lay: Layout) -> list[Blocks]:
    """The zero-mean prior of each inter-system bias."""
    idx = np.array(list(lay.isb.values()), int)
    return [scalar_blocks(idx[:, None], np.ones((len(idx), 1)), np.zeros(len(idx)), cfg.isb_sigma_m)]


def doppler_blocks(trace: Trace, inp: EpochInputs, cfg: GraphConfig, lay: Layout) -> list[Blocks]:
    """The robust Doppler factors on v(k), c(k) and d(k) (or the drift the Doppler sees, j(k), tied to d(k) by
    the epoch's white jump): GTSAM's ``DopplerFactor``, linear in them."""
    raw, st = inp.raw, lay.start
    ks, ss = np.nonzero(raw.doppler & inp.keep[:, None])
    grad, rhs = doppler_rows_at(trace, raw, inp.init_pos, ks, ss)
    H = DRIFT_HORIZON_S
    drift = np.where(st["jdrift"] >= 0, st["jdrift"], st["drift"])
    cols = np.concatenate([_cols(st["vel"], ks, 3), st["clk"][ks, None], drift[ks, None]], 1)
    coeffs = np.concatenate([grad, np.full((len(ks), 1), -1.0 / H), np.full((len(ks), 1), 1.0 / H)], 1)
    out = [scalar_blocks(cols, coeffs, rhs, raw.prr_sigma[ks, ss], cfg.robust, cfg.rate_robust_k)]
    js = np.flatnonzero(st["jdrift"] >= 0)
    if len(js):
        out.append(scalar_blocks(np.stack([st["jdrift"][js], st["drift"][js]], 1), np.tile([1.0, -1.0], (len(js), 1)),
                                 np.zeros(len(js)), inp.doppler_jump_mps * H))
    return out


def carrier_blocks(trace: Trace, inp: EpochInputs, cfg: GraphConfig, lay: Layout) -> list[Blocks]:
    """The displacement definitions, carrier-clock chain priors and robust time-differenced carrier
    factors (``build.add_carriers``)."""
    raw, st = inp.raw, lay.start
    has = carrier_epochs(trace, inp)
    ks = np.flatnonzero(has)
    w = 1.0 / DISPLACEMENT_SIGMA_M
    disp_cols = np.concatenate([_cols(st["disp"], ks, 3), _cols(st["pos"], ks, 3), _cols(st["pos"], ks - 1, 3)], 1)
    disp = whitened_blocks(disp_cols,
                           np.tile(np.hstack([w * _I3, -w * _I3, w * _I3]), (len(ks), 1, 1)), np.zeros((len(ks), 3)))
    starts = ks[~has[ks - 1]]
    chain = scalar_blocks(st["qclk"][starts - 1, None], np.ones((len(starts), 1)), inp.init_clock_m[starts - 1], 1.0)
    kk, ss = np.nonzero((raw.tdcp_prev >= 0) & has[:, None])
    grad, measured = carrier_rows(trace, raw, inp.init_pos if raw.lin_pos is None else raw.lin_pos, kk, ss)
    cols = np.concatenate([_cols(st["disp"], kk, 3), st["qclk"][kk - 1, None], st["qclk"][kk, None]], 1)
    coeffs = np.concatenate([grad, -np.ones((len(kk), 1)), np.ones((len(kk), 1))], 1)
    tdcp = scalar_blocks(cols, coeffs, measured, raw.tdcp_sigma[kk, ss], cfg.robust, cfg.rate_robust_k)
    return [disp, chain, tdcp]


def prior_blocks(inp: EpochInputs, cfg: GraphConfig, lay: Layout, epochs: np.ndarray) -> list[Blocks]:
    """The position priors (a learned model's), robust on their Mahalanobis distance."""
    ks = epochs[inp.prior_ok[epochs]]
    return [whitened_blocks(_cols(lay.start["pos"], ks, 3), np.tile(_I3, (len(ks), 1, 1)), inp.prior_mean[ks],
                            inp.prior_cov[ks], cfg.prior_robust, cfg.prior_robust_k)]


def motion_blocks(inp: EpochInputs, cfg: GraphConfig, lay: Layout, epochs: np.ndarray) -> list[Blocks]:
    """The motion model's links from ``k - 1`` and its component starts (:mod:`fusion.estimate.graph.motion`)."""
    model = motion_model(inp.init_pos, inp.init_vel, inp.dt, cfg, motion_only(inp), level_sigma(inp, cfg))
    link = (epochs > 0) & inp.pos_link[epochs]
    k = epochs[link]
    pos = lay.start["pos"]
    if cfg.motion == "rw":
        return [whitened_blocks(np.concatenate([_cols(pos, k - 1, 3), _cols(pos, k, 3)], 1),
                                np.tile(np.hstack([-_I3, _I3]), (len(k), 1, 1)), np.zeros((len(k), 3)), model.cov[k])]
    vel, s = lay.start["vel"], epochs[~link]
    w = model.pos_sqrt_info[k][:, None, None]
    A = np.concatenate([w * _I3, -w * _I3, -w * inp.dt[k][:, None, None] * _I3], axis=2)
    step = whitened_blocks(np.concatenate([_cols(pos, k, 3), _cols(pos, k - 1, 3), _cols(vel, k - 1, 3)], 1),
                           A, np.zeros((len(k), 3)))
    walk = whitened_blocks(np.concatenate([_cols(vel, k - 1, 3), _cols(vel, k, 3)], 1),
                           np.tile(np.hstack([-_I3, _I3]), (len(k), 1, 1)), np.zeros((len(k), 3)), model.vel_cov[k])
    start = whitened_blocks(_cols(vel, s, 3), np.tile(_I3 / START_VEL_SIGMA_MPS, (len(s), 1, 1)),
                            inp.init_vel[s] / START_VEL_SIGMA_MPS)
    if model.level_row is None:
        return [step, walk, start]
    level = scalar_blocks(_cols(vel, epochs, 3), model.level_row[epochs], np.zeros(len(epochs)), 1.0)
    return [step, walk, start, level]


@dataclass
class VectorGraph:
    """A trace's fused graph as factor blocks: the system, its layout and initial state (N,)."""

    system: System
    layout: Layout
    x0: np.ndarray

    @property
    def n_factors(self) -> int:
        """How many factors (GTSAM's graph holds as many)."""
        return sum(len(b) for b in self.system.blocks)


def supported(trace: Trace, inp: EpochInputs, cfg: GraphConfig) -> bool:
    """Whether :func:`vector_graph` can hold this graph (no odometry, no carrier relinearisation, a
    velocity state wherever Doppler needs one, every carrier step between two kept epochs)."""
    if cfg.motion not in ("cv", "rw") or cfg.tdcp_relinearise:
        return False
    if inp.odometry is not None and len(inp.odometry.factors):
        return False
    if inp.raw is not None:
        if cfg.motion != "cv" and (inp.raw.doppler & inp.keep[:, None]).any():
            return False
        ks = np.flatnonzero(carrier_epochs(trace, inp))
        if len(ks) and (ks.min() == 0 or not inp.keep[ks - 1].all()):
            return False
    return True


def vector_graph(trace: Trace, inp: EpochInputs, cfg: GraphConfig) -> VectorGraph | None:
    """The graph ``build.graph_pieces`` makes, as factor blocks (None where :func:`supported` says no)."""
    if not supported(trace, inp, cfg):
        return None
    epochs = np.flatnonzero(inp.keep)
    lay = make_layout(trace, inp, cfg, epochs)
    blocks = pseudorange_blocks(trace, inp, cfg, lay) + isb_blocks(inp, cfg, lay) + clock_blocks(inp, cfg, lay, epochs)
    if inp.raw is not None:
        blocks += doppler_blocks(trace, inp, cfg, lay)
        if inp.raw.has_tdcp:
            blocks += carrier_blocks(trace, inp, cfg, lay)
    blocks += prior_blocks(inp, cfg, lay, epochs) + motion_blocks(inp, cfg, lay, epochs)
    blocks = [b for b in blocks if len(b)]
    return VectorGraph(System(blocks, lay.n, lay.n_local), lay, initial_state(trace, inp, lay))


def to_values(lay: Layout, x: np.ndarray) -> gtsam.Values:
    """The state x (N,) as GTSAM values (clocks and drifts in seconds)."""
    vals = gtsam.Values()
    for key, i, dim, unit in lay.keys():
        if dim == 3:
            vals.insert(key, x[i:i + 3].copy())
        else:
            vals.insert(key, c=float(x[i] * unit))
    return vals


def from_values(lay: Layout, vals: gtsam.Values) -> np.ndarray:
    """GTSAM values as the state (N,) (clocks and drifts in metres)."""
    x = np.zeros(lay.n)
    for key, i, dim, unit in lay.keys():
        if dim == 3:
            x[i:i + 3] = vals.atPoint3(key)
        else:
            x[i] = vals.atDouble(key) / unit
    return x


def same_layout(a: Layout, b: Layout) -> bool:
    """Whether two layouts hold the same variables at the same places (a solution of one starts the other)."""
    return a.n == b.n and a.isb == b.isb and all(np.array_equal(a.start[k], b.start[k]) for k in a.start)


def banded_marginals(vec: VectorGraph, x: np.ndarray, epochs: np.ndarray, E: int,
                     states: tuple[str, ...] = ("pos",)) -> dict[str, np.ndarray] | None:
    """state -> (E,3,3) ECEF marginal covariances of that 3-vector state ("pos", "vel") at the solution x (N,)
    (NaN off ``epochs``; a state the layout lacks is left out), from the information matrix there (robust losses
    reweighted, as ``gtsam.Marginals`` linearises), one recursion for all; None where the recursion of
    :func:`~fusion.estimate.graph.marginals.information_marginals` does not pay. RuntimeError where the graph is
    singular at the solution."""
    states = tuple(k for k in states if not len(epochs) or vec.layout.start[k][epochs[0]] >= 0)
    out = {k: np.full((E, 3, 3), np.nan) for k in states}
    if not len(epochs) or not states:
        return out
    r, c, h = information_triplets(vec.system, x)
    p0 = np.concatenate([vec.layout.start[k][epochs] for k in states])
    got = information_marginals(r, c, h, vec.layout.n, vec.layout.n_local, p0)
    if got is None:
        return None
    for i, k in enumerate(states):
        out[k][epochs] = got[i * len(epochs):(i + 1) * len(epochs)]
    return out


def vector_isb_estimates(lay: Layout, x: np.ndarray, inp: EpochInputs) -> dict[str, float]:
    """Estimated inter-system biases [m], keyed and ordered as :func:`~fusion.estimate.graph.isb.isb_estimates`
    gives them (:func:`~fusion.estimate.graph.isb.isb_label`)."""
    order = sorted((g, c) for c, g in lay.isb)          # GTSAM's order: by group, then component
    return {isb_label(inp.isb.groups[g], c): -float(x[lay.isb[(c, g)]]) for g, c in order}


def vector_velocities(lay: Layout, x: np.ndarray, epochs: np.ndarray, E: int) -> np.ndarray | None:
    """(E,3) ECEF velocities [m/s] of the solution (NaN off ``epochs``), None without velocity states."""
    st = lay.start["vel"]
    if not len(epochs) or st[epochs[0]] < 0:
        return None
    vel = np.full((E, 3), np.nan)
    vel[epochs] = x[st[epochs, None] + np.arange(3)]
    return vel
