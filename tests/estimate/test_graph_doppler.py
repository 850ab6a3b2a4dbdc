"""Doppler and carrier phase: the simulator's truth-known Doppler/ADR, the graph's Doppler and
time-differenced carrier factors, chains broken at slips and resets, batch vs incremental, and
traces without the fields solved exactly as before."""
from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from tests.run_options import parse_run_options
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import (_linear_factor, displacement_factor_xxu, doppler_factor_vcd,
                                           drift_walk_factor_cdcd, tdcp_factor_uqq)
from fusion.estimate.graph.fuse import carrier_linked, fuse
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.keys import DRIFT_HORIZON_S, carrier_clock_key, clock_key, disp_key, drift_key, pos_key, vel_key
from fusion.estimate.graph.raw_inputs import RawInputs
from fusion.geometry import C_LIGHT, line_of_sight, range_rate
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate
from fusion.trace import OPTIONAL_SLOT_FIELDS

RAW = SimConfig(doppler=True, carrier=True, slip_prob=0.005)


@pytest.fixture(scope="module")
def nav():
    return read_rinex_nav(default_nav_path())


@pytest.fixture(scope="module")
def sim(nav):
    return simulate(n_epochs=200, nav=nav, seed=11, config=RAW)


@pytest.fixture(scope="module")
def wls(sim):
    return solve_initial(sim.trace, RunOptions())


def pos_err(trace, pos) -> np.ndarray:
    return np.linalg.norm(pos - trace.truth, axis=1)


def solve(trace, wls, **switches):
    return fuse(trace, wls, RunOptions(graph=GraphConfig(**switches)), want_cov=False)


# ------------------------------------------------------------------------------ simulator
def test_doppler_and_carrier_leave_the_pseudoranges_as_they_were(nav):
    plain = simulate(n_epochs=80, nav=nav, seed=5)
    raw = simulate(n_epochs=80, nav=nav, seed=5, config=SimConfig(doppler=True, carrier=True, slip_prob=0.1))
    for key in ("t_ms", "sat_pos", "pr", "mask", "sat_id", "truth"):
        np.testing.assert_array_equal(getattr(plain.trace, key), getattr(raw.trace, key))
    np.testing.assert_array_equal(plain.clock_m, raw.clock_m)
    assert plain.trace.prr is None and plain.trace.adr is None
    assert raw.trace.has_doppler and raw.trace.has_carrier


def test_simulated_doppler_and_carrier_follow_their_models(sim):
    tr, m = sim.trace, sim.trace.mask
    prr_res = tr.prr - range_rate(tr.sat_pos, tr.sat_vel, tr.truth, sim.rx_vel_mps) - sim.clock_drift_mps[:, None]
    assert abs(prr_res[m].std() - RAW.prr_sigma_mps) < 0.02 and abs(prr_res[m].mean()) < 0.02
    adr_res = tr.adr - line_of_sight(tr.sat_pos, tr.truth)[0] - sim.clock_m[:, None] - sim.ambiguity_m
    assert abs(adr_res[m].std() - RAW.adr_sigma_m) < 0.0005
    # the ambiguity changes only where a slip is flagged, always when one is, by a big jump
    same_sat = m[1:] & m[:-1] & (tr.sat_id[1:] == tr.sat_id[:-1])
    jump = np.abs(np.diff(sim.ambiguity_m, axis=0))
    slip = tr.adr_slip[1:]
    assert same_sat.any() and (slip & same_sat).any()
    assert np.all(jump[same_sat & ~slip] == 0)
    assert np.all(jump[same_sat & slip] >= RAW.slip_jump_m[0])


# ------------------------------------------------------------------------------ factors
def test_doppler_factor_is_zero_at_the_truth(sim):
    tr, k = sim.trace, 50
    v = gtsam.Values()
    v.insert(vel_key(k), sim.rx_vel_mps[k])
    clock_s = sim.clock_m[k] / C_LIGHT
    v.insert(clock_key(k), clock_s)
    v.insert(drift_key(k), clock_s + sim.clock_drift_mps[k] * DRIFT_HORIZON_S / C_LIGHT)
    model = gtsam.noiseModel.Isotropic.Sigma(1, 1.0)
    errs = [doppler_factor_vcd(k, tr.prr[k, s], tr.sat_pos[k, s], tr.sat_vel[k, s], tr.truth[k] + 20.0,
                               model).unwhitenedError(v)[0] for s in np.flatnonzero(tr.mask[k])]
    assert np.max(np.abs(errs)) < 4 * RAW.prr_sigma_mps       # only the simulated noise is left


