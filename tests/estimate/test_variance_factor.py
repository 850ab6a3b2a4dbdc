"""The windowed a-posteriori variance factor and the covariance calibration built on it
(fusion.estimate.variance_factor): it recovers a known noise scale, follows a change of environment,
leaves every position untouched, and metrics.json reports the calibrated sigmas."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.estimate.variance_factor import (DEFAULTS, SigmaCalibration, calibrate_cov, disagreement_var, epoch_chi2,
                                             snapshot_var, whitened_residuals, windowed_factor)
from fusion.geometry import ecef2ned_cov, ecef2ned_vec, geodetic2ecef, line_of_sight, ned2ecef_cov, ned2ecef_vec
from fusion.trace import Trace


def linear_factor(noise_scale: float, rng: np.random.Generator, E: int = 400, n: int = 9, p: int = 4) -> np.ndarray:
    """Per-epoch chi2 and dof of E independent linear least-squares problems y = A x + e with the model
    sigma 1 and the true noise ``noise_scale``; returns the windowed factor (E,)."""
    A = rng.normal(size=(E, n, p))
    y = np.einsum("enp,ep->en", A, rng.normal(size=(E, p))) + noise_scale * rng.normal(size=(E, n))
    x = np.linalg.solve(np.einsum("enp,enq->epq", A, A), np.einsum("enp,en->ep", A, y)[..., None])[..., 0]
    r = y - np.einsum("enp,ep->en", A, x)
    return windowed_factor(np.arange(E, dtype=float), epoch_chi2(r), np.full(E, n - p), window_s=1e6)


def test_variance_factor_recovers_a_known_noise_scale_on_a_linear_problem():
    rng = np.random.default_rng(0)
    assert linear_factor(1.0, rng)[0] == pytest.approx(1.0, rel=0.1)
    assert linear_factor(2.0, rng)[0] == pytest.approx(4.0, rel=0.1)      # sigma 2x the model: 4x in variance


def test_window_follows_a_change_of_environment():
    rng = np.random.default_rng(1)
    E, n = 600, 8
    scale = np.where(np.arange(E) < E // 2, 1.0, 3.0)            # open sky, then a street canyon
    z = scale[:, None] * rng.normal(size=(E, n))
    F = windowed_factor(np.arange(E, dtype=float), epoch_chi2(z), np.full(E, n), window_s=60.0)
    assert np.median(F[:200]) == pytest.approx(1.0, rel=0.2)
    assert np.median(F[400:]) == pytest.approx(9.0, rel=0.2)


def test_window_without_enough_dof_takes_the_trace_factor():
    F = windowed_factor(np.array([0.0, 100.0, 200.0]), np.array([8.0, 8.0, 8.0]), np.array([2, 2, 2]),
                        window_s=10.0, min_dof=5.0)
    assert np.allclose(F, 4.0)


def pseudorange_trace(noise_m: float, sigma_m: float, rng: np.random.Generator, E: int = 300, S: int = 10):
    """A static receiver seen by S satellites scattered over the sky, pseudoranges with a clock and
    Gaussian noise ``noise_m`` while the reported sigma says ``sigma_m``; returns (trace, receiver (E,3))."""
    rx = geodetic2ecef(np.array([[37.4, -122.1, 10.0]]))[0]
    up = rx / np.linalg.norm(rx)
    dirs = rng.normal(size=(E, S, 3)) + 2.0 * up
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
    sat = rx + 2.0e7 * dirs
    pos = np.tile(rx, (E, 1))
    rng_m, _ = line_of_sight(sat, pos)
    pr = rng_m + 1000.0 + noise_m * rng.normal(size=(E, S))
    trace = Trace(t_ms=np.arange(E, dtype=np.int64) * 1000, sat_pos=sat, sat_vel=np.zeros_like(sat), pr=pr,
                  pr_sigma=np.full((E, S), sigma_m), sat_id=np.tile(np.arange(S, dtype=np.int32) + 1001, (E, 1)),
                  signal=np.zeros((E, S), np.int8), mask=np.ones((E, S), bool), clock_reset=np.zeros(E, bool))
    return trace, pos


def test_pseudorange_residuals_at_the_truth_give_the_noise_ratio_squared():
    trace, pos = pseudorange_trace(noise_m=4.0, sigma_m=2.0, rng=np.random.default_rng(2))
    sel = trace.mask.copy()
    z, dof = whitened_residuals(trace, pos, sel, trace.pr_sigma)
    assert (dof == trace.n_slots - 1).all()                      # one clock per epoch
    F = windowed_factor(trace.t_ms / 1000.0, epoch_chi2(z), dof, window_s=1e6)
    assert F[0] == pytest.approx(4.0, rel=0.1)


def test_fitted_epochs_without_a_spare_satellite_count_no_dof():
    """A WLS track's residuals at an epoch of 4 satellites (one signal) are zero by construction: such
    epochs count no dof, so a stretch of them takes the trace's factor instead of a factor of ~0 (which had
    shrunk WLS sigmas to millimetres where the errors were tens of metres)."""
    from fusion.estimate.wls import solve_wls

    trace, _ = pseudorange_trace(noise_m=3.0, sigma_m=3.0, rng=np.random.default_rng(4), E=120)
    few = np.zeros_like(trace.mask)
    few[:, :4] = True
    trace = trace.select_slots(np.where((np.arange(120) >= 60)[:, None], few, trace.mask))
    wls = solve_wls(trace)
    pos, used = np.where(np.asarray(wls.valid)[:, None], wls.pos, np.nan), np.asarray(wls.used, bool)
    assert (used[60:].sum(axis=1) == 4).sum() >= 40         # the rest: a satellite below the mask, unsolved
    z, dof = whitened_residuals(trace, pos, used, trace.pr_sigma, fitted=True)
    assert (dof[:60] == used[:60].sum(axis=1) - 1).all() and (dof[:60] > 3).all() and (dof[60:] == 0).all()
    assert np.nanmax(np.abs(z[60:])) < 1e-3                      # zero residuals: nothing learned from them
    F = windowed_factor(trace.t_ms / 1000.0, epoch_chi2(z), dof, window_s=15.0)
    assert F[60:].min() == pytest.approx(F[0:60].mean(), rel=0.5) and F.min() > 0.2
    _, counted = whitened_residuals(trace, pos, used, trace.pr_sigma)
    four = used[60:].sum(axis=1) == 4
    assert (counted[60:][four] == 3).all()                       # at a given (not fitted) track they count


def test_snapshot_variance_matches_the_least_squares_covariance():
    trace, pos = pseudorange_trace(noise_m=1.0, sigma_m=1.0, rng=np.random.default_rng(3), E=3)
    var = snapshot_var(trace, pos, trace.mask, trace.pr_sigma)
    _, los = line_of_sight(trace.sat_pos[0], pos[0])
    H = np.c_[-los, np.ones(trace.n_slots)]
    want = np.diagonal(ecef2ned_cov(np.linalg.inv(H.T @ H)[:3, :3], pos[0]))
    assert np.allclose(var[0], want)


def test_calibrate_cov_scales_per_axis_and_adds_the_floor():
    pos = geodetic2ecef(np.array([[37.4, -122.1, 10.0]]))
    cov = ned2ecef_cov(np.diag([1.0, 4.0, 9.0])[None], pos)
    cal = SigmaCalibration(a=(1.0, 2.0, 3.0), b=1.0, floor_m=(0.0, 0.0, 1.0))
    out = np.diagonal(ecef2ned_cov(calibrate_cov(cov, pos, np.array([2.0]), cal), pos), axis1=1, axis2=2)
    assert np.allclose(out[0], [2.0, 16.0, 55.0])


def test_disagreement_adds_the_windowed_squared_difference_unscaled():
    pos = geodetic2ecef(np.array([[37.4, -122.1, 10.0]] * 5))
    shift = np.array([[3.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 0.0], [np.nan] * 3, [1.0, 1.0, 2.0]])
    ref = pos - ned2ecef_vec(np.nan_to_num(shift), pos)
    ref[3] = np.nan                                                   # no unlearned solve there
    t = np.arange(5.0)
    dis = disagreement_var(t, pos, ref, window_s=2.0)                 # epochs k-1..k+1
    np.testing.assert_allclose(dis[0], [4.5, 8.0, 0.0], atol=1e-9)    # (9 + 0) / 2, (0 + 16) / 2
    np.testing.assert_allclose(dis[3], [0.5, 0.5, 2.0], atol=1e-9)    # epochs 2 and 4 only
    np.testing.assert_allclose(disagreement_var(t, pos, ref, 100.0)[2], [2.5, 4.25, 1.0], atol=1e-9)
    cov = ned2ecef_cov(np.tile(np.diag([1.0, 4.0, 9.0]), (5, 1, 1)), pos)
    cal = SigmaCalibration(a=(1.0, 2.0, 3.0), b=1.0, floor_m=(0.0, 0.0, 1.0), disagreement=2.0)
    out = np.diagonal(ecef2ned_cov(calibrate_cov(cov, pos, np.full(5, 2.0), cal, dis_var=dis), pos), axis1=1, axis2=2)
    np.testing.assert_allclose(out, [2.0, 16.0, 55.0] + 2.0 * dis)
    off = SigmaCalibration(a=(1.0, 2.0, 3.0), b=1.0, floor_m=(0.0, 0.0, 1.0))
    out = np.diagonal(ecef2ned_cov(calibrate_cov(cov, pos, np.full(5, 2.0), off, dis_var=dis), pos), axis1=1, axis2=2)
    np.testing.assert_allclose(out, np.tile([2.0, 16.0, 55.0], (5, 1)))


@pytest.fixture(scope="module")
def short_trace(shipped_trace_dir):
    from fusion.prepare.load import load_trace
    trace = load_trace(shipped_trace_dir, min_sats=1)
    return trace.select(np.arange(300))


def test_calibration_changes_sigmas_only(short_trace):
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    modes = ["wls", "dnn", "fused-nodnn", "fused"]
    on = run_modes(short_trace, modes, RunOptions())
    off = run_modes(short_trace, modes, RunOptions(sigma_calibration=False))
    for m in modes:
        assert on[m].pos.tobytes() == off[m].pos.tobytes(), m
        assert on[m].valid.tobytes() == off[m].valid.tobytes(), m
        ok = on[m].valid
        assert not np.allclose(on[m].cov[ok], off[m].cov[ok]), m
        assert np.isfinite(on[m].cov[ok]).all(), m
        assert on[m].info["variance_factor_p50"] > 0, m
    assert set(DEFAULTS) == set(modes)


def test_fused_widens_by_its_disagreement_with_the_unlearned_solve(short_trace):
    """The fused mode keeps its first, unlearned solve; a calibration with a disagreement share adds that
    share of the windowed squared difference to the variances and moves no position."""
    from dataclasses import replace
    from fusion.estimate.variance_factor import calibrate_result
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    raw = run_modes(short_trace, ["fused"], RunOptions(sigma_calibration=False))["fused"]
    ref = raw.info["unlearned_pos"]
    assert ref.shape == raw.pos.shape and np.isfinite(ref[raw.valid]).all()
    assert 0 < np.nanmax(np.linalg.norm(raw.pos - ref, axis=1)) < 50.0          # the learned inputs moved it
    sel, sigma, bias = raw.info["pr_noise"]
    cals = {d: replace(DEFAULTS["fused"], disagreement=d) for d in (0.0, 2.0)}
    out = {}
    for d, cal in cals.items():
        r = run_modes(short_trace, ["fused"], RunOptions(sigma_calibration=False))["fused"]
        out[d] = calibrate_result(r, short_trace, "fused", sel, sigma, bias, cal=cal, unlearned=ref)
        assert out[d].pos.tobytes() == raw.pos.tobytes()
    ok = raw.valid
    ned = {d: np.diagonal(ecef2ned_cov(o.cov[ok], o.pos[ok]), axis1=1, axis2=2) for d, o in out.items()}
    dis = disagreement_var(short_trace.t_ms / 1000.0, raw.pos, ref, cals[2.0].window_s)[ok]
    np.testing.assert_allclose(ned[2.0] - ned[0.0], 2.0 * dis, rtol=1e-6, atol=1e-9)


def test_dnn_widens_by_its_disagreement_with_the_wls_it_corrected(short_trace, monkeypatch):
    """The dnn mode keeps the robust WLS positions it corrected; its disagreement share adds that share of the
    windowed squared difference to the variances and moves no position."""
    from dataclasses import replace
    from fusion.modes import run_modes, solve_initial
    from fusion.run_types import RunOptions
    from learned.modes import fault_screen
    mask = short_trace.mask.copy()
    mask[10, np.flatnonzero(mask[10])[2:]] = False                  # two satellites: no WLS there
    trace = replace(short_trace, mask=mask)
    raw = run_modes(trace, ["dnn"], RunOptions(sigma_calibration=False))["dnn"]
    ref, ok = raw.info["unlearned_pos"], raw.valid
    wls = solve_initial(trace, RunOptions())
    np.testing.assert_array_equal(ref[ok], fault_screen(trace, wls, RunOptions())[1][ok])   # its guess
    assert not wls.valid[10] and np.isnan(ref[10]).all()
    assert 0 < np.nanmax(np.linalg.norm(raw.pos[ok] - ref[ok], axis=1)) < 50.0
    h = np.linalg.norm(ecef2ned_vec(raw.pos[ok] - ref[ok], raw.pos[ok])[:, :2], axis=1)      # what the run says
    assert raw.info["learned_move_h_p50_m"] == pytest.approx(np.median(h))
    assert raw.info["learned_move_h_p95_m"] == pytest.approx(np.percentile(h, 95))
    out = {}
    for d in (0.0, 0.5):
        monkeypatch.setitem(DEFAULTS, "dnn", replace(DEFAULTS["dnn"], disagreement=d))
        out[d] = run_modes(trace, ["dnn"], RunOptions())["dnn"]
        assert out[d].pos.tobytes() == raw.pos.tobytes()
    ned = {d: np.diagonal(ecef2ned_cov(o.cov[ok], o.pos[ok]), axis1=1, axis2=2) for d, o in out.items()}
    dis = disagreement_var(trace.t_ms / 1000.0, np.where(ok[:, None], raw.pos, np.nan), ref,
                           DEFAULTS["dnn"].window_s)[ok]
    np.testing.assert_allclose(ned[0.5] - ned[0.0], 0.5 * dis, rtol=1e-6, atol=1e-9)


def test_metrics_json_reports_the_calibrated_sigmas(short_trace, tmp_path):
    from fusion.eval.metrics import mode_metrics, trace_errors, within_sigma
    from fusion.io.estimates import write_outputs
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    on = run_modes(short_trace, ["fused-nodnn"], RunOptions())["fused-nodnn"]
    off = run_modes(short_trace, ["fused-nodnn"], RunOptions(sigma_calibration=False))["fused-nodnn"]
    write_outputs(tmp_path / "fused-nodnn", short_trace, "fused-nodnn", on, mode_metrics(short_trace, on))
    text = (tmp_path / "fused-nodnn" / "metrics.json").read_text()
    err = trace_errors(short_trace, on)
    want = within_sigma(err, np.where(on.valid[:, None], on.pos, np.nan), on.cov)
    raw = within_sigma(err, np.where(off.valid[:, None], off.pos, np.nan), off.cov)
    got = json.loads(text)
    for k in ("within1sigma_n", "within1sigma_e", "within1sigma_d", "within2sigma_d"):
        assert got["metrics"][k] == pytest.approx(want[k]), k
    assert want["within1sigma_d"] != raw["within1sigma_d"]      # the calibration moved what is reported
    assert got["info"]["variance_factor_p50"] == pytest.approx(on.info["variance_factor_p50"])


def test_raw_sigmas_flag_switches_the_calibration_off():
    from tests.run_options import parse_run_options

    assert parse_run_options([]).sigma_calibration is True
    assert parse_run_options(["--raw-sigmas"]).sigma_calibration is False


def test_conditioning_screen_decides_as_the_svd():
    """well_conditioned settles most epochs by trace^n / det and agrees with np.linalg.cond everywhere,
    near-singular, singular and badly scaled matrices included."""
    from fusion.estimate.variance_factor import well_conditioned

    rng = np.random.default_rng(0)
    for n in (4, 5, 7):
        for scale in (1e-9, 1.0, 1e6):
            q, _ = np.linalg.qr(rng.normal(size=(2000, n, n)))
            ev = np.exp(rng.uniform(0.0, np.log(1e14), (2000, n))) * scale
            ev[:, 0] = ev[:, 1:].max(1) / 10 ** rng.uniform(9.0, 15.0, 2000)      # around the 1e12 limit
            N = np.einsum("kij,kj,klj->kil", q, ev, q)
            N = (N + N.transpose(0, 2, 1)) / 2
            N[::40] = 0.0
            assert np.array_equal(well_conditioned(N, 1e12), np.linalg.cond(N) < 1e12)
    assert well_conditioned(np.zeros((0, 4, 4)), 1e12).shape == (0,)


def test_only_least_squares_positions_count_as_fitted():
    from fusion.estimate.variance_factor import fitted_positions

    assert fitted_positions("wls", {}) and fitted_positions("dnn", {"output": "wls"})
    assert not fitted_positions("dnn", {"output": "correction"})       # WLS plus the paper's correction
    assert not fitted_positions("fused", {}) and not fitted_positions("fused-nodnn", {})


def test_carrier_tied_epochs_take_the_carrier_setting_and_the_others_keep_theirs(short_trace):
    """calibrate_graph: the epochs ``info["carrier_linked"]`` marks get the mode's CARRIER_DEFAULTS, the rest what
    DEFAULTS gives them; a trace without carrier, or a run with ``carrier_sigma_calibration`` off, is calibrated as
    before, and nothing moves a position."""
    from dataclasses import replace
    from fusion.estimate.variance_factor import CARRIER_DEFAULTS, calibrate_graph, calibrate_result, wls_track
    from fusion.modes import run_modes, solve_initial
    from fusion.run_types import RunOptions
    opts = RunOptions()
    wls = solve_initial(short_trace, opts)
    raw = run_modes(short_trace, ["fused"], RunOptions(sigma_calibration=False), wls=wls)["fused"]
    linked = np.zeros(short_trace.n_epochs, bool)
    linked[100:200] = True
    fresh = lambda tied: replace(raw, cov=raw.cov.copy(), info=dict(raw.info, carrier_linked=tied))  # noqa: E731
    args = (short_trace, "fused", *raw.info["pr_noise"])
    track = wls_track(short_trace, wls, opts.elev_mask_deg)
    want = {name: calibrate_result(fresh(linked), *args, cal=cal, wls=track, unlearned=raw.info["unlearned_pos"]).cov
            for name, cal in (("default", DEFAULTS["fused"]), ("carrier", CARRIER_DEFAULTS["fused"]))}
    got = calibrate_graph(fresh(linked), short_trace, "fused", opts, wls)
    ok = raw.valid
    assert got.pos.tobytes() == raw.pos.tobytes()
    np.testing.assert_allclose(got.cov[ok & linked], want["carrier"][ok & linked])
    np.testing.assert_allclose(got.cov[ok & ~linked], want["default"][ok & ~linked])
    assert not np.allclose(want["carrier"][ok & linked], want["default"][ok & linked])
    assert got.info["carrier_calibrated"] == int((ok & linked).sum())
    none = calibrate_graph(fresh(np.zeros_like(linked)), short_trace, "fused", opts, wls)
    np.testing.assert_array_equal(none.cov, want["default"])
    assert "carrier_calibrated" not in none.info
    general = calibrate_graph(fresh(linked), short_trace, "fused", replace(opts, carrier_sigma_calibration=False), wls)
    np.testing.assert_array_equal(general.cov, want["default"])             # the switch: every epoch the general
    assert "carrier_calibrated" not in general.info
    assert "fused-nodnn" not in CARRIER_DEFAULTS               # its own setting gained nothing on the tuning traces
