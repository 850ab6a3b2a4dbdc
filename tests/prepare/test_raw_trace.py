"""Raw observations -> Trace (satellite states, clock / atmosphere corrections, counted skips),
raw-log trace folders through load_trace and the CLI, and the Pixel5 RINEX targets."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fusion.cli import main as cli_main
from fusion.errors import DataError
from fusion.estimate.wls import solve_wls
from fusion.geometry import C_LIGHT, geodetic2ecef, line_of_sight
from fusion.gpstime import gps_ms_from_calendar
from fusion.prepare.load import load_trace
from fusion.io.raw import RawObs, finish_raw
from fusion.prepare.raw_load import RawSources
from fusion.prepare.raw_trace import raw_to_trace
from fusion.io.rinex_nav import default_nav_path, read_nav
from fusion.io.rinex_obs import read_rinex_obs
from fusion.nav.orbits import select_ephemeris, transmit_states

DATA = Path(__file__).resolve().parents[1] / "data"
P5_HEAD = DATA / "pixel5_head.21o"
#: Pixel5 truth at its first epoch (ground_truth.csv, height fixed by -63.1 m).
P5_START = geodetic2ecef(np.array([[37.3958422483, -122.1029571933, 58.31 - 63.1]]))[0]


@pytest.fixture(scope="module")
def nav():
    return read_nav(default_nav_path())


def _visible(nav, t_ms, min_el=15.0):
    """GPS PRNs above ``min_el`` degrees at P5_START at ``t_ms``."""
    from fusion.geometry import elevation_azimuth
    prns = np.arange(1, 33)
    idx = select_ephemeris(nav.kepler, prns, t_ms)
    prns, idx = prns[idx >= 0], idx[idx >= 0]
    st, _ = transmit_states(nav.kepler, idx, np.broadcast_to(P5_START, (len(prns), 3)), np.full(len(prns), t_ms))
    _, los = line_of_sight(st["pos"], P5_START)
    el, _ = elevation_azimuth(los, P5_START)
    return prns[el > min_el]


def _synthetic(nav, rx, t_rx_ms, prns, rx_clock_m=1234.5, extra_rows=()):
    """A raw frame of exact GPS L1 pseudoranges (no noise, no atmosphere) from ``rx`` at true
    receive time ``t_rx_ms`` by a receiver whose clock (and so its time tag) runs ``rx_clock_m``
    ahead, plus extra (const, svid) rows."""
    idx = select_ephemeris(nav.kepler, prns, t_rx_ms)
    st, tau = transmit_states(nav.kepler, idx, np.broadcast_to(rx, (len(prns), 3)), np.full(len(prns), t_rx_ms))
    pr = tau * C_LIGHT + rx_clock_m - C_LIGHT * st["clock_s"]
    n = len(prns) + len(extra_rows)
    const = ["G"] * len(prns) + [c for c, _ in extra_rows]
    svid = list(prns) + [s for _, s in extra_rows]
    pr = np.r_[pr, np.full(len(extra_rows), 2.2e7)]
    frame = finish_raw({
        "t_ns": np.full(n, t_rx_ms * 1_000_000 + round(rx_clock_m / C_LIGHT * 1e9), np.int64), "const": np.array(const, object),
        "svid": np.array(svid), "signal": np.array(["GPS_L1" if c == "G" else "GAL_E1" for c in const], object),
        "pr_m": pr, "pr_sigma_m": np.full(n, np.nan), "prr_mps": np.full(n, 100.0),
        "prr_sigma_mps": np.full(n, np.nan), "adr_m": np.full(n, 5.0), "adr_sigma_m": np.full(n, np.nan),
        "adr_ok": np.ones(n, bool), "adr_slip": np.zeros(n, bool), "cn0": np.full(n, 40.0),
        "glo_k": np.zeros(n, np.int64), "clock_reset": np.zeros(n, bool),
    })
    return RawObs(frame=frame, path=Path("synthetic.obs")), st


@pytest.mark.parametrize("rx_clock_m", [1234.5, 3.0e5])
def test_exact_pseudoranges_give_geometry_plus_clock(nav, rx_clock_m):
    """With the atmosphere switched off (no Klobuchar, tropo subtracted back), corrected
    pseudoranges equal the Sagnac range from the true receiver plus its clock, to millimetres,
    also for a 1 ms clock: the pseudorange itself fixes the transmit time, whatever the
    receiver's time tag is off by."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    assert len(prns) >= 6
    raw, st = _synthetic(nav, P5_START, t, prns, rx_clock_m=rx_clock_m, extra_rows=[("E", 11)])
    nav.klobuchar, klob = None, nav.klobuchar
    try:
        with pytest.warns(UserWarning, match="synthetic.obs: no ionosphere model"):
            tr = raw_to_trace(raw, nav, signals=["GPS_L1", "GAL_E1"])
    finally:
        nav.klobuchar = klob
    m = tr.mask[0]
    assert m.sum() == len(prns) and tr.skipped == {"rows_constellation_without_navigation": 1}
    rng, _ = line_of_sight(tr.sat_pos[0][m], P5_START)
    from fusion.nav.atmosphere import tropo_delay
    from fusion.geometry import ecef2geodetic, elevation_azimuth
    _, los = line_of_sight(tr.sat_pos[0][m], P5_START)
    el, _ = elevation_azimuth(los, P5_START)
    llh = ecef2geodetic(P5_START)
    tropo = tropo_delay(llh[0], llh[2], el)
    np.testing.assert_allclose(tr.pr[0][m] + tropo - rng, rx_clock_m, atol=0.003)
    # Doppler + c * satellite clock drift, carrier + c * satellite clock
    order = np.argsort(prns)
    np.testing.assert_allclose(tr.prr[0][m] - 100.0, C_LIGHT * st["clock_drift"][order], atol=1e-6)
    np.testing.assert_allclose(tr.adr[0][m] - 5.0, C_LIGHT * st["clock_s"][order], atol=1e-3)
    assert tr.prr_ok[0][m].all() and tr.adr_ok[0][m].all() and np.all(tr.pr_sigma[0][m] == 3.0)


