"""Multi-system broadcast navigation: RINEX 3 mixed / RINEX 2 readers, Keplerian orbits of every
system (BeiDou GEO included), GLONASS RK4, precise SP3 + CLK states, malformed files."""
from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from fusion.errors import DataError
from fusion.io.clk import read_clk
from fusion.io.rinex_nav import GAMMA_L5, default_nav_path, read_nav, read_rinex_nav
from fusion.nav.glonass import glonass_state, select_glonass
from fusion.nav.orbits import sat_state
from fusion.nav.sat_states import broadcast_states
from fusion.trace import SIGNALS

MIXED = Path(__file__).resolve().parents[1] / "data" / "brdc_2023073_mixed_305.rnx"


@pytest.fixture(scope="module")
def mixed():
    return read_nav(MIXED)


def _consecutive_gap(nav, ids, toe, state_fn):
    """Position [m] and clock [ns] differences of consecutive records of a satellite at the
    midpoint of their reference times (each extrapolated half-way)."""
    i = np.flatnonzero((ids[1:] == ids[:-1]) & (toe[1:] - toe[:-1] <= 4 * 3_600_000))
    tm = (toe[i] + toe[i + 1]) // 2
    a, b = state_fn(nav, i, tm), state_fn(nav, i + 1, tm)
    return ids[i], np.linalg.norm(a["pos"] - b["pos"], axis=1), np.abs(a["clock_s"] - b["clock_s"]) * 1e9


