"""GSDC loaders: the shipped trace, the shared real traces (skipped when absent), bad input."""
from __future__ import annotations

import gzip
import shutil
from datetime import datetime, timezone

import numpy as np
import pandas as pd
import pytest

from fusion.errors import DataError, GnssfuseError
from fusion.geometry import C_LIGHT, ecef2geodetic, ecef2ned_vec, geodetic2ecef
from fusion.gpstime import GPS_EPOCH_UNIX_MS, gps_ms_to_unix_ms, unix_ms_to_gps_ms
from fusion.io.gsdc import load_derived_2021, load_device_gnss
from fusion.prepare.load import find_traces, load_dataset, load_trace
from fusion.io.truth import (GSDC2021_TRUTH_HEIGHT_ERROR_M, gsdc2021_height_offsets, interp_gapped, read_truth_csv)
from fusion.io.nmea import read_span_nmea
from fusion.trace import SIGNALS

SJC = "gsdc2021/train/2021-04-28-US-SJC-1/Pixel4"


# ---------------------------------------------------------------------------- synthetic files
def _derived_rows(n_epochs=3, n_sats=5, t0=1_303_683_549_433, collection="2021-04-28-US-MTV-1"):
    """Plausible GSDC 2021 derived rows (one epoch late, like the real files)."""
    e, s = np.meshgrid(np.arange(n_epochs), np.arange(n_sats), indexing="ij")
    e, s = e.ravel(), s.ravel()
    t = t0 + 1000 * e
    raw = 2.2e7 + 1e5 * s
    ang = 0.4 * s
    return pd.DataFrame({
        "collectionName": collection, "phoneName": "Pixel4", "millisSinceGpsEpoch": t,
        "constellationType": 1, "svid": s + 2, "signalType": "GPS_L1",
        # receive time = millis - 1000, so received = that - flight time
        "receivedSvTimeInGpsNanos": (t - 1000) * 1_000_000 - np.round(raw / C_LIGHT * 1e9).astype(np.int64),
        "xSatPosM": 2.6e7 * np.cos(ang), "ySatPosM": 2.6e7 * np.sin(ang), "zSatPosM": 1.0e6 * s,
        "xSatVelMps": 100.0, "ySatVelMps": 200.0, "zSatVelMps": 300.0,
        "satClkBiasM": 100.0, "satClkDriftMps": 0.0, "rawPrM": raw, "rawPrUncM": 5.0, "isrbM": 0.0,
        "ionoDelayM": 3.0, "tropoDelayM": 2.0,
    })


def _truth_rows(times, height=58.31):
    return pd.DataFrame({"collectionName": "c", "phoneName": "Pixel4", "millisSinceGpsEpoch": times,
                         "latDeg": 37.4, "lngDeg": -122.1, "heightAboveWgs84EllipsoidM": height})


def _write(tmp_path, df, name="Pixel4_derived.csv", truth=None, folder="coll/Pixel4"):
    d = tmp_path / folder
    d.mkdir(parents=True, exist_ok=True)
    df.to_csv(d / name, index=False)
    if truth is not None:
        truth.to_csv(d / "ground_truth.csv", index=False)
    return d


def _device_rows(n_epochs=4, n_sats=5, unix0=1_619_735_725_999, clk=None):
    e, s = np.meshgrid(np.arange(n_epochs), np.arange(n_sats), indexing="ij")
    e, s = e.ravel(), s.ravel()
    ang = 0.4 * s
    return pd.DataFrame({
        "MessageType": "Raw", "utcTimeMillis": unix0 + 1000 * e,
        "HardwareClockDiscontinuityCount": 16 if clk is None else np.asarray(clk)[e],
        "ConstellationType": 1, "Svid": s + 2, "SignalType": "GPS_L1_CA",
        "SvPositionXEcefMeters": 2.6e7 * np.cos(ang), "SvPositionYEcefMeters": 2.6e7 * np.sin(ang),
        "SvPositionZEcefMeters": 1.0e6 * s, "SvClockBiasMeters": 100.0,
        "RawPseudorangeMeters": 2.2e7 + 1e5 * s, "RawPseudorangeUncertaintyMeters": 4.0,
        "IsrbMeters": 0.0, "IonosphericDelayMeters": 3.0, "TroposphericDelayMeters": 2.0,
    })