def test_a_dropped_epoch_passes_its_clock_reset_and_a_slip_to_the_next_kept_one(nav):
    """Three epochs; the middle one has two satellites (dropped at min_sats=4) and carries the
    receiver's clock reset: the reset still happened before the third epoch, and every carrier
    chain from the first to the third epoch is broken."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    frames = []
    for k, sats in enumerate([prns, prns[:2], prns]):
        raw, _ = _synthetic(nav, P5_START, t + 1000 * k, sats)
        f = raw.frame.copy()
        f["clock_reset"] = k == 1
        frames.append(f)
    raw = RawObs(frame=pd.concat(frames, ignore_index=True), path=Path("synthetic.obs"))
    tr = raw_to_trace(raw, nav, signals=["GPS_L1"], min_sats=4)
    assert tr.n_epochs == 2 and tr.skipped["epochs_lt4_sats"] == 1
    assert tr.clock_reset.tolist() == [False, True]
    assert tr.adr_slip[1][tr.mask[1]].all() and not tr.adr_slip[0].any()


def test_default_signals_follow_navigation(nav):
    """Without --signals, constellations the navigation lacks are a counted skip, not a crash."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    raw, _ = _synthetic(nav, P5_START, t, prns, extra_rows=[("E", 11), ("E", 12)])
    with pytest.warns(UserWarning, match=r"no navigation for Galileo \(2 measurements\); the navigation covers GPS"):
        tr = raw_to_trace(raw, nav)
    assert tr.skipped == {"rows_constellation_without_navigation": 2} and tr.mask.sum() == len(prns)
    with pytest.raises(DataError, match="no pseudorange of signal"):
        raw_to_trace(raw, nav, signals=["BDS_B1I"])
    # a chosen signal of a constellation the navigation lacks: that is what the user hears, not a wrong day
    with pytest.warns(UserWarning, match=r"no navigation for Galileo \(2 measurements\)"):
        with pytest.raises(DataError, match=r"no pseudorange of signal\(s\) GAL_E1 \(navigation covers GPS\)"):
            raw_to_trace(raw, nav, signals=["GAL_E1"])
    with pytest.warns(UserWarning, match=r"no navigation for Galileo \(2 measurements\)"):
        tr = raw_to_trace(raw, nav, signals=["GPS_L1", "GAL_E1"])
    assert tr.skipped["rows_constellation_without_navigation"] == 2 and tr.mask.sum() == len(prns)
    with pytest.raises(DataError, match="no navigation data"):
        raw_to_trace(raw, None)
    late, _ = _synthetic(nav, P5_START, t, prns)
    late.frame["t_ns"] += 10 * 86_400 * 10**9                   # ten days after the navigation file
    # the wrong day is named, with both dates
    with pytest.raises(DataError, match=r"synthetic.obs: the log runs 2021-05-08 12:00:0\d to 2021-05-08 12:00:0\d "
                       r"GPS time but the navigation \(hour1180.21n\) covers 2021-04-2\d .* to 2021-04-2\d .*: "
                       r"pass a navigation file of the log's day"):
        raw_to_trace(late, nav)


