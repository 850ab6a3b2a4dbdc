"""Simulator: trajectories, measurement model, output format, CLI and bad input."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from fusion.errors import DataError, GeometryError
from fusion.geometry import ecef2geodetic, ecef2ned_vec, line_of_sight
from fusion.gpstime import gps_ms_from_calendar
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.cli.simulate import main
from fusion.io.gsdc_write import write_gsdc2021
from fusion.sim.simulate import DEFAULT_START_MS, SimConfig, simulate, simulate_dataset, simulate_trajectory
from fusion.sim.trajectory import (GSDC2021_HEIGHT_ERROR_M, Trajectory, load_gsdc_trajectory, random_ne_path, random_trajectory)


@pytest.fixture(scope="module")
def nav():
    return read_rinex_nav(default_nav_path())


def _gauss_newton(tr, x0):
    """Plain least squares on the Trace model (stand-in independent of fusion.estimate.wls)."""
    x = np.concatenate([x0, np.zeros((len(x0), 1))], axis=1)
    for _ in range(8):
        rng, los = line_of_sight(tr.sat_pos, x[:, :3])
        res = np.where(tr.mask, tr.pr - rng - x[:, 3:4], 0.0)
        G = np.concatenate([-los, np.ones(rng.shape + (1,))], axis=-1) * tr.mask[..., None]
        N = np.einsum("esi,esj->eij", G, G)
        x = x + np.linalg.solve(N, np.einsum("esi,es->ei", G, res)[..., None])[..., 0]
    return x, np.linalg.inv(N)


# ------------------------------------------------------------------------------ trajectories
def test_random_path_is_a_smooth_car_drive():
    for seed in range(20):
        ne, speed = random_ne_path(300, 1.0, np.random.default_rng(seed))
        assert ne.shape == (301, 2) and np.all(speed <= 30.0 + 1e-6)
        acc = np.linalg.norm(np.diff(ne, n=2, axis=0), axis=1)      # 1 s steps
        assert acc.max() < 4.5
    ne, _ = random_ne_path(10, 10.0, np.random.default_rng(0))
    assert ne.shape == (101, 2)
    a, _ = random_ne_path(60, 1.0, np.random.default_rng(5))
    b, _ = random_ne_path(60, 1.0, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert np.abs(a).max() > 20.0   # it does move


def test_random_trajectory_is_horizontal_anywhere():
    for lat, lon in [(37.4, -122.1), (-77.8, 166.7), (0.0, 180.0), (64.1, -21.9)]:
        tr = random_trajectory((lat, lon, 120.0), 200, DEFAULT_START_MS, np.random.default_rng(1))
        llh = ecef2geodetic(tr.ecef)
        np.testing.assert_allclose(llh[:, 2], 120.0, atol=1e-6)
        np.testing.assert_allclose(llh[0, :2], [lat, lon], atol=1e-9)
        assert np.all(np.diff(tr.t_ms) == 1000)
        step = np.linalg.norm(np.diff(tr.ecef, axis=0), axis=1)
        assert step.max() <= 30.0 + 1e-3


def test_replay_gsdc_ground_truth(tmp_path):
    p = tmp_path / "2020-05-14-US-MTV-2" / "Pixel4" / "ground_truth.csv"
    p.parent.mkdir(parents=True)
    p.write_text(
        "collectionName,phoneName,millisSinceGpsEpoch,latDeg,lngDeg,heightAboveWgs84EllipsoidM\n"
        "c,Pixel4,1000,37.0,-122.0,70.0\nc,Pixel4,2000,37.0001,-122.0,70.0\n"
        "c,Pixel4,2000,37.0001,-122.0,70.0\nc,Pixel4,3000,37.0002,-122.0,nan\nc,Pixel4,4000,37.0003,-122.0,70.0\n")
    tr = load_gsdc_trajectory(p)
    np.testing.assert_array_equal(tr.t_ms, [1000, 2000, 4000])
    np.testing.assert_allclose(ecef2geodetic(tr.ecef)[:, 2], 70.0 - GSDC2021_HEIGHT_ERROR_M, atol=1e-6)
    assert tr.name == "2020-05-14-US-MTV-2/Pixel4"
    assert tr.skipped == {"truth_rows_unreadable": 1, "truth_rows_not_increasing": 1}
    np.testing.assert_allclose(ecef2geodetic(load_gsdc_trajectory(p, height_error_m=0).ecef)[:, 2], 70.0, atol=1e-6)
    assert tr.retimed(DEFAULT_START_MS).t_ms[-1] == DEFAULT_START_MS + 3000
    bad = tmp_path / "bad.csv"
    bad.write_text("millisSinceGpsEpoch,latDeg\n1,2\n")
    with pytest.raises(DataError, match="missing column"):
        load_gsdc_trajectory(bad)


def test_replay_real_track(shared_data, nav):
    gt = shared_data / "gsdc2021/trajectories/2020-05-14-US-MTV-2/Pixel4/ground_truth.csv"
    tr = load_gsdc_trajectory(gt).retimed(DEFAULT_START_MS)
    tr = Trajectory(tr.t_ms[:300], tr.ecef[:300], tr.name)
    res = simulate_trajectory(tr, nav=nav, seed=0)
    assert res.trace.n_epochs == 300
    np.testing.assert_allclose(res.trace.truth, tr.ecef)
    assert ecef2geodetic(tr.ecef)[:, 2].max() < 20.0    # heights back near the Bay's shore


# ------------------------------------------------------------------------------ measurement model
def test_noise_free_measurements_give_the_truth(nav):
    res = simulate(n_epochs=120, nav=nav, seed=3, config=SimConfig(sigma_m=0.0))
    tr = res.trace
    x, _ = _gauss_newton(tr, tr.truth + 500.0)
    assert np.abs(x[:, :3] - tr.truth).max() < 1e-4
    assert np.abs(x[:, 3] - res.clock_m).max() < 1e-4


def test_noise_free_through_solve_wls(nav):
    from fusion.estimate import wls

    res = simulate((-33.9, 151.2, 50.0), n_epochs=100, nav=nav, seed=4, config=SimConfig(sigma_m=0.0))
    out = wls.solve_wls(res.trace, elev_mask_deg=5.0)
    assert out.valid.all()
    assert np.abs(out.pos - res.trace.truth).max() < 0.01
    assert np.abs(out.clock_m - res.clock_m).max() < 0.01
    # Default noise (6 m): solve_wls errors have the DOP-predicted size.
    noisy = simulate(n_epochs=1500, nav=nav, seed=14)
    out = wls.solve_wls(noisy.trace, elev_mask_deg=5.0, weighting="uncertainty")
    _, Ninv = _gauss_newton(noisy.trace, noisy.trace.truth)
    z = (out.pos - noisy.trace.truth) / (6.0 * np.sqrt(np.einsum("eii->ei", Ninv)[:, :3]))
    print(f"\nsolve_wls normalised error std per ECEF axis: {np.round(z.std(axis=0), 3)} (expect 1)")
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.1)


def test_model_decomposition_and_sat_selection(nav):
    cfg = SimConfig(nlos=True)
    res = simulate(n_epochs=400, nav=nav, seed=5, config=cfg)
    tr = res.trace
    m = tr.mask
    rng, _ = line_of_sight(tr.sat_pos, tr.truth)
    resid = tr.pr - rng - res.clock_m[:, None] - res.noise_m - res.bias_m
    assert np.abs(resid[m]).max() < 1e-6
    assert np.all(tr.n_sats >= 4) and np.all(tr.n_sats <= 10)
    assert np.all(res.elev_deg[m] >= cfg.elev_mask_deg)
    assert np.all(tr.pr_sigma[m] == 6.0)
    assert np.all(tr.sat_id[m] // 1000 == 1)
    ids = np.where(m, tr.sat_id, 10**6)
    assert np.all(np.diff(ids, axis=1) > 0)                      # distinct, sorted by PRN
    # NLOS: Poisson(1) biased satellites per epoch, each U[50, 200] m, never on padding.
    nb = (res.bias_m != 0).sum(axis=1)
    assert 0.85 < nb.mean() < 1.15 and np.all(res.bias_m[~m] == 0)
    b = res.bias_m[res.bias_m != 0]
    assert b.min() >= 50.0 and b.max() <= 200.0
    # Noise sigma 6 m: empirical std within sampling error.
    assert abs(res.noise_m[m].std() - 6.0) < 0.3
    # Clock: random walk with drift, continuous (no jumps larger than drift + noise).
    assert np.abs(np.diff(res.clock_m, n=2)).max() < 2.0


def test_all_visible_are_used_without_cap(nav):
    capped = simulate(n_epochs=50, nav=nav, seed=6, config=SimConfig(max_sats=7))
    full = simulate(n_epochs=50, nav=nav, seed=6, config=SimConfig(max_sats=None))
    assert full.trace.n_sats.min() > 7 >= capped.trace.n_sats.max()
    # Same trajectory: the capped set is a random subset of the visible set.
    np.testing.assert_array_equal(capped.trace.n_sats, np.minimum(full.trace.n_sats, 7))
    vis = set(map(tuple, np.argwhere(full.trace.mask)))
    ids_full = {(e, i) for e, row in enumerate(full.trace.sat_id) for i in row if i}
    ids_cap = {(e, i) for e, row in enumerate(capped.trace.sat_id) for i in row if i}
    assert ids_cap < ids_full and len(vis) == len(ids_full)
    # Which satellites are dropped varies from epoch to epoch (random subset, not the lowest PRNs).
    assert len({tuple(r) for r in capped.trace.sat_id}) > 5


def test_error_matches_dop(nav):
    """WLS error std per axis equals sigma * sqrt(diag((G^T G)^-1)) (the DOP prediction)."""
    res = simulate(n_epochs=2000, nav=nav, seed=7, rate_hz=1.0)
    tr = res.trace
    x, Ninv = _gauss_newton(tr, tr.truth + 100.0)
    z = (x[:, :3] - tr.truth) / (6.0 * np.sqrt(np.einsum("eii->ei", Ninv)[:, :3]))
    print(f"\nnormalised WLS error std per ECEF axis: {np.round(z.std(axis=0), 3)} (expect 1)")
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.08)
    assert np.abs(z.mean(axis=0)).max() < 0.08


def test_elevation_dependent_noise(nav):
    res = simulate(n_epochs=300, nav=nav, seed=8, config=SimConfig(sigma_m=2.0, elevation_noise=True))
    m = res.trace.mask
    expect = 2.0 / np.sin(np.radians(res.elev_deg[m]))
    np.testing.assert_allclose(res.trace.pr_sigma[m], expect, rtol=1e-9)
    assert abs((res.noise_m[m] / expect).std() - 1.0) < 0.05


def test_seeded_and_deterministic(nav):
    a = simulate(n_epochs=30, nav=nav, seed=11, config=SimConfig(nlos=True))
    b = simulate(n_epochs=30, nav=nav, seed=11, config=SimConfig(nlos=True))
    c = simulate(n_epochs=30, nav=nav, seed=12, config=SimConfig(nlos=True))
    np.testing.assert_array_equal(a.trace.pr, b.trace.pr)
    np.testing.assert_array_equal(a.trace.truth, b.trace.truth)
    assert not np.array_equal(a.trace.truth, c.trace.truth)
    g = np.random.default_rng(11)
    d = simulate(n_epochs=30, nav=nav, seed=g, config=SimConfig(nlos=True))
    np.testing.assert_array_equal(a.trace.pr, d.trace.pr)


def test_dataset_many_origins(nav):
    traces = simulate_dataset(20, 15, seed=0, nav=nav)
    assert len(traces) == 20
    origins = np.array([ecef2geodetic(t.truth[0]) for t in traces])
    assert np.ptp(origins[:, 0]) > 30 and np.ptp(origins[:, 1]) > 60   # spread over the globe
    assert all(t.n_epochs + t.skipped.get("sim_too_few_visible_sats", 0) == 15 for t in traces)
    again = simulate_dataset(20, 15, seed=0, nav=nav)
    for a, b in zip(traces, again):
        np.testing.assert_array_equal(a.pr, b.pr)
    # Each trace is internally consistent (noise only): truth reproduces pr up to the clock.
    for t in traces[:5]:
        x, _ = _gauss_newton(t, t.truth + 50.0)
        assert np.abs(x[:, :3] - t.truth).max() < 200.0
    fixed = simulate_dataset(3, 10, origins=[(10.0, 20.0), (-40.0, -70.0, 300.0)], seed=1, nav=nav)
    np.testing.assert_allclose(ecef2geodetic(fixed[2].truth[0])[:2], [10.0, 20.0], atol=1e-9)
    one = simulate_dataset(4, 10, seed=2, nav=nav, concatenate=True)
    assert one.n_epochs == 40 and one.clock_reset.sum() == 3 and np.all(np.diff(one.t_ms) > 0)
    # a trace boundary stays flagged when that trace's first epochs are dropped (too few satellites)
    from fusion.sim.simulate import SimConfig
    high = simulate_dataset(6, 60, seed=12, nav=nav, config=SimConfig(elev_mask_deg=38), concatenate=True)
    clock = high.pr[:, 0] - np.linalg.norm(high.sat_pos[:, 0] - high.truth, axis=1)   # ~ receiver clock
    jumps = np.abs(np.diff(clock)) > 500.0
    assert jumps.any() and np.all(high.clock_reset[1:][jumps])


# ------------------------------------------------------------------------------ bad input
def test_time_outside_nav_validity(nav):
    late = gps_ms_from_calendar(2021, 5, 10, 12, 0, 0.0)
    with pytest.raises(DataError, match=r"outside the validity of the navigation file.*hour1180\.21n|hour1180\.21n.*outside"):
        simulate(n_epochs=5, start_ms=late, nav=nav)
    # A trajectory running off the end of the file is refused up front, naming the epoch.
    lo, hi = nav.span_ms()
    with pytest.raises(DataError, match="epoch"):
        simulate(n_epochs=4000, start_ms=hi - 1_000_000, nav=nav)


def test_too_few_satellites(nav):
    with pytest.raises(GeometryError, match="fewer than 4 GPS satellites"):
        simulate(n_epochs=5, nav=nav, config=SimConfig(elev_mask_deg=80.0))
    # Partly too few: those epochs are skipped and counted, the rest kept.
    # 100 minutes at 0.1 Hz: the visible count changes; require the largest count seen.
    kw = dict(n_epochs=600, rate_hz=0.1, nav=nav, seed=9)
    base = simulate(**kw, config=SimConfig(max_sats=None))
    n_vis = base.trace.n_sats
    need = int(n_vis.max())
    assert 0 < (n_vis < need).sum() < n_vis.size
    part = simulate(**kw, config=SimConfig(max_sats=None, min_sats=need))
    assert part.trace.n_epochs == (n_vis >= need).sum()
    assert part.trace.skipped["sim_too_few_visible_sats"] == (n_vis < need).sum()
    np.testing.assert_array_equal(part.trace.t_ms, base.trace.t_ms[n_vis >= need])


def test_bad_config():
    with pytest.raises(ValueError):
        SimConfig(sigma_m=-1).validate()
    with pytest.raises(ValueError):
        SimConfig(max_sats=3).validate()



def test_dataset_bad_rate_is_a_value_error(nav):
    """Regression: rate_hz=0 raised ZeroDivisionError before the rate was validated."""
    for rate in (0, 0.0, -1.0, 3.0):   # 3 Hz: 333.33 ms per epoch is not a whole number
        with pytest.raises(ValueError, match="rate_hz"):
            simulate_dataset(2, 5, seed=0, nav=nav, rate_hz=rate)


# ------------------------------------------------------------------------------ output + CLI
def test_gsdc2021_files_round_trip(tmp_path, nav):
    res = simulate(n_epochs=40, nav=nav, seed=10, config=SimConfig(nlos=True))
    tr = res.trace
    d_path, g_path = write_gsdc2021(res, tmp_path, "2021-04-28-US-SIM-1", "SimPhone")
    assert d_path == tmp_path / "2021-04-28-US-SIM-1/SimPhone/SimPhone_derived.csv"
    df = pd.read_csv(d_path)
    assert len(df) == tr.mask.sum()
    e, s = np.nonzero(tr.mask)
    np.testing.assert_array_equal(df.millisSinceGpsEpoch, tr.t_ms[e] + 1000)   # one second late
    pr = df.rawPrM + df.satClkBiasM - df.isrbM - df.ionoDelayM - df.tropoDelayM
    np.testing.assert_allclose(pr, tr.pr[e, s], atol=1.5e-3)
    assert (df.ionoDelayM > 0).all() and (df.tropoDelayM > 0).all() and df.satClkBiasM.abs().max() > 100
    # Receive time on the receiver clock = transmit time (satellite clock) + raw range / c.
    # (integer ns differences first: a float GPS-ms count resolves only ~0.2 us.)
    rx_rel_ms = (df.receivedSvTimeInGpsNanos.to_numpy() - tr.t_ms[e] * 1_000_000) / 1e6 \
        + df.rawPrM.to_numpy() / 299_792.458
    extra_m = res.clock_m[e] + res.noise_m[e, s] + res.bias_m[e, s] + df.ionoDelayM + df.tropoDelayM
    np.testing.assert_allclose(rx_rel_ms, extra_m / 299_792.458, atol=1e-5)
    gt = pd.read_csv(g_path)
    h = ecef2geodetic(tr.truth)[:, 2]
    np.testing.assert_allclose(gt.heightAboveWgs84EllipsoidM, h + GSDC2021_HEIGHT_ERROR_M, atol=1e-4)
    v_ned = ecef2ned_vec(np.gradient(tr.truth, axis=0), tr.truth)
    np.testing.assert_allclose(gt.speedMps, np.hypot(v_ned[:, 0], v_ned[:, 1]), atol=2e-3)


def test_round_trip_through_load_trace(tmp_path, nav):
    from fusion.prepare import load as io

    res = simulate(n_epochs=40, nav=nav, seed=13, config=SimConfig(nlos=True))
    a = res.trace
    d_path, _ = write_gsdc2021(res, tmp_path, "2021-04-28-US-SIM-13")
    b = io.load_trace(d_path.parent, fix_truth_height=True)
    np.testing.assert_array_equal(b.t_ms, a.t_ms)
    np.testing.assert_array_equal(b.mask, a.mask)
    np.testing.assert_array_equal(b.sat_id, a.sat_id)
    np.testing.assert_allclose(b.pr[b.mask], a.pr[a.mask], atol=1.5e-3)
    np.testing.assert_allclose(b.sat_pos[b.mask], a.sat_pos[a.mask], atol=1e-3)
    np.testing.assert_allclose(b.truth, a.truth, atol=1e-3)
    np.testing.assert_allclose(b.pr_sigma[b.mask], a.pr_sigma[a.mask], atol=1e-3)


def test_cli(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--epochs", "20", "--seed", "3", "--bias-scenario"]) == 0
    out = capsys.readouterr().out
    assert "simulated 20 epochs" in out
    files = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.csv"))
    assert files == ["2021-04-28-US-SIM-3/SimPhone/SimPhone_derived.csv", "2021-04-28-US-SIM-3/SimPhone/ground_truth.csv"]
    gt = pd.read_csv(tmp_path / files[1])
    np.testing.assert_allclose(gt.latDeg.iloc[0], 37.3958, atol=1e-9)
    assert main(["--out", str(tmp_path / "b"), "--origin", "48.1,11.6,520", "--epochs", "5",
                 "--start", "2021-04-28T06:00:00", "--collection", "x", "--phone", "P"]) == 0
    gt = pd.read_csv(tmp_path / "b/x/P/ground_truth.csv")
    assert gt.millisSinceGpsEpoch.iloc[0] == gps_ms_from_calendar(2021, 4, 28, 6, 0, 0.0)
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--origin", "91,0"])
    # Replay a (tiny) GSDC 2021 truth track: all of it, heights fixed, re-timed to --start.
    track = tmp_path / "track.csv"
    track.write_text("millisSinceGpsEpoch,latDeg,lngDeg,heightAboveWgs84EllipsoidM\n"
                     + "".join(f"{1273538830442 + 1000 * k},37.69,{-122.39 + 1e-4 * k},35.0\n" for k in range(7)))
    assert main(["--out", str(tmp_path / "r"), "--trajectory", str(track), "--collection", "rp"]) == 0
    gt = pd.read_csv(tmp_path / "r/rp/SimPhone/ground_truth.csv")
    assert len(gt) == 7 and gt.millisSinceGpsEpoch.iloc[0] == DEFAULT_START_MS
    np.testing.assert_allclose(gt.heightAboveWgs84EllipsoidM, 35.0, atol=1e-3)  # error removed, re-added


def test_cli_errors_are_one_line(tmp_path, capsys):
    from fusion.cli import main as gnssfuse
    bad = tmp_path / "empty.21n"
    bad.write_text("")
    assert gnssfuse(["simulate", "--out", str(tmp_path), "--nav", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "empty.21n" in err and "Traceback" not in err
    assert gnssfuse(["simulate", "--out", str(tmp_path), "--start", "2021-06-01T00:00:00"]) == 2
    assert "outside the validity" in capsys.readouterr().err
    for bad, said in ((["--seed", "-1"], "--seed must be >= 0"), (["--rate", "nan"], "--rate: epochs per second"),
                      (["--origin", "10,10,-1e7"], "--origin: a height of")):
        with pytest.raises(SystemExit) as stop:                         # argparse's own usage error
            gnssfuse(["simulate", "--out", str(tmp_path), "--epochs", "5", *bad])
        err = capsys.readouterr().err
        assert stop.value.code == 2
        assert said in err and "Traceback" not in err


def test_a_folder_holding_the_other_format_is_refused_and_the_same_one_overwritten(tmp_path, capsys):
    """The README's two simulate commands into one --out used to leave two measurement files and one truth
    behind, which no command reads: the second is refused, naming the file; the same format is rewritten."""
    from fusion.cli import main as gnssfuse

    args = ["simulate", "--out", str(tmp_path), "--epochs", "10", "--seed", "1"]
    assert gnssfuse(args) == 0 and gnssfuse(args) == 0
    assert gnssfuse(args + ["--scenario", "urban"]) == 2
    err = capsys.readouterr().err
    assert "already holds SimPhone_derived.csv of another simulation" in err and err.strip().count("\n") == 0
    assert not (tmp_path / "2021-04-28-US-SIM-1/SimPhone/device_gnss.csv").exists()
    assert gnssfuse(["simulate", "--out", str(tmp_path / "c"), "--epochs", "10", "--scenario", "urban"]) == 0
    assert gnssfuse(["simulate", "--out", str(tmp_path / "c"), "--epochs", "10"]) == 2
    assert "already holds device_gnss.csv, sim_labels.csv" in capsys.readouterr().err
