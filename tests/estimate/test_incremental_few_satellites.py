"""The incremental smoother (ISAM2) on a phone with too few satellites: an update only where the stretch it opens is
determined (fusion.estimate.graph.incremental.feed_epochs), and a retry with carrier pairs counted by satellite
(fusion.estimate.graph.fuse.incremental_or_retry, fusion.estimate.graph.raw_inputs.tdcp_pairs)."""
from __future__ import annotations

import json

import numpy as np

from fusion.cli import main as cli
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.raw_inputs import MIN_TDCP_SATS, tdcp_pairs
from fusion.eval.summary import incremental_words, run_summary
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate
from tests.thinning import three_satellites


def test_fused_runs_incrementally_on_a_dual_frequency_gps_phone_in_deep_streets(tmp_path):
    """A simulated GPS L1 + L5 phone with Doppler and carrier in the deep canyon: ISAM2 had found its first epoch
    (three satellites, held by the network's prior) singular, and the run wrote nothing."""
    assert cli(["simulate", "--out", str(tmp_path), "--scenario", "deep", "--constellations", "GPS", "--carrier",
                "--seed", "3", "--collection", "d3", "--epochs", "120"]) == 0
    out = tmp_path / "out"
    assert cli(["run", str(tmp_path / "d3" / "SimPhone"), "--signals", "all", "--mode", "fused", "--incremental",
                "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mode"] == "fused" and metrics["epochs_solved"] > 60
    assert "incremental_retried" not in metrics["info"]          # solved at the first try
    assert incremental_words(metrics["info"]) == ""


def test_incremental_retries_with_carrier_pairs_counted_by_satellite_where_isam2_finds_the_system_singular(tmp_path):
    """A simulated GPS L1 + L5 phone in deep streets whose carrier pairs of three or four satellites on two
    frequencies ISAM2 finds singular: the smoother solves it once more, its pairs counted by satellite and its
    carrier clocks held loosely at the code clock, and places every epoch the batch graph places."""
    assert cli(["simulate", "--out", str(tmp_path), "--scenario", "deep", "--constellations", "GPS", "--carrier",
                "--seed", "8", "--collection", "d8", "--epochs", "200"]) == 0
    solved = {}
    for extra in ([], ["--incremental"]):
        out = tmp_path / f"out{len(extra)}"
        assert cli(["run", str(tmp_path / "d8" / "SimPhone"), "--signals", "all", "--mode", "fused-nodnn",
                    "--out", str(out), *extra]) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        solved[len(extra)] = metrics["epochs_solved"]
    assert metrics["info"]["incremental_retried"] == 1
    assert solved[1] == solved[0] > 80
    assert "incremental smoother: solved a second time" in run_summary(metrics)


def test_incremental_waits_for_four_satellites_where_a_prior_starts_a_stretch_of_three():
    """A dual-frequency phone's stretch of three satellites with a prior at every epoch, Doppler on all of them,
    then four and more: the prior fixes the position but not the clock, velocity and drift, so ISAM2 takes the
    stretch with the first epoch of four satellites (it had found its first epoch singular) and solves it all; a
    stretch of three alone, cut off by gaps, is left out and counted. The batch solver places both."""
    tr = simulate(n_epochs=60, nav=read_rinex_nav(default_nav_path()), seed=12,
                  config=SimConfig(doppler=True, carrier=False, dual_frequency=True)).trace
    # epochs 0-9 alone, then 25-29 (3 satellites) and 30-59
    tr = three_satellites(tr, range(30)).select(np.r_[0:10, 25:60])

    def truth_prior(trace, init_pos, valid):
        return trace.truth.copy(), np.tile(np.eye(3), (trace.n_epochs, 1, 1)), np.arange(trace.n_epochs) < 15

    w = solve_initial(tr, RunOptions())
    inc = fuse(tr, w, RunOptions(graph=GraphConfig(incremental=True)), provider=truth_prior, want_cov=False)
    assert inc.info["incremental_unanchored"] == 10 and not inc.valid[:10].any() and inc.valid[10:].all()
    assert incremental_words(inc.info).startswith("incremental smoother: 10 epochs left out")
    vel = inc.info["vel"]                              # read where added, NaN where left out
    assert np.isfinite(vel[10:]).all() and np.isnan(vel[:10]).all()
    assert np.nanmax(np.linalg.norm(inc.pos - tr.truth, axis=1)[10:]) < 10.0
    batch = fuse(tr, w, RunOptions(), provider=truth_prior)
    assert batch.valid.all()
    # the marginals of the graph ISAM2 solved, the stretch left out aside: near the batch graph's there
    cov = fuse(tr, w, RunOptions(graph=GraphConfig(incremental=True)), provider=truth_prior).cov
    assert np.isnan(cov[:10]).all()
    sig, batch_sig = (np.sqrt(np.diagonal(c[10:], axis1=1, axis2=2)) for c in (cov, batch.cov))
    np.testing.assert_allclose(sig, batch_sig, rtol=0.1)


def test_a_carrier_pair_counts_its_satellites_only_where_asked():
    """Five differences of three satellites (two on two frequencies) repeat three directions: with
    ``tdcp_min_distinct_sats`` = 5 (the incremental smoother's retry) the pair keeps none, as with three
    single-frequency satellites; by default it keeps all five, in the batch graph and the incremental one."""
    tr = simulate(n_epochs=30, seed=7, config=SimConfig(doppler=True, carrier=True, slip_prob=0.0,
                                                        dual_frequency=True)).trace
    tr = three_satellites(tr, (20, 21), on_two=2)
    assert tr.mask[21].sum() >= MIN_TDCP_SATS
    above, link = np.ones(tr.mask.shape, bool), np.arange(tr.n_epochs) - 1
    counts = {}
    prev, _ = tdcp_pairs(tr, above, link, GraphConfig(tdcp_min_distinct_sats=MIN_TDCP_SATS), counts)
    assert not (prev[21] >= 0).any() and (prev[22] < 0).all()        # 22 pairs with the thinned 21: the same three
    assert counts["carrier_too_few_satellites"] >= 2 * tr.mask[21].sum() and (prev[19] >= 0).sum() >= MIN_TDCP_SATS
    for cfg in (GraphConfig(), GraphConfig(incremental=True)):
        kept, _ = tdcp_pairs(tr, above, link, cfg, {})
        assert (kept[21] >= 0).sum() == tr.mask[21].sum()