def test_several_navigation_files_are_each_dated_when_the_log_is_not_covered(nav):
    """Two navigation files of different days merge into one span: the warning also says which day each
    file's records are of (the second file here, of 2023, serves the log's Galileo rows nothing)."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    raw, _ = _synthetic(nav, P5_START, t, prns, extra_rows=[("E", s) for s in range(1, 31)])
    other = Path(__file__).resolve().parents[1] / "data" / "brdc_2023073_mixed_305.rnx"
    both = read_nav([default_nav_path(), other])
    with pytest.warns(UserWarning, match=r"hour1180.21n: records 2021-04-2\d .* to 2021-04-2\d .*; "
                                         r"brdc_2023073_mixed_305.rnx: records 2023-03-1\d"):
        raw_to_trace(raw, both)


def test_pixel5_head_rinex(nav):
    """The shipped Pixel5 RINEX head: GPS L1 + L5 with the L5 inter-signal bias removed, WLS
    within tens of metres of the truth, Doppler and carrier carried."""
    raw = read_rinex_obs(P5_HEAD)
    with pytest.warns(UserWarning, match="no navigation for Galileo"):
        tr = raw_to_trace(raw, nav)
    assert tr.n_epochs == 5 and set(np.unique(tr.signal[tr.mask])) == {0, 1}
    assert tr.skipped["rows_constellation_without_navigation"] > 0
    assert tr.has_doppler and tr.has_carrier and not tr.clock_reset.any()
    np.testing.assert_array_equal(tr.t_ms % 1000, 430)           # 22:19:22.4299102 -> .430
    w = solve_wls(tr, robust=True)
    assert w.valid.all() and np.linalg.norm(w.pos - P5_START, axis=1).max() < 60


def test_raw_folder_through_cli(tmp_path, nav):
    """A folder with a RINEX file in supplemental/ and truth (2022/23 columns): ``gnssfuse run``
    with --nav; truth is interpolated between its rows, not matched to the nearest."""
    folder = tmp_path / "drive" / "phone"
    (folder / "supplemental").mkdir(parents=True)
    shutil.copy(P5_HEAD, folder / "supplemental" / "x.21o")
    import pandas as pd
    from fusion.gpstime import gps_ms_to_unix_ms
    t0 = gps_ms_from_calendar(2021, 4, 28, 22, 19, 22.0)
    times = t0 + 1000 * np.arange(6)
    lat = 37.3958 + 1e-4 * np.arange(6)                          # ~11 m per second northwards
    pd.DataFrame({"UnixTimeMillis": gps_ms_to_unix_ms(times), "LatitudeDegrees": lat,
                  "LongitudeDegrees": -122.103, "AltitudeMeters": -5.0}).to_csv(folder / "ground_truth.csv", index=False)
    with pytest.raises(DataError, match="no navigation data"):
        load_trace(folder, signals=None)
    tr = load_trace(folder, signals=None, raw_sources=RawSources(nav=(default_nav_path(),)), min_sats=1)
    assert tr.name == "drive/phone"
    expect = geodetic2ecef(np.c_[37.3958 + 1e-4 * 0.43 + 1e-4 * np.arange(5), np.full(5, -122.103), np.full(5, -5.0)])
    np.testing.assert_allclose(tr.truth, expect, atol=0.01)
    # the log itself, or its supplemental/ folder, named instead: the same trace, truth included
    for named in (folder / "supplemental" / "x.21o", folder / "supplemental"):
        same = load_trace(named, signals=None, raw_sources=RawSources(nav=(default_nav_path(),)), min_sats=1)
        assert same.name == "drive/phone"
        np.testing.assert_allclose(same.truth, expect, atol=0.01)
    out = tmp_path / "out"
    rc = cli_main(["run", str(folder), "--nav", str(default_nav_path()), "--mode", "wls", "--out", str(out)])
    assert rc == 0 and (out / "estimates.csv").is_file() and (out / "metrics.json").is_file()
    assert cli_main(["run", str(folder), "--clk", "x.clk", "--out", str(out)]) == 2
    # train takes such folders too, with the same navigation options
    ckpt = tmp_path / "raw.pt"
    assert cli_main(["train", "--data", str(folder), "--nav", str(default_nav_path()), "--epochs", "1",
                     "--guess-mix", "box=1", "--val-frac", "0", "--quiet", "--out", str(ckpt)]) == 0
    assert ckpt.is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli_main(["run", str(empty), "--out", str(out)]) == 2


def test_a_truth_file_that_cannot_be_used_costs_the_accuracy_not_the_run(tmp_path):
    """A phone log beside a ground_truth.csv with no rows: solved without truth, with a warning and a count; asked
    for explicitly (truth="csv"), the same file is refused."""
    folder = tmp_path / "phone"
    folder.mkdir()
    shutil.copy(P5_HEAD, folder / "x.21o")
    (folder / "ground_truth.csv").write_text("UnixTimeMillis,LatitudeDegrees,LongitudeDegrees,AltitudeMeters\n")
    nav = RawSources(nav=(default_nav_path(),))
    with pytest.warns(UserWarning, match=r"ground_truth\.csv: .*no data rows; solved without truth"):
        tr = load_trace(folder, signals=None, raw_sources=nav, min_sats=1)
    assert tr.truth is None and tr.skipped["truth_unusable"] == 1 and tr.n_epochs == 5
    with pytest.raises(DataError, match="no data rows"):
        load_trace(folder, signals=None, raw_sources=nav, min_sats=1, truth="csv")


def test_a_log_no_epoch_of_which_solves_says_why(tmp_path):
    """GPS L5 alone in the Pixel5 log: three satellites at every epoch, and the refusal says so."""
    folder = tmp_path / "phone"
    folder.mkdir()
    shutil.copy(P5_HEAD, folder / "x.21o")
    with pytest.raises(DataError, match=r"x\.21o: no epoch could be solved .*no epoch has 4 satellites on one "
                                        r"signal \(at most 3\)"):
        load_trace(folder, signals=("GPS_L5",), raw_sources=RawSources(nav=(default_nav_path(),)), min_sats=1)


def test_pixel5_targets(shared_data):
    """Issue targets on the Pixel5 RINEX trace with GPS broadcast navigation: wls no worse than
    RTKLIB single point (18.0 m) over >= 95 % of truth epochs (figures: benchmarks/bench_pixel5.py)."""
    from fusion.eval.metrics import horizontal, ned_errors
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions

    folder = shared_data / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
    tr = load_trace(folder, signals=None, min_sats=1,
                    raw_sources=RawSources(nav=(shared_data / "ephemeris/gps_nav/hour1180.21n",)))
    assert tr.n_epochs == 1985 and np.isfinite(tr.truth).all()
    res = run_modes(tr, ["wls"], RunOptions(signals=None))["wls"]
    h = horizontal(ned_errors(res.pos, tr.truth))
    ok = np.isfinite(h)
    assert ok.mean() >= 0.95
    assert np.mean(np.percentile(h[ok], [50, 95])) <= 18.0


def test_gnss_logger_log_matches_gsdc_derived(shared_data):
    """GnssLogger path (2020-05-14 sample, nav of the day): our GPS L1 satellite positions match
    the derived file's to a millimetre, corrected pseudoranges to decimetres (the derived file's
    iono/tropo are at Google's position, ours at our WLS fix)."""
    import pandas as pd
    from fusion.io.gnss_log import read_gnss_log

    raw = read_gnss_log(shared_data / "gsdc2021/samples/Pixel4_GnssLog.txt")
    tr = raw_to_trace(raw, read_nav(shared_data / "ephemeris/gps_nav/hour1350.20n"), signals=["GPS_L1"])
    d = pd.read_csv(shared_data / "gsdc2021/samples/Pixel4_derived.csv")
    d = d[(d["signalType"] == "GPS_L1") & (d["millisSinceGpsEpoch"] - 1000 == tr.t_ms[0])].set_index("svid")
    e, s = np.nonzero(tr.mask)
    svid = tr.sat_id[e, s] % 1000
    assert len(svid) == 8 and set(svid) <= set(d.index)
    ref = d.loc[svid]
    dpos = np.linalg.norm(tr.sat_pos[e, s] - ref[["xSatPosM", "ySatPosM", "zSatPosM"]].to_numpy(), axis=1)
    assert dpos.max() < 0.005
    ref_pr = (ref["rawPrM"] + ref["satClkBiasM"] - ref["isrbM"] - ref["ionoDelayM"] - ref["tropoDelayM"]).to_numpy()
    assert np.abs(tr.pr[e, s] - ref_pr).max() < 0.5