# ---------------------------------------------------------------------------- shipped trace
def test_shipped_trace_loads(shipped_trace_dir):
    tr = load_trace(shipped_trace_dir)
    assert tr.name == "2021-04-28-US-MTV-1/Pixel4"
    assert tr.n_epochs == 1998 and tr.n_slots >= 8
    assert np.isfinite(tr.truth).all(axis=1).sum() == 1998
    m = tr.mask
    assert (tr.n_sats >= 4).all()
    assert (tr.signal[m] == SIGNALS.index("GPS_L1")).all()
    assert ((tr.sat_id[m] > 1000) & (tr.sat_id[m] <= 1032)).all()
    r = np.linalg.norm(tr.sat_pos[m], axis=-1)
    assert r.min() > 2.5e7 and r.max() < 2.75e7             # GPS orbit radius ~26,560 km
    assert tr.pr[m].min() > 1.9e7 and tr.pr[m].max() < 2.7e7
    assert (np.diff(tr.t_ms) > 0).all() and not tr.clock_reset.any()
    # pr minus the geometric range to truth is the receiver clock plus metres of error: its spread
    # within an epoch (Sagnac, iono/tropo residuals, multipath) stays well under 100 m.
    rng = np.linalg.norm(tr.sat_pos - tr.truth[:, None, :], axis=-1)
    resid = np.where(m, tr.pr - rng, np.nan)
    spread = np.nanmax(resid, axis=1) - np.nanmin(resid, axis=1)
    assert np.median(spread) < 60 and np.percentile(spread, 95) < 150


def test_shipped_trace_time_shift(shipped_trace_dir):
    """Trace times are the rows' own receive times; truth rows sit at those times (trap a)."""
    raw = pd.read_csv(shipped_trace_dir / "Pixel4_derived.csv.gz")
    rx_ms = raw["receivedSvTimeInGpsNanos"] / 1e6 + raw["rawPrM"] / C_LIGHT * 1e3
    late = (raw["millisSinceGpsEpoch"] - rx_ms).to_numpy()
    assert np.all(np.abs(late - 1000) < 2)                     # the file is one epoch late
    tr = load_trace(shipped_trace_dir)
    assert np.isin(tr.t_ms, raw["millisSinceGpsEpoch"].to_numpy() - 1000).all()
    truth_t = read_truth_csv(shipped_trace_dir / "ground_truth.csv")["t_ms"].to_numpy()
    nearest = np.abs(truth_t[np.searchsorted(truth_t, tr.t_ms).clip(0, truth_t.size - 1)] - tr.t_ms)
    assert nearest.max() <= 2


def test_shipped_truth_height_fix(shipped_trace_dir):
    fixed = load_trace(shipped_trace_dir)
    raw = load_trace(shipped_trace_dir, fix_truth_height=False)
    dh = ecef2geodetic(raw.truth)[:, 2] - ecef2geodetic(fixed.truth)[:, 2]
    np.testing.assert_allclose(dh, GSDC2021_TRUTH_HEIGHT_ERROR_M, atol=1e-6)
    # Mountain View is ~30 m above sea level with a geoid ~ -32 m: ellipsoidal height near 0.
    assert -15 < np.median(ecef2geodetic(fixed.truth)[:, 2]) < 10
    assert load_trace(shipped_trace_dir, truth="none").truth is None


def test_csv_and_gz_load_identically(shipped_trace_dir, tmp_path):
    d = tmp_path / "c" / "Pixel4"
    d.mkdir(parents=True)
    with gzip.open(shipped_trace_dir / "Pixel4_derived.csv.gz", "rb") as src, open(d / "Pixel4_derived.csv", "wb") as dst:
        shutil.copyfileobj(src, dst)
    shutil.copy(shipped_trace_dir / "ground_truth.csv", d)
    gz = tmp_path / "g" / "Pixel4"
    gz.mkdir(parents=True)
    shutil.copy(shipped_trace_dir / "Pixel4_derived.csv.gz", gz)
    with open(shipped_trace_dir / "ground_truth.csv", "rb") as src, gzip.open(gz / "ground_truth.csv.gz", "wb") as dst:
        shutil.copyfileobj(src, dst)
    a, b = load_trace(d), load_trace(gz)
    np.testing.assert_array_equal(a.t_ms, b.t_ms)
    np.testing.assert_array_equal(a.pr, b.pr)
    assert a.truth is not None
    np.testing.assert_array_equal(a.truth, b.truth)


