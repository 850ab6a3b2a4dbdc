"""Klobuchar and Saastamoinen against the GSDC 2021 derived file's ionoDelayM / tropoDelayM (the
shipped 2021-04-28-US-MTV-1/Pixel4 trace, whose navigation day is the shipped hour1180.21n)."""
from __future__ import annotations

import numpy as np
import pandas as pd

from fusion.geometry import ecef2geodetic, elevation_azimuth, line_of_sight
from fusion.io.rinex_nav import default_nav_path, read_nav
from fusion.io.truth import llh_ecef, match_nearest, read_truth_csv
from fusion.nav.atmosphere import iono_scale, klobuchar_l1, saastamoinen_zenith, tropo_delay, tropo_mapping


def _derived_rows(folder):
    df = pd.read_csv(folder / "Pixel4_derived.csv.gz")
    t = df["millisSinceGpsEpoch"].to_numpy() - 1000          # derived times are one epoch late
    tr = read_truth_csv(folder / "ground_truth.csv")
    rx = match_nearest(t, tr["t_ms"].to_numpy(), llh_ecef(tr.assign(height_m=tr["height_m"] - 63.1)), 20)
    ok = np.isfinite(rx).all(axis=1)
    df, rx, t = df[ok], rx[ok], t[ok]
    _, los = line_of_sight(df[["xSatPosM", "ySatPosM", "zSatPosM"]].to_numpy()[:, None, :], rx)
    el, az = elevation_azimuth(los, rx)
    return df, rx, t, el[:, 0], az[:, 0]


def test_iono_and_tropo_vs_gsdc_derived(shipped_trace_dir):
    df, rx, t, el, az = _derived_rows(shipped_trace_dir)
    llh = ecef2geodetic(rx)
    nav = read_nav(default_nav_path())
    iono = klobuchar_l1(nav.klobuchar, llh[:, 0], llh[:, 1], az, el, (t % 604_800_000) / 1000.0)
    d_iono = np.abs(iono - df["ionoDelayM"].to_numpy())
    assert len(d_iono) > 10_000 and np.median(df["ionoDelayM"]) > 3.0
    assert d_iono.max() < 0.01                           # same model, same coefficients: < 1 cm
    trop = tropo_delay(llh[:, 0], llh[:, 2], el)
    d_trop = np.abs(trop - df["tropoDelayM"].to_numpy())
    high = el > 15
    # a different mapping function: decimetres at most above 15 degrees, 2.5 m zenith delays
    assert np.median(d_trop) < 0.2 and np.percentile(d_trop[high], 99) < 0.3


def test_model_shapes_and_limits():
    # L5 delay = L1 delay * (f1/f5)^2 = 1.79x
    np.testing.assert_allclose(iono_scale(np.array([1575.42e6, 1176.45e6])), [1.0, 1.7933], rtol=1e-4)
    z = saastamoinen_zenith(np.array([0.0, 45.0]), np.array([0.0, 0.0]))
    assert np.all((z > 2.3) & (z < 2.6))                 # ~2.3 m dry + wet at sea level
    assert saastamoinen_zenith(37.0, 3000.0) < 0.75 * saastamoinen_zenith(37.0, 0.0)
    m = tropo_mapping(np.array([90.0, 30.0, 5.0, 0.0, -3.0]))
    assert abs(m[0] - 1.0) < 1e-3 and abs(m[1] - 2.0) < 0.01 and np.all(np.isfinite(m)) and m[3] == m[4]
    night = klobuchar_l1(np.r_[np.full(4, 1e-8), np.full(4, 1e5)], 37.0, -122.0, 0.0, 90.0, 10 * 3600.0)
    np.testing.assert_allclose(night, 5e-9 * 299_792_458.0 * (1 + 16 * (0.53 - 0.5) ** 3), rtol=1e-9)