def _two_signals(nav, t, l1_prns, l5_prns, l5_bias_m):
    """One epoch of exact GPS L1 pseudoranges of ``l1_prns`` and GPS L5 ones of ``l5_prns`` whose receiver
    channel adds ``l5_bias_m`` (an inter-signal bias)."""
    l1, _ = _synthetic(nav, P5_START, t, l1_prns)
    l5, _ = _synthetic(nav, P5_START, t, l5_prns)
    f5 = l5.frame.copy()
    f5["signal"], f5["pr_m"] = "GPS_L5", f5["pr_m"] + l5_bias_m
    cols = {c: np.r_[l1.frame[c].to_numpy(), f5[c].to_numpy()] for c in l1.frame.columns if c != "carrier_hz"}
    return RawObs(frame=finish_raw(cols), path=Path("synthetic.obs"))


def _clocks_at_truth(nav, raw, signals):
    """Load ``raw`` without the ionosphere model and return each first-epoch pseudorange minus its troposphere
    and range from the truth (its clock as corrected, (K,)), and its signal index (K,)."""
    from fusion.nav.atmosphere import tropo_delay
    from fusion.geometry import ecef2geodetic, elevation_azimuth
    nav.klobuchar, klob = None, nav.klobuchar
    try:
        with pytest.warns(UserWarning, match="no ionosphere model"):
            tr = raw_to_trace(raw, nav, signals=signals)
    finally:
        nav.klobuchar = klob
    m = tr.mask[0]
    rng, los = line_of_sight(tr.sat_pos[0][m], P5_START)
    el, _ = elevation_azimuth(los, P5_START)
    llh = ecef2geodetic(P5_START)
    return tr.pr[0][m] + tropo_delay(llh[0], llh[2], el) - rng, tr.signal[0][m], tr


