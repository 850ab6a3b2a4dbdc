"""Simulator environment: constellations, C/N0 and DLL noise, urban canyon, device_gnss output."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from fusion.geometry import line_of_sight, range_rate
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.sim.canyon import BLOCKED, DIFFRACTED, LOS, NLOS, CanyonModel, classify
from fusion.sim.cn0 import Cn0Model, dll_sigma_m
from fusion.sim.config import SimConfig, config_from_options, scenario_config
from fusion.sim.constellations import WALKER, build_sky, parse_systems, walker_records
from fusion.cli.simulate import main
from fusion.sim.simulate import DEFAULT_START_MS, simulate
from fusion.sim.write import LABELS_FILE, write_device_gnss
from fusion.trace import SIGNALS


@pytest.fixture(scope="module")
def nav():
    return read_rinex_nav(default_nav_path())


@pytest.fixture(scope="module")
def urban(nav):
    return simulate(n_epochs=600, nav=nav, seed=21, config=scenario_config("urban", carrier=True))


@pytest.fixture(scope="module")
def open_sky(nav):
    return simulate(n_epochs=600, nav=nav, seed=21, config=scenario_config("open"))


def _sig(name: str) -> int:
    return SIGNALS.index(name)


# ------------------------------------------------------------------------------ constellations
def test_walker_orbits_are_circles_of_the_design_radius():
    from fusion.nav.orbits import sat_state
    for system, (T, P, F, a, inc, svid0) in WALKER.items():
        recs = walker_records(system)
        idx = np.arange(T)
        st = sat_state(recs, idx, np.full(T, DEFAULT_START_MS), 0.0)
        np.testing.assert_allclose(np.linalg.norm(st["pos"], axis=1), a, rtol=1e-9)
        v_inertial = st["vel"] + np.cross([0.0, 0.0, 7.2921151467e-5], st["pos"])
        np.testing.assert_allclose(np.linalg.norm(v_inertial, axis=1), np.sqrt(3.986005e14 / a), rtol=1e-6)
        h = np.cross(st["pos"], v_inertial)
        np.testing.assert_allclose(np.degrees(np.arccos(h[:, 2] / np.linalg.norm(h, axis=1))), inc, atol=1e-6)
        assert np.all(recs.sat_id // 1000 == {"G": 1, "R": 3, "E": 6, "C": 5}[system])
        assert np.all(recs.prn == svid0 + np.arange(T))
        assert len({tuple(np.round(p, -3)) for p in st["pos"]}) == T            # no two satellites together


def test_parse_systems():
    assert parse_systems("GPS,gal , BDS") == ("G", "E", "C")
    assert parse_systems("all") == ("G", "R", "E", "C")
    with pytest.raises(ValueError, match="XYZ"):
        parse_systems("GPS,XYZ")


def test_multi_constellation_signals_present(open_sky):
    tr = open_sky.trace
    m = tr.mask
    present = {SIGNALS[k] for k in np.unique(tr.signal[m])}
    assert present == {"GPS_L1", "GPS_L5", "GLO_G1", "GAL_E1", "GAL_E5A", "BDS_B1I"}
    assert set(np.unique(tr.sat_id[m] // 1000)) == {1, 3, 5, 6}
    # each system brings several satellites to every epoch
    for c in (1, 3, 5, 6):
        n = ((tr.sat_id // 1000 == c) & m & np.isin(tr.signal, [_sig("GPS_L1"), _sig("GLO_G1"), _sig("GAL_E1"),
                                                                _sig("BDS_B1I")])).sum(axis=1)
        assert n.mean() >= 4, (c, n.mean())
    # L5 only from the GPS satellites that broadcast it
    l5 = tr.sat_id[m & (tr.signal == _sig("GPS_L5"))] % 1000
    assert l5.size and set(l5) <= {1, 3, 4, 6, 8, 9, 10, 14, 18, 23, 24, 25, 26, 27, 30, 32}


def test_model_decomposition_every_system(urban):
    """pr = geometric range + clock + noise + NLOS path + multipath, to the micrometre, for all systems."""
    tr = urban.trace
    m = tr.mask
    rng_m, _ = line_of_sight(tr.sat_pos, tr.truth)
    resid = tr.pr - rng_m - urban.clock_m[:, None] - urban.noise_m - urban.nlos_delay_m - urban.multipath_m
    assert np.abs(resid[m]).max() < 1e-6
    assert np.all(urban.multipath_m[urban.los_class != LOS] == 0)


def test_real_multi_gnss_file_is_used(shared_data):
    from fusion.io.rinex_nav import read_nav
    from fusion.nav.glonass import glonass_state
    path = shared_data / "ephemeris/gnss_lib_py_nav/BRDC00WRD_S_20230730000_01D_MN.rnx"
    if not path.is_file():
        pytest.skip("multi-GNSS nav sample not present")
    nav = read_nav(path)
    sky = build_sky(nav, ("G", "R", "E", "C"))
    assert sky.origin["R"] == sky.origin["E"] == str(path)
    t0 = int(nav.glonass.toe_ms.min())
    res = simulate(n_epochs=30, start_ms=t0, nav=nav, seed=0, config=scenario_config("open", min_sats=1))
    tr = res.trace
    glo = tr.mask & (tr.sat_id // 1000 == 3)
    assert glo.any()
    # a GLONASS slot holds the broadcast state at its transmit time (the file's state vector integrated)
    e, s = np.argwhere(glo)[0]
    idx = np.flatnonzero(nav.glonass.sat_id == tr.sat_id[e, s])
    k = idx[np.argmin(np.abs(nav.glonass.toe_ms[idx] - tr.t_ms[e]))]
    st = glonass_state(nav.glonass, np.array([k]), np.array([tr.t_ms[e]]), -res.flight_s[e, s])
    np.testing.assert_allclose(st["pos"][0], tr.sat_pos[e, s], atol=1e-3)


# ------------------------------------------------------------------------------ C/N0
def test_dll_sigma_formula():
    m = Cn0Model(floor_m=0.0)
    c = 10 ** 4.5
    chips = np.sqrt(1.0 * 0.5 / (2 * c) * (1 + 2 / (0.02 * 1.5 * c)))
    np.testing.assert_allclose(dll_sigma_m(45.0, _sig("GPS_L1"), m), chips * 299_792_458.0 / 1.023e6, rtol=1e-12)
    s = dll_sigma_m(np.arange(20.0, 50.0), _sig("GPS_L1"), Cn0Model())
    assert np.all(np.diff(s) < 0)                                          # weaker signal, noisier code
    assert dll_sigma_m(35.0, _sig("GPS_L5"), m) < dll_sigma_m(35.0, _sig("GPS_L1"), m) / 5   # 10x chip rate


def test_cn0_physics_and_noise_tied_to_it(open_sky):
    tr, res = open_sky.trace, open_sky
    m = tr.mask & (tr.signal == _sig("GPS_L1"))
    assert np.corrcoef(res.elev_deg[m], tr.cn0[m])[0, 1] > 0.5            # low satellites weaker
    assert tr.cn0[tr.mask].min() >= Cn0Model().track_db
    # reported sigma = the DLL sigma at the reported C/N0; the drawn noise has that sigma
    np.testing.assert_allclose(tr.pr_sigma[tr.mask], dll_sigma_m(tr.cn0[tr.mask], tr.signal[tr.mask], Cn0Model()))
    z = res.noise_m[tr.mask] / tr.pr_sigma[tr.mask]
    assert abs(z.std() - 1.0) < 0.03 and abs(z.mean()) < 0.03
    low, high = tr.cn0[m] < np.percentile(tr.cn0[m], 25), tr.cn0[m] > np.percentile(tr.cn0[m], 75)
    assert np.abs(res.noise_m[m][low]).mean() > 2 * np.abs(res.noise_m[m][high]).mean()


# ------------------------------------------------------------------------------ urban canyon
def _layout(az_street_deg, w_r, w_l, h_r, h_l):
    """One epoch's street (see fusion.sim.canyon.street_layout)."""
    a = np.radians(az_street_deg)
    one = lambda v: np.array([v])  # noqa: E731
    return dict(azimuth_rad=one(a), w_right=one(w_r), w_left=one(w_l), h_right=one(h_r), h_left=one(h_l),
                normal_ne=np.array([[-np.sin(a), np.cos(a)]]), right_held=one(False), left_held=one(False),
                street=one(0), refl_u=np.array([[0.5]]))


