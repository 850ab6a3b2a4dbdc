"""The banded solver's vectorised copy of the fused graph against GTSAM's graph: the same cost at any
values, kind by kind, the same Gauss-Newton solution, marginals and side outputs, and GTSAM's solvers
where the copy has no room for a graph or a step fails."""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from fusion.estimate.graph import banded_gn
from fusion.estimate.graph.batch import solve_batch
from fusion.estimate.graph.build import graph_pieces
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.keys import vel_key
from fusion.estimate.graph.priors import learned_from_providers
from fusion.estimate.graph.vector_graph import from_values, to_values, vector_graph
from fusion.estimate.wls import solve_wls
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.doppler_carrier import with_drift_jumps
from fusion.sim.simulate import SimConfig, simulate
from tests.estimate.test_graph import _two_system_trace, synth_trace, truth_prior


@pytest.fixture(scope="module")
def raw_sim():
    """A simulated phone trace with Doppler and carrier phase (clock drift states, displacement states,
    carrier clocks, slips)."""
    tr = simulate(n_epochs=150, nav=read_rinex_nav(default_nav_path()), seed=11,
                  config=SimConfig(doppler=True, carrier=True, slip_prob=0.01)).trace
    return tr, solve_initial(tr, RunOptions())


@pytest.fixture(scope="module")
def doppler_sim():
    """Doppler without carrier phase (a log with no accumulated delta ranges): both graphs used to fail."""
    tr = simulate(n_epochs=100, nav=read_rinex_nav(default_nav_path()), seed=12,
                  config=SimConfig(doppler=True, carrier=False)).trace
    assert tr.has_doppler and not tr.has_carrier
    return tr, solve_initial(tr, RunOptions())


def _two_systems():
    """Two signal groups, two motion components (a bias state each), a learned position prior."""
    tr = _two_system_trace(isb_m=8.0, gap_at=50, E=100)
    return tr, solve_wls(tr)


def _cases(raw_sim, doppler_sim):
    prior = truth_prior(2.0)
    two, two_wls = _two_systems()
    syn = synth_trace(E=60)
    return {
        "doppler+carrier": (raw_sim[0], raw_sim[1], GraphConfig(), None),
        "doppler drift jumps": (with_drift_jumps(raw_sim[0], 0.6, seed=5), raw_sim[1], GraphConfig(), None),
        "doppler only": (doppler_sim[0], doppler_sim[1], GraphConfig(), None),
        "isb+prior geman-mcclure": (two, two_wls, GraphConfig(), prior),
        "isb+prior cauchy": (two, two_wls, GraphConfig(unlearned_robust="cauchy", unlearned_robust_k=1.5), prior),
        "isb+prior huber": (two, two_wls, GraphConfig(unlearned_robust="huber", prior_robust="huber"), prior),
        "random walk": (syn, solve_wls(syn), GraphConfig(motion="rw", unlearned_robust="none"), None),
        "no drift states": (two, two_wls, GraphConfig(clock_drift_states="doppler"), prior),
        "level prior": (raw_sim[0], raw_sim[1], GraphConfig(cv_level_sigma_mps=0.5), None),
        "level prior, no Doppler": (two, two_wls, GraphConfig(cv_level_sigma_no_doppler_mps=0.5), prior),
        "own robust scales": (raw_sim[0], raw_sim[1], GraphConfig(unlearned_robust_k=1.0, rate_robust_k=3.0), None),
    }


def _inputs(trace, wls, cfg, provider):
    at = np.asarray(wls.pos, float)
    learned = None if provider is None else learned_from_providers(trace, provider, None, at)
    return prepare_inputs(trace, wls, cfg, 10.0, learned)


@pytest.mark.parametrize("case", ["doppler+carrier", "doppler drift jumps", "doppler only", "isb+prior geman-mcclure",
                                  "isb+prior cauchy", "isb+prior huber", "random walk", "no drift states",
                                  "level prior", "level prior, no Doppler", "own robust scales"])
def test_vector_graph_has_gtsams_cost_at_any_values(raw_sim, doppler_sim, case):
    trace, wls, cfg, provider = _cases(raw_sim, doppler_sim)[case]
    inp = _inputs(trace, wls, cfg, provider)
    assert (inp.doppler_jump_mps > 0) == (case == "doppler drift jumps")
    vec = vector_graph(trace, inp, cfg)
    pieces = graph_pieces(trace, inp, cfg)
    graph, values = pieces.graph(), pieces.values()
    assert vec.n_factors == graph.size()
    np.testing.assert_allclose(from_values(vec.layout, values), vec.x0, rtol=0, atol=1e-6)
    rng = np.random.default_rng(3)
    for scale in (0.0, 0.5, 30.0):                   # at the start, near it, and where robust losses bite
        x = vec.x0 + scale * rng.standard_normal(vec.x0.shape)
        assert banded_gn.cost(vec.system, x) == pytest.approx(graph.error(to_values(vec.layout, x)), rel=1e-9)


