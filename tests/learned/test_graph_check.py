"""The adaptation's graph check (learned/graph_check.py): satellites held out of the fused graph."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.cli import main as cli
from fusion.errors import GnssfuseError
from fusion.prepare.load import load_trace
from learned.adapt import AdaptConfig, adapt
from learned.checkpoint import read_checkpoint
from learned.graph_check import CAP, graph_decision, heldout_residuals, satellite_folds
from learned.infer import SHIPPED_WEIGHTS

FEW = 150


@pytest.fixture(scope="module")
def trace(shipped_trace_dir):
    return load_trace(shipped_trace_dir).select(np.arange(FEW))


def test_folds_deal_whole_satellites_and_every_one_once(trace):
    fold = satellite_folds(trace, 4, seed=0)
    assert (fold[~trace.mask] == -1).all() and set(np.unique(fold[trace.mask])) == {0, 1, 2, 3}
    for sid in np.unique(trace.sat_id[trace.mask]):          # one satellite, one fold, at every epoch
        assert len(np.unique(fold[trace.mask & (trace.sat_id == sid)])) == 1
    assert np.array_equal(fold, satellite_folds(trace, 4, seed=0))
    assert not np.array_equal(fold, satellite_folds(trace, 4, seed=1))


def test_held_out_residuals_see_where_the_phone_is_not_the_clock(trace):
    held = satellite_folds(trace, 4) == 0
    at_truth = heldout_residuals(trace, trace.truth, held)
    assert at_truth.size == (held & trace.mask & np.isfinite(trace.truth).all(1)[:, None]).sum()
    # a clock common to every satellite of an epoch changes nothing: the kept satellites fix it
    clocked = replace(trace, pr=trace.pr + np.linspace(0.0, 3e5, trace.n_epochs)[:, None])
    assert np.allclose(heldout_residuals(clocked, trace.truth, held), at_truth, atol=1e-6)
    # positions 10 and 30 m east of the truth predict the held-out pseudoranges worse and worse
    from fusion.geometry import ned2ecef_vec
    scores = [np.minimum(heldout_residuals(trace, trace.truth + ned2ecef_vec(
        np.tile([0.0, east, 0.0], (trace.n_epochs, 1)), trace.truth), held), CAP).mean() for east in (0, 10, 30)]
    assert scores[0] < scores[1] < scores[2]
    # unsolved epochs score nothing
    gone = trace.truth.copy()
    gone[:10] = np.nan
    assert heldout_residuals(trace, gone, held).size == (held[10:] & trace.mask[10:]).sum()


def test_graph_decision_wants_a_gain_beyond_the_noise():
    from learned.graph_check import GraphScores
    rng = np.random.default_rng(0)
    base = rng.uniform(0.0, 8.0, 4000)
    blocks = np.arange(4000) // 60
    better = GraphScores(np.stack([base, base - 0.2]), blocks, 0)          # 5 % lower everywhere
    keep, why = graph_decision(better, 0.0)
    assert keep and "gain 5.0" in why
    noisy = GraphScores(np.stack([base, base + rng.normal(-0.01, 1.0, 4000)]), blocks, 0)   # 0.25 % in noise
    keep, why = graph_decision(noisy, 0.0)
    assert not keep and "standard errors" in why
    assert not graph_decision(better, 0.1)[0]                              # the margin still applies
    assert not graph_decision(GraphScores(np.zeros((2, 0)), np.zeros(0, int), 3), 0.0)[0]
    # a standard error clustered by block: the same differences repeated within blocks count once per block
    gain, se = GraphScores(np.stack([base, base + np.repeat(rng.normal(0, 1, 67), 60)[:4000]]), blocks, 0).gain(0, 1)
    _, se_iid = GraphScores(np.stack([base, base + rng.normal(0, 1, 4000)]), blocks, 0).gain(0, 1)
    assert se > 4 * se_iid


def test_a_graph_check_that_fails_writes_the_base_weights_and_says_why(shipped_trace_dir, tmp_path, capsys):
    out = tmp_path / "w.pt"      # the self-check keeps anything (-1); no adaptation gains 99 % in the graph
    assert cli(["adapt", str(shipped_trace_dir), "--max-epochs", str(FEW), "--epochs", "1", "--margin", "-1",
                "--graph-margin", "0.99", "--lr", "1e-2", "--out", str(out), "--threads", "1"]) == 0
    said = capsys.readouterr().out.splitlines()[0]
    assert said.startswith("adaptation DECLINED") and "graph check" in said
    base, new = read_checkpoint(SHIPPED_WEIGHTS), read_checkpoint(out)
    assert all(np.array_equal(base["model_state"][k], new["model_state"][k]) for k in base["model_state"])
    assert new["config"]["input_ranges"] == base["config"]["input_ranges"]
    rec = new["config"]["adapted"][-1]
    g = rec["graph_check"]
    assert rec["decision"] == "declined" and rec["best_epoch"] == 0 and g["folds"] == 4
    assert g["measurements"] > 0 and g["base_m"] > 0 and g["adapted_m"] > 0 and g["base_m"] != g["adapted_m"]
    assert g["gain_se"] > 0


def test_the_api_refuses_a_graph_check_without_folds(shipped_trace_dir, tmp_path):
    with pytest.raises(GnssfuseError, match="at least 2 satellite folds"):
        adapt([shipped_trace_dir], tmp_path / "w.pt", cfg=AdaptConfig(max_epochs=FEW, graph_folds=1))


def test_graph_errors_are_paired_and_skip_a_fold_any_graph_cannot_solve(trace, monkeypatch):
    import learned.graph_check as gc
    from fusion.errors import GeometryError
    from fusion.run_types import RunOptions
    calls = []

    def positions(tr, opts):      # the truth, 5 m off for the second option, which fails its 2nd fold and
        calls.append(opts.elev_mask_deg)                       # leaves its first 20 epochs unsolved
        if opts.elev_mask_deg == 11.0 and len(calls) == 4:
            raise GeometryError("too few satellites")
        pos = trace.truth + (5.0 if opts.elev_mask_deg == 11.0 else 0.0)
        return np.where(np.arange(trace.n_epochs)[:, None] < 20, np.nan, pos) if opts.elev_mask_deg == 11.0 else pos

    monkeypatch.setattr(gc, "_positions", positions)
    scores = gc.graph_errors([trace], [RunOptions(), RunOptions(elev_mask_deg=11.0)], folds=4)
    a, b = scores.summary(0), scores.summary(1)
    assert a["folds_unsolved"] == b["folds_unsolved"] == 1
    assert a["measurements"] == b["measurements"] > 0          # the same measurements for both
    assert scores.blocks.size == a["measurements"] and scores.blocks.min() >= 20 // gc.BLOCK
    assert a["error_m"] < b["error_m"] and scores.gain(0, 1)[0] < 0
