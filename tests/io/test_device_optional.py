"""GSDC 2022/2023 device_gnss: the optional Trace fields (C/N0, Doppler, carrier phase)."""
from __future__ import annotations

import numpy as np
import pandas as pd

from fusion.io.gsdc import load_derived_2021, load_device_gnss


def _device(n_epochs=3, n_sats=5) -> pd.DataFrame:
    e, s = np.meshgrid(np.arange(n_epochs), np.arange(n_sats), indexing="ij")
    e, s = e.ravel(), s.ravel()
    ang = 0.4 * s
    state = np.where(s == 1, 0, np.where((s == 2) & (e == 1), 1 | 4, 1))  # sat 1 invalid, sat 2 slips once
    return pd.DataFrame({
        "MessageType": "Raw", "utcTimeMillis": 1_619_735_725_999 + 1000 * e,
        "HardwareClockDiscontinuityCount": 16, "ConstellationType": 1, "Svid": s + 2, "SignalType": "GPS_L1_CA",
        "SvPositionXEcefMeters": 2.6e7 * np.cos(ang), "SvPositionYEcefMeters": 2.6e7 * np.sin(ang),
        "SvPositionZEcefMeters": 1.0e6 * s, "SvClockBiasMeters": 100.0 + s,
        "RawPseudorangeMeters": 2.2e7 + 1e5 * s, "RawPseudorangeUncertaintyMeters": 4.0,
        "IsrbMeters": 0.0, "IonosphericDelayMeters": 3.0, "TroposphericDelayMeters": 2.0,
        "Cn0DbHz": 30.0 + s, "PseudorangeRateMetersPerSecond": np.where(s == 3, np.nan, -100.0 * s),
        "PseudorangeRateUncertaintyMetersPerSecond": 0.1, "SvClockDriftMetersPerSecond": 0.01 * s,
        "AccumulatedDeltaRangeMeters": 1000.0 * s + 10 * e, "AccumulatedDeltaRangeUncertaintyMeters": 0.003,
        "AccumulatedDeltaRangeState": state,
    })


def test_optional_fields_semantics(tmp_path):
    path = tmp_path / "device_gnss.csv"
    _device().to_csv(path, index=False)
    tr = load_device_gnss(path, min_sats=0)
    s = tr.sat_id - 1002                       # slot = satellite here (rows sorted by svid)
    np.testing.assert_allclose(tr.cn0, 30.0 + s)
    ok = s != 3
    assert (tr.prr_ok == ok).all() and tr.has_doppler
    np.testing.assert_allclose(tr.prr[ok], (-100.0 * s + 0.01 * s)[ok])   # satellite clock drift removed
    assert (tr.prr[~ok] == 0).all() and (tr.prr_sigma[~ok] == 1).all() and (tr.prr_sigma[ok] == 0.1).all()
    aok = s != 1
    assert (tr.adr_ok == aok).all() and tr.has_carrier
    e = np.arange(3)[:, None]
    np.testing.assert_allclose(tr.adr[aok], (1000.0 * s + 10 * e + 100.0 + s)[aok])  # + satellite clock
    assert tr.adr_slip.sum() == 1 and tr.adr_slip[1, 2]


def test_an_epoch_dropped_for_too_few_satellites_breaks_every_carrier_chain_across_it(tmp_path):
    """Epoch 1 keeps two satellites (dropped at min_sats=4); the slip flagged there must not vanish,
    and the phase between epochs 0 and 2 may hide others: every slot slips on epoch 2."""
    df = _device(n_epochs=4)
    df = df[~((df["utcTimeMillis"] == df["utcTimeMillis"].unique()[1]) & (df["Svid"] > 3))]
    path = tmp_path / "device_gnss.csv"
    df.to_csv(path, index=False)
    tr = load_device_gnss(path, min_sats=4)
    assert tr.n_epochs == 3 and tr.skipped["epochs_lt4_sats"] == 1
    assert tr.adr_slip[1][tr.mask[1]].all()
    assert not tr.adr_slip[2].any() and not tr.adr_slip[0].any()


def test_optional_fields_absent(tmp_path):
    path = tmp_path / "device_gnss.csv"
    _device().drop(columns=["SvClockDriftMetersPerSecond", "AccumulatedDeltaRangeState", "Cn0DbHz"]).to_csv(path, index=False)
    tr = load_device_gnss(path, min_sats=0)
    # Without the drift the Doppler cannot be put on the pr's footing: left out, not faked.
    assert tr.prr is None and tr.adr is None and tr.cn0 is None


def test_real_samples_carrier_agrees_with_doppler(shared_data):
    """Between consecutive epochs without a slip, the change of carrier phase is the integral of the
    pseudorange rate: both carry the same satellite-clock correction, so they agree to decimetres."""
    for p in ("gsdc2022/samples/device_gnss.csv", "gsdc2023/samples/2023-09-07-18-59-us-ca/pixel7pro/device_gnss.csv"):
        tr = load_device_gnss(shared_data / p, signals="all")
        assert tr.has_doppler and tr.has_carrier
        same = (tr.sat_id[1:] == tr.sat_id[:-1]) & (tr.signal[1:] == tr.signal[:-1])
        m = same & tr.adr_ok[1:] & tr.adr_ok[:-1] & ~tr.adr_slip[1:] & tr.prr_ok[1:] & tr.prr_ok[:-1]
        dt = np.diff(tr.t_ms)[:, None] / 1000.0
        gap = (tr.adr[1:] - tr.adr[:-1]) - 0.5 * (tr.prr[1:] + tr.prr[:-1]) * dt
        assert m.sum() > 50 and np.median(np.abs(gap[m])) < 0.2


def test_derived_2021_unchanged(shipped_trace_dir):
    tr = load_derived_2021(shipped_trace_dir / "Pixel4_derived.csv.gz")
    assert tr.cn0 is None and tr.prr is None and tr.adr is None
