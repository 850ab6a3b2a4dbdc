"""The batch graph's nonlinear solver: Gauss-Newton with Levenberg-Marquardt as its safety net.

The fused graph is linear but for its robust losses and the pseudorange geometry, so a Gauss-Newton
step is what a Levenberg-Marquardt step with GTSAM's tiny starting damping (1e-5) is anyway; Gauss-Newton
skips the damped copy of the linear system LM builds every iteration: with a METIS ordering an
iteration costs 130 against 168 ms of CPU on the Pixel5 trace (16 iterations against LM's 15). Where a Gauss-Newton step raises the cost or meets a singular system, Levenberg-Marquardt
carries on from the best values so far, so a hard trace converges as it did before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam

from fusion.errors import GnssfuseError
from fusion.estimate.graph.config import GraphConfig

#: GTSAM's default absolute cost decrease below which its optimisers stop
ABS_ERROR_TOL = 1e-5
SOLVERS = ("banded", "gauss-newton", "levenberg-marquardt")


@dataclass
class Optimised:
    """The solution, the iterations taken (Gauss-Newton + Levenberg-Marquardt), the final cost, whether
    Levenberg-Marquardt had to take over, and the Gauss-Newton elimination ordering (for another solve of
    a graph over the same variables and links)."""

    values: gtsam.Values
    iterations: int
    error: float
    fell_back: bool = False
    ordering: gtsam.Ordering | None = None


def converged(before: float, after: float, rel_tol: float) -> bool:
    """GTSAM's stopping rule: the cost fell by less than ``rel_tol`` of itself (or by < 1e-5)."""
    return before - after <= max(rel_tol * before, ABS_ERROR_TOL)


def at_optimum(before: float, after: float, rel_tol: float) -> bool:
    """A step that raised the cost by no more than the stopping tolerance: round-off at the optimum (GTSAM's
    own optimisers stop there too), not a failed step."""
    return math.isfinite(after) and after - before <= max(rel_tol * before, ABS_ERROR_TOL)


def optimise_values(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, cfg: GraphConfig,
                    ordering: gtsam.Ordering | None = None) -> Optimised:
    """Minimise ``graph``'s cost from ``values`` with ``cfg.batch_solver`` (GTSAM's Gauss-Newton for "banded",
    whose vectorised copy of the graph has no room for this one), stopping at ``cfg.lm_rel_tol``
    (relative cost decrease) or after ``cfg.lm_max_iter`` iterations. ordering: Gauss-Newton's elimination
    ordering from an earlier solve of a graph with the same variables and links (unary factors added or
    changed leave it valid), instead of a new METIS ordering (~60 ms on the Pixel5 graph)."""
    if cfg.batch_solver == "levenberg-marquardt":
        return levenberg_marquardt(graph, values, cfg, 0)
    if cfg.batch_solver not in SOLVERS:
        raise GnssfuseError(f"GraphConfig.batch_solver must be one of {', '.join(SOLVERS)}, got {cfg.batch_solver!r}")
    params = gtsam.GaussNewtonParams()
    # METIS: the chain's elimination ~18 % cheaper than with COLAMD (81 vs 99 ms on the Pixel5 graph);
    # with LM's damped system it gained nothing
    ordering = gtsam.Ordering.MetisNonlinearFactorGraph(graph) if ordering is None else ordering
    params.setOrdering(ordering)
    opt = gtsam.GaussNewtonOptimizer(graph, values, params)
    best, err, n = values, opt.error(), 0
    while n < cfg.lm_max_iter:
        try:
            opt.iterate()
        except RuntimeError:              # a singular step: LM's damping copes (and the marginals tell)
            return levenberg_marquardt(graph, best, cfg, n)
        n += 1
        new = opt.error()
        if not math.isfinite(new) or new > err:
            if at_optimum(err, new, cfg.lm_rel_tol):
                return Optimised(best, n, err, ordering=ordering)
            return levenberg_marquardt(graph, best, cfg, n)
        best = gtsam.Values(opt.values())
        if converged(err, new, cfg.lm_rel_tol):
            return Optimised(best, n, new, ordering=ordering)
        err = new
    return Optimised(best, n, err, ordering=ordering)


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, cfg: GraphConfig,
                         done: int) -> Optimised:
    """Levenberg-Marquardt from ``values``, after ``done`` Gauss-Newton iterations."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max(cfg.lm_max_iter - done, 1))
    params.setRelativeErrorTol(cfg.lm_rel_tol)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return Optimised(result, done + opt.iterations(), opt.error(), fell_back=done > 0 or cfg.batch_solver != "levenberg-marquardt")
