"""A second batch solve of the same trace (the fused mode's solve with the learned inputs) starts from
the first one's solution, and reuses it outright where the inputs build the same graph."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.estimate.graph.batch import BatchSolution, same_inputs
from fusion.estimate.graph.fuse import fuse, learned_guess_and_start
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.priors import learned_from_providers
from fusion.estimate.wls import solve_wls
from fusion.run_types import RunOptions
from tests.estimate.test_graph import assert_centimetres_apart, synth_trace, truth_prior


#: the fused mode's second solve, by each batch solver: GTSAM's graph is patched, the banded solver's copy
#: (10 ms to build) is built again; both start from the first solution
SOLVERS = ("banded", "gauss-newton")


def _setup(solver: str = "banded"):
    trace = synth_trace(E=80)
    return trace, solve_wls(trace), RunOptions(graph=replace(RunOptions().graph, batch_solver=solver))


def test_same_inputs_tells_graphs_apart():
    trace, wls, opts = _setup()
    a = prepare_inputs(trace, wls, opts.graph, opts.elev_mask_deg, None)
    b = prepare_inputs(trace, wls, opts.graph, opts.elev_mask_deg, None)
    assert a is not b and same_inputs(a, b)
    at, _ = learned_guess_and_start(trace, wls, RunOptions(graph=opts.graph))
    learned = learned_from_providers(trace, truth_prior(2.0), None, at)
    c = prepare_inputs(trace, wls, opts.graph, opts.elev_mask_deg, learned)
    assert not same_inputs(a, c)
    b.sigma = b.sigma.copy()
    b.sigma[3, 0] *= 1.5
    assert not same_inputs(a, b)


@pytest.mark.parametrize("solver", SOLVERS)
def test_identical_graph_is_not_solved_twice(solver):
    trace, wls, opts = _setup(solver)
    opts = RunOptions(graph=replace(opts.graph, guess_rel_tol=opts.graph.lm_rel_tol))
    at, start = learned_guess_and_start(trace, wls, opts)
    assert isinstance(start, BatchSolution)
    cold = fuse(trace, wls, opts)
    again = fuse(trace, wls, opts, start=start)
    assert again.info["reused_solution"] == 1 and again.info["iterations"] == 0
    np.testing.assert_array_equal(again.pos, start.pos)
    np.testing.assert_allclose(again.pos, cold.pos, atol=1e-6)
    np.testing.assert_allclose(again.cov[again.valid], cold.cov[cold.valid], rtol=1e-6, atol=1e-12)
    assert "batch_solution" not in again.info       # GTSAM objects stay out of the result


@pytest.mark.parametrize("solver", SOLVERS)
def test_loose_first_solve_is_carried_on(solver):
    """The first solve stops at guess_rel_tol; the same graph solved again continues from it to the
    cold solution rather than taking it as the answer."""
    trace, wls, opts = _setup(solver)
    assert opts.graph.guess_rel_tol > opts.graph.lm_rel_tol
    _, start = learned_guess_and_start(trace, wls, opts)
    again = fuse(trace, wls, opts, start=start)
    cold = fuse(trace, wls, opts)
    assert "reused_solution" not in again.info and again.info["graph_patched"] == (solver == "gauss-newton")
    assert 0 < again.info["iterations"] < cold.info["iterations"]
    assert_centimetres_apart(again.pos, cold.pos)


@pytest.mark.parametrize("solver", SOLVERS)
def test_warm_start_converges_to_the_cold_solution(solver):
    trace, wls, opts = _setup(solver)
    # converged tightly, so that what differs is where each solve starts, not where lm_rel_tol stopped it
    # (at 1e-4 the cold solve stops 1-2 cm short of the optimum the warm one reaches)
    opts = RunOptions(graph=replace(opts.graph, lm_rel_tol=1e-6))
    at, start = learned_guess_and_start(trace, wls, opts)
    learned = learned_from_providers(trace, truth_prior(2.0), None, at)
    cold = fuse(trace, wls, opts, learned=learned)
    warm = fuse(trace, wls, opts, learned=learned, start=start)
    assert "reused_solution" not in warm.info
    assert warm.info["iterations"] <= cold.info["iterations"]
    assert_centimetres_apart(warm.pos, cold.pos)


@pytest.mark.parametrize("solver", SOLVERS)
def test_other_settings_are_solved_again(solver):
    trace, wls, opts = _setup(solver)
    _, start = learned_guess_and_start(trace, wls, opts)
    other = RunOptions(graph=replace(opts.graph, robust_k=4.0))
    again = fuse(trace, wls, other, start=start)
    assert "reused_solution" not in again.info and again.info["iterations"] > 0


def _slot_noise(trace, at, valid):
    """A slot-noise provider: sigmas growing with the slot index, a 1 m bias on slot 0."""
    sigma = np.broadcast_to(2.0 + 0.5 * np.arange(trace.n_slots), trace.pr.shape).copy()
    bias = np.zeros(trace.pr.shape)
    bias[:, 0] = 1.0
    return sigma, bias


def test_learned_inputs_patch_the_first_graph():
    """The second solve takes the first graph with new pseudorange noise and appended priors: the same
    cost as a graph built from scratch, at any values, and the same solution."""
    from fusion.estimate.graph.batch import patchable, patched_graph
    from fusion.estimate.graph.build import graph_pieces

    trace, wls, opts = _setup("gauss-newton")
    at, start = learned_guess_and_start(trace, wls, opts)
    learned = learned_from_providers(trace, truth_prior(2.0), _slot_noise, at)
    inp = prepare_inputs(trace, wls, opts.graph, opts.elev_mask_deg, learned)
    assert patchable(start, inp, opts.graph)
    patched, built = patched_graph(start, trace, inp, opts.graph), graph_pieces(trace, inp, opts.graph)
    assert patched.size() == built.graph().size()
    for values in (start.values, built.values()):
        assert np.isclose(patched.error(values), built.graph().error(values), rtol=1e-12)
    patched_solve = fuse(trace, wls, opts, learned=learned, start=start)
    built_solve = fuse(trace, wls, opts, learned=learned, start=replace(start, pseudorange=None))  # not patchable
    assert patched_solve.info["graph_patched"] == 1 and built_solve.info["graph_patched"] == 0
    np.testing.assert_allclose(patched_solve.pos, built_solve.pos, atol=1e-6)
    np.testing.assert_allclose(patched_solve.cov, built_solve.cov, rtol=1e-6, atol=1e-12)


def test_other_inputs_are_built_again():
    trace, wls, opts = _setup("gauss-newton")
    from fusion.estimate.graph.batch import patchable

    _, start = learned_guess_and_start(trace, wls, opts)
    inp = prepare_inputs(trace, wls, opts.graph, opts.elev_mask_deg, None)
    inp.sel = inp.sel.copy()
    inp.sel[5, np.flatnonzero(inp.sel[5])[0]] = False        # one measurement fewer: other factors
    assert not patchable(start, inp, opts.graph)
    assert not patchable(start, inp, replace(opts.graph, robust_k=4.0))