def test_a_sparse_gps_l1_leaves_the_reference_to_a_signal_that_solves_alone(nav):
    """GPS L1 with three satellites, L5 with six and a 25 m bias of its own: GPS L1 cannot solve the receiver
    guess alone (before: no guess, the log refused), so L5 is the reference and GPS L1 gets the bias instead;
    every corrected pseudorange then agrees with the geometry and one clock."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    assert len(prns) >= 6
    raw = _two_signals(nav, t, prns[:3], prns[:6], l5_bias_m=25.0)
    clock, sig, tr = _clocks_at_truth(nav, raw, ["GPS_L1", "GPS_L5"])
    l5 = sig == 1
    # L5 keeps its own clock (bias included); GPS L1 is moved onto it: within the L5 group delay's metres
    assert np.ptp(clock[l5]) < 5.0 and np.ptp(clock[~l5]) < 5.0
    assert abs(np.median(clock[~l5]) - np.median(clock[l5])) < 3.0
    assert np.median(clock[l5]) - 1234.5 == pytest.approx(25.0, abs=3.0)
    w = solve_wls(tr, robust=False)
    assert w.valid.all() and np.linalg.norm(w.pos - P5_START, axis=1).max() < 15.0


def test_reference_signal_choice():
    """GPS L1 while it solves at least half as many epochs alone as the best signal; else the best; GLONASS
    (a bias per FDMA channel) only when nothing else solves an epoch alone."""
    from fusion.prepare.raw_trace import _reference_rows

    def rows(counts):             # signal -> satellites per epoch, over two epochs
        sig, ep = [], []
        for s, per in counts.items():
            for e, n in enumerate(per):
                sig += [s] * n
                ep += [e] * n
        return pd.DataFrame({"signal": np.array(sig, object)}), np.array(ep)

    def ref(counts):
        r, e = rows(counts)
        chosen = set(r["signal"][_reference_rows(r, e)])
        assert len(chosen) == 1
        return chosen.pop()

    assert ref({"GPS_L1": [6, 7], "GAL_E1": [8, 9]}) == "GPS_L1"
    assert ref({"GPS_L1": [4, 3], "GAL_E1": [5, 6]}) == "GPS_L1"       # one of two: half
    assert ref({"GPS_L1": [3, 3], "GAL_E1": [5, 6], "GLO_G1": [9, 9]}) == "GAL_E1"
    assert ref({"GPS_L1": [3, 2], "GLO_G1": [5, 6]}) == "GLO_G1"
    assert ref({"GPS_L1": [3, 2], "GAL_E1": [2, 3]}) == "GPS_L1"       # nothing solves alone: as before
    assert ref({"BDS_B1I": [3, 3], "GAL_E1": [2, 2]}) == "BDS_B1I"     # ... the most common signal


def test_signals_none_of_which_solves_alone_get_a_clock_each(nav):
    """Three GPS L1 and three L5 satellites, the L5 ones 25 m late: neither signal solves an epoch alone,
    but with a clock each (five unknowns, six pseudoranges) the epoch gives the receiver guess, and the L5
    bias is measured and removed against GPS L1 (before: no guess, the log refused)."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    raw = _two_signals(nav, t, prns[:3], prns[3:6], l5_bias_m=25.0)
    clock, sig, _ = _clocks_at_truth(nav, raw, ["GPS_L1", "GPS_L5"])
    l5 = sig == 1
    assert l5.sum() == 3 and np.median(clock[~l5]) == pytest.approx(1234.5, abs=0.01)
    assert abs(np.median(clock[l5]) - 1234.5) < 3.0           # the 25 m gone, to the L5 group delay's metres