# ---------------------------------------------------------------------------- shared real traces
def test_span_nmea_confirms_shift_and_height(shared_data):
    """On SJC: the CSV truth is the SPAN fix at t_ms (not one second off) and ~63.1 m too high."""
    folder = shared_data / SJC
    nmea = folder / "supplemental" / "SPAN_Pixel4_10Hz.nmea"
    off = gsdc2021_height_offsets(folder / "ground_truth.csv", nmea)
    off = off[np.isfinite(off)]
    assert off.size > 1900 and 63.0 < np.median(off) < 63.25 and off.std() < 0.05
    raw = load_trace(folder, truth="csv", fix_truth_height=False)
    span = read_span_nmea(nmea)
    llh = span[["lat_deg", "lon_deg", "height_m"]].to_numpy()
    horiz = {}
    for shift in (0, 1000):
        s = interp_gapped(raw.t_ms + shift, span["t_ms"].to_numpy(), geodetic2ecef(llh))
        ned = ecef2ned_vec(raw.truth - s, s)
        horiz[shift] = np.median(np.hypot(ned[:, 0], ned[:, 1]))
    assert horiz[0] < 0.05 and horiz[1000] > 1.0
    # auto truth = SPAN: heights differ from the fixed CSV by only the residual of the fixed 63.1 m
    auto, csv = load_trace(folder), load_trace(folder, truth="csv")
    dh = ecef2geodetic(csv.truth)[:, 2] - ecef2geodetic(auto.truth)[:, 2]
    assert np.abs(dh - (np.median(off) - GSDC2021_TRUTH_HEIGHT_ERROR_M)).max() < 0.1


