"""GnssLogger reader: pseudoranges against Google's own derived values, flags, malformed logs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fusion.errors import DataError
from fusion.io.gnss_log import read_gnss_log
from fusion.io.raw import check_raw
from fusion.trace import SIGNALS, signal_index

DATA = Path(__file__).resolve().parents[1] / "data"
PIXEL4_LOG = DATA / "pixel4_gnss_log.txt"              # GSDC 2021 samples/Pixel4_GnssLog.txt (one epoch)
PIXEL4_DERIVED = DATA / "pixel4_derived_first_epoch.csv"  # its rows of samples/Pixel4_derived.csv
P7_LOG = DATA / "pixel7pro_gnss_log_2ep.txt"           # first 2 epochs of the GSDC 2023 sample gnss_log.txt
P7_DEVICE = DATA / "pixel7pro_device_gnss_2ep.csv"     # the matching device_gnss.csv rows (some columns)


def _match_derived(frame: pd.DataFrame, derived: pd.DataFrame) -> pd.DataFrame:
    d = derived.assign(sat_id=derived.constellationType * 1000 + derived.svid)
    # Derived 2021 timestamps are the receive time + 1 s (data README, fact 1).
    f = frame.assign(ms=frame.t_ns // 10**6 + 1000)
    return f.merge(d, left_on=["ms", "sat_id", "signal"], right_on=["millisSinceGpsEpoch", "sat_id", "signalType"])


def _match_device(frame: pd.DataFrame, device: pd.DataFrame) -> pd.DataFrame:
    """Pair rows by epoch order, satellite and signal (2023 signal names lose their code suffix)."""
    d = device.assign(sat_id=device.ConstellationType * 1000 + device.Svid,
                      ep=np.searchsorted(np.unique(device.TimeNanos), device.TimeNanos))
    idx = signal_index(d.SignalType)
    d["signal"] = [SIGNALS[i] if i >= 0 else None for i in idx]
    f = frame.assign(ep=np.searchsorted(np.unique(frame.t_ns), frame.t_ns))
    return f.merge(d, on=["ep", "sat_id", "signal"])


def _check_2021(log: Path, derived: Path) -> None:
    raw = read_gnss_log(log)
    check_raw(raw.frame)
    m = _match_derived(raw.frame, pd.read_csv(derived))
    assert len(m) >= 0.9 * len(raw.frame) and len(m) > 20
    # rawPrM is written with 3 decimals: agreement to the millimetre.
    assert np.abs(m.pr_m - m.rawPrM).max() < 1e-3
    assert np.abs(m.pr_sigma_m - m.rawPrUncM).max() < 1e-3


def _check_2023(log: Path, device: Path) -> None:
    dev = pd.read_csv(device)
    for fixed in (False, True):
        m = _match_device(read_gnss_log(log, fixed_full_bias=fixed).frame, dev)
        assert len(m) >= 0.9 * len(dev)
        diff = m.pr_m - m.RawPseudorangeMeters
        assert diff.notna().all()
        # Google's 2023 values hold FullBiasNanos at the drive's first epoch: an offset common to
        # every satellite (per epoch with our per-epoch bias, for the whole log with ours fixed).
        spread = diff.groupby(m.ep if not fixed else np.zeros(len(m))).agg(np.ptp)
        assert spread.max() < 1e-3
        np.testing.assert_allclose(m.prr_mps, m.PseudorangeRateMetersPerSecond, atol=1e-9)
        np.testing.assert_allclose(m.cn0, m.Cn0DbHz, atol=1e-9)
        ok = m.adr_ok.to_numpy()
        assert ok.sum() > 10 and (ok == ((m.AccumulatedDeltaRangeState & 1) == 1)).all()
        np.testing.assert_allclose(m.adr_m[ok], m.AccumulatedDeltaRangeMeters[ok], atol=1e-9)


def test_pixel4_fixture_matches_derived_rawPrM():
    _check_2021(PIXEL4_LOG, PIXEL4_DERIVED)


def test_pixel7pro_fixture_matches_device_gnss():
    _check_2023(P7_LOG, P7_DEVICE)


def test_shared_samples(shared_data):
    _check_2021(shared_data / "gsdc2021/samples/Pixel4_GnssLog.txt", shared_data / "gsdc2021/samples/Pixel4_derived.csv")
    d = shared_data / "gsdc2023/samples/2023-09-07-18-59-us-ca/pixel7pro"
    _check_2023(d / "gnss_log.txt", d / "device_gnss.csv")


def test_signals_glonass_and_flags():
    f = read_gnss_log(PIXEL4_LOG).frame
    assert set(f.signal) == {"GPS_L1", "GPS_L5", "GLO_G1", "GAL_E1", "GAL_E5A"}
    glo = f[f.const == "R"]
    np.testing.assert_allclose(glo.carrier_hz, 1602e6 + glo.glo_k * 0.5625e6, rtol=1e-9)
    assert ((glo.glo_k >= -7) & (glo.glo_k <= 6)).all() and (f.glo_k[f.const != "R"] == 0).all()
    # ADR state 25 (valid | half-cycle resolved | ...) = no slip; states with bit 2 or 4 = slip.
    assert f.adr_slip.any() and not f.adr_slip[~f.adr_ok].any()
    assert not f.clock_reset.any()


def _edit(tmp_path: Path, src: Path, fn) -> Path:
    lines = src.read_text().splitlines(keepends=True)
    out = tmp_path / "gnss_log.txt"
    out.write_text("".join(fn(lines)))
    return out


def _raw_index(lines: list[str], k: int = 0) -> int:
    return [i for i, l in enumerate(lines) if l.startswith("Raw,")][k]


def test_state_clock_discontinuity_and_adr_bits(tmp_path):
    def edit(lines):
        header = next(l for l in lines if l.startswith("# Raw,"))[2:].strip().split(",")
        col = {n: i for i, n in enumerate(header)}
        out = []
        for l in lines:
            if l.startswith("Raw,"):
                v = l.rstrip("\n").split(",")
                if int(v[col["TimeNanos"]]) > 67624000000:
                    v[col["HardwareClockDiscontinuityCount"]] = "11"  # second epoch: the clock jumped
                if v[col["Svid"]] == "2" and v[col["ConstellationType"]] == "1":
                    v[col["State"]] = "1"  # code lock only: no time of week, pseudorange ambiguous
                    v[col["AccumulatedDeltaRangeState"]] = "5"  # valid + cycle slip
                l = ",".join(v) + "\n"
            out.append(l)
        return out
    raw = read_gnss_log(_edit(tmp_path, P7_LOG, edit))
    f = raw.frame
    epochs = np.unique(f.t_ns)
    assert list(f.groupby("t_ns").clock_reset.all()) == [False, True]
    assert list(f.groupby("t_ns").clock_reset.any()) == [False, True]
    g2 = f[(f.sat_id == 1002) & (f.signal == "GPS_L1")]
    assert g2.pr_m.isna().all() and g2.prr_mps.notna().all() and len(g2) == len(epochs)
    assert g2.adr_slip.all() and g2.adr_ok.all()
    assert raw.skipped["pr_state_invalid"] == 2


def test_truncated_last_line_and_bad_number(tmp_path):
    def edit(lines):
        i = _raw_index(lines, 3)
        v = lines[i].split(",")
        v[14] = "12x4"  # ReceivedSvTimeNanos
        lines[i] = ",".join(v)
        j = _raw_index(lines, 5)
        v = lines[j].split(",")
        v[16] = "3O.5"  # Cn0DbHz with a letter O
        lines[j] = ",".join(v)
        return lines + ["Raw,1589494245442,21091250000000,,,-12735083"]
    p = _edit(tmp_path, PIXEL4_LOG, edit)
    bad_line = _raw_index(p.read_text().splitlines(), 3) + 1
    n_lines = len(p.read_text().splitlines())
    with pytest.warns(UserWarning) as rec:
        raw = read_gnss_log(p)
    messages = " | ".join(str(w.message) for w in rec)
    assert f"gnss_log.txt:{n_lines}: wrong number of fields" in messages
    assert f"gnss_log.txt:{bad_line}: unreadable number" in messages
    assert raw.skipped["records_wrong_field_count"] == 1 and raw.skipped["records_bad_number"] == 2
    assert len(raw.frame) == len(read_gnss_log(PIXEL4_LOG).frame) - 2


def test_missing_gnss_time_is_counted(tmp_path):
    def edit(lines):
        i = _raw_index(lines, 0)
        v = lines[i].split(",")
        v[5] = ""  # FullBiasNanos
        lines[i] = ",".join(v)
        return lines
    raw = read_gnss_log(_edit(tmp_path, PIXEL4_LOG, edit))
    assert raw.skipped["records_no_gnss_time"] == 1


def test_a_blank_svid_or_state_is_a_counted_skip(tmp_path):
    """A record with an empty Svid names no satellite (read as a number it would become a huge
    negative one and miss every ephemeris); an empty State says nothing of the pseudorange."""
    def edit(lines):
        header = next(l for l in lines if l.startswith("# Raw,"))[2:].strip().split(",")
        col = {n: i for i, n in enumerate(header)}
        for k, name in ((0, "Svid"), (1, "State")):
            i = _raw_index(lines, k)
            v = lines[i].split(",")
            v[col[name]] = ""
            lines[i] = ",".join(v)
        return lines
    raw = read_gnss_log(_edit(tmp_path, PIXEL4_LOG, edit))
    assert raw.skipped["records_blank_svid_constellation_or_state"] == 2
    assert len(raw.frame) == len(read_gnss_log(PIXEL4_LOG).frame) - 2
    assert (raw.frame.svid > 0).all()


def test_unusable_files_are_one_line_errors(tmp_path):
    garbage = tmp_path / "garbage.txt"
    garbage.write_bytes(bytes(range(256)) * 20)
    with pytest.raises(DataError, match=r"garbage\.txt: no '# Raw"):
        read_gnss_log(garbage)
    header_only = _edit(tmp_path, PIXEL4_LOG, lambda ls: [l for l in ls if not l.startswith("Raw,")])
    with pytest.raises(DataError, match="no 'Raw,' records"):
        read_gnss_log(header_only)
    no_col = _edit(tmp_path, PIXEL4_LOG, lambda ls: [l.replace(",FullBiasNanos,", ",FullBias,") for l in ls])
    with pytest.raises(DataError, match="lacks column.*FullBiasNanos"):
        read_gnss_log(no_col)
    with pytest.raises(DataError, match="absent.txt: GnssLogger file not found"):
        read_gnss_log(tmp_path / "absent.txt")


def test_second_frequencies_by_carrier_and_code_type(tmp_path):
    """GPS records moved to the L2 carrier read as GPS_L2 with CodeType L (L2C) and are another
    signal with CodeType W (P(Y)); Galileo at 1207.14 MHz is E5b."""
    def move(lines):
        out, k = [], 0
        for ln in lines:
            f = ln.rstrip("\n").split(",")
            if ln.startswith("Raw,") and f[28] in ("1", "6"):          # ConstellationType GPS / Galileo
                k += 1
                f[22] = "1227600000" if f[28] == "1" else "1207140000"
                f[35] = ("L" if k % 2 else "W") if f[28] == "1" else "Q"
                ln = ",".join(f) + "\n"
            out.append(ln)
        return out
    raw = read_gnss_log(_edit(tmp_path, P7_LOG, move))
    sig = set(raw.frame.signal)
    assert {"GPS_L2", "GAL_E5B"} <= sig and "GPS_L1" not in sig and "GAL_E1" not in sig
    l2 = raw.frame[raw.frame.signal == "GPS_L2"]
    assert (l2.carrier_hz == 1227.60e6).all()
    assert raw.skipped["records_other_signals"] > 0          # the CodeType W ones


def test_beidou_b1c_and_b2a_by_carrier_and_b1i_without_one(tmp_path):
    """BeiDou records at 1575.42 MHz are B1C and at 1176.45 MHz B2a (newer phones log them); a BeiDou record
    without a carrier frequency, from a log older than dual-frequency phones, is B1I (it was dropped as
    a BeiDou signal on the L1 carrier before)."""
    carriers = ("1575420000", "1176450000", "")

    def to_beidou(lines):
        out, k = [], 0
        for ln in lines:
            f = ln.rstrip("\n").split(",")
            if ln.startswith("Raw,") and f[28] == "1":                 # the GPS records become BeiDou ones
                f[28], f[22], f[35] = "5", carriers[k % 3], ""
                k += 1
                ln = ",".join(f) + "\n"
            out.append(ln)
        return out
    f = read_gnss_log(_edit(tmp_path, P7_LOG, to_beidou)).frame
    bds = f[f.const == "C"]
    assert set(bds.signal) == {"BDS_B1C", "BDS_B2A", "BDS_B1I"}
    for name, hz in (("BDS_B1C", 1575.42e6), ("BDS_B2A", 1176.45e6), ("BDS_B1I", 1561.098e6)):
        assert (bds.carrier_hz[bds.signal == name] == hz).all()
