"""Where one batch iteration of the fused graph goes, on the Pixel5 RINEX trace (``fused-nodnn``'s graph):
GTSAM's linearisation, its elimination under each ordering and linear solver it offers, a whole
Gauss-Newton iteration, and what handing the linearised system to scipy would cost before any solve
(the sparse Jacobian and the normal equations' assembly); then the same iteration by the banded solver
(``GraphConfig.batch_solver = "banded"``, the default: :mod:`fusion.estimate.graph.banded_gn` on the graph's
vectorised copy). A diagnostic for the speed issue, not part of ``run_all``: why GTSAM's batch solver is
not faster, and what its replacement costs.

    GNSSFUSE_SHARED_DATA=../shared/data python benchmarks/graph_iteration_cost.py
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import gtsam

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.bench_pixel5 import NAV, TRACE  # noqa: E402
from fusion.estimate.graph.banded_gn import cost, normal_equations, solve_normal  # noqa: E402
from fusion.estimate.graph.build import graph_pieces  # noqa: E402
from fusion.estimate.graph.inputs import prepare_inputs  # noqa: E402
from fusion.estimate.graph.marginals import _column_order, _jacobian_pairs  # noqa: E402
from fusion.estimate.graph.vector_graph import vector_graph  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.prepare.raw_load import RawSources  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

REPEATS = 3


def best_ms(f) -> float:
    """Best of REPEATS wall times of ``f()`` [ms]."""
    ts = []
    for _ in range(REPEATS):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return 1000 * min(ts)


def time_ordering(values: gtsam.Values) -> gtsam.Ordering:
    """Every per-epoch variable by epoch (clocks first within one), trace-wide ones last."""
    def key(k):
        s = gtsam.Symbol(k)
        ch = chr(s.chr())
        return (s.index() if ch != "i" else 1 << 40, "cdqvux".find(ch))
    order = gtsam.Ordering()
    for k in sorted(values.keys(), key=key):
        order.push_back(k)
    return order


def eliminations(lin: gtsam.GaussianFactorGraph, orderings: dict) -> None:
    for name, order in orderings.items():
        for how in ("Multifrontal", "Sequential"):
            def solve():
                getattr(lin, f"eliminate{how}")(order).optimize()
            try:
                print(f"  eliminate + back-substitute, {name + ',':11s} {how.lower():12s} {best_ms(solve):7.1f} ms")
            except RuntimeError as exc:
                print(f"  eliminate, {name}, {how.lower()}: fails ({str(exc).strip().splitlines()[0]})")


def iterations(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, order: gtsam.Ordering) -> None:
    for solver in ("MULTIFRONTAL_CHOLESKY", "SEQUENTIAL_CHOLESKY", "MULTIFRONTAL_QR", "SUITESPARSE"):
        params = gtsam.GaussNewtonParams()
        params.setOrdering(order)
        try:
            params.setLinearSolverType(solver)
            opt = gtsam.GaussNewtonOptimizer(graph, values, params)
            print(f"  Gauss-Newton iteration, {solver:30s} {best_ms(opt.iterate):7.1f} ms")
        except (RuntimeError, ValueError) as exc:     # ValueError: a solver this GTSAM build lacks
            print(f"  Gauss-Newton iteration, {solver}: fails ({str(exc).strip().splitlines()[0]})")


def main() -> None:
    opts = RunOptions()
    trace = load_trace(TRACE, signals=None, min_sats=1, raw_sources=RawSources(nav=(NAV,)))
    inp = prepare_inputs(trace, solve_initial(trace, opts), opts.graph, opts.elev_mask_deg, None)
    pieces = graph_pieces(trace, inp, opts.graph)
    graph, values = pieces.graph(), pieces.values()
    print(f"{trace.name}: {graph.size()} factors, {values.size()} variables (fused-nodnn, broadcast GPS); "
          f"best of {REPEATS}")
    lin = graph.linearize(values)
    print(f"  linearise                                              {best_ms(lambda: graph.linearize(values)):7.1f} ms")
    print(f"  error (the stopping test)                              {best_ms(lambda: graph.error(values)):7.1f} ms")
    metis = gtsam.Ordering.MetisNonlinearFactorGraph(graph)
    print(f"  METIS ordering                                         "
          f"{best_ms(lambda: gtsam.Ordering.MetisNonlinearFactorGraph(graph)):7.1f} ms")
    orderings = {"METIS": metis, "COLAMD": gtsam.Ordering.ColamdNonlinearFactorGraph(graph),
                 "time order": time_ordering(values)}
    eliminations(lin, orderings)
    iterations(graph, values, metis)
    jac = graph.clone()
    for i in sorted(pieces.dense, reverse=True):
        jac.remove(int(i))
    jlin = jac.linearize(values)
    col = _column_order(values)[0]
    print(f"  to scipy: sparse Jacobian (no dense factors) {best_ms(jlin.sparseJacobian_):6.1f} ms, normal "
          f"equations' entries {best_ms(lambda: _jacobian_pairs(jlin, col)):6.1f} ms (both before any solve)")
    banded(trace, inp, opts)


def banded(trace, inp, opts: RunOptions) -> None:
    """The banded solver's build and one iteration (normal equations, banded Cholesky + Schur, the cost)."""
    vec = vector_graph(trace, inp, opts.graph)
    print(f"banded solver: {vec.n_factors} factors, {vec.layout.n} scalar unknowns, band {vec.system.band}")
    print(f"  build the vectorised graph                             "
          f"{best_ms(lambda: vector_graph(trace, inp, opts.graph)):7.1f} ms")
    eq = normal_equations(vec.system, vec.x0)
    print(f"  normal equations (linearise + reweight + assemble)     "
          f"{best_ms(lambda: normal_equations(vec.system, vec.x0)):7.1f} ms")
    print(f"  banded Cholesky + Schur complement + solve             {best_ms(lambda: solve_normal(eq)):7.1f} ms")
    print(f"  cost (the stopping test)                               {best_ms(lambda: cost(vec.system, vec.x0)):7.1f} ms")


if __name__ == "__main__":
    main()
