"""The batch solver: Gauss-Newton ends where Levenberg-Marquardt does (within LM's own tolerance), and
hands over to LM where a step fails."""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from fusion.errors import GnssfuseError
from fusion.estimate.graph import optimiser
from fusion.estimate.graph.build import graph_pieces
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.wls import solve_wls
from fusion.eval.metrics import horizontal, ned_errors
from fusion.run_types import RunOptions
from tests.estimate.test_graph import assert_centimetres_apart, synth_trace


def _graph():
    trace = synth_trace(E=60)
    cfg = GraphConfig()
    inp = prepare_inputs(trace, solve_wls(trace), cfg, 10.0, None)
    p = graph_pieces(trace, inp, cfg)
    return p.graph(), p.values(), cfg


def test_gauss_newton_matches_levenberg_marquardt():
    trace = synth_trace(E=150, pr_noise_m=5.0)
    trace.pr[40:44, 2] += 80.0                             # outliers: the robust loss reweights
    wls = solve_wls(trace)
    got = {s: fuse(trace, wls, RunOptions(graph=replace(GraphConfig(), batch_solver=s)), want_cov=False)
           for s in optimiser.SOLVERS}
    gn, lm = got["gauss-newton"], got["levenberg-marquardt"]
    assert gn.info["solver_fell_back"] == 0
    assert_centimetres_apart(gn.pos, lm.pos)
    assert gn.info["final_error"] <= lm.info["final_error"] * (1 + 1e-3)
    err = {s: np.nanpercentile(horizontal(ned_errors(r.pos, trace.truth)), 95) for s, r in got.items()}
    assert err["gauss-newton"] == pytest.approx(err["levenberg-marquardt"], rel=0.01)


_REAL_GN = gtsam.GaussNewtonOptimizer


class _Failing:
    """A Gauss-Newton optimiser whose second step fails as ``how`` says."""

    def __init__(self, how):
        self.how, self.n = how, 0

    def __call__(self, graph, values, params):
        self.real = _REAL_GN(graph, values, params)
        return self

    def error(self):
        return self.real.error() * (10.0 if self.how == "worse" and self.n >= 2 else 1.0)

    def values(self):
        return self.real.values()

    def iterate(self):
        self.n += 1
        if self.n >= 2 and self.how == "raise":
            raise RuntimeError("Indeterminant linear system")
        self.real.iterate()


@pytest.mark.parametrize("how", ["raise", "worse"])
def test_levenberg_marquardt_takes_over_a_failed_step(monkeypatch, how):
    graph, values, cfg = _graph()
    lm = optimiser.optimise_values(graph, values, replace(cfg, batch_solver="levenberg-marquardt"))
    monkeypatch.setattr(optimiser.gtsam, "GaussNewtonOptimizer", _Failing(how))
    got = optimiser.optimise_values(graph, values, cfg)
    assert got.fell_back and got.iterations >= 2
    assert graph.error(got.values) <= lm.error * (1 + 1e-3)


def test_unknown_solver_is_an_error():
    graph, values, cfg = _graph()
    with pytest.raises(GnssfuseError, match="batch_solver"):
        optimiser.optimise_values(graph, values, replace(cfg, batch_solver="dogleg"))


@pytest.mark.parametrize("partial", [True, False])
def test_isam2_partial_relinearisation_check_is_a_setting(partial):
    from fusion.estimate.graph.incremental import isam2

    cfg = replace(GraphConfig(), isam_partial_relin_check=partial)
    assert isam2(cfg).params().enablePartialRelinearizationCheck is partial
    trace = synth_trace(E=80)
    wls = solve_wls(trace)
    inc = fuse(trace, wls, RunOptions(graph=replace(cfg, incremental=True)))
    batch = fuse(trace, wls, RunOptions(graph=cfg), want_cov=False)
    gap = np.linalg.norm(inc.pos - batch.pos, axis=1)
    assert np.nanmedian(gap) < 0.05
