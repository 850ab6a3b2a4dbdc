"""The whole trace at once: the batch solver (``GraphConfig.batch_solver``: Gauss-Newton, Levenberg-Marquardt
where a step fails) over the fused graph, with marginal covariances."""
from __future__ import annotations

import time
from dataclasses import dataclass, fields, is_dataclass, replace

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.banded_gn import gauss_newton
from fusion.estimate.graph.build import graph_pieces, prior_factors, pseudorange_factors, relinearise_carriers
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.inputs import EpochInputs
from fusion.estimate.graph.isb import isb_estimates
from fusion.estimate.graph.keys import pos_key, vel_key
from fusion.estimate.graph.marginals import marginal_positions
from fusion.estimate.graph.optimiser import optimise_values
from fusion.estimate.graph.solve_errors import geometry_error
from fusion.estimate.graph.vector_graph import (VectorGraph, banded_marginals, from_values, same_layout, to_values,
                                                vector_graph, vector_isb_estimates, vector_velocities)
from fusion.trace import Trace


def read_velocities(values: gtsam.Values, epochs: np.ndarray, E: int) -> np.ndarray | None:
    """(E,3) ECEF velocity estimates [m/s] (NaN for epochs not in ``epochs``), or None without
    velocity states (random-walk motion)."""
    if len(epochs) == 0 or not values.exists(vel_key(int(epochs[0]))):
        return None
    vel = np.full((E, 3), np.nan)
    for k in epochs:
        vel[k] = values.atPoint3(vel_key(int(k)))
    return vel


def optimise(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, epochs: np.ndarray, E: int, cfg: GraphConfig,
             ordering: gtsam.Ordering | None = None):
    """:func:`~fusion.estimate.graph.optimiser.optimise_values` from ``values`` (with ``ordering``, if
    given): (what it returned, its solution ``.values`` included; positions (E,3), NaN off ``epochs``)."""
    opt = optimise_values(graph, values, cfg, ordering)
    pos = np.full((E, 3), np.nan)
    for k in epochs:
        pos[k] = opt.values.atPoint3(pos_key(int(k)))
    return opt, pos


@dataclass
class BatchSolution:
    """A solved batch graph kept for a second solve of the same trace (the ``fused`` mode): GTSAM's graph, its
    dense factor positions (for :func:`marginal_positions`), the solution, the inputs and settings it was
    built from, what :func:`solve_batch` returned (pos (E,3), valid (E,), info), where its pseudorange
    factors are and its elimination ordering (for :func:`patched_graph`); or, solved by the banded solver,
    no GTSAM graph or values but the vectorised graph and its solution x (N,). Neither travels between
    processes (GTSAM objects; the vectorised graph's closures): :func:`~fusion.estimate.graph.fuse.solve_graph`
    drops it from results unless asked to keep it."""

    graph: gtsam.NonlinearFactorGraph
    dense: list
    values: gtsam.Values
    inp: EpochInputs
    cfg: GraphConfig
    pos: np.ndarray
    valid: np.ndarray
    info: dict
    pseudorange: slice | None = None
    ordering: gtsam.Ordering | None = None
    vector: VectorGraph | None = None
    x: np.ndarray | None = None


def same_inputs(a, b, ignore: frozenset = frozenset()) -> bool:
    """Whether two :class:`EpochInputs` (or their parts) build the same graph: every array equal (NaN
    equal to NaN), every nested dataclass likewise, other objects identical; counts (dicts) and the fields
    of ``a`` named in ``ignore`` left out."""
    if a is b:
        return True
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
    if is_dataclass(a):
        return all(same_inputs(getattr(a, f.name), getattr(b, f.name)) for f in fields(a)
                   if f.name not in ignore and not isinstance(getattr(a, f.name), dict))
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(same_inputs(x, y) for x, y in zip(a, b))
    return isinstance(a, (bool, int, float, str, np.generic)) and a == b


def warm_values(values: gtsam.Values, start: gtsam.Values | None) -> gtsam.Values:
    """``values`` with those of ``start`` where it has them, or ``values`` as they are if ``start`` is None
    or holds a variable ``values`` lacks (then it is another graph's solution)."""
    if start is None:
        return values
    warm = gtsam.Values(values)
    warm.insert_or_assign(start)
    return warm if warm.size() == values.size() else values


#: the inputs a learned model changes that a solved graph takes in place: pseudorange noise and priors
PATCHABLE = frozenset({"sigma", "pr_bias", "pr_losses", "prior_mean", "prior_cov", "prior_ok"})


def patchable(start: BatchSolution | None, inp: EpochInputs, cfg: GraphConfig) -> bool:
    """Whether ``inp`` builds ``start``'s graph but for the pseudorange noise and added position priors
    (the ``fused`` mode's second solve): same settings, every other input equal, no prior in ``start``."""
    if start is None or start.pseudorange is None or cfg.tdcp_relinearise:
        return False
    # the first solve may have stopped at a looser tolerance (GraphConfig.guess_rel_tol): same graph
    if replace(start.cfg, lm_rel_tol=cfg.lm_rel_tol) != cfg or (start.inp.prior_ok & start.inp.keep).any():
        return False
    return same_inputs(start.inp, inp, ignore=PATCHABLE)