def test_canyon_geometry_by_hand():
    """Street running north, 20 m buildings 10 m either side, antenna 1.5 m: a satellite due east."""
    model = CanyonModel(diffraction_deg=3.0)
    lay = _layout(0.0, 10.0, 10.0, 20.0, 20.0)
    el = np.array([[30.0, 40.0, 70.0, 60.0, 10.0]])
    az = np.array([[90.0, 90.0, 90.0, 90.0, 0.0]])               # last one: along the street
    vel = np.array([[0.0, 1.0]])                                   # 1 m/s east, towards the right facade
    c = classify(el, az, lay, vel, model)
    mask_deg = np.degrees(np.arctan(18.5 / 10.0))                  # 61.6 deg
    np.testing.assert_allclose(c["mask_deg"][0, :4], mask_deg)
    # 30 deg: the reflection off the west facade would come in under the east roof -> blocked;
    # 40 deg: reflected (30 m * tan 40 = 25.2 m clears 18.5 m; reflection point at 8.4 m < 18.5 m);
    # 70 deg: direct; 60 deg: reflected too (the reflection wins over diffraction); along the street: direct.
    assert list(c["cls"][0]) == [BLOCKED, NLOS, LOS, NLOS, LOS]
    np.testing.assert_allclose(c["delay_m"][0, 1], 2 * 10.0 * np.cos(np.radians(40.0)))
    # moving towards the right (satellite-side) facade = away from the reflecting west facade:
    # the reflected path lengthens at 2 cos(el) * 1 m/s
    np.testing.assert_allclose(c["rate_err_mps"][0, 1], 2 * np.cos(np.radians(40.0)))
    assert model.reflection_loss_db[0] <= c["loss_db"][0, 1] <= model.reflection_loss_db[1]
    # no west building: nothing to reflect off; 1.6 deg below the east roof edge the signal diffracts
    c = classify(el, az, _layout(0.0, 10.0, 10.0, 20.0, 0.0), vel, model)
    assert list(c["cls"][0]) == [BLOCKED, BLOCKED, LOS, DIFFRACTED, LOS]
    assert 6.0 < c["loss_db"][0, 3] < model.diffraction_max_db and c["rate_err_mps"][0, 3] == 0
    assert c["delay_m"][0, 3] > 0 and c["delay_m"][0, 2] == c["delay_m"][0, 4] == 0