def test_signals_none_of_which_solves_an_epoch_are_refused_not_left_biased(nav):
    """Three GPS L1 and two L5 satellites with a 25 m L5 bias, and the header's approximate position: no
    epoch solves, alone or with a clock per signal (five unknowns, nothing to spare). The position would serve
    the atmosphere models, but nothing measures the L5 bias, which would stay in the pseudoranges (kilometres
    of error on a phone log): one line naming the file. One signal alone needs no bias and still loads from the
    header's position."""
    t = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = _visible(nav, t)
    raw = _two_signals(nav, t, prns[:3], prns[3:5], l5_bias_m=25.0)
    raw.approx_pos = P5_START + 100.0
    with pytest.raises(DataError, match="synthetic.obs: no epoch could be solved, by one signal alone or with a "
                                        "clock per signal, so the biases between its signals cannot be measured"):
        raw_to_trace(raw, nav, signals=["GPS_L1", "GPS_L5"])
    tr = raw_to_trace(raw, nav, signals=["GPS_L1"])
    assert tr.n_epochs == 1 and tr.mask.sum() == 3


def test_a_clock_file_that_misses_the_log_is_said(recwarn):
    """A clock file beside the SP3 that covers another hour (the shared CODE file holds 19:30-20:30 only) leaves
    the SP3's own clocks to the log: the run says so, with the file's span and how many measurements it misses."""
    import pandas as pd
    from fusion.io.clk import PreciseClocks
    from fusion.nav.precise import PreciseOrbits
    from fusion.prepare.raw_trace import _check_clock_coverage

    t0 = gps_ms_from_calendar(2021, 4, 28, 19, 30, 0.0)
    clk = PreciseClocks(t_ms=t0 + 30_000 * np.arange(121), sats=np.array(["G01"]), bias=np.zeros((121, 1)),
                        source="day.clk")
    rows = pd.DataFrame({"t_ns": (t0 + np.array([1_800_000, 3_600_000, 9_000_000, 9_001_000])) * 1_000_000})
    with pytest.warns(UserWarning, match=r"day\.clk: the clock file covers 2021-04-28 19:30:00 to 2021-04-28 "
                                         r"20:30:00 GPS time; 2 of 4 measurements outside it"):
        _check_clock_coverage(rows, PreciseOrbits(sp3=None, clk=clk))
    recwarn.clear()
    _check_clock_coverage(rows.iloc[:2], PreciseOrbits(sp3=None, clk=clk))
    assert not recwarn.list