def patched_graph(start: BatchSolution, trace: Trace, inp: EpochInputs, cfg: GraphConfig
                  ) -> gtsam.NonlinearFactorGraph:
    """``start``'s graph with its pseudorange factors rebuilt from ``inp`` (new sigmas and biases) and the
    position priors of ``inp`` appended: the rest of the graph (clocks, Doppler, carrier, motion) is built
    once per run (see :func:`patchable`)."""
    graph = start.graph.clone()
    _, factors = pseudorange_factors(trace, inp, cfg, np.flatnonzero(inp.keep))
    for i, f in zip(range(start.pseudorange.start, start.pseudorange.stop), factors, strict=True):
        graph.replace(i, f)
    for f in prior_factors(inp, cfg, np.flatnonzero(inp.keep))[1]:
        graph.add(f)
    return graph


def solve_batch(trace: Trace, inp: EpochInputs, cfg: GraphConfig, want_cov: bool = True,
                start: BatchSolution | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """The batch solver (``GraphConfig.batch_solver``) over the whole trace, from the WLS-derived values, or
    from ``start``, a previous solution of the trace: where ``inp`` builds the same graph as ``start.inp`` (a
    learned model whose every output its guard turned off) under the same settings, that solution is the
    answer and only the marginals are computed; otherwise the solver starts from its values where the
    variables are the same. "banded" solves the graph's vectorised copy (:mod:`~fusion.estimate.graph.vector_graph`)
    where it has one, GTSAM's graph otherwise. Returns pos (E,3), valid (E,), cov (E,3,3)|None, info (with
    the :class:`BatchSolution` as ``batch_solution``)."""
    if start is not None and start.cfg == cfg and same_inputs(start.inp, inp):
        return _reuse(trace, start, want_cov)
    if cfg.batch_solver == "banded":
        t0 = time.perf_counter()
        vec = vector_graph(trace, inp, cfg)
        if vec is not None:
            return _solve_banded(trace, inp, cfg, vec, want_cov, start, t0)
    return _solve_gtsam(trace, inp, cfg, want_cov, start)


def _solve_banded(trace: Trace, inp: EpochInputs, cfg: GraphConfig, vec: VectorGraph, want_cov: bool,
                  start: BatchSolution | None, t0: float):
    """:func:`solve_batch` by :func:`~fusion.estimate.graph.banded_gn.gauss_newton` on ``vec`` (built from
    ``t0``); where a step fails, GTSAM's Levenberg-Marquardt carries on from the best values so far."""
    x0 = vec.x0
    if start is not None and start.vector is not None and same_layout(start.vector.layout, vec.layout):
        x0 = start.x
    elif start is not None and start.values is not None:    # GTSAM's solution (a graph it had to solve)
        x0 = from_values(vec.layout, warm_values(to_values(vec.layout, x0), start.values))
    t1 = time.perf_counter()
    sol = gauss_newton(vec.system, x0, cfg.lm_rel_tol, cfg.lm_max_iter)
    if not sol.ok:
        return _solve_gtsam(trace, inp, replace(cfg, batch_solver="levenberg-marquardt"), want_cov, None,
                            initial=to_values(vec.layout, sol.x), handed_over=sol.iterations)
    E, epochs = trace.n_epochs, np.flatnonzero(inp.keep)
    pos = np.full((E, 3), np.nan)
    pos[epochs] = sol.x[vec.layout.start["pos"][epochs, None] + np.arange(3)]
    t2 = time.perf_counter()
    try:
        cov, vel_cov = _banded_cov(trace, inp, cfg, vec, sol.x) if want_cov else (None, None)
    except RuntimeError as exc:
        raise geometry_error(trace, exc) from None
    valid = np.zeros(E, bool)
    valid[epochs] = np.isfinite(pos[epochs]).all(axis=1)
    info = {"factors": vec.n_factors, "iterations": sol.iterations, "final_error": sol.error, "solver_fell_back": 0,
            "build_s": t1 - t0, "solve_s": t2 - t1, "cov_s": time.perf_counter() - t2, "graph_patched": 0,
            "isb_m": vector_isb_estimates(vec.layout, sol.x, inp),
            "vel": vector_velocities(vec.layout, sol.x, epochs, E), "vel_cov": vel_cov}
    info["batch_solution"] = BatchSolution(None, [], None, inp, cfg, pos, valid, dict(info), vector=vec, x=sol.x)
    return pos, valid, cov, info


def _banded_cov(trace: Trace, inp: EpochInputs, cfg: GraphConfig, vec: VectorGraph, x: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """(E,3,3) position and velocity marginals of the banded solution x (N,): from its information matrix in one
    recursion; where that does not pay (a wide band), the positions' from GTSAM's graph at x and no velocities'
    (None, as without velocity states)."""
    epochs = np.flatnonzero(inp.keep)
    got = banded_marginals(vec, x, epochs, trace.n_epochs, ("pos", "vel"))
    if got is not None:
        return got["pos"], got.get("vel")
    return _graph_cov(trace, inp, cfg, to_values(vec.layout, x)), None


def _graph_cov(trace: Trace, inp: EpochInputs, cfg: GraphConfig, values: gtsam.Values) -> np.ndarray:
    """(E,3,3) position marginals of GTSAM's graph that ``inp`` and ``cfg`` build, at ``values``."""
    pieces = graph_pieces(trace, inp, cfg)
    return marginal_positions(pieces.graph(), values, np.flatnonzero(inp.keep), trace.n_epochs, pieces.dense)


def marginals_at(trace: Trace, inp: EpochInputs, cfg: GraphConfig, values: gtsam.Values
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """(E,3,3) position and velocity marginals of the graph ``inp`` and ``cfg`` build, at another solver's answer
    ``values`` (ISAM2's), which holds the variables of every kept epoch: the banded recursion where the graph has a
    vectorised copy, else GTSAM's graph (positions only; velocities None). RuntimeError where the graph is
    singular there."""
    vec = vector_graph(trace, inp, cfg)
    if vec is not None:
        return _banded_cov(trace, inp, cfg, vec, from_values(vec.layout, values))
    return _graph_cov(trace, inp, cfg, values), None


def _solve_gtsam(trace: Trace, inp: EpochInputs, cfg: GraphConfig, want_cov: bool, start: BatchSolution | None,
                 initial: gtsam.Values | None = None, handed_over: int | None = None):
    """:func:`solve_batch` on GTSAM's graph: patched from ``start``'s where :func:`patchable` allows, else built,
    and solved from ``start``'s values, else ``initial`` (the banded solver's values where a step failed after
    ``handed_over`` iterations), else the WLS-derived values."""
    E = trace.n_epochs
    t0 = time.perf_counter()
    if patchable(start, inp, cfg):
        pieces, graph, values = None, patched_graph(start, trace, inp, cfg), start.values
        dense, pr_slice, ordering = start.dense, start.pseudorange, start.ordering
    else:
        pieces = graph_pieces(trace, inp, cfg)
        graph, dense, pr_slice = pieces.graph(), pieces.dense, pieces.pseudorange
        values = warm_values(pieces.values(), initial if start is None else start.values)
        ordering = None
    epochs = np.flatnonzero(inp.keep)
    t1 = time.perf_counter()
    try:
        opt, pos = optimise(graph, values, epochs, E, cfg, ordering)
        opt_iterations = (handed_over or 0) + opt.iterations
        if pieces is not None and pieces.carrier is not None and cfg.tdcp_relinearise:
            # the carrier factors keep their linearisation point: move it from the WLS track to the
            # solution and polish (a few warm iterations; see GraphConfig.tdcp_relinearise)
            relinearise_carriers(graph, pieces, trace, inp, cfg, pos)
            opt, pos = optimise(graph, opt.values, epochs, E, cfg, opt.ordering)
            opt_iterations += opt.iterations
        t2, result = time.perf_counter(), opt.values
        cov = marginal_positions(graph, result, epochs, E, dense) if want_cov else None
    except RuntimeError as exc:
        raise geometry_error(trace, exc) from None
    if not np.isfinite(opt.error):
        # GTSAM leaves the start values (the WLS track) where the error is NaN: not an answer of this graph
        raise GeometryError(f"{trace.name}: the graph's error is not finite at its start (a noise of zero, or a "
                            "non-finite input or setting); nothing solved")
    t3 = time.perf_counter()
    valid = np.zeros(E, bool)
    valid[epochs] = np.isfinite(pos[epochs]).all(axis=1)
    info = {"factors": int(graph.size()), "iterations": int(opt_iterations),
            "final_error": float(opt.error), "solver_fell_back": int(opt.fell_back or handed_over is not None),
            "build_s": t1 - t0, "solve_s": t2 - t1, "cov_s": t3 - t2, "graph_patched": int(pieces is None),
            "isb_m": isb_estimates(result, inp), "vel": read_velocities(result, epochs, E)}
    info["batch_solution"] = BatchSolution(graph, dense, result, inp, cfg, pos, valid, dict(info), pr_slice,
                                           opt.ordering)
    return pos, valid, cov, info


def _reuse(trace: Trace, start: BatchSolution, want_cov: bool):
    """:func:`solve_batch`'s answer from the identical graph solved before: its solution, and its marginals."""
    t0 = time.perf_counter()
    epochs = np.flatnonzero(start.inp.keep)
    try:
        cov, vel_cov = (None, None) if not want_cov else (
            _banded_cov(trace, start.inp, start.cfg, start.vector, start.x) if start.vector is not None
            else (marginal_positions(start.graph, start.values, epochs, trace.n_epochs, start.dense), None))
    except RuntimeError as exc:
        raise geometry_error(trace, exc) from None
    info = {**start.info, "build_s": 0.0, "solve_s": 0.0, "cov_s": time.perf_counter() - t0, "iterations": 0,
            "reused_solution": 1, "batch_solution": start, "vel_cov": vel_cov}
    return start.pos.copy(), start.valid.copy(), cov, info