@pytest.mark.parametrize("case", ["doppler+carrier", "doppler drift jumps", "doppler only", "isb+prior geman-mcclure",
                                  "isb+prior cauchy", "isb+prior huber", "random walk", "no drift states",
                                  "level prior", "level prior, no Doppler", "own robust scales"])
def test_banded_solution_is_gtsams(raw_sim, doppler_sim, case):
    trace, wls, cfg, provider = _cases(raw_sim, doppler_sim)[case]
    inp = _inputs(trace, wls, cfg, provider)
    banded = solve_batch(trace, inp, replace(cfg, batch_solver="banded"))
    gtsam_gn = solve_batch(trace, inp, replace(cfg, batch_solver="gauss-newton"))
    assert banded[3]["batch_solution"].vector is not None and gtsam_gn[3]["batch_solution"].vector is None
    np.testing.assert_array_equal(banded[1], gtsam_gn[1])
    # ECEF coordinates are ~4e6 m: two factorisations of the same system agree to ~1e-12 of that (a few
    # micrometres, BLAS-dependent); any modelling difference shows as centimetres or more
    np.testing.assert_allclose(banded[0], gtsam_gn[0], rtol=0, atol=5e-5)
    np.testing.assert_allclose(banded[2], gtsam_gn[2], rtol=1e-6, atol=1e-12)
    a, b = banded[3], gtsam_gn[3]
    assert a["iterations"] == b["iterations"] and a["final_error"] == pytest.approx(b["final_error"], rel=1e-9)
    assert list(a["isb_m"]) == list(b["isb_m"])           # same keys in the same order
    for key, value in a["isb_m"].items():
        assert value == pytest.approx(b["isb_m"][key], abs=1e-6)
    if a["vel"] is None:
        assert b["vel"] is None and a["vel_cov"] is None
    else:
        np.testing.assert_allclose(a["vel"], b["vel"], atol=1e-6)
        # the velocity marginals of the same recursion as the positions', against GTSAM's own
        sol, epochs = b["batch_solution"], np.flatnonzero(banded[1])[::7]
        marg = gtsam.Marginals(sol.graph, sol.values)
        ref = np.array([marg.marginalCovariance(vel_key(int(k))) for k in epochs])
        np.testing.assert_allclose(a["vel_cov"][epochs], ref, rtol=1e-5, atol=1e-12)


def test_a_gtsam_solution_starts_the_banded_solver(raw_sim):
    trace, wls = raw_sim
    cfg = GraphConfig()
    inp = _inputs(trace, wls, cfg, None)
    gtsam_start = solve_batch(trace, inp, replace(cfg, batch_solver="gauss-newton"), want_cov=False)[3]["batch_solution"]
    cold = solve_batch(trace, inp, replace(cfg, robust_k=3.0), want_cov=False)
    warm = solve_batch(trace, inp, replace(cfg, robust_k=3.0), want_cov=False, start=gtsam_start)
    assert warm[3]["iterations"] < cold[3]["iterations"]
    assert np.nanmax(np.linalg.norm(warm[0] - cold[0], axis=1)) < 0.05


def test_a_factor_names_each_variable_once():
    """The normal equations' pair products count a variable once per factor: a repeated one is refused."""
    with pytest.raises(ValueError, match="distinct"):
        banded_gn.Blocks(np.array([[0, 1, 1]]), np.ones((1, 1, 3)), np.zeros((1, 1)))
    with pytest.raises(ValueError, match="distinct"):
        banded_gn.Blocks(np.array([[-1, 2]]), np.ones((1, 1, 2)), np.zeros((1, 1)))


def test_a_cost_rise_within_tolerance_ends_at_the_optimum():
    """Round-off at the optimum (a step raising the cost by less than the stopping tolerance) ends the
    iteration there instead of handing over to Levenberg-Marquardt."""
    from fusion.estimate.graph.optimiser import at_optimum

    assert at_optimum(100.0, 100.0 + 5e-3, 1e-4) and at_optimum(1.0, 1.0 + 5e-6, 1e-4)
    assert not at_optimum(100.0, 100.1, 1e-4) and not at_optimum(100.0, float("nan"), 1e-4)


