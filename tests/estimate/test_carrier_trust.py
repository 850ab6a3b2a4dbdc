"""Which carrier phase the graph trusts: time-differenced carrier sigmas raised by C/N0
(GraphConfig.tdcp_cn0_ref_dbhz) and, in the fused mode, by the learned pseudorange multiplier of the same
satellite (GraphConfig.learned_carrier_power): a reflected signal's carrier follows the reflected path; the same
distrust on the Doppler (GraphConfig.learned_doppler_power, shipped off)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.priors import LearnedGraphInputs
from fusion.estimate.graph.raw_inputs import (RawInputs, carrier_sigma_by_pseudorange, doppler_sigma_by_pseudorange,
                                              tdcp_pairs)
from fusion.estimate.variance_factor import sigma_model
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate

RAW = SimConfig(doppler=True, carrier=True, slip_prob=0.0)


@pytest.fixture(scope="module")
def sim():
    return simulate(n_epochs=120, seed=4, config=RAW).trace


def _pairs(trace, cfg):
    E = trace.n_epochs
    return tdcp_pairs(trace, np.ones(trace.mask.shape, bool), np.arange(E) - 1, cfg, {})


def test_weak_carrier_gets_larger_sigmas_at_the_weaker_end_of_its_pair(sim):
    strong = dataclasses.replace(sim, cn0=np.where(sim.mask, 45.0, 0.0))
    prev, off = _pairs(strong, GraphConfig())
    used = prev >= 0
    assert used.sum() > 500
    _, same = _pairs(strong, GraphConfig(tdcp_cn0_ref_dbhz=40.0))
    np.testing.assert_allclose(same[used], off[used])                      # above the reference: as before
    cn0 = np.where(sim.mask, 45.0, 0.0)
    cn0[60] = np.where(sim.mask[60], 30.0, 0.0)                             # one weak epoch
    _, weak = _pairs(dataclasses.replace(sim, cn0=cn0), GraphConfig(tdcp_cn0_ref_dbhz=40.0))
    for k in (60, 61):                                                      # both pairs it ends
        np.testing.assert_allclose(weak[k][used[k]], off[k][used[k]] * 10 ** 0.5)
    np.testing.assert_allclose(weak[62][used[62]], off[62][used[62]])
    _, unknown = _pairs(dataclasses.replace(sim, cn0=None), GraphConfig(tdcp_cn0_ref_dbhz=40.0))
    np.testing.assert_allclose(unknown[used], off[used])                   # no C/N0: the reported sigma


def _raw(prev):
    prev = np.asarray(prev)
    return RawInputs(doppler=np.zeros(prev.shape, bool), prr_sigma=np.ones(prev.shape), tdcp_prev=prev,
                     tdcp_sigma=np.full(prev.shape, 0.02))


def test_a_distrusted_pseudorange_raises_its_carrier_and_the_pair_takes_the_worse_end():
    raw = _raw([[-1, -1, -1, -1], [0, 1, 2, 3], [0, 1, 2, 3], [0, 1, 2, -1]])
    ratio = np.ones((4, 4))
    ratio[1, 2] = 8.0                      # the head distrusts slot 2 at epoch 1 ...
    ratio[3] = [0.5, 0.5, 0.5, 0.5]        # ... and trusts all of epoch 3 alike: relative, nothing stands out
    ratio[3, 1] = 2.0
    sigma, n = carrier_sigma_by_pseudorange(raw, ratio, 2.0)
    assert sigma[1, 2] == pytest.approx(0.02 * 64)        # its own end
    assert sigma[2, 2] == pytest.approx(0.02 * 64)        # the next pair starts there
    assert sigma[3, 1] == pytest.approx(0.02 * 16)        # 4 x its epoch's median
    assert sigma[3, 0] == pytest.approx(0.02)             # below the median: never tightened
    assert n == 3
    kneed, n4 = carrier_sigma_by_pseudorange(raw, ratio, 2.0, knee=4.0)   # distrust counted from 4 x the median
    assert kneed[1, 2] == pytest.approx(0.02 * 4) and kneed[2, 2] == pytest.approx(0.02 * 4)
    assert kneed[3, 1] == pytest.approx(0.02) and n4 == 2
    few, n_few = carrier_sigma_by_pseudorange(raw, ratio, 2.0, min_count=4)  # epoch 3 holds three differences
    np.testing.assert_allclose(few[:3], sigma[:3])
    np.testing.assert_array_equal(few[3], raw.tdcp_sigma[3])
    assert n_few == 2
    same, n0 = carrier_sigma_by_pseudorange(raw, ratio, 0.0)
    np.testing.assert_array_equal(same, raw.tdcp_sigma)
    assert n0 == 0
    nan = np.full((4, 4), np.nan)                          # no learned sigma anywhere: nothing moves
    np.testing.assert_array_equal(carrier_sigma_by_pseudorange(raw, nan, 2.0)[0], raw.tdcp_sigma)


def test_a_distrusted_pseudorange_raises_its_doppler_sigma_alone():
    raw = _raw([[-1] * 5] * 2)
    raw.doppler = np.array([[True, True, True, True, False], [True] * 5])
    raw.prr_sigma = np.full((2, 5), 0.1)
    ratio = np.array([[1.0, 1.0, 1.0, 3.0, 5.0], [1.0, 1.0, 1.0, 1.0, np.nan]])
    sigma, n = doppler_sigma_by_pseudorange(raw, ratio, 2.0)
    np.testing.assert_allclose(sigma[0], [0.1, 0.1, 0.1, 0.9, 0.1])     # the last slot has no Doppler factor
    np.testing.assert_allclose(sigma[1], 0.1)
    assert n == 1
    np.testing.assert_array_equal(doppler_sigma_by_pseudorange(raw, ratio, 0.0)[0], raw.prr_sigma)


def _reflected(sim, slots, rates, start: int):
    """sim with satellites ``slots`` reflected from epoch ``start`` on: their code 40 m long, their carrier
    paths changing by ``rates`` [m per epoch] (a street's reflections as the car drives), no slip flagged."""
    k = np.arange(sim.n_epochs) - start
    adr, pr = sim.adr.copy(), sim.pr.copy()
    for s, rate in zip(slots, rates):
        adr[:, s] += np.where(k >= 0, rate * k, 0.0)
        pr[start:, s] += 40.0
    return dataclasses.replace(sim, adr=adr, pr=pr)


def test_the_fused_graph_drops_reflected_carrier_the_head_distrusts(sim):
    slots = np.flatnonzero(sim.mask.all(axis=0))[:3]
    assert len(slots) == 3
    tr = _reflected(sim, slots, [0.1, -0.08, 0.06], 40)    # 3-5 of the differences' sigmas: no outliers
    wls = solve_initial(tr, RunOptions())
    _, phys = sigma_model(tr, tr.truth, 0.0)
    head = np.where(tr.mask, phys, np.nan)
    head[40:, slots] *= 30.0                               # the head's view of the reflected pseudoranges

    def err(power):
        opts = RunOptions(graph=GraphConfig(learned_carrier_power=power))
        res = fuse(tr, wls, opts, learned=LearnedGraphInputs(pr_sigma=head), want_cov=False)
        return np.linalg.norm(res.pos[40:] - tr.truth[40:], axis=1).mean(), res.info

    plain, _ = err(0.0)
    trusted, info = err(2.0)
    assert plain > 3.0                                     # the reflected carrier drags the track away ...
    assert trusted < 0.4 * plain                           # ... and the head's distrust lets it go
    assert info["learned_carrier_sigmas_raised"] >= 3 * 79

    inp = prepare_inputs(tr, wls, GraphConfig(learned_carrier_power=2.0), learned=LearnedGraphInputs(pr_sigma=head))
    off = prepare_inputs(tr, wls, GraphConfig(learned_carrier_power=0.0), learned=LearnedGraphInputs(pr_sigma=head))
    assert "learned_carrier_sigmas_raised" not in off.dropped
    assert (inp.raw.tdcp_prev[41:, slots] >= 0).all()
    ratio = inp.raw.tdcp_sigma[41:, slots] / off.raw.tdcp_sigma[41:, slots]
    assert ratio.min() > 100, np.argwhere(ratio <= 100)
    others = np.setdiff1d(np.flatnonzero(sim.mask.all(axis=0)), slots)
    np.testing.assert_allclose(inp.raw.tdcp_sigma[41:, others], off.raw.tdcp_sigma[41:, others], rtol=1e-3)