@pytest.mark.parametrize("nothing", [None])
def test_nlos_share_grows_with_building_height(nav, nothing):
    shares, received = [], []
    for h in ((3.0, 8.0), (15.0, 25.0), (40.0, 60.0)):
        cfg = scenario_config("urban", canyon=CanyonModel(height_m=h, gap_prob=0.0), min_sats=1)
        res = simulate(n_epochs=300, nav=nav, seed=5, config=cfg)
        m = res.trace.mask
        shares.append(np.mean(res.los_class[m] != LOS))
        received.append(m.sum() / res.trace.n_epochs)
    print(f"\nnon-LOS share by building height: {np.round(shares, 3)}, signals/epoch {np.round(received, 1)}")
    assert shares[0] < shares[1] < shares[2] and shares[2] > 0.2
    assert received[0] > received[1] > received[2]


def test_nlos_delay_positive_and_weaker(urban):
    tr, res = urban.trace, urban
    m = tr.mask
    cls = res.los_class[m]
    nlos = cls == NLOS
    assert nlos.mean() > 0.1
    assert np.all(res.nlos_delay_m[m][nlos] > 0) and np.all(res.nlos_delay_m[m][cls == LOS] == 0)
    assert tr.cn0[m][nlos].mean() < tr.cn0[m][cls == LOS].mean() - 5.0
    # NLOS pseudoranges are longer on average than LOS ones at the truth
    err = (tr.pr - line_of_sight(tr.sat_pos, tr.truth)[0] - res.clock_m[:, None])[m]
    assert err[nlos].mean() > err[cls == LOS].mean() + 5.0