def test_signal_selection_sjc(shared_data):
    folder = shared_data / SJC
    l1 = load_trace(folder, truth="none")
    assert (l1.signal[l1.mask] == 0).all()
    two = load_trace(folder, signals=("GPS_L1", "GAL_E1_C_P"), truth="none")
    got = set(np.unique(two.signal[two.mask]))
    assert got == {SIGNALS.index("GPS_L1"), SIGNALS.index("GAL_E1")}
    assert two.mask.sum() > l1.mask.sum()
    every = load_trace(folder, signals="all", truth="none")
    assert len(np.unique(every.signal[every.mask])) == 6
    # one row per satellite per signal per epoch
    key = every.sat_id.astype(np.int64) * 100 + every.signal
    for e in (0, every.n_epochs // 2):
        k = key[e][every.mask[e]]
        assert k.size == np.unique(k).size
    with pytest.raises(GnssfuseError, match="unknown signal"):
        load_trace(folder, signals=("GPS_L9",))


def test_unshifted_rows_are_retimed(shared_data):
    """SF-2 has rows (and whole epochs) that are not one epoch late: none may be mixed into an
    epoch one second away from its own receive time."""
    path = shared_data / "gsdc2021/train/2020-09-04-US-SF-2/Pixel4/Pixel4_derived.csv"
    raw = pd.read_csv(path)
    rx = (raw["receivedSvTimeInGpsNanos"] / 1e6 + raw["rawPrM"] / C_LIGHT * 1e3).to_numpy()
    assert (np.abs(raw["millisSinceGpsEpoch"] - rx) < 2).sum() > 10   # the trap is really there
    tr = load_derived_2021(path, min_sats=0)
    slots = pd.DataFrame(tr.sat_pos[tr.mask], columns=["xSatPosM", "ySatPosM", "zSatPosM"])
    slots["t_ms"] = np.broadcast_to(tr.t_ms[:, None], tr.mask.shape)[tr.mask]
    raw["rx"] = rx
    both = raw.merge(slots, on=["xSatPosM", "ySatPosM", "zSatPosM"], how="inner", validate="one_to_one")
    assert len(both) == len(raw) == tr.mask.sum()
    assert np.abs(both["t_ms"] - both["rx"]).max() < 2


def test_other_shared_samples(shared_data):
    s = shared_data / "gsdc2021/samples"
    clk = load_trace(s / "Pixel4_derived_clkdiscnt.csv", signals="all")
    assert clk.n_epochs == 10 and not clk.clock_reset.any() and clk.has_truth
    nt = load_trace(s / "Pixel4XL_derived.csv")
    assert nt.truth is None and nt.n_epochs > 250
    # every derived file is found; the samples folder contributes each file on its own
    found = find_traces(shared_data)
    assert shared_data / SJC in found and s / "Pixel4XL_derived.csv" in found
    assert not any(p.name == "Pixel5" for p in found)   # RINEX only: no loader yet


def test_gsdc2022_and_2023_samples(shared_data):
    d22 = shared_data / "gsdc2022/samples"
    t22 = load_trace(d22, signals="all")
    raw = pd.read_csv(d22 / "device_gnss.csv")
    assert t22.n_epochs == raw["utcTimeMillis"].nunique() == 6
    assert np.isfinite(t22.truth).all() and not t22.clock_reset.any()
    arrival = raw.groupby("utcTimeMillis")["ArrivalTimeNanosSinceGpsEpoch"].first().to_numpy() / 1e6
    assert np.abs(t22.t_ms - arrival).max() < 1.0               # Unix -> GPS with 18 leap seconds
    n_missing = sum(v for k, v in t22.skipped.items() if k.startswith("rows_missing:"))
    assert n_missing == raw["RawPseudorangeMeters"].isna().sum()
    # truth heights are ellipsoidal already (Mountain View: near 0), no 63 m correction
    assert -15 < np.median(ecef2geodetic(t22.truth)[:, 2]) < 10

    d23 = shared_data / "gsdc2023/samples/2023-09-07-18-59-us-ca/pixel7pro"
    t23 = load_trace(d23)                                     # GPS_L1 <- GPS_L1_CA
    assert t23.name == "2023-09-07-18-59-us-ca/pixel7pro"
    assert t23.n_epochs == 5 and np.isfinite(t23.truth).all() and (t23.signal[t23.mask] == 0).all()
    gal = load_trace(d23, signals=("GAL_E1",), min_sats=0)    # <- GAL_E1_C_P
    assert gal.mask.sum() > 0
    with pytest.raises(DataError, match="nmea"):
        load_trace(d23, truth="nmea")


# ---------------------------------------------------------------------------- formats & traps
def test_device_gnss_clock_reset(tmp_path):
    clk = [3, 3, 4, 4, 5, 5]
    df = _device_rows(n_epochs=6, clk=clk)
    df = df.drop(df[(df["utcTimeMillis"] == df["utcTimeMillis"].unique()[4]) & (df["Svid"] > 3)].index)
    d = _write(tmp_path, df, "device_gnss.csv")
    tr = load_trace(d)
    assert tr.skipped["epochs_lt4_sats"] == 1
    # epoch 4 (count 5) was skipped: the jump still shows on epoch 5
    np.testing.assert_array_equal(tr.clock_reset, [False, False, True, False, True])
    every = load_device_gnss(d / "device_gnss.csv", min_sats=0)
    np.testing.assert_array_equal(every.clock_reset, [False, False, True, False, True, False])
    np.testing.assert_array_equal(tr.t_ms[0], unix_ms_to_gps_ms(1_619_735_725_999))


def test_retime_synthetic(tmp_path):
    df = _derived_rows(n_epochs=3, n_sats=5)
    # epoch 2's rows were stamped on time, not one epoch late: they belong one second later
    late = df["millisSinceGpsEpoch"] == df["millisSinceGpsEpoch"].max()
    df.loc[late, "receivedSvTimeInGpsNanos"] += 1_000_000_000
    tr = load_derived_2021(_write(tmp_path, df) / "Pixel4_derived.csv")
    t0 = 1_303_683_549_433 - 1000
    np.testing.assert_array_equal(tr.t_ms, [t0, t0 + 1000, t0 + 3000])
    # a bad receive time (0) must not move its row to 1980: it keeps the files' one-epoch rule
    df.loc[0, "receivedSvTimeInGpsNanos"] = 0
    tr = load_derived_2021(_write(tmp_path, df, folder="bad/Pixel4") / "Pixel4_derived.csv", min_sats=1)
    np.testing.assert_array_equal(tr.t_ms, [t0, t0 + 1000, t0 + 3000])
    assert tr.n_sats.tolist() == [5, 5, 5]


def test_read_span_nmea(tmp_path):
    def sentence(body):
        cs = 0
        for ch in body:
            cs ^= ord(ch)
        return f"${body}*{cs:02X}"
    gga = "GPGGA,{},3720.0499537,N,12154.0145819,W,{},14,0.6,25.25,M,-32.64,M,,"
    lines = [sentence("GPRMC,235959.80,A,3720.050,N,12154.015,W,0.0,45.3,280421,,,A"),
             sentence(gga.format("235959.80", 1)), sentence(gga.format("235959.90", 0)),
             sentence(gga.format("000000.00", 1)),
             sentence(gga.format("000000.10", 1))[:-2] + "00", "garbage"]
    p = tmp_path / "SPAN_Pixel4_10Hz.nmea"
    p.write_text("\n".join(lines) + "\n")
    skipped = {}
    df = read_span_nmea(p, skipped=skipped)
    assert skipped == {"nmea_no_fix": 1, "nmea_bad_checksum": 1}
    expect0 = (datetime(2021, 4, 28, 23, 59, 59, 800000, tzinfo=timezone.utc).timestamp() * 1000
               - GPS_EPOCH_UNIX_MS + 18_000)
    np.testing.assert_array_equal(df["t_ms"], [int(round(expect0)), int(round(expect0)) + 200])  # over midnight
    np.testing.assert_allclose(df["height_m"], 25.25 - 32.64)
    np.testing.assert_allclose(df["lat_deg"], 37 + 20.0499537 / 60)
    np.testing.assert_allclose(df["lon_deg"], -(121 + 54.0145819 / 60))
    # without RMC the date comes from a reference time
    p2 = tmp_path / "no_rmc.nmea"
    p2.write_text("\n".join(lines[1:2]) + "\n")
    assert read_span_nmea(p2, ref_gps_ms=int(expect0) + 5000)["t_ms"].iat[0] == int(round(expect0))
    with pytest.raises(DataError, match="RMC"):
        read_span_nmea(p2)
    with pytest.raises(DataError, match="more than a day"):
        read_span_nmea(p, ref_gps_ms=int(expect0) + 10 * 86_400_000)
    # the RMC dates 23:59:59.8 but the first GGA with a fix is after midnight: the next day
    p3 = tmp_path / "rmc_before_midnight.nmea"
    p3.write_text("\n".join([lines[0], lines[2], lines[3]]) + "\n")
    assert read_span_nmea(p3)["t_ms"].iat[0] == int(round(expect0)) + 200


def test_gpstime_roundtrip():
    u = np.array([1_483_228_799_000, 1_483_228_800_000, 1_619_735_725_999])
    g = unix_ms_to_gps_ms(u)
    np.testing.assert_array_equal(g - (u - GPS_EPOCH_UNIX_MS), [17_000, 18_000, 18_000])
    np.testing.assert_array_equal(gps_ms_to_unix_ms(g), u)


# ---------------------------------------------------------------------------- bad input
def test_missing_and_empty_files(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_derived_2021(tmp_path / "nope_derived.csv")
    with pytest.raises(DataError, match="no such trace"):
        load_trace(tmp_path / "nope")
    with pytest.raises(DataError, match="no .*measurement file"):
        load_trace(tmp_path)
    e = tmp_path / "e_derived.csv"
    e.write_text("")
    with pytest.raises(DataError, match="empty"):
        load_derived_2021(e)
    h = tmp_path / "h_derived.csv"
    h.write_text(",".join(_derived_rows().columns) + "\n")
    with pytest.raises(DataError, match="no data rows"):
        load_derived_2021(h)
    g = tmp_path / "g_derived.csv.gz"
    g.write_bytes(b"\x1f\x8b\x08\x00garbage")
    with pytest.raises(DataError, match=f"{g.name}: corrupt gzip"):
        load_derived_2021(g)


def test_missing_columns_named(tmp_path):
    d = _write(tmp_path, _derived_rows().drop(columns=["rawPrM", "isrbM"]))
    with pytest.raises(DataError, match="rawPrM, isrbM"):
        load_trace(d)
    t = tmp_path / "t.csv"
    pd.DataFrame({"foo": [1]}).to_csv(t, index=False)
    with pytest.raises(DataError, match="latDeg"):
        read_truth_csv(t)


def test_non_numeric_row_skipped_and_counted_per_column(tmp_path):
    df = _derived_rows(n_epochs=3, n_sats=6).astype({"rawPrM": object, "ionoDelayM": object})
    df.loc[7, "rawPrM"] = "abc"
    df.loc[3, "ionoDelayM"] = "inf"
    df.loc[3, "rawPrM"] = "x"                       # counted once, under its first bad column
    tr = load_trace(_write(tmp_path, df))
    assert tr.skipped == {"rows_nonnumeric:rawPrM": 2}
    assert tr.n_epochs == 3 and tr.mask.sum() == 16
    df.loc[3, "rawPrM"] = 2.2e7
    tr = load_trace(_write(tmp_path, df, folder="b/Pixel4"))
    assert tr.skipped == {"rows_nonnumeric:rawPrM": 1, "rows_nonfinite:ionoDelayM": 1}


def test_nan_rows_dropped_and_counted(tmp_path):
    df = _derived_rows(n_epochs=3, n_sats=6)
    df.loc[[0, 8], "ionoDelayM"] = np.nan
    tr = load_trace(_write(tmp_path, df))
    assert tr.skipped["rows_missing:ionoDelayM"] == 2 and tr.n_epochs == 3 and tr.mask.sum() == 16
    # a row missing only the satellite velocity (used by no estimator) keeps its pseudorange
    vel = _derived_rows(n_epochs=3, n_sats=6)
    vel.loc[[2], ["xSatVelMps", "ySatVelMps"]] = np.nan
    tv = load_trace(_write(tmp_path, vel, folder="v/Pixel4"))
    assert not tv.skipped and tv.mask.sum() == 18
    assert (tv.sat_vel[tv.mask][:, 2] == 300.0).all() and (tv.sat_vel[tv.mask][:, 0] == 0.0).sum() == 1
    df["rawPrM"] = np.nan
    with pytest.raises(DataError, match=r"no usable measurement row .*rows_missing:rawPrM: 18"):
        load_trace(_write(tmp_path, df))


def test_duplicates_and_bad_values_counted(tmp_path):
    df = _derived_rows(n_epochs=2, n_sats=5)
    df = pd.concat([df, df.iloc[[3]]]).sort_values("millisSinceGpsEpoch", kind="stable")
    df.loc[df.index[1], ["xSatPosM", "ySatPosM", "zSatPosM"]] = 0.0   # satellite at the Earth's centre
    tr = load_trace(_write(tmp_path, df), min_sats=0)
    assert tr.skipped == {"duplicate_rows": 1, "rows_bad_values": 1}
    conflicting = _derived_rows(n_epochs=2, n_sats=5)
    conflicting = pd.concat([conflicting, conflicting.iloc[[3]].assign(rawPrM=2.3e7)])
    tc = load_trace(_write(tmp_path, conflicting, folder="c/Pixel4"))
    assert tc.skipped == {"conflicting_duplicate_rows": 1} and tc.mask.sum() == 10
    assert tr.mask.sum() == 9


def test_few_satellite_epochs_skipped(tmp_path):
    df = _derived_rows(n_epochs=4, n_sats=5)
    df = df.drop(df[(df["millisSinceGpsEpoch"] == df["millisSinceGpsEpoch"].unique()[1]) & (df["svid"] > 4)].index)
    d = _write(tmp_path, df)
    tr = load_trace(d)
    assert tr.n_epochs == 3 and tr.skipped["epochs_lt4_sats"] == 1
    all_ep = load_trace(d, min_sats=0)
    assert all_ep.n_epochs == 4 and all_ep.n_sats.tolist() == [5, 3, 5, 5] and "epochs_lt0_sats" not in all_ep.skipped
    with pytest.raises(DataError, match=">= 6 satellites"):
        load_trace(d, min_sats=6)


def test_truth_matching_and_no_overlap(tmp_path):
    df = _derived_rows(n_epochs=4)
    t_true = np.unique(df["millisSinceGpsEpoch"]) - 1000
    truth = _truth_rows(t_true[:3] + np.array([1, -15, 40]))     # third row too far: NaN
    tr = load_trace(_write(tmp_path, df, truth=truth))
    assert np.isfinite(tr.truth).all(axis=1).tolist() == [True, True, False, False]
    bad = _truth_rows(t_true + 3_600_000)
    with pytest.raises(DataError, match=r"do not overlap.*ground truth"):
        load_trace(_write(tmp_path, df, truth=bad, folder="c2/Pixel4"))
    nan_truth = _truth_rows(t_true)
    nan_truth.loc[1, "latDeg"] = np.nan
    tr = load_trace(_write(tmp_path, df, truth=nan_truth, folder="c3/Pixel4"))
    assert tr.skipped["truth_rows_missing:latDeg"] == 1 and np.isnan(tr.truth[1]).all()


def test_rows_out_of_time_order_are_reordered(tmp_path):
    df = _derived_rows(n_epochs=3)
    ref = load_trace(_write(tmp_path, df))
    by_sat = load_trace(_write(tmp_path, df.sort_values(["svid", "millisSinceGpsEpoch"]), folder="s/Pixel4"))
    shuffled = load_trace(_write(tmp_path, df.sample(frac=1.0, random_state=1), folder="r/Pixel4"))
    for tr in (by_sat, shuffled):
        assert not tr.skipped
        np.testing.assert_array_equal(tr.t_ms, ref.t_ms)
        np.testing.assert_array_equal(tr.pr, ref.pr)
        np.testing.assert_array_equal(tr.sat_id, ref.sat_id)
    dev = _device_rows()
    ref = load_trace(_write(tmp_path, dev, "device_gnss.csv", folder="d/Pixel4"))
    rev = load_trace(_write(tmp_path, dev.iloc[::-1], "device_gnss.csv", folder="e/Pixel4"))
    np.testing.assert_array_equal(rev.t_ms, ref.t_ms)
    np.testing.assert_array_equal(rev.pr, ref.pr)


def test_truth_out_of_order_and_duplicated(tmp_path):
    t = 1_303_683_548_434 + 1000 * np.arange(5)
    truth = _truth_rows(t)
    truth["latDeg"] = 37.4 + 1e-4 * np.arange(5)
    p = tmp_path / "gt.csv"
    pd.concat([truth.iloc[::-1], truth.iloc[[2]]]).to_csv(p, index=False)
    skipped = {}
    out = read_truth_csv(p, skipped)
    assert skipped == {"truth_duplicate_rows": 1}
    np.testing.assert_array_equal(out["t_ms"], t)
    np.testing.assert_allclose(out["lat_deg"], truth["latDeg"])


def test_find_traces_and_load_dataset(tmp_path, shipped_trace_dir):
    with pytest.raises(DataError, match="no such folder"):
        find_traces(tmp_path / "nope")
    with pytest.raises(DataError, match="no trace found"):
        find_traces(tmp_path)
    a = _write(tmp_path / "train", _derived_rows(), folder="c1/Pixel4")
    b = _write(tmp_path / "train", _device_rows(), "device_gnss.csv", folder="c2/Pixel7")
    bad = _write(tmp_path / "train", _derived_rows().drop(columns=["rawPrM"]), folder="c3/Pixel5")
    assert find_traces(tmp_path / "train") == [a, b, bad]
    assert find_traces(a) == [a]
    assert find_traces(shipped_trace_dir) == [shipped_trace_dir]
    with pytest.raises(DataError, match="rawPrM"):
        list(load_dataset(tmp_path / "train"))
    with pytest.warns(UserWarning, match="skipping trace"):
        names = [t.name for t in load_dataset(tmp_path / "train", on_error="skip")]
    assert names == ["c1/Pixel4", "c2/Pixel7"]


def test_resolve_signals_all_any_case():
    """Regression: "ALL", "All" or "all" among other names selects every signal."""
    from fusion.trace import resolve_signals

    every = np.arange(len(SIGNALS))
    for sel in ("all", "ALL", ["All"], ("GPS_L1", " all "), None):
        np.testing.assert_array_equal(resolve_signals(sel), every)
    np.testing.assert_array_equal(resolve_signals(["GAL_E1_C_P", "GPS_L1"]),
                                  [SIGNALS.index("GPS_L1"), SIGNALS.index("GAL_E1")])
    with pytest.raises(GnssfuseError, match="unknown signal"):
        resolve_signals(["GPS_L1", "allx"])


def test_interp_gapped_keeps_exact_fixes_next_to_a_gap():
    ref_t = np.array([0, 1000, 5000, 5100])
    val = np.arange(4.0)[:, None] * np.array([[1.0, 2.0]])
    out = interp_gapped(np.array([0, 500, 1000, 3000, 5000, 5050, 5100]), ref_t, val, max_gap_ms=250)
    np.testing.assert_allclose(out[[0, 2, 4, 6], 0], [0, 1, 2, 3])     # on fixes, even beside the gap
    assert np.isnan(out[[1, 3]]).all()                                 # inside gaps > 250 ms
    np.testing.assert_allclose(out[5], [2.5, 5.0])