def test_tdcp_factor_at_the_truth_and_its_slope(sim):
    tr, k = sim.trace, 30
    s = np.flatnonzero(tr.mask[k] & tr.mask[k - 1] & (tr.sat_id[k] == tr.sat_id[k - 1]) & ~tr.adr_slip[k])
    assert s.size >= 4
    rng = np.random.default_rng(0)
    guess = tr.truth[k - 1:k + 1] + rng.normal(0, 10.0, (2, 3))           # a WLS-quality guess
    model = gtsam.noiseModel.Isotropic.Sigma(1, 1.0)
    v = gtsam.Values()
    v.insert(disp_key(k), tr.truth[k] - tr.truth[k - 1])
    for j in (k - 1, k):
        v.insert(carrier_clock_key(j), sim.clock_m[j])               # metres, unlike c(k)
    step = np.array([0.7, -0.4, 0.2])
    for i in s:
        f = tdcp_factor_uqq(k, tr.adr[k, i] - tr.adr[k - 1, i], tr.sat_pos[k - 1, i], tr.sat_pos[k, i],
                            guess[0], guess[1], model)
        # carrier noise (2 x 3 mm) + linearisation at a 10 m guess (~1 mm)
        assert abs(f.unwhitenedError(v)[0]) < 0.03
        v2 = gtsam.Values(v)
        v2.update(disp_key(k), tr.truth[k] - tr.truth[k - 1] + step)
        los = tr.sat_pos[k, i] - tr.truth[k]
        los /= np.linalg.norm(los)
        # the range grows by -los . step when the receiver moves by step
        assert f.unwhitenedError(v2)[0] - f.unwhitenedError(v)[0] == pytest.approx(-los @ step, abs=1e-4)


def test_displacement_factor_ties_u_to_the_positions():
    v = gtsam.Values()
    v.insert(pos_key(4), np.array([1.0, 2.0, 3.0]))
    v.insert(pos_key(5), np.array([1.5, 2.0, 2.0]))
    v.insert(disp_key(5), np.array([0.5, 0.0, -1.0]))
    assert displacement_factor_xxu(5, 1e-3).error(v) == pytest.approx(0.0, abs=1e-12)
    v.update(disp_key(5), np.array([0.5, 0.002, -1.0]))
    assert displacement_factor_xxu(5, 1e-3).error(v) == pytest.approx(0.5 * 2.0**2)


def test_four_key_linear_factor_is_exact():
    keys = [drift_key(2), clock_key(2), drift_key(1), clock_key(1)]
    v = gtsam.Values()
    x = np.array([0.3, -0.2, 0.5, 1.1])
    for key, xi in zip(keys, x):
        v.insert(key, float(xi))
    a = np.array([1.0, -1.0, -1.0, 1.0])
    assert _linear_factor(keys, list(a), 0.5).error(v) == pytest.approx(0.5 * (a @ x / 0.5) ** 2)
    sigma_mps = 0.3
    expect = 0.5 * ((a @ x) * C_LIGHT / DRIFT_HORIZON_S / sigma_mps) ** 2
    assert drift_walk_factor_cdcd(1, 2, sigma_mps).error(v) == pytest.approx(expect)


# ------------------------------------------------------------------------------ inputs
def test_carrier_chains_break_at_slips_invalid_phase_and_clock_resets(sim, wls):
    tr = sim.trace
    base = prepare_inputs(tr, wls, GraphConfig()).raw
    k = 100
    assert (base.tdcp_prev[k] >= 0).sum() >= 4 and np.all(base.tdcp_prev[tr.adr_slip] < 0)
    s0 = int(np.flatnonzero(base.tdcp_prev[k] >= 0)[0])
    slip, bad = tr.adr_slip.copy(), tr.adr_ok.copy()
    slip[k, s0] = True
    bad[k + 1, s0] = False
    reset = tr.clock_reset.copy()
    reset[k + 5] = True
    edited = dataclasses.replace(tr, adr_slip=slip, adr_ok=bad, clock_reset=reset)
    raw = prepare_inputs(edited, wls, GraphConfig()).raw
    assert raw.tdcp_prev[k, s0] < 0 and raw.tdcp_prev[k + 1, s0] < 0
    assert np.all(raw.tdcp_prev[k + 5] < 0) and (base.tdcp_prev[k + 5] >= 0).any()
    assert raw.counts["carrier_chain_broken_by_clock"] > 0
    # k+2 pairs with k+1, where s0 had no valid phase; the other satellites keep their chains
    assert (raw.tdcp_prev[k + 2] >= 0).sum() == (base.tdcp_prev[k + 2] >= 0).sum() - 1
    assert (raw.tdcp_prev[k + 3] >= 0).sum() == (base.tdcp_prev[k + 3] >= 0).sum()