@pytest.mark.parametrize("clock, said", [
    (0.0, "too few epochs \\(10 around each time\\), or a hole of over 30 minutes"),
    (np.nan, "it holds no satellite clock \\(pass a clock file, --clk\\)")])
def test_a_precise_file_that_spans_the_log_but_serves_none_of_it_says_why(clock, said):
    """An SP3 whose span holds the log but that gave no measurement a state: a hole where the log is, or no
    clock in it; not "pass a navigation file of the log's day", which it is."""
    import pandas as pd
    from types import SimpleNamespace

    from fusion.io.sp3 import Sp3Orbits
    from fusion.nav.precise import PreciseOrbits
    from fusion.prepare.raw_trace import _check_coverage

    t0 = gps_ms_from_calendar(2021, 4, 28, 18, 0, 0.0)
    t = t0 + np.array([0, 6 * 3_600_000])                       # two epochs, six hours apart
    sp3 = Sp3Orbits(t_ms=t, sats=np.array(["G01"]), pos=np.zeros((2, 1, 3)), source="p.sp3",
                    clock=np.full((2, 1), clock))
    rows = pd.DataFrame({"t_ns": (t0 + 3_600_000 + 1000 * np.arange(3)) * 1_000_000})
    with pytest.raises(DataError, match=rf"covers 2021-04-28 18:00:00 to 2021-04-29 00:00:00: {said}"):
        _check_coverage(SimpleNamespace(path="x.21o"), rows, np.zeros(3, bool), None, PreciseOrbits(sp3))
