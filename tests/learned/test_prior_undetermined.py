"""The fused mode's learned prior is withheld where the graph without anything learned cannot place the epoch
(learned.modes.prior_where_determined): the prior alone would place it, asked at an interpolated WLS guess."""
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