def test_nlos_doppler_is_the_rate_of_the_reflected_path(urban):
    """prr carries the NLOS path's rate, and that rate is the time derivative of the NLOS delay."""
    tr, res = urban.trace, urban
    rate = range_rate(tr.sat_pos, tr.sat_vel, tr.truth, res.rx_vel_mps)
    noise = tr.prr - rate - res.clock_drift_mps[:, None] - res.prr_error_mps
    assert np.abs(noise[tr.mask]).max() < 10 * tr.prr_sigma[tr.mask].max()
    z = noise[tr.mask] / tr.prr_sigma[tr.mask]
    assert abs(z.std() - 1.0) < 0.05
    # central difference of the delay of one satellite staying NLOS in one street over 3 epochs
    key = np.where(tr.mask, tr.sat_id.astype(np.int64) * 100 + tr.signal, -1)
    gap = []
    for e in range(1, tr.n_epochs - 1):
        if not (res.street[e - 1] == res.street[e] == res.street[e + 1]):
            continue
        for s in np.flatnonzero(res.los_class[e] == NLOS):
            prev = np.flatnonzero(key[e - 1] == key[e, s])
            nxt = np.flatnonzero(key[e + 1] == key[e, s])
            if prev.size and nxt.size and res.los_class[e - 1, prev[0]] == NLOS == res.los_class[e + 1, nxt[0]]:
                d = (res.nlos_delay_m[e + 1, nxt[0]] - res.nlos_delay_m[e - 1, prev[0]]) / 2.0
                gap.append(abs(d - res.prr_error_mps[e, s]))
    gap = np.array(gap)
    print(f"\n|d(delay)/dt - NLOS Doppler error|: median {np.median(gap):.4f} m/s, "
          f"95% {np.percentile(gap, 95):.4f} m/s over {gap.size} checks")
    # satellite motion (mm/s) is not in the analytic rate; a facade reaching min_wall_m mid-way
    # (a few per cent of epochs) breaks the central difference
    assert gap.size > 200 and np.median(gap) < 0.01 and np.mean(gap < 0.05) > 0.95


def test_carrier_follows_the_reflected_path(urban):
    tr, res = urban.trace, urban
    rng_m, _ = line_of_sight(tr.sat_pos, tr.truth)
    resid = tr.adr - rng_m - res.clock_m[:, None] - res.ambiguity_m - res.nlos_delay_m
    assert np.abs(resid[tr.adr_ok]).max() < 0.05


def test_a_signal_that_turns_reflected_or_back_slips(nav, urban):
    """Every change of a satellite's arrival class between consecutive epochs is a flagged slip (the loop loses
    lock); without slip_on_class_change those epochs keep their arcs (this urban config has no random slips)."""
    tr, res = urban.trace, urban
    key = np.where(tr.mask, tr.sat_id.astype(np.int64) * 100 + tr.signal, -1)
    changed = np.zeros(tr.mask.shape, bool)
    for e in range(1, tr.n_epochs):
        for s in np.flatnonzero(tr.mask[e]):
            prev = np.flatnonzero(key[e - 1] == key[e, s])
            changed[e, s] = bool(prev.size) and res.los_class[e - 1, prev[0]] != res.los_class[e, s]
    assert changed.sum() > 50
    assert tr.adr_slip[changed].all()
    kept = simulate(n_epochs=600, nav=nav, seed=21,
                    config=scenario_config("urban", carrier=True, slip_on_class_change=False)).trace
    assert not kept.adr_slip[changed].any()
    np.testing.assert_array_equal(kept.adr_slip, tr.adr_slip & ~changed)


def test_the_deep_canyon_blocks_more_of_the_sky_than_the_urban_one(nav, urban):
    deep = simulate(n_epochs=600, nav=nav, seed=21, config=scenario_config("deep", carrier=True))
    per_epoch = {name: r.trace.mask.sum(axis=1).mean() for name, r in (("urban", urban), ("deep", deep))}
    assert per_epoch["deep"] < 0.8 * per_epoch["urban"]
    # the same drive, the same receiver: only the buildings differ
    np.testing.assert_allclose(deep.trace.truth, urban.trace.truth)