def test_doppler_without_satellite_velocity_or_sigma_is_a_counted_skip(sim, wls):
    tr = sim.trace
    sat_vel, prr_sigma = tr.sat_vel.copy(), tr.prr_sigma.copy()
    sat_vel[10, 0] = 0.0
    prr_sigma[11, 0] = np.nan
    raw = prepare_inputs(dataclasses.replace(tr, sat_vel=sat_vel, prr_sigma=prr_sigma), wls, GraphConfig()).raw
    assert not raw.doppler[10, 0] and not raw.doppler[11, 0]
    assert raw.counts["doppler_without_satellite_velocity"] == 1 and raw.counts["doppler_bad_sigma"] == 1
    # random-walk motion has no velocity states for Doppler to constrain: all counted, none used
    rw = prepare_inputs(tr, wls, GraphConfig(motion="rw")).raw
    assert not rw.doppler.any() and not rw.use_drift
    assert rw.counts["doppler_without_velocity_states"] > 5 * tr.n_epochs and rw.counts["tdcp_factors"] > 0


def test_doppler_of_epochs_with_too_few_satellites_is_a_counted_skip(sim, wls):
    tr = sim.trace
    prr_ok = tr.prr_ok.copy()
    prr_ok[20:30] &= np.cumsum(tr.mask[20:30], axis=1) <= 2              # ten epochs with two Dopplers left
    thin = dataclasses.replace(tr, prr_ok=prr_ok)
    kept = prepare_inputs(thin, wls, GraphConfig()).raw
    assert (kept.doppler[20:30].sum(axis=1) == 2).all() and "doppler_few_satellites" not in kept.counts
    cut = prepare_inputs(thin, wls, GraphConfig(doppler_min_sats=3)).raw
    assert not cut.doppler[20:30].any() and cut.counts["doppler_few_satellites"] == 20
    assert np.array_equal(cut.doppler[:20], kept.doppler[:20])
    assert np.array_equal(cut.doppler[30:], kept.doppler[30:])


def test_switches_and_traces_without_the_fields(sim, wls):
    tr = sim.trace
    bare = dataclasses.replace(tr, **{k: None for k in OPTIONAL_SLOT_FIELDS})
    assert prepare_inputs(bare, wls, GraphConfig()).raw is None
    assert prepare_inputs(tr, wls, GraphConfig(use_doppler=False, use_carrier=False)).raw is None
    off = solve(tr, wls, use_doppler=False, use_carrier=False)
    plain = solve(bare, wls)
    np.testing.assert_array_equal(off.pos, plain.pos)
    assert "doppler_factors" not in plain.info and "tdcp_factors" not in plain.info
    assert not plain.info["carrier_linked"].any() and not off.info["carrier_linked"].any()
    linked = solve(tr, wls).info["carrier_linked"]
    assert linked.shape == (tr.n_epochs,) and linked.mean() > 0.9


def test_carrier_linked_epochs_are_those_a_carrier_difference_ties_to_a_neighbour():
    prev = np.array([[-1, -1], [0, 1], [-1, -1], [-1, -1], [-1, 0], [-1, -1]])
    raw = RawInputs(doppler=np.zeros(prev.shape, bool), prr_sigma=np.ones(prev.shape), tdcp_prev=prev,
                    tdcp_sigma=np.ones(prev.shape))
    # epoch 1 differences with 0, epoch 4 with 3; 2 and 5 are tied to neither neighbour
    np.testing.assert_array_equal(carrier_linked(raw, 6), [True, True, False, True, True, False])
    assert not carrier_linked(None, 6).any()


# ------------------------------------------------------------------------------ solutions
#: the pseudorange loss for this file's Gaussian errors (see :func:`solutions`)
GAUSSIAN = {"unlearned_robust": "cauchy", "unlearned_robust_k": 2.0}


@pytest.fixture(scope="module")
def solutions(sim, wls):
    # the simulated errors here are Gaussian: pseudoranges under Cauchy at the Doppler's robust scale (2), not
    # the loss chosen for real logs' multipath and reflections (GraphConfig.unlearned_robust: Geman-McClure at
    # 2), which on Gaussian errors costs efficiency (experiments/robust_scale_clean.py,
    # experiments/results/unlearned_robust.md); test_doppler_helps_at_the_defaults checks the defaults
    return {(d, c): solve(sim.trace, wls, use_doppler=d, use_carrier=c, **GAUSSIAN)
            for d, c in ((False, False), (True, False), (True, True))}


def test_doppler_improves_velocity_and_position(sim, solutions):
    tr = sim.trace
    none, dop = solutions[(False, False)], solutions[(True, False)]
    v_none = np.linalg.norm(none.info["vel"] - sim.rx_vel_mps, axis=1)
    v_dop = np.linalg.norm(dop.info["vel"] - sim.rx_vel_mps, axis=1)
    assert np.median(v_dop) < 0.5 * np.median(v_none)
    assert np.median(v_dop) < 0.3
    assert np.median(pos_err(tr, dop.pos)) < np.median(pos_err(tr, none.pos))
    assert np.percentile(pos_err(tr, dop.pos), 95) < np.percentile(pos_err(tr, none.pos), 95)
    assert dop.info["doppler_factors"] > 5 * tr.n_epochs


