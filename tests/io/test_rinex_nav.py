"""RINEX navigation parsing, ephemeris selection, broadcast orbits and clocks."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fusion.errors import DataError
from fusion.geometry import C_LIGHT
from fusion.nav.orbits import sat_state, select_ephemeris, transmit_states
from fusion.gpstime import gps_ms_from_calendar
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav

DAY118_MS = gps_ms_from_calendar(2021, 4, 28, 0, 0, 0.0)


@pytest.fixture(scope="module")
def nav():
    return read_rinex_nav(default_nav_path())


def _records(path: Path, n: int) -> tuple[list[str], list[list[str]]]:
    """Header lines and the first ``n`` 8-line records of a RINEX 2 nav file."""
    lines = path.read_text().splitlines()
    body = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    return lines[:body], [lines[body + 8 * k: body + 8 * (k + 1)] for k in range(n)]


def _to_rinex3(rec: list[str]) -> list[str]:
    """Rewrite a RINEX 2 GPS record in RINEX 3 layout (same numbers)."""
    head = rec[0]
    prn = int(head[:2])
    yy, mo, dd, hh, mi, ss = head[3:22].split()
    first = f"G{prn:02d} {2000 + int(yy):04d} {int(mo):02d} {int(dd):02d} {int(hh):02d} {int(mi):02d} " \
            f"{int(float(ss)):02d}" + head[22:]
    return [first] + [" " + ln for ln in rec[1:]]


def test_shipped_nav_parses(nav):
    assert len(nav) > 300                       # a full day of hourly-merged GPS ephemerides
    assert set(np.unique(nav.prn)) <= set(range(1, 33)) and len(np.unique(nav.prn)) >= 28
    assert np.all(nav.params["health"] == 0)
    # toe falls on 2021 day 118 (with the usual few records for 00:00 of the next day).
    assert nav.toe_ms.min() >= DAY118_MS and nav.toe_ms.max() <= DAY118_MS + 86_400_000
    assert np.all(np.abs(nav.toe_ms - nav.toc_ms) <= 3_600_000)
    assert np.all(np.abs(nav.params["sqrt_a"] ** 2 - 26_560e3) < 200e3)
    lo, hi = nav.span_ms()
    assert hi - lo > 24 * 3_600_000


def test_rinex3_mixed_matches_rinex2(tmp_path, nav):
    header, recs = _records(default_nav_path(), 3)
    glo = ["R05 2021 04 28 00 15 00 1.234567890123D-05 0.000000000000D+00 0.000000000000D+00"] + \
          ["     0.000000000000D+00 0.000000000000D+00 0.000000000000D+00 0.000000000000D+00"] * 3
    gal = ["E11 2021 04 28 00 10 00-1.646194141358D-05 3.737454790098D-12 0.000000000000D+00"] + \
          ["     3.100000000000D+01 1.210937500000D+02 2.883334388165D-09 2.062630372514D+00"] * 6 + \
          ["     9.999000000000D+08"]
    body = _to_rinex3(recs[0]) + glo + _to_rinex3(recs[1]) + gal + _to_rinex3(recs[2])
    p = tmp_path / "mixed.rnx"
    p.write_text("\n".join([
        "     3.04           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE",
        "                                                            END OF HEADER"] + body) + "\n")
    p2 = tmp_path / "three.21n"
    p2.write_text("\n".join(header + [ln for r in recs for ln in r]) + "\n")
    n3, n2 = read_rinex_nav(p), read_rinex_nav(p2)
    assert len(n3) == 3 and n3.skipped == {"non_gps_records": 2}
    np.testing.assert_array_equal(n3.prn, n2.prn)
    np.testing.assert_array_equal(n3.toe_ms, n2.toe_ms)
    for k in n2.params:
        np.testing.assert_array_equal(n3.params[k], n2.params[k], err_msg=k)


def test_bad_nav_files(tmp_path):
    only_gal = tmp_path / "gal.rnx"
    only_gal.write_text("\n".join([
        "     3.04           N: GNSS NAV DATA    E: Galileo          RINEX VERSION / TYPE",
        "                                                            END OF HEADER",
        "E11 2021 04 28 00 10 00-1.646194141358D-05 3.737454790098D-12 0.000000000000D+00"]
        + ["     3.100000000000D+01 1.210937500000D+02 2.883334388165D-09 2.062630372514D+00"] * 7) + "\n")
    with pytest.raises(DataError, match="no GPS records"):
        read_rinex_nav(only_gal)
    glonass2 = tmp_path / "brdc1180.21g"
    glonass2.write_text("     2.01           G: GLONASS NAV DATA                     RINEX VERSION / TYPE\n")
    with pytest.raises(DataError, match="no GPS records"):
        read_rinex_nav(glonass2)
    header, recs = _records(default_nav_path(), 2)
    # a broken record costs itself alone, with a warning and a count; a file with none readable is refused
    trunc = tmp_path / "trunc.21n"
    trunc.write_text("\n".join(header + recs[0] + recs[1][:5]) + "\n")
    with pytest.warns(UserWarning, match=r"trunc\.21n:\d+: truncated ephemeris record .*1 ephemeris record"):
        nav = read_rinex_nav(trunc)
    assert len(nav) == 1 and nav.skipped["records_unreadable"] == 1
    garbage = tmp_path / "garbage.21n"
    bad = [recs[0][0]] + [recs[0][1].replace("0.", "x.", 1)] + recs[0][2:]
    garbage.write_text("\n".join(header + bad + recs[1]) + "\n")
    with pytest.warns(UserWarning, match=r"garbage\.21n:\d+: cannot read number"):
        assert len(read_rinex_nav(garbage)) == 1
    garbage.write_text("\n".join(header + bad) + "\n")
    with pytest.raises(DataError, match=r"garbage\.21n:\d+: cannot read number .*no ephemeris record"):
        read_rinex_nav(garbage)
    with pytest.raises(DataError, match="not found"):
        read_rinex_nav(tmp_path / "missing.21n")
    text = tmp_path / "x.txt"
    text.write_text("hello\n")
    with pytest.raises(DataError, match="not a RINEX"):
        read_rinex_nav(text)


def test_a_record_of_an_orbit_no_satellite_flies_is_skipped(tmp_path):
    """sqrt(A) a thousand times too small (a corrupt record): the satellite is left without that ephemeris, with
    a warning naming it and a count, rather than pulling every position it enters."""
    header, recs = _records(default_nav_path(), 2)
    corrupt = list(recs[1])
    sqrt_a = float(corrupt[2][60:79].replace("D", "E"))
    corrupt[2] = corrupt[2][:60] + f"{sqrt_a / 1000:19.12E}".replace("E", "D") + corrupt[2][79:]
    p = tmp_path / "corrupt.21n"
    p.write_text("\n".join(header + recs[0] + corrupt) + "\n")
    prn = int(corrupt[0][:2])
    with pytest.warns(UserWarning, match=rf"corrupt\.21n: 1 ephemeris record\(s\) with an orbit .*G{prn:02d}"):
        nav = read_rinex_nav(p)
    assert len(nav) == 1 and nav.skipped["records_implausible_orbit"] == 1
    assert nav.params["sqrt_a"][0] == pytest.approx(float(recs[0][2][60:79].replace("D", "E")))


def test_unhealthy_records_dropped(tmp_path):
    header, recs = _records(default_nav_path(), 2)
    sick = list(recs[1])
    # SV health is the second field of orbit line 6.
    sick[6] = sick[6][:22] + " 0.100000000000D+01" + sick[6][41:]
    p = tmp_path / "sick.21n"
    p.write_text("\n".join(header + recs[0] + sick) + "\n")
    n = read_rinex_nav(p)
    assert len(n) == 1 and n.skipped["unhealthy_or_bad_prn"] == 1


def test_select_nearest_valid_toe(nav):
    prn = int(nav.prn[0])
    toes = nav.toe_ms[nav.prn == prn]
    t = np.array([toes[1] + 1000, toes[1] - 1000, (toes[1] + toes[2]) // 2 + 60_000])
    idx = select_ephemeris(nav, np.full(3, prn), t)
    np.testing.assert_array_equal(nav.toe_ms[idx], [toes[1], toes[1], toes[2]])
    lo, hi = nav.span_ms()
    out = select_ephemeris(nav, np.array([prn, prn, 33]), np.array([lo - 1, hi + 1, toes[1]]))
    np.testing.assert_array_equal(out, [-1, -1, -1])


def test_velocity_matches_finite_difference(nav):
    idx = np.arange(0, len(nav), 7)
    t = nav.toe_ms[idx] + 1_234_567
    h = 0.01
    p0 = sat_state(nav, idx, t, -h)["pos"]
    p1 = sat_state(nav, idx, t, h)["pos"]
    st = sat_state(nav, idx, t)
    np.testing.assert_allclose(st["vel"], (p1 - p0) / (2 * h), atol=1e-3)
    c0 = sat_state(nav, idx, t, -h)["clock_s"]
    c1 = sat_state(nav, idx, t, h)["clock_s"]
    np.testing.assert_allclose(st["clock_drift"], (c1 - c0) / (2 * h), atol=1e-14)
    r = np.linalg.norm(st["pos"], axis=1)
    assert np.all((r > 25_500e3) & (r < 27_700e3))
    assert np.all(np.abs(st["clock_rel_s"]) * C_LIGHT < 30.0)  # e < 0.03: |dtr| < ~25 m


def test_transmit_time_is_consistent(nav):
    rx = np.array([[-2_694_000.0, -4_296_000.0, 3_854_000.0]] * 5)
    idx = np.flatnonzero(nav.prn == nav.prn[0])[:1].repeat(5)
    t = nav.toe_ms[idx] + np.arange(5) * 1000
    st, tau = transmit_states(nav, idx, rx, t)
    again = sat_state(nav, idx, t, -tau)["pos"]
    np.testing.assert_allclose(st["pos"], again, atol=1e-9)
    # The flight time is the light time of the Earth-rotated range it produced.
    from fusion.geometry import sagnac_rotate
    rng = np.linalg.norm(sagnac_rotate(st["pos"][:, None, :], rx)[:, 0] - rx, axis=1)
    np.testing.assert_allclose(tau * C_LIGHT, rng, atol=1e-3)
    assert np.all((tau > 0.06) & (tau < 0.15))


def test_broadcast_vs_precise_sp3(shared_data):
    from fusion.io.sp3 import read_sp3
    sp = read_sp3(shared_data / "ephemeris/precise/COD0MGXFIN_20211180000_01D_05M_ORB.SP3")
    nav = read_rinex_nav(shared_data / "ephemeris/gnss_lib_py_nav/brdc1180.21n")
    g = np.array([s.startswith("G") for s in sp.sats])
    prn = np.array([int(s[1:]) for s in sp.sats[g]])
    idx = select_ephemeris(nav, prn[None, :], sp.t_ms[:, None])
    ok = (idx >= 0) & np.isfinite(sp.pos[:, g, 0])
    st = sat_state(nav, np.where(ok, idx, 0), np.broadcast_to(sp.t_ms[:, None], idx.shape))
    d = np.linalg.norm(st["pos"] - sp.pos[:, g], axis=-1)[ok]
    rms = float(np.sqrt(np.mean(d**2)))
    print(f"\nbroadcast vs SP3: {ok.sum()} sat-epochs, RMS 3-D {rms:.3f} m, "
          f"median {np.median(d):.3f} m, max {d.max():.3f} m")
    assert ok.sum() > 1000
    # Metre level: centre of mass vs antenna phase centre plus broadcast orbit error.
    assert 0.3 < rms < 3.0 and d.max() < 10.0


def test_sat_positions_and_clock_vs_gsdc_derived(shared_data):
    df = pd.read_csv(shared_data / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel4/Pixel4_derived.csv")
    df = df[df.constellationType == 1]
    nav = read_rinex_nav(default_nav_path())
    ns = df.receivedSvTimeInGpsNanos.to_numpy(np.int64)
    t_ms, dt = ns // 1_000_000, (ns % 1_000_000) * 1e-9
    idx = select_ephemeris(nav, df.svid.to_numpy(), t_ms)
    assert (idx >= 0).all()
    # receivedSvTimeInGpsNanos is on the satellite's clock: GPS time = t_sv - dt_sv.
    st = sat_state(nav, idx, t_ms, dt)
    for _ in range(2):
        st = sat_state(nav, idx, t_ms, dt - st["clock_s"])
    d = np.linalg.norm(st["pos"] - df[["xSatPosM", "ySatPosM", "zSatPosM"]].to_numpy(), axis=1)
    c = st["clock_s"] * C_LIGHT - df.satClkBiasM.to_numpy()
    print(f"\nvs Pixel4_derived ({len(df)} rows): sat position RMS {np.sqrt(np.mean(d**2)):.4f} m, "
          f"max {d.max():.4f} m; sat clock RMS {np.sqrt(np.mean(c**2)):.4f} m, max {np.abs(c).max():.4f} m")
    assert np.sqrt(np.mean(d**2)) < 0.05 and d.max() < 0.1
    assert np.abs(c).max() < 0.01