# ------------------------------------------------------------------------------ output and read-back
def test_device_gnss_round_trip_and_wls(tmp_path, urban, open_sky):
    from fusion.estimate.wls import solve_wls
    from fusion.prepare.load import find_traces, load_trace
    errors = {}
    for name, res in (("urban", urban), ("open", open_sky)):
        d_path, g_path, l_path = write_device_gnss(res, tmp_path, f"2021-04-28-US-SIM-{name}")
        a = res.trace
        b = load_trace(d_path.parent, signals="all")
        assert find_traces(tmp_path / f"2021-04-28-US-SIM-{name}") == [d_path.parent]  # labels are no trace
        np.testing.assert_array_equal(b.t_ms, a.t_ms)
        np.testing.assert_array_equal(b.sat_id[b.mask], a.sat_id[a.mask])
        np.testing.assert_array_equal(b.signal[b.mask], a.signal[a.mask])
        np.testing.assert_allclose(b.pr[b.mask], a.pr[a.mask], atol=1.5e-3)
        np.testing.assert_allclose(b.cn0[b.mask], a.cn0[a.mask], atol=0.006)
        np.testing.assert_allclose(b.prr[b.mask], a.prr[a.mask], atol=2e-4)
        np.testing.assert_allclose(b.pr_sigma[b.mask], a.pr_sigma[a.mask], atol=1e-3)
        np.testing.assert_allclose(b.truth, a.truth, atol=1e-3)
        if a.adr is not None:
            np.testing.assert_allclose(b.adr[b.adr_ok], a.adr[a.adr_ok], atol=2e-4)
            np.testing.assert_array_equal(b.adr_slip, a.adr_slip)
        labels = pd.read_csv(l_path)
        assert l_path.name == LABELS_FILE and len(labels) == a.mask.sum()
        assert set(labels.Class) <= {"LOS", "NLOS", "DIFFRACTED"}
        assert (labels.ExtraPathM[labels.Class == "NLOS"] > 0).all()
        out = solve_wls(b, robust="none")
        errors[name] = float(np.mean(np.linalg.norm(out.pos - b.truth, axis=1)))
    print(f"\nWLS mean 3-D error: open sky {errors['open']:.2f} m, urban canyon {errors['urban']:.2f} m")
    assert errors["urban"] > 3 * errors["open"]


def test_seeded_and_deterministic(nav):
    cfg = scenario_config("urban", carrier=True)
    a = simulate(n_epochs=60, nav=nav, seed=3, config=cfg)
    b = simulate(n_epochs=60, nav=nav, seed=3, config=cfg)
    c = simulate(n_epochs=60, nav=nav, seed=4, config=cfg)
    for k in ("pr", "cn0", "prr", "adr", "sat_id", "signal"):
        np.testing.assert_array_equal(getattr(a.trace, k), getattr(b.trace, k))
    np.testing.assert_array_equal(a.los_class, b.los_class)
    np.testing.assert_array_equal(a.nlos_delay_m, b.nlos_delay_m)
    assert not np.array_equal(a.trace.truth, c.trace.truth)
    g = np.random.default_rng(3)
    d = simulate(n_epochs=60, nav=nav, seed=g, config=cfg)
    np.testing.assert_array_equal(a.trace.pr, d.trace.pr)


def test_environment_leaves_the_default_draws_alone(nav):
    """Switching C/N0 on (no canyon, noise still fixed) keeps the same picks, clock and noise."""
    base = simulate(n_epochs=50, nav=nav, seed=8, config=SimConfig(nlos=True, doppler=True))
    with_cn0 = simulate(n_epochs=50, nav=nav, seed=8,
                        config=SimConfig(nlos=True, doppler=True, cn0=Cn0Model(track_db=0.0)))
    np.testing.assert_array_equal(base.trace.pr, with_cn0.trace.pr)
    np.testing.assert_array_equal(base.trace.prr, with_cn0.trace.prr)
    assert base.trace.cn0 is None and with_cn0.trace.cn0 is not None


def test_dataset_with_canyon_keeps_traces_apart(nav):
    from fusion.sim.simulate import simulate_dataset
    res = simulate_dataset(8, 40, seed=2, nav=nav, config=scenario_config("urban"), results=True,
                           origins=[(37.4, -122.1)])
    streets = [set(np.unique(r.street)) for r in res]
    for i in range(len(streets)):
        for j in range(i + 1, len(streets)):
            assert not streets[i] & streets[j]                          # no street shared across traces
    assert all(r.trace.cn0 is not None for r in res)