def test_doppler_helps_at_the_defaults(sim, wls):
    tr = sim.trace
    none, dop = (solve(tr, wls, use_doppler=d, use_carrier=False) for d in (False, True))
    v_none = np.linalg.norm(none.info["vel"] - sim.rx_vel_mps, axis=1)
    v_dop = np.linalg.norm(dop.info["vel"] - sim.rx_vel_mps, axis=1)
    assert np.median(v_dop) < 0.5 * np.median(v_none)
    assert np.percentile(pos_err(tr, dop.pos), 95) < 0.95 * np.percentile(pos_err(tr, none.pos), 95)


def test_carrier_tightens_further(sim, solutions):
    tr = sim.trace
    dop, both = solutions[(True, False)], solutions[(True, True)]
    assert both.info["tdcp_factors"] > 5 * tr.n_epochs
    assert np.median(pos_err(tr, both.pos)) < 0.7 * np.median(pos_err(tr, dop.pos))
    # consecutive-epoch displacement: what carrier phase measures, to centimetres
    d_err = np.linalg.norm(np.diff(both.pos - tr.truth, axis=0), axis=1)
    d_err_dop = np.linalg.norm(np.diff(dop.pos - tr.truth, axis=0), axis=1)
    assert np.median(d_err) < 0.05 and np.median(d_err) < 0.2 * np.median(d_err_dop)


def test_flagged_slips_with_big_jumps_do_not_corrupt_the_solution(nav, solutions, sim):
    slipping = simulate(n_epochs=200, nav=nav, seed=11,
                        config=dataclasses.replace(RAW, slip_prob=0.1, slip_jump_m=(500.0, 5000.0)))
    tr = slipping.trace
    assert tr.adr_slip.sum() > 0.1 * tr.mask.sum()
    res = solve(tr, solve_initial(tr, RunOptions()))
    clean = pos_err(sim.trace, solutions[(True, True)].pos)
    assert np.percentile(pos_err(tr, res.pos), 95) < 2.0 * np.percentile(clean, 95) + 0.5
    assert np.max(pos_err(tr, res.pos)) < 5.0


def test_an_unflagged_slip_is_held_off_by_the_robust_loss(sim, wls, solutions):
    tr = sim.trace
    k = 120
    s = np.flatnonzero(tr.mask[k] & ~tr.adr_slip[k])[0]
    adr = tr.adr.copy()
    same = tr.sat_id == tr.sat_id[k, s]
    adr[k:][same[k:]] += 50.0                                  # a 50 m jump nobody flagged
    res = solve(dataclasses.replace(tr, adr=adr), wls)
    clean = solutions[(True, True)].pos
    assert np.max(np.linalg.norm(res.pos - clean, axis=1)) < 0.5


def test_batch_and_incremental_agree(sim, wls, solutions):
    inc = solve(sim.trace, wls, use_doppler=True, use_carrier=True, incremental=True, **GAUSSIAN)
    gap = np.linalg.norm(inc.pos - solutions[(True, True)].pos, axis=1)
    # ISAM2 relinearises only past its thresholds, so a few epochs may lag the batch solution
    assert np.median(gap) < 0.05 and np.percentile(gap, 95) < 0.2 and np.max(gap) < 1.0
    assert np.median(np.linalg.norm(inc.info["vel"] - sim.rx_vel_mps, axis=1)) < 0.3


def test_cli_switches():
    on = parse_run_options([])
    off = parse_run_options(["--no-doppler", "--no-carrier"])
    assert (on.use_doppler, on.use_carrier) == (True, True)
    assert (off.use_doppler, off.use_carrier) == (False, False)


def test_relinearised_carrier_factors_agree_with_the_wls_linearisation(sim, wls):
    """GraphConfig.tdcp_relinearise replaces the carrier factors by ones linearised at the solution and
    polishes: same factors, more iterations, and (WLS good to metres here) the same answer to centimetres."""
    # Cauchy on the pseudoranges: a loss that redescends (the default) has optima of its own centimetres apart
    cfg = GraphConfig(use_doppler=False, unlearned_robust="cauchy")
    off = fuse(sim.trace, wls, RunOptions(), cfg=cfg, want_cov=False)
    on = fuse(sim.trace, wls, RunOptions(), cfg=dataclasses.replace(cfg, tdcp_relinearise=True), want_cov=False)
    assert on.info["factors"] == off.info["factors"] and on.info["tdcp_factors"] > 0
    assert on.info["iterations"] > off.info["iterations"]
    assert np.nanmedian(np.linalg.norm(on.pos - off.pos, axis=1)) < 0.02
