"""The clock drift as the log's own Doppler shows it (fusion.estimate.graph.drift_noise): measured without
truth, and where it jumps from epoch to epoch, a variable of each epoch's Doppler that the clock does not
integrate."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.drift_noise import doppler_jump, drift_change
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.doppler_carrier import with_drift_jumps
from fusion.sim.simulate import SimConfig, simulate


@pytest.fixture(scope="module")
def nav():
    return read_rinex_nav(default_nav_path())


def doppler_trace(nav, drift_walk: float, seed: int = 3):
    """A simulated GPS drive with Doppler whose receiver clock drift walks ``drift_walk`` m/s per sqrt(s)."""
    cfg = SimConfig(doppler=True, clock_drift_rw_mps=drift_walk)
    return simulate(n_epochs=240, nav=nav, seed=seed, config=cfg).trace


def change_of(trace, cfg: GraphConfig = GraphConfig()):
    return drift_change(trace, prepare_inputs(trace, solve_initial(trace, RunOptions()), cfg))


def test_the_simulated_drift_jump_is_one_seeded_offset_per_epoch_on_its_dopplers_alone(nav):
    trace = doppler_trace(nav, 0.02)
    ok = trace.prr_ok.copy()
    ok[::7, 0] = False                                   # slots without a Doppler keep their (unused) value
    trace = dataclasses.replace(trace, prr_ok=ok)
    jumped = with_drift_jumps(trace, 0.5, seed=3)
    step = np.where(ok, jumped.prr - trace.prr, np.nan)
    has = ok.any(axis=1)
    assert np.nanmax(step[has], axis=1) - np.nanmin(step[has], axis=1) == pytest.approx(0.0, abs=1e-9)
    assert 0.43 < np.nanstd(np.nanmean(step[has], axis=1)) < 0.57             # 240 epochs of sigma 0.5
    assert np.array_equal(jumped.prr[~ok], trace.prr[~ok])
    assert np.array_equal(with_drift_jumps(trace, 0.5, seed=3).prr, jumped.prr)
    assert not np.array_equal(with_drift_jumps(trace, 0.5, seed=4).prr, jumped.prr)


def test_a_steady_clock_gets_no_jump(nav):
    change = change_of(doppler_trace(nav, 0.02))
    assert change is not None and change < GraphConfig().drift_rw_mps
    assert doppler_jump(change, GraphConfig()) == 0.0


def test_a_walking_drift_is_measured(nav):
    assert 0.6 < change_of(doppler_trace(nav, 0.8)) < 1.0


def test_a_drift_that_jumps_each_epoch_is_measured_beyond_the_doppler_noise(nav):
    trace = doppler_trace(nav, 0.02)
    # white jumps of 0.5 m/s change the drift by 0.71 m/s from one epoch to the next; the estimate errs low
    # (the fits' noise it takes off is the stated sigmas', raised where the fits show more, never lowered)
    change = change_of(with_drift_jumps(trace, 0.5, seed=0))
    assert 0.4 < change < 0.85
    assert 0.25 < doppler_jump(change, GraphConfig()) < 0.6
    # noise of each Doppler on its own is the fits' business, not the clock's
    rng = np.random.default_rng(1)
    noisy = dataclasses.replace(trace, prr=trace.prr + rng.normal(0.0, 0.5, trace.prr.shape),
                                prr_sigma=np.full(trace.prr.shape, 0.5))
    assert doppler_jump(change_of(noisy), GraphConfig()) == 0.0


@pytest.mark.parametrize("seed", [0, 1])
def test_epochs_that_barely_know_the_drift_do_not_hide_its_jumps(nav, seed):
    # half the epochs' Dopplers ten times noisier (and said to be): their fits know the drift to ~2.7 m/s (the
    # others' to ~0.3), their changes swamp the spread and their variances the noise taken off it, and the
    # 0.5 m/s jumps would vanish into them (an estimate of 0 with every epoch counted); counting only epochs
    # that know the drift to KNOWN_SD_MPS keeps the jumps in sight
    trace = with_drift_jumps(doppler_trace(nav, 0.02), 0.5, seed=0)
    rng = np.random.default_rng(seed)
    scale = np.where(rng.random(trace.n_epochs) < 0.5, 10.0, 1.0)[:, None]
    noise = rng.normal(0.0, 1.0, trace.prr.shape) * trace.prr_sigma * (scale - 1.0)
    blurred = dataclasses.replace(trace, prr=np.where(trace.prr_ok, trace.prr + noise, trace.prr),
                                  prr_sigma=trace.prr_sigma * scale)
    assert 0.3 < change_of(blurred) < 0.85


def test_the_jump_is_what_the_walk_leaves_of_the_change():
    assert doppler_jump(0.7, GraphConfig()) == pytest.approx(np.sqrt((0.7 ** 2 - 0.2 ** 2) / 2))
    assert doppler_jump(0.15, GraphConfig()) == 0.0
    assert doppler_jump(None, GraphConfig()) == 0.0


def test_too_few_dopplers_give_no_estimate(nav):
    trace = doppler_trace(nav, 0.8)
    few = dataclasses.replace(trace, prr_ok=trace.prr_ok & (np.cumsum(trace.prr_ok, axis=1) <= 5))
    inp = prepare_inputs(few, solve_initial(few, RunOptions()), GraphConfig())
    # five Dopplers an epoch leave one spare for four unknowns: the fits need two
    assert drift_change(few, inp) is None
    assert inp.doppler_jump_mps == 0.0 and inp.dropped["doppler_drift_jump_mps"] is None   # unknown, not steady
    inp = prepare_inputs(trace, solve_initial(trace, RunOptions()), GraphConfig(use_doppler=False))
    assert drift_change(trace, inp) is None and inp.doppler_jump_mps == 0.0


def test_drift_steps_at_clock_resets_are_not_jumps(nav):
    trace = doppler_trace(nav, 0.02)
    reset = np.arange(trace.n_epochs) % 2 == 1                  # the clock steps at every other epoch
    step = 5.0 * np.cumsum(reset)
    stepped = dataclasses.replace(trace, clock_reset=reset,
                                  prr=np.where(trace.prr_ok, trace.prr + step[:, None], trace.prr))
    assert change_of(stepped) < GraphConfig().drift_rw_mps


def test_the_jump_follows_the_epoch_interval(nav):
    cfg = SimConfig(doppler=True, clock_drift_rw_mps=0.02)
    trace = with_drift_jumps(simulate(n_epochs=300, rate_hz=2.0, nav=nav, seed=4, config=cfg).trace, 0.5, seed=0)
    inp = prepare_inputs(trace, solve_initial(trace, RunOptions()), GraphConfig())
    assert inp.doppler_jump_mps == pytest.approx(doppler_jump(drift_change(trace, inp), GraphConfig(), 0.5))
    # at 10 Hz the same change per sqrt(s) is a jump sqrt(10) times smaller than at 1 Hz
    assert doppler_jump(1.0, GraphConfig(), 0.1) == pytest.approx(doppler_jump(1.0, GraphConfig()) / np.sqrt(10))


def test_the_jump_factor_is_one_sigma_at_its_sigma():
    import gtsam
    from fusion.estimate.graph.factors import doppler_drift_factor_jd
    from fusion.estimate.graph.keys import DRIFT_HORIZON_S, doppler_drift_key, drift_key
    from fusion.geometry import C_LIGHT
    values = gtsam.Values()
    values.insert(drift_key(7), 1e-3)
    values.insert(doppler_drift_key(7), 1e-3 + 0.4 * DRIFT_HORIZON_S / C_LIGHT)    # the drift + 0.4 m/s
    assert doppler_drift_factor_jd(7, 0.4).error(values) == pytest.approx(0.5, rel=1e-6)
    assert doppler_drift_factor_jd(7, 0.2).error(values) == pytest.approx(2.0, rel=1e-6)


def test_the_graph_gives_the_doppler_a_drift_of_its_own_and_reports_it(nav):
    trace = with_drift_jumps(doppler_trace(nav, 0.02), 0.5, seed=0)
    wls = solve_initial(trace, RunOptions())
    inp = prepare_inputs(trace, wls, GraphConfig())
    assert 0.25 < inp.doppler_jump_mps < 0.6
    res = fuse(trace, wls, RunOptions(), cfg=GraphConfig())
    assert res.info["doppler_drift_jump_mps"] == pytest.approx(inp.doppler_jump_mps, abs=1e-3)
    without = fuse(trace, wls, RunOptions(), cfg=GraphConfig(doppler_jump_from_log=False))
    assert "doppler_drift_jump_mps" not in without.info
    err = [np.linalg.norm(r.pos - trace.truth, axis=1).mean() for r in (res, without)]
    assert np.abs(res.pos - without.pos).max() > 1e-3
    assert err[0] < err[1]                    # the jumps no longer leak into the velocity
    # incremental (ISAM2) builds the same variables
    inc = fuse(trace, wls, RunOptions(), cfg=GraphConfig(incremental=True))
    assert inc.valid.all() and np.linalg.norm(inc.pos - trace.truth, axis=1).mean() < 2 * err[0]


def test_a_steady_clock_keeps_the_graph_it_had(nav):
    trace = doppler_trace(nav, 0.02)
    wls = solve_initial(trace, RunOptions())
    a = fuse(trace, wls, RunOptions(), cfg=GraphConfig())
    b = fuse(trace, wls, RunOptions(), cfg=GraphConfig(doppler_jump_from_log=False))
    assert a.info["doppler_drift_jump_mps"] == 0.0
    np.testing.assert_allclose(a.pos, b.pos, rtol=0.0, atol=1e-9)