def test_chunked_passes_are_seeded_and_keep_streets_apart(nav, monkeypatch):
    """With C/N0 the data set goes through in chunks (memory): same seed, same data; streets unique."""
    import fusion.sim.measurements as meas
    import fusion.sim.simulate as sim
    monkeypatch.setattr(meas, "CHUNK_EPOCHS", 100)
    monkeypatch.setattr(sim, "CHUNK_EPOCHS", 100)
    cfg = scenario_config("urban", min_sats=1)
    a = sim.simulate_dataset(6, 40, seed=1, nav=nav, config=cfg, results=True, origins=[(37.4, -122.1)])
    b = sim.simulate_dataset(6, 40, seed=1, nav=nav, config=cfg, results=True, origins=[(37.4, -122.1)])
    assert len(a) == 6
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.trace.pr, y.trace.pr)
        np.testing.assert_array_equal(x.trace.cn0, y.trace.cn0)
    streets = [set(np.unique(r.street)) for r in a]
    assert all(not (streets[i] & streets[j]) for i in range(6) for j in range(i + 1, 6))
    one = sim.simulate_dataset(6, 40, seed=1, nav=nav, config=cfg, results=True, concatenate=True,
                               origins=[(37.4, -122.1)])
    trace_id = np.cumsum(one.trace.clock_reset)
    assert trace_id[-1] == 5
    per = [set(np.unique(one.street[trace_id == k])) for k in range(6)]
    assert all(not (per[i] & per[j]) for i in range(6) for j in range(i + 1, 6))


# ------------------------------------------------------------------------------ settings and CLI
def test_date_outside_the_file_is_refused_even_with_synthetic_systems(nav):
    from fusion.errors import DataError
    from fusion.gpstime import gps_ms_from_calendar
    late = gps_ms_from_calendar(2021, 6, 1, 0, 0, 0.0)
    with pytest.raises(DataError, match="outside the validity"):
        simulate(n_epochs=5, start_ms=late, nav=nav, config=scenario_config("open"))
    # systems all synthetic: any date works
    res = simulate(n_epochs=5, start_ms=late, nav=nav, config=scenario_config("open", systems=("R", "E", "C")))
    assert set(np.unique(res.trace.sat_id[res.trace.mask] // 1000)) == {3, 5, 6}


def test_bad_settings():
    with pytest.raises(ValueError, match="C/N0"):
        SimConfig(canyon=CanyonModel()).validate()
    with pytest.raises(ValueError, match="scenario"):
        scenario_config("moon")
    with pytest.raises(ValueError, match="height_m"):
        scenario_config("urban", canyon=CanyonModel(height_m=(30.0, 10.0)))
    cfg = config_from_options("urban", "GPS,GAL", max_sats=0, elev_mask_deg=15.0)
    assert cfg.systems == ("G", "E") and cfg.max_sats is None and cfg.elev_mask_deg == 15.0
    assert config_from_options().systems == ("G",) and config_from_options().cn0 is None


def test_cli_scenario_and_formats(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--epochs", "30", "--seed", "1", "--scenario", "urban"]) == 0
    files = sorted(p.name for p in (tmp_path / "2021-04-28-US-SIM-1/SimPhone").iterdir())
    assert files == ["device_gnss.csv", "ground_truth.csv", LABELS_FILE]
    df = pd.read_csv(tmp_path / "2021-04-28-US-SIM-1/SimPhone/device_gnss.csv")
    assert {"Cn0DbHz", "PseudorangeRateMetersPerSecond", "SignalType"} <= set(df.columns)
    assert set(df.ConstellationType) == {1, 3, 5, 6}
    assert main(["--out", str(tmp_path / "b"), "--epochs", "10", "--constellations", "GPS,GAL",
                 "--format", "gsdc2021", "--collection", "x"]) == 0
    derived = pd.read_csv(tmp_path / "b/x/SimPhone/SimPhone_derived.csv")
    assert set(derived.signalType) == {"GPS_L1", "GAL_E1"}
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--constellations", "GPS,XYZ"])
    assert "XYZ" in capsys.readouterr().err
