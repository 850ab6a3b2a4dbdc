"""The fused mode where too few satellites are seen: its learned prior is withheld where the graph without anything
learned cannot place the epoch (learned.modes.prior_where_determined: the prior alone would place it, asked at an
interpolated WLS guess), and its epochs of fewer than 4 satellites are flagged bridged, a prior there or not
(learned.modes.flag_few_satellites)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import learned.modes
from fusion.estimate.graph.priors import LearnedGraphInputs
from fusion.modes import run_modes
from fusion.prepare.load import load_trace
from fusion.run_types import RunOptions
from learned.modes import prior_where_determined
from tests.thinning import three_satellites


def test_the_prior_is_withheld_exactly_where_the_unlearned_graph_left_the_epoch_unsolved():
    E = 6
    learned = LearnedGraphInputs(prior_mean=np.zeros((E, 3)), prior_cov=np.tile(np.eye(3), (E, 1, 1)),
                                 prior_ok=np.array([1, 1, 0, 1, 1, 1], bool), info={"learned_epochs_asked": E})
    solved = np.array([1, 0, 0, 1, 0, 1], bool)
    out = prior_where_determined(learned, solved)
    assert out.prior_ok.tolist() == [True, False, False, True, False, True]
    assert out.info == {"learned_epochs_asked": E, "learned_prior_withheld": 2}
    assert learned.prior_ok.tolist() == [True, True, False, True, True, True]        # the input is not changed
    assert prior_where_determined(learned, None) is learned                          # prior_at = "wls": no graph
    assert prior_where_determined(replace(learned, prior_ok=None), solved).prior_ok is None


@pytest.fixture(scope="module")
def isolated(shipped_trace_dir):
    """The shipped trace with epoch 50 cut off by 30 s gaps and four pseudoranges of two satellites left there
    (as a dual-frequency phone's two satellites give): enough for the network to be asked, too few for the graph,
    so nothing but the network's prior can place it."""
    tr = load_trace(shipped_trace_dir).select(np.r_[0:50, 80:81, 110:140])
    mask, sat_id = tr.mask.copy(), tr.sat_id.copy()
    slots = np.flatnonzero(mask[50])
    mask[50, slots[4:]] = False
    sat_id[50, slots[2:4]] = sat_id[50, slots[:2]]
    return replace(tr, mask=mask, sat_id=sat_id)


def test_fused_leaves_unsolved_what_the_graph_without_the_network_cannot_place(isolated, monkeypatch):
    opts = RunOptions()
    res = run_modes(isolated, ["fused-nodnn", "fused"], opts)
    nodnn, fused = res["fused-nodnn"], res["fused"]
    assert not nodnn.valid[50] and not fused.valid[50]
    assert np.array_equal(nodnn.valid, fused.valid) and fused.valid.sum() == isolated.n_epochs - 1
    assert fused.info["learned_prior_withheld"] == 1 and fused.info["epochs_undetermined"] == 1
    # the code before: the network's prior alone placed the epoch
    monkeypatch.setattr(learned.modes, "prior_where_determined", lambda learned_inputs, solved: learned_inputs)
    before = run_modes(isolated, ["fused"], opts)["fused"]
    assert before.valid.all() and "learned_prior_withheld" not in before.info


def test_the_run_summary_says_how_many_epochs_lost_their_prior():
    from fusion.eval.summary import learned_words
    assert "its prior withheld at 3 epochs the graph without it cannot place" in learned_words(
        {"learned_epochs_asked": 10, "learned_prior_withheld": 3})
    assert "withheld" not in learned_words({"learned_epochs_asked": 10, "learned_prior_withheld": 0})
    assert "physical model at 4 epochs of too few satellites" in learned_words(
        {"learned_epochs_asked": 10, "learned_epochs_few_satellites": 4})


def test_fused_flags_the_epochs_of_too_few_satellites_its_prior_holds(monkeypatch):
    """Three satellites on two frequencies at epochs 40-49: four pseudoranges, so the network is asked and its prior
    holds those epochs; they are flagged and counted as fused-nodnn flags them, and the sigmas are left alone."""
    from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
    from fusion.sim.simulate import SimConfig, simulate
    from fusion.trace import SIGNALS

    tr = simulate(n_epochs=80, nav=read_rinex_nav(default_nav_path()), seed=12,
                  config=SimConfig(doppler=False, carrier=False, dual_frequency=True)).trace
    tr = three_satellites(tr, range(40, 50))
    opts = RunOptions(signals=SIGNALS)
    res = run_modes(tr, ["fused-nodnn", "fused"], opts)
    nodnn, fused = res["fused-nodnn"], res["fused"]
    assert nodnn.info["epochs_bridged"] == 10 and nodnn.info["bridged"][40:50].all()
    assert fused.valid.all() and fused.info["epochs_bridged"] == 10
    assert np.array_equal(fused.info["bridged"], nodnn.info["bridged"])
    assert fused.info["longest_bridge_s"] == nodnn.info["longest_bridge_s"]
    # the graph's own flag (no prior) left those epochs unflagged; the covariance is the same either way
    monkeypatch.setattr(learned.modes, "flag_few_satellites", lambda r, trace: r)
    before = run_modes(tr, ["fused"], opts)["fused"]
    assert before.info["epochs_bridged"] == 0
    np.testing.assert_array_equal(before.cov, fused.cov)


def test_the_learned_sigmas_power_is_zero_where_too_few_satellites_are_above_the_mask():
    """learned.modes.power_where_redundant: epochs of fewer distinct satellites than learned_sigma_min_sats get
    power 0 (the physical model's sigma); off (0) as shipped, the power passes through untouched."""
    from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
    from fusion.sim.simulate import SimConfig, simulate
    from learned.modes import power_where_redundant
    tr = simulate(n_epochs=20, nav=read_rinex_nav(default_nav_path()), seed=5,
                  config=SimConfig(doppler=True, carrier=False, dual_frequency=True)).trace
    tr = three_satellites(tr, range(5, 9), on_two=2)          # three satellites, five pseudoranges
    opts = RunOptions()
    assert power_where_redundant(4.0, tr, tr.truth, opts) == (4.0, None)
    graph = replace(opts.graph, learned_sigma_min_sats=4)
    power, few = power_where_redundant(np.full((tr.n_epochs, 1), 3.0), tr, tr.truth, replace(opts, graph=graph))
    assert few == 4 and power.shape == (tr.n_epochs, 1)
    assert (power[5:9] == 0).all() and (np.delete(power, np.s_[5:9]) == 3.0).all()
