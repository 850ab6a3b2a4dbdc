"""The chain recursion for position marginals (fusion.estimate.graph.marginals) against
gtsam.Marginals on small graphs: pseudoranges only, with inter-system biases (trace-wide variables),
and with Doppler and carrier (the four-key drift walk, added as dense information)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fusion.estimate.graph import marginals as mg
from fusion.estimate.graph.build import graph_pieces
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.keys import pos_key
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate
from tests.estimate.test_graph import _two_system_trace, synth_trace


def _solved(trace, cfg: GraphConfig = GraphConfig()):
    wls = solve_initial(trace, RunOptions(graph=cfg))
    inp = prepare_inputs(trace, wls, cfg, 10.0, None)
    p = graph_pieces(trace, inp, cfg)
    graph, values = p.graph(), p.values()
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return graph, result, np.flatnonzero(inp.keep), p.dense


def _reference(graph, result, epochs) -> np.ndarray:
    marg = gtsam.Marginals(graph, result)
    return np.array([marg.marginalCovariance(pos_key(int(k))) for k in epochs])


def _assert_same(got, ref):
    scale = np.abs(ref).max(axis=(1, 2))[:, None, None]
    assert np.max(np.abs(got - ref) / scale) < 1e-6


@pytest.mark.parametrize("motion", ["cv", "rw"])
@pytest.mark.parametrize("drift", ["doppler", "always"])
def test_chain_marginals_equal_gtsam_pseudoranges_only(motion, drift):
    graph, result, epochs, dense = _solved(synth_trace(E=60), GraphConfig(motion=motion, clock_drift_states=drift))
    assert (len(dense) > 0) == (drift == "always")         # the drift walk without Doppler too
    got = mg.chain_marginals(graph, result, epochs, dense)
    _assert_same(got, _reference(graph, result, epochs))


def test_chain_marginals_equal_gtsam_with_intersystem_biases():
    graph, result, epochs, dense = _solved(_two_system_trace(isb_m=12.0, E=60, gap_at=30))
    assert any(chr(gtsam.Symbol(k).chr()) == "i" for k in result.keys())      # trace-wide variables exist
    _assert_same(mg.chain_marginals(graph, result, epochs, dense), _reference(graph, result, epochs))


def test_chain_marginals_equal_gtsam_with_doppler_and_carrier():
    nav = read_rinex_nav(default_nav_path())
    sim = simulate(n_epochs=80, nav=nav, seed=3, config=SimConfig(doppler=True, carrier=True, slip_prob=0.01))
    graph, result, epochs, dense = _solved(sim.trace)
    assert len(dense) > 0                                   # the drift walk's Hessian factors
    _assert_same(mg.chain_marginals(graph, result, epochs, dense), _reference(graph, result, epochs))
    # not told which factors are dense: GTSAM's own marginals answer instead
    E = int(epochs.max()) + 1
    _assert_same(mg.marginal_positions(graph, result, epochs, E)[epochs], _reference(graph, result, epochs))


def test_wide_band_falls_back_to_gtsam(monkeypatch):
    graph, result, epochs, dense = _solved(synth_trace(E=40))
    monkeypatch.setattr(mg, "MAX_BAND", 2)
    assert mg.chain_marginals(graph, result, epochs, dense) is None
    cov = mg.marginal_positions(graph, result, epochs, 45, dense)
    _assert_same(cov[epochs], _reference(graph, result, epochs))
    assert np.isnan(cov[40:]).all()


def test_singular_graph_raises():
    graph, result, epochs, dense = _solved(synth_trace(E=20))
    # an extra position no factor constrains
    free = gtsam.Values(result)
    free.insert(pos_key(99), np.ones(3))
    graph.add(gtsam.BetweenFactorPoint3(pos_key(98), pos_key(99), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    free.insert(pos_key(98), np.ones(3))
    with pytest.raises(RuntimeError):
        mg.chain_marginals(graph, free, np.r_[epochs, 99], dense)
