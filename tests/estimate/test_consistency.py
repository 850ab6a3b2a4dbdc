"""The Doppler / carrier sigma check: each kind's robust residual scale in its own one-epoch fits, windowed,
raises sigmas that are too small and leaves honest or cautious ones alone."""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.consistency import epoch_fit, kind_scale, row_medians, windowed_scale
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate


def geometry(E: int, S: int, seed: int):
    """Random line-of-sight gradients (E,S,3) above the horizon, unknowns (E,4) and exact measurements (E,S)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(E, S, 3))
    u[..., 2] = np.abs(u[..., 2])
    grad = -u / np.linalg.norm(u, axis=2, keepdims=True)
    x = rng.normal(0.0, 5.0, (E, 4))
    b = np.einsum("esi,ei->es", grad, x[:, :3]) + x[:, 3:]
    return rng, grad, b


def scale_of(noise_sigma: float, stated: float = 0.1, E: int = 300, S: int = 10, seed: int = 0,
             outliers: float = 0.0) -> np.ndarray:
    rng, grad, b = geometry(E, S, seed)
    b = b + rng.normal(0.0, noise_sigma, (E, S))
    bad = rng.random((E, S)) < outliers
    b = b + np.where(bad, 30.0 * stated * rng.choice([-1.0, 1.0], (E, S)), 0.0)
    t = np.arange(E, dtype=float)
    return kind_scale(grad, b, np.full((E, S), stated), np.ones((E, S), bool), t, window_s=60.0)


def test_row_medians_are_numpys_nanmedian():
    x = np.random.default_rng(2).normal(size=(50, 9))
    x[np.random.default_rng(3).random(x.shape) < 0.3] = np.nan
    x[7] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # the all-NaN row
        np.testing.assert_allclose(row_medians(x), np.nanmedian(x, axis=1), equal_nan=True)


def test_exact_measurements_leave_the_sigmas_alone():
    _, grad, b = geometry(50, 8, 1)
    z = epoch_fit(grad, b, np.full(b.shape, 0.1), np.ones(b.shape, bool))
    assert np.isfinite(z).all() and np.abs(z).max() < 1e-6
    np.testing.assert_array_equal(scale_of(0.0), 1.0)


def test_noise_beyond_the_stated_sigma_is_measured():
    s = scale_of(0.3, stated=0.1)               # three times what the file says
    assert 2.6 < np.median(s) < 3.4 and s.min() > 2.3


def test_honest_or_cautious_sigmas_are_never_lowered():
    assert np.median(scale_of(0.1)) < 1.15
    np.testing.assert_array_equal(scale_of(0.03), 1.0)


def test_a_minority_of_gross_errors_does_not_set_the_scale():
    # the robust losses down-weight them; the check is about the bulk
    assert np.median(scale_of(0.1, outliers=0.05)) < 1.3


def test_the_window_follows_a_change_of_environment():
    rng, grad, b = geometry(400, 10, 3)
    noise = np.where(np.arange(400)[:, None] < 200, 0.4, 0.1)
    b = b + rng.normal(0.0, 1.0, b.shape) * noise
    s = kind_scale(grad, b, np.full(b.shape, 0.1), np.ones(b.shape, bool), np.arange(400.0), window_s=60.0)
    assert 3.3 < np.median(s[:150]) < 4.7
    assert np.median(s[250:]) < 1.15


def test_epochs_without_spare_measurements_take_the_window_or_trace_value():
    _, grad, b = geometry(40, 10, 4)
    use = np.ones(b.shape, bool)
    use[10, 5:] = False                          # five measurements: one spare, not enough
    z = epoch_fit(grad, b + 0.3 * np.random.default_rng(0).normal(size=b.shape), np.full(b.shape, 0.1), use)
    assert np.isnan(z[10]).all() and np.isfinite(np.delete(z, 10, axis=0)).all()
    s = windowed_scale(z, 60)
    assert np.isfinite(s).all() and s[10] > 2
    np.testing.assert_array_equal(windowed_scale(np.full((5, 4), np.nan), 60), 1.0)


@pytest.fixture(scope="module")
def raw_sim():
    return simulate(n_epochs=150, nav=read_rinex_nav(default_nav_path()), seed=7,
                    config=SimConfig(doppler=True, carrier=True, slip_prob=0.0))


def test_the_graph_inputs_raise_understated_doppler_sigmas(raw_sim):
    trace = raw_sim.trace
    wls = solve_initial(trace, RunOptions())
    honest = prepare_inputs(trace, wls, GraphConfig())
    low = dataclasses.replace(trace, prr_sigma=trace.prr_sigma / 10)
    off = prepare_inputs(low, wls, GraphConfig(doppler_check_window_s=0.0))
    checked = prepare_inputs(low, wls, GraphConfig())
    dop = checked.raw.doppler
    # as simulated, the stated sigmas are the noise's: (nearly) nothing to raise
    assert honest.dropped["doppler_sigmas_raised"] < 0.1 * dop.sum()
    # stated ten times too small: raised back to about the simulated noise
    assert "doppler_sigmas_raised" not in off.dropped
    assert checked.dropped["doppler_sigmas_raised"] == dop.sum()
    ratio = np.median(checked.raw.prr_sigma[dop]) / np.median(honest.raw.prr_sigma[dop])
    assert 0.7 < ratio < 1.3


def test_the_graph_inputs_raise_carrier_sigmas_below_the_carriers_noise(raw_sim):
    trace = raw_sim.trace
    wls = solve_initial(trace, RunOptions())
    cfg = GraphConfig(carrier_check_window_s=60.0)
    honest = prepare_inputs(trace, wls, cfg)
    tdcp = honest.raw.tdcp_prev >= 0
    # the simulated carrier noise is under the graph's 2 cm floor: nothing to raise
    assert honest.dropped["carrier_sigmas_raised"] == 0
    # 10 cm of multipath on every phase (14 cm on a difference) against the ~2 cm the sigmas say
    rng = np.random.default_rng(0)
    noisy = dataclasses.replace(trace, adr=trace.adr + np.where(trace.adr_ok, rng.normal(0.0, 0.1, trace.adr.shape), 0.0))
    checked = prepare_inputs(noisy, wls, cfg)
    assert checked.dropped["carrier_sigmas_raised"] == tdcp.sum()
    assert 4 < np.median(checked.raw.tdcp_sigma[tdcp]) / np.median(honest.raw.tdcp_sigma[tdcp]) < 9
    # off by default (experiments/results/raw_sigma_check.md)
    default = prepare_inputs(noisy, wls, GraphConfig())
    assert "carrier_sigmas_raised" not in default.dropped
    np.testing.assert_array_equal(default.raw.tdcp_sigma, honest.raw.tdcp_sigma)


def test_a_clock_per_group_is_fitted_and_counted_as_unknowns():
    rng, grad, b = geometry(60, 10, 5)
    groups = np.tile(np.r_[np.zeros(6, int), np.full(4, 3)], (60, 1))     # two signals, as GPS L1 and L5
    b = b + np.where(groups == 3, 250.0, 0.0)                               # an inter-signal offset
    stated = np.full(b.shape, 0.1)
    use = np.ones(b.shape, bool)
    one_clock = epoch_fit(grad, b, stated, use)
    per_group = epoch_fit(grad, b, stated, use, groups)
    assert np.nanmax(np.abs(one_clock)) > 100 and np.nanmax(np.abs(per_group)) < 1e-5
    use[0, :4] = False          # 6 measurements, 5 unknowns: one spare, not enough
    assert np.isnan(epoch_fit(grad, b, stated, use, groups)[0]).all()
    assert np.isfinite(epoch_fit(grad, b, stated, use)[0][4:]).all()   # one clock: 4 unknowns, enough


def test_the_graph_inputs_raise_understated_pseudorange_sigmas_when_asked(raw_sim):
    trace = raw_sim.trace
    wls = solve_initial(trace, RunOptions())
    cfg = GraphConfig(pseudorange_check_window_s=60.0)
    honest = prepare_inputs(trace, wls, cfg)
    # the physical model's sigmas are at least the simulated noise: nothing much to raise
    assert honest.dropped["pseudorange_sigmas_raised"] < 0.1 * honest.sel.sum()
    rng = np.random.default_rng(1)
    noisy = dataclasses.replace(trace, pr=trace.pr + np.where(trace.mask, rng.normal(0.0, 15.0, trace.pr.shape), 0.0))
    checked = prepare_inputs(noisy, wls, cfg)
    off = prepare_inputs(noisy, wls, GraphConfig())
    assert "pseudorange_sigmas_raised" not in off.dropped           # off by default
    assert checked.dropped["pseudorange_sigmas_raised"] == checked.sel.sum()
    ratio = checked.sigma[checked.sel] / off.sigma[checked.sel]
    assert ratio.min() > 1.5
    # one factor per epoch: the ratios between satellites are kept
    per_epoch = np.where(checked.sel, checked.sigma / off.sigma, np.nan)
    assert np.nanmax(np.nanmax(per_epoch, axis=1) - np.nanmin(per_epoch, axis=1)) < 1e-9