def test_two_components_get_a_bias_each():
    trace, wls = _two_systems()
    vec = vector_graph(trace, _inputs(trace, wls, GraphConfig(), None), GraphConfig())
    assert sorted(vec.layout.isb) == [(0, 0), (1, 0)] and vec.layout.n - vec.layout.n_local == 2


def test_graphs_without_a_vectorised_copy_go_to_gtsam(raw_sim):
    trace, wls = raw_sim
    cfg = GraphConfig(tdcp_relinearise=True)
    inp = _inputs(trace, wls, cfg, None)
    assert vector_graph(trace, inp, cfg) is None
    pos, valid, _, info = solve_batch(trace, inp, cfg, want_cov=False)
    assert info["batch_solution"].vector is None and info["batch_solution"].graph is not None
    assert valid.sum() > 100 and np.isfinite(pos[valid]).all()


def test_a_failed_step_hands_over_to_levenberg_marquardt(raw_sim, monkeypatch):
    trace, wls = raw_sim
    cfg = GraphConfig()
    inp = _inputs(trace, wls, cfg, None)
    lm = solve_batch(trace, inp, replace(cfg, batch_solver="levenberg-marquardt"), want_cov=False)

    def singular(eq):
        raise np.linalg.LinAlgError("not positive definite")
    monkeypatch.setattr(banded_gn, "solve_normal", singular)
    pos, valid, _, info = solve_batch(trace, inp, cfg, want_cov=False)
    assert info["solver_fell_back"] == 1 and info["batch_solution"].vector is None
    np.testing.assert_allclose(pos[valid], lm[0][valid], atol=1e-3)


def test_fused_mode_second_solve_starts_from_the_first(raw_sim):
    trace, wls = raw_sim
    opts = RunOptions()
    learned_at = np.asarray(wls.pos, float)
    learned = learned_from_providers(trace, truth_prior(2.0), None, learned_at)
    cold = fuse(trace, wls, opts, learned=learned, want_cov=False)
    first = solve_batch(trace, _inputs(trace, wls, opts.graph, None), opts.graph, want_cov=False)[3]["batch_solution"]
    warm = fuse(trace, wls, opts, learned=learned, want_cov=False, start=first)
    assert warm.info["iterations"] < cold.info["iterations"]
    assert np.nanmax(np.linalg.norm(warm.pos - cold.pos, axis=1)) < 0.05


def test_pixel5_graph_matches_gtsam(shared_data):
    """The real phone graph (pseudoranges, Doppler, carrier, drift; 1,985 epochs): same cost, same solution."""
    from fusion.prepare.load import load_trace
    from fusion.prepare.raw_load import RawSources

    nav = shared_data / "ephemeris" / "gps_nav" / "hour1180.21n"
    trace = load_trace(shared_data / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel5",
                       raw_sources=RawSources(nav=(nav,)))
    opts = RunOptions()
    wls = solve_initial(trace, opts)
    inp = prepare_inputs(trace, wls, opts.graph, opts.elev_mask_deg)
    vec, pieces = vector_graph(trace, inp, opts.graph), graph_pieces(trace, inp, opts.graph)
    assert banded_gn.cost(vec.system, vec.x0) == pytest.approx(pieces.graph().error(pieces.values()), rel=1e-9)
    banded = solve_batch(trace, inp, opts.graph, want_cov=False)
    gtsam_gn = solve_batch(trace, inp, replace(opts.graph, batch_solver="gauss-newton"), want_cov=False)
    np.testing.assert_allclose(banded[0], gtsam_gn[0], rtol=0, atol=1e-5)


def test_doppler_and_carrier_take_their_own_robust_scale(raw_sim):
    """Pseudorange blocks carry the unlearned loss and scale (a graph without learned sigmas); Doppler and
    carrier blocks ``robust`` at ``rate_robust_k``."""
    from fusion.estimate.graph.vector_graph import carrier_blocks, doppler_blocks, make_layout, pseudorange_blocks
    trace, wls = raw_sim
    cfg = GraphConfig(unlearned_robust_k=1.0, rate_robust_k=3.0)
    inp = _inputs(trace, wls, cfg, None)
    lay = make_layout(trace, inp, cfg, np.arange(trace.n_epochs))
    assert {(b.robust, b.k) for b in pseudorange_blocks(trace, inp, cfg, lay) if len(b.cols)} == {("gm", 1.0)}
    assert {(b.robust, b.k) for b in doppler_blocks(trace, inp, cfg, lay)} == {("cauchy", 3.0)}
    assert carrier_blocks(trace, inp, cfg, lay)[-1].k == 3.0