def test_mixed_305_fixture(mixed):
    """Every modelled system is read, GLONASS 3.05 five-line records included; header values kept."""
    assert mixed.systems() == {"G", "E", "C", "J", "R"}
    assert set(mixed.kepler.sat_id // 1000) == {1, 4, 5, 6}
    assert 4194 in mixed.kepler.sat_id                  # QZSS J02 is Android svid 194
    assert mixed.leap_s == 18 and mixed.klobuchar.shape == (8,) and mixed.klobuchar[4] == 1.2902e5
    g = mixed.glonass
    assert len(g) == 2 and set(g.k) == {1, -4}          # R02 channel -4, R01 channel 1 (file values)
    np.testing.assert_allclose(np.linalg.norm(g.pos, axis=1), 25.5e6, rtol=5e-3)
    # GLONASS epochs are UTC: + 18 s leap to GPS
    assert np.all(g.toe_ms % 60_000 == 18_000)
    # BeiDou epochs are BDT: toc and toe move to GPS time by +14 s
    bds = mixed.kepler.sat_id // 1000 == 5
    assert np.all(mixed.kepler.toc_ms[bds] % 60_000 == 14_000)
    gal = mixed.kepler.sat_id // 1000 == 6
    # Galileo E1 uses BGD(E1,E5b) (the record's iodc slot), E5a (f1/f5)^2 BGD(E1,E5a) (its tgd slot)
    par = mixed.kepler.params
    np.testing.assert_array_equal(par["tgd"][gal], par["iodc"][gal])


def test_keplerian_records_continuous_every_system(shared_data):
    """Consecutive records of one satellite agree where both are valid: the orbit and clock
    equations (per-system constants, BDT, the BeiDou GEO rotation) are right to < 1.5 m / 2 ns."""
    nav = read_nav(shared_data / "ephemeris/gnss_lib_py_nav/BRDM00DLR_S_20230730000_01D_MN.rnx")
    k = nav.kepler
    ids, dpos, dclk = _consecutive_gap(k, k.sat_id, k.toe_ms, sat_state)
    assert {1, 4, 5, 6} <= set(ids // 1000) and {5001, 5002} <= set(ids)   # C01/C02 are GEO
    assert dpos.max() < 1.5 and dclk.max() < 2.0
    gids, gpos, gclk = _consecutive_gap(nav.glonass, nav.glonass.sat_id, nav.glonass.toe_ms, glonass_state)
    assert gids.size >= 3 and gpos.max() < 3.0 and gclk.max() < 3.0


def test_beidou_geo_is_geostationary(mixed, shared_data):
    nav = read_nav(shared_data / "ephemeris/gnss_lib_py_nav/BRDM00DLR_S_20230730000_01D_MN.rnx")
    k = nav.kepler
    geo = np.flatnonzero(np.isin(k.sat_id, [5001, 5002]))
    st = sat_state(k, geo, k.toe_ms[geo] + 900_000)
    r = np.linalg.norm(st["pos"], axis=1)
    lat = np.degrees(np.arcsin(st["pos"][:, 2] / r))
    np.testing.assert_allclose(r, 42.17e6, rtol=1e-3)
    assert np.all(np.abs(lat) < 2) and np.all(np.linalg.norm(st["vel"], axis=1) < 200)
    # the MEO/IGSO equations on the same elements put the satellite kilometres away, 5 degrees off
    k.prn = k.prn.copy()
    k.prn[geo] += 10                                     # C11/C12: not GEO numbers
    wrong = sat_state(k, geo, k.toe_ms[geo] + 900_000)["pos"]
    assert np.linalg.norm(wrong - st["pos"], axis=1).min() > 1000


def test_glonass_rk4_matches_record_after_integration(mixed):
    g = mixed.glonass
    st = glonass_state(g, np.array([0, 0]), g.toe_ms[[0, 0]], np.array([0.0, 1e-9]))
    np.testing.assert_allclose(st["pos"], g.pos[[0, 0]], atol=1e-3)
    assert select_glonass(g, np.array([3001, 3001, 3009]), g.toe_ms[[0, 0, 0]] + [0, 10**8, 0]).tolist()[1:] == [-1, -1]


def test_broadcast_states_group_delays_and_skips(mixed):
    """L5-class signals take tgd_l5 instead of the L1 group delay; no record -> ok False."""
    k = mixed.kepler
    gps = int(np.flatnonzero(k.sat_id == 1001)[0])
    t = np.full(3, k.toe_ms[gps])
    sig = np.array([SIGNALS.index("GPS_L1"), SIGNALS.index("GPS_L5"), SIGNALS.index("GPS_L1")], np.int8)
    st = broadcast_states(mixed, np.array([1001, 1001, 1030]), sig, t, 0.0)
    assert st["ok"].tolist() == [True, True, False] and np.all(st["pos"][2] == 0)
    tgd = k.params["tgd"][gps]
    np.testing.assert_allclose(st["clock_s"][1] - st["clock_s"][0], tgd - GAMMA_L5 * tgd, atol=1e-15)


def test_rinex2_and_gzip_and_multiple_files(tmp_path):
    nav = read_nav(default_nav_path())
    assert nav.systems() == {"G"} and nav.klobuchar is not None and nav.leap_s == 18
    gz = tmp_path / "hour1180.21n.gz"
    gz.write_bytes(gzip.compress(default_nav_path().read_bytes()))
    both = read_nav([gz, MIXED])
    assert len(both.kepler) == len(nav.kepler) + len(read_nav(MIXED).kepler)
    np.testing.assert_array_equal(both.klobuchar, nav.klobuchar)       # first file's header wins


def test_rinex2_glonass_file(tmp_path):
    """A RINEX 2 .g file: 4-line records, PRN in columns 1-2, UTC epochs."""
    rec = ["R02 2023 03 14 00 15 00-2.314336597919e-05 0.000000000000e+00 1.728000000000e+05",
           "     1.433783544922e+04-1.395797729492e+00 0.000000000000e+00 0.000000000000e+00",
           "    -6.566218261719e+03 2.361273765564e+00-9.313225746155e-10-4.000000000000e+00",
           "     2.012003320313e+04 1.763606071472e+00-9.313225746155e-10 0.000000000000e+00"]
    v2 = [" 2 23  3 14  0 15  0.0" + rec[0][23:].replace("e", "D")] + ["   " + ln[4:].replace("e", "D") for ln in rec[1:]]
    p = tmp_path / "brdc0730.23g"
    p.write_text("     2.01           G: GLONASS NAV DATA                     RINEX VERSION / TYPE\n"
                 "    18                                                      LEAP SECONDS\n"
                 "                                                            END OF HEADER\n" + "\n".join(v2) + "\n")
    g2, g3 = read_nav(p).glonass, read_nav(MIXED).glonass
    j = int(np.flatnonzero(g3.svid == 2)[0])
    assert len(g2) == 1 and g2.k[0] == -4 and g2.toe_ms[0] == g3.toe_ms[j]
    np.testing.assert_array_equal(g2.pos[0], g3.pos[j])


def test_malformed_navigation(tmp_path):
    lines = MIXED.read_text().splitlines()
    body = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    trunc = tmp_path / "trunc_MN.rnx"
    trunc.write_text("\n".join(lines[:body + 3]) + "\n")
    with pytest.raises(DataError, match=r"trunc_MN\.rnx:\d+: truncated"):
        read_nav(trunc)
    bad = tmp_path / "bad_MN.rnx"
    bad.write_text("\n".join(lines[:body] + [lines[body]] + [lines[body + 1].replace("e", "x", 1)] + lines[body + 2:]) + "\n")
    with pytest.warns(UserWarning, match=rf"bad_MN\.rnx:{body + 2}: cannot read number"):
        nav = read_nav(bad)
    assert nav.skipped["records_unreadable"] == 1
    sbas = tmp_path / "sbas_MN.rnx"
    sbas.write_text("\n".join(lines[:body] + ["S20 2023 03 14 00 00 00 0.0 0.0 0.0"] + ["     0.0"] * 3) + "\n")
    with pytest.raises(DataError, match="no GPS, QZSS, Galileo, BeiDou or GLONASS records"):
        read_nav(sbas)
    v5 = tmp_path / "v5.rnx"
    v5.write_text("     5.00           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE\n")
    with pytest.raises(DataError, match="version 5.0 is not supported"):
        read_nav(v5)
    gzbad = tmp_path / "x_MN.rnx.gz"
    gzbad.write_bytes(b"not gzip")
    with pytest.raises(DataError, match="corrupt gzip navigation file"):
        read_nav(gzbad)
    with pytest.raises(DataError, match="not found"):
        read_nav(tmp_path / "none.rnx")


def _as_rinex4(lines: list[str], version: str = "4.01") -> list[str]:
    """The RINEX 3 mixed fixture rewritten as RINEX 4: Klobuchar in an ION frame, each record in an EPH frame
    (Galileo's message from its data-source field, BeiDou GEO D2), GLONASS with the 4.01 fifth line, and the
    frames a reader must pass over (STO, a Galileo NeQuick ION frame before the GPS one, EOP, a GPS CNAV and an
    SBAS ephemeris)."""
    body = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    head = [f"{version:>9s}           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE"]
    head += [ln for ln in lines[1:body] if "IONOSPHERIC CORR" not in ln]
    alpha = [float(lines[1][5 + 12 * k: 17 + 12 * k]) for k in range(4)]
    beta = [float(lines[2][5 + 12 * k: 17 + 12 * k]) for k in range(4)]
    num = lambda vals: "".join(f"{v:19.12e}" for v in vals)  # noqa: E731
    out = head + ["> STO G01 LNAV", "    2023 03 13 23 48 00 GPUT", "     " + num([1.7e5, 0.0, 0.0, 0.0])[1:],
                  "> ION E08 IFNV", "    2023 03 13 23 48 00" + num([41.0, -0.1, 0.001]), "    " + num([0.0]),
                  "> ION G01 LNAV", "    2023 03 13 23 48 00" + num(alpha[:3]), "    " + num(alpha[3:] + beta[:3]),
                  "    " + num(beta[3:])]
    recs, cur = [], None
    for ln in lines[body:]:
        if ln[:1].strip():
            cur = [ln]
            recs.append(cur)
        elif cur is not None:
            cur.append(ln)
    for rec in recs:
        sys_letter, prn = rec[0][0], int(rec[0][1:3])
        if sys_letter == "E":
            src = int(float(rec[5][23:42]))
            msg = "FNAV" if src & 2 else "INAV"
        else:
            msg = {"G": "LNAV", "J": "LNAV", "R": "FDMA", "C": "D2" if prn <= 5 else "D1"}[sys_letter]
        out += [f"> EPH {rec[0][:3]} {msg}"] + rec[:4 if sys_letter == "R" else 8]
        if sys_letter == "R":
            out.append("     " + num([0.0, 0.0, 0.0, 0.0])[1:])
    gps = next(r for r in recs if r[0][0] == "G")
    out += ["> EPH G05 CNAV"] + [gps[0]] + ["     " + num([9.0] * 4)[1:]] * 8
    out += ["> EPH S36 SBAS", "S36 2023 03 14 00 00 00" + num([0.0] * 3)] + ["    " + num([0.0] * 4)] * 3
    out += ["> EOP G05 CNVX", "    2023 03 14 00 00 00" + num([0.0] * 3)] + ["    " + num([0.0] * 3)] * 2
    return out


def test_rinex4_matches_rinex3(tmp_path):
    """A RINEX 4 file gives the records, Klobuchar and leap seconds of the same file in RINEX 3 (a record whose
    last line is blank included); the modernised messages are skipped and counted, the other frames passed over."""
    lines = MIXED.read_text().splitlines()
    first_gps = next(i for i, ln in enumerate(lines) if ln.startswith("G"))
    lines[first_gps + 7] = " " * 40                 # its spare line written blank
    v3 = tmp_path / "blank_MN.rnx"
    v3.write_text("\n".join(lines) + "\n")
    v4 = tmp_path / "BRD400DLR_S_20230730000_01D_MN.rnx"
    v4.write_text("\n".join(_as_rinex4(lines)) + "\n")
    mixed, nav = read_nav(v3), read_nav(v4)
    assert nav.systems() == mixed.systems() and nav.leap_s == mixed.leap_s
    np.testing.assert_array_equal(nav.klobuchar, mixed.klobuchar)
    for k in ("sat_id", "toc_ms", "toe_ms", "msg"):
        np.testing.assert_array_equal(getattr(nav.kepler, k), getattr(mixed.kepler, k))
    for k, v in mixed.kepler.params.items():
        np.testing.assert_array_equal(nav.kepler.params[k], v, err_msg=k)
    for k in ("svid", "toe_ms", "pos", "vel", "acc", "tau", "gamma", "k"):
        np.testing.assert_array_equal(getattr(nav.glonass, k), getattr(mixed.glonass, k))
    assert nav.skipped.get("records_G_CNAV_not_modelled") == 1 and nav.skipped.get("records_S_SBAS_not_modelled") == 1
    gps = read_rinex_nav(v4)
    assert gps.toe_ms.size == np.sum(mixed.kepler.sat_id // 1000 == 1)
    assert gps.skipped.get("records_G_CNAV_not_modelled") == 1      # a GPS record, not counted as another system's


def test_rinex4_klobuchar_from_the_gps_ion_frame(tmp_path):
    """Klobuchar comes from the GPS LNAV ION frame (signs and all), not from a Galileo or BeiDou one before it;
    without one, from header lines a writer kept."""
    lines = _as_rinex4(MIXED.read_text().splitlines())
    i = lines.index("> ION G01 LNAV")
    want = [2.3e-08, 0.0, -1.2e-07, 1.2e-07, 1.35e05, -8.2e04, 6.5e04, -4.6e05]
    num = lambda vals: "".join(f"{v:19.12e}" for v in vals)  # noqa: E731
    lines[i + 1:i + 4] = ["    2024 02 17 00 18 54" + num(want[:3]), "    " + num(want[3:7]), "    " + num(want[7:])]
    lines.insert(i, "> ION C19 CNVX")
    lines.insert(i + 1, "    2024 02 17 00 00 00" + num([9.0, 9.0, 9.0]))
    p = tmp_path / "ion_MN.rnx"
    p.write_text("\n".join(lines) + "\n")
    np.testing.assert_array_equal(read_nav(p).klobuchar, want)
    j = lines.index("> ION G01 LNAV")
    header_ion = MIXED.read_text().splitlines()[1:3]                # the GPSA / GPSB IONOSPHERIC CORR lines
    p.write_text("\n".join(lines[:1] + header_ion + lines[1:j] + lines[j + 4:]) + "\n")
    np.testing.assert_array_equal(read_nav(p).klobuchar, read_nav(MIXED).klobuchar)


def test_rinex4_malformed(tmp_path):
    good = _as_rinex4(MIXED.read_text().splitlines(), "4.00")
    body = next(i for i, ln in enumerate(good) if "END OF HEADER" in ln) + 1
    ion = good.index("> ION G01 LNAV")
    cases = {
        "stray": (good[:body] + ["G01 2023 03 14 00 00 00"] + good[body:], r"expected a RINEX 4 record marker"),
        "wrong": ([ln.replace("> EPH G", "> EPH E", 1).replace("LNAV", "INAV") if ln.startswith("> EPH G") else ln
                   for ln in good],
                  r"record of 'G\d\d' under the marker for 'E\d\d'"),
        "prn": ([ln.replace("> EPH C05", "> EPH C15") for ln in good], r"record of 'C05' under the marker for 'C15'"),
        "ion": (good[:ion + 2] + good[ion + 4:], r"truncated ION record \(1 of 3"),
    }
    for name, (lines, match) in cases.items():
        p = tmp_path / f"{name}_MN.rnx"
        p.write_text("\n".join(lines) + "\n")
        with pytest.raises(DataError, match=rf"{name}_MN\.rnx:\d+: {match}"):
            read_nav(p)
    p = tmp_path / "trunc_MN.rnx"      # a record cut short: skipped and counted, the others read
    p.write_text("\n".join(good + ["> EPH E11 INAV", "E11 2023 03 14 00 10 00" + " 0.0" * 3]) + "\n")
    with pytest.warns(UserWarning, match=r"trunc_MN\.rnx:\d+: truncated ephemeris record \(1 of 8.*1 ephemeris"):
        assert len(read_nav(p).kepler) == len(read_nav(MIXED).kepler)


def test_gps_broadcast_vs_precise_states(shared_data):
    """Broadcast (brdc1180.21n) vs CODE MGEX SP3 + CLK through the same per-row interfaces:
    metre-level orbits, nanosecond-level clocks after removing the per-epoch common offset
    (precise clocks have their own reference)."""
    from fusion.io.sp3 import read_sp3
    from fusion.nav.precise import PreciseOrbits, precise_states

    pre = shared_data / "ephemeris/precise"
    prec = PreciseOrbits(read_sp3(pre / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3"),
                         read_clk(pre / "COD0MGXFIN_20211180000_01D_30S_CLK.CLK"))
    nav = read_nav(shared_data / "ephemeris/gnss_lib_py_nav/brdc1180.21n")
    assert prec.systems() == {"G", "R", "E", "C", "J"}
    t0 = prec.clk.t_ms[0] + 600_000                     # inside both the SP3 and the CLK spans
    ids = np.arange(1001, 1033)
    t = np.full(ids.size, t0)
    sig = np.zeros(ids.size, np.int8)
    b, p = broadcast_states(nav, ids, sig, t, 0.0), precise_states(prec, ids, sig, t, 0.0, nav)
    ok = b["ok"] & p["ok"]
    assert ok.sum() >= 25
    dpos = np.linalg.norm(b["pos"][ok] - p["pos"][ok], axis=1)
    dclk = (b["clock_s"][ok] - p["clock_s"][ok]) * 1e9
    assert np.median(dpos) < 2.0 and dpos.max() < 6.0
    assert np.median(np.abs(dclk - np.median(dclk))) < 2.0
    np.testing.assert_allclose(np.linalg.norm(p["vel"][ok], axis=1), np.linalg.norm(b["vel"][ok], axis=1), atol=0.05)


def test_precise_states_every_constellation(shared_data):
    """SP3 + CLK give states for GLONASS, Galileo, BeiDou and QZSS too (no broadcast file of that
    day exists here to compare against: orbit radius and clock plausibility instead)."""
    from fusion.io.sp3 import read_sp3
    from fusion.nav.precise import PreciseOrbits, precise_states, sat_ids

    pre = shared_data / "ephemeris/precise"
    prec = PreciseOrbits(read_sp3(pre / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3"),
                         read_clk(pre / "COD0MGXFIN_20211180000_01D_30S_CLK.CLK"))
    ids = sat_ids(prec.sp3.sats)
    t = np.full(ids.size, prec.clk.t_ms[0] + 123_456)
    st = precise_states(prec, ids, np.zeros(ids.size, np.int8), t, 0.0)
    assert st["ok"].mean() > 0.9 and set(ids[st["ok"]] // 1000) == {1, 3, 4, 5, 6}
    r = np.linalg.norm(st["pos"][st["ok"]], axis=1)
    # Galileo E14/E18 fly eccentric orbits (17,000-26,000 km), QZSS IGSO up to ~45,000 km
    assert r.min() > 17e6 and r.max() < 46e6
    assert np.abs(st["clock_s"][st["ok"]]).max() < 1e-2
    # outside the SP3 span: counted as not ok, never extrapolated
    late = precise_states(prec, ids[:3], np.zeros(3, np.int8), np.full(3, prec.sp3.t_ms[-1] + 3_600_000), 0.0)
    assert not late["ok"].any()


def test_clk_malformed(tmp_path):
    p = tmp_path / "x.clk"
    p.write_text("     3.00           C                                       RINEX VERSION / TYPE\n"
                 "                                                            END OF HEADER\n"
                 "AS G01  2021 04 28 19 30  0.000000  2    abc\n")
    with pytest.raises(DataError, match=r"x\.clk:3: cannot read satellite clock record"):
        read_clk(p)
    q = tmp_path / "y.clk"
    q.write_text("hello\n")
    with pytest.raises(DataError, match="not a RINEX clock file"):
        read_clk(q)


def test_lagrange_interpolation_is_exact_for_its_degree_and_at_the_samples():
    """Ten samples fit a degree-9 polynomial exactly, on uneven sample times too, and a query at a sample
    time returns that sample (to rounding: the weights' numerators never divide by a zero time difference)."""
    from fusion.nav.precise import N_LAGRANGE, _lagrange

    rng = np.random.default_rng(4)
    t_ref = np.cumsum(rng.uniform(200.0, 400.0, 30))
    t_ref -= t_ref[0]
    coeffs = rng.normal(size=(N_LAGRANGE, 2))                 # two satellites' degree-9 polynomials
    x = t_ref / t_ref[-1]
    values = np.stack([np.polyval(coeffs[:, i], x) for i in range(2)], axis=1)[:, :, None]   # (T, N, 1)
    t_q = np.r_[rng.uniform(0.0, t_ref[-1], 200), t_ref[[0, 7, 29]]]
    col = rng.integers(0, 2, t_q.size)
    got = _lagrange((t_ref * 1000).astype(np.int64), t_ref, values, col, t_q)[:, 0]
    want = np.array([np.polyval(coeffs[:, c], t / t_ref[-1]) for c, t in zip(col, t_q)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(values).max())
    np.testing.assert_allclose(got[-3:], values[[0, 7, 29], col[-3:], 0], rtol=1e-14, atol=0)


def test_beidou_b1c_takes_tgd1_and_b2a_no_group_delay(mixed):
    """A D1 / D2 record's clock refers to B3I and carries group delays for B1I (TGD1) and B2I (TGD2) only:
    B1C takes TGD1, B2a none."""
    k = mixed.kepler
    rec = int(np.flatnonzero(k.sat_id == 5006)[0])
    names = ("BDS_B1I", "BDS_B1C", "BDS_B2A", "BDS_B2I")
    sig = np.array([SIGNALS.index(s) for s in names], np.int8)
    st = broadcast_states(mixed, np.full(4, 5006), sig, np.full(4, k.toe_ms[rec]), 0.0)
    assert st["ok"].all()
    tgd1, tgd2 = k.params["tgd"][rec], k.params["iodc"][rec]
    assert tgd1 != 0 and tgd2 != 0
    b1i, b1c, b2a, b2i = st["clock_s"]
    assert b1c == b1i
    assert b2a - b1i == pytest.approx(tgd1, abs=1e-15)
    assert b2i - b1i == pytest.approx(tgd1 - tgd2, abs=1e-15)


def test_lagrange_declines_too_few_samples_and_windows_across_a_gap():
    """Three samples of a file, or a window holding a hole of hours, would swing the polynomial kilometres off
    (a precise orbit file cut short put the Pixel5 42 km north): NaN there, the usual answer elsewhere."""
    from fusion.nav.precise import N_LAGRANGE, _lagrange

    t_ref = np.arange(40) * 300.0
    t_ref[20:] += 3 * 3600.0                                          # three hours missing after sample 19
    values = np.sin(t_ref / 4000.0)[:, None, None]
    col = np.zeros(4, np.int64)
    t_q = np.array([600.0, 5600.0, 9300.0, t_ref[30] + 10.0])         # early, next to the hole, in it, well after
    got = _lagrange((t_ref * 1000).astype(np.int64), t_ref, values, col, t_q)[:, 0]
    assert np.isfinite(got[[0, 3]]).all() and np.isnan(got[[1, 2]]).all()
    np.testing.assert_allclose(got[[0, 3]], np.sin(t_q[[0, 3]] / 4000.0), atol=1e-9)
    few = t_ref[:N_LAGRANGE - 1]
    assert np.isnan(_lagrange((few * 1000).astype(np.int64), few, values[:N_LAGRANGE - 1], col, t_q[:1])).all()
    short = np.r_[np.arange(20) * 300.0, 5700.0 + 1500.0 + np.arange(20) * 300.0]     # a 25-min step: a cm, kept
    got = _lagrange((short * 1000).astype(np.int64), short, np.sin(short / 4000.0)[:, None, None], col[:1],
                    np.array([6500.0]))[:, 0]
    np.testing.assert_allclose(got, np.sin(6500.0 / 4000.0), atol=1e-6)


def test_sp3_epochs_written_again_and_records_cut_short(tmp_path):
    """Two days joined (each ends with the next one's first epoch) keep each epoch's first block, and a position
    record cut inside its z coordinate is skipped, not read as a few digits; both with a warning."""
    from fusion.io.sp3 import read_sp3

    head = "#dP2021  4 28  0  0  0.00000000       3 ORBIT IGS14 HLM  COD\n%c M  cc GPS ccc cccc cccc cccc cccc ccccc\n"

    def block(minute: int, x: float, cut: bool = False) -> str:
        p = f"PG01{x:14.6f}{-15000.0:14.6f}{20000.0:14.6f}{12.5:14.6f}"
        return f"*  2021  4 28  0 {minute:2d}  0.00000000\n" + (p[:40] if cut else p) + "\n"
    p = tmp_path / "joined.sp3"
    p.write_text(head + block(0, 10000.0) + block(5, 10001.0) + block(5, 99999.0) + block(10, 10002.0, cut=True)
                 + "EOF\n")
    with pytest.warns(UserWarning) as seen:
        orb = read_sp3(p)
    said = " ".join(str(w.message) for w in seen)
    assert "1 epoch(s) written again" in said and "joined.sp3:10: position record cut short" in said
    assert orb.t_ms.size == 3 and np.all(np.diff(orb.t_ms) == 300_000)
    np.testing.assert_allclose(orb.pos[:2, 0, 0], [10_000_000.0, 10_001_000.0])
    assert np.isnan(orb.pos[2, 0]).all()
