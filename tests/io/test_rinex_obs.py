"""RINEX 3 observation reader: values against a plain per-line reference parse, flags, malformed files."""
from __future__ import annotations

import gzip
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fusion.errors import DataError
from fusion.io.raw import RAW_COLUMNS, check_raw
from fusion.io.rinex_obs import read_rinex_obs

DATA = Path(__file__).resolve().parents[1] / "data"
FIXTURE = DATA / "pixel5_head.21o"  # header + first 5 epochs of the GSDC 2021 Pixel5 RINEX log
C = 299_792_458.0


def _reference(path: Path) -> dict[tuple[int, str, int, str], float]:
    """Slow, obviously-right parse: (epoch index, system, prn, obs type) -> value (0.0 / blank skipped)."""
    lines = path.read_text().splitlines()
    end = next(i for i, l in enumerate(lines) if "END OF HEADER" in l)
    types, sys = {}, ""
    for l in lines[:end]:
        if l[60:].strip() == "SYS / # / OBS TYPES":
            sys = l[0] if l[0] != " " else sys
            types.setdefault(sys, []).extend(l[7:60].split())
    out, epoch = {}, -1
    for l in lines[end + 1:]:
        if l.startswith(">"):
            epoch += 1
            continue
        for i, t in enumerate(types[l[0]]):
            text = l[3 + 16 * i: 3 + 16 * i + 14].strip()
            if text and float(text) != 0.0:
                out[(epoch, l[0], int(l[1:3]), t)] = float(text)
    return out


def _write(tmp_path: Path, text: str | bytes, name: str = "x.21o") -> Path:
    p = tmp_path / name
    p.write_bytes(text.encode() if isinstance(text, str) else text)
    return p


def test_fixture_matches_reference_parse():
    raw = read_rinex_obs(FIXTURE)
    check_raw(raw.frame)
    f = raw.frame
    assert list(f.columns) == list(RAW_COLUMNS)
    assert raw.n_epochs == 5 and raw.approx_pos is None  # the phone wrote zeros
    ref = _reference(FIXTURE)
    epoch = np.searchsorted(np.unique(f.t_ns), f.t_ns)
    code = {"GPS_L1": "1C", "GPS_L5": "5X", "GLO_G1": "1C", "GAL_E1": "1C", "GAL_E5A": "5X"}
    n_checked = 0
    for row, e in zip(f.itertuples(), epoch):
        key = (int(e), row.const, row.svid % 1000)
        c = code[row.signal]
        pr = ref.get(key + ("C" + c,), math.nan)
        assert (math.isnan(pr) and math.isnan(row.pr_m)) or pr == row.pr_m
        wl = C / row.carrier_hz
        for obs, got, scale in (("L", row.adr_m, wl), ("D", row.prr_mps, -wl)):
            want = ref.get(key + (obs + c,), math.nan) * scale
            assert (math.isnan(want) and math.isnan(got)) or got == pytest.approx(want, abs=1e-9), (key, obs)
        assert row.cn0 == ref[key + ("S" + c,)]
        n_checked += 1
    assert n_checked == len(f) > 50


def test_fixture_time_flags_and_glonass():
    f = read_rinex_obs(FIXTURE).frame
    # 2021-04-28 22:19:22.4299102 GPS = week 2155, 3 days + 80362.4299102 s.
    assert f.t_ns.iloc[0] == (2155 * 604800 + 3 * 86400 + 80362) * 10**9 + 429910200
    assert np.all(np.diff(np.unique(f.t_ns)) == 10**9)
    r21 = f[(f.const == "R") & (f.svid == 21)]
    assert (r21.glo_k == 4).all() and np.allclose(r21.carrier_hz, 1602e6 + 4 * 0.5625e6)
    # LLI 1 on G12 L1C in the second epoch: a slip there, none in the first.
    g12 = f[(f.sat_id == 1012) & (f.signal == "GPS_L1")]
    assert list(g12.adr_slip.iloc[:2]) == [False, True]
    assert not f.clock_reset.any()
    assert (f.adr_ok == np.isfinite(f.adr_m)).all()


def test_gzip_same_as_plain(tmp_path):
    gz = _write(tmp_path, gzip.compress(FIXTURE.read_bytes()), "x_MO.rnx.gz")
    assert read_rinex_obs(gz).frame.equals(read_rinex_obs(FIXTURE).frame)


def test_rinex4_same_as_rinex3(tmp_path):
    """RINEX 4 observation records are RINEX 3.05's; its new header lines are passed over."""
    lines = _lines()
    v4 = [f"{'4.02':>9s}" + lines[0][9:],
          "10.1234/a-doi                                               DOI                 \n",
          "CC BY 4.0                                                   LICENSE OF USE      \n"] + lines[1:]
    a, b = read_rinex_obs(FIXTURE).frame, read_rinex_obs(_write(tmp_path, "".join(v4))).frame
    pd.testing.assert_frame_equal(a, b)


def test_corrupt_gzip_is_one_line_error(tmp_path):
    bad = _write(tmp_path, b"\x1f\x8b\x08\x00" + b"\xff" * 300, "x.21o.gz")
    with pytest.raises(DataError, match=r"x\.21o\.gz: corrupt gzip"):
        read_rinex_obs(bad)
    # a stream cut inside the header keeps what was decompressed (the shared policy), which has no header end
    cut = _write(tmp_path, gzip.compress(FIXTURE.read_bytes())[:200], "y.21o.gz")
    with pytest.warns(UserWarning, match="gzip stream ends early"), \
            pytest.raises(DataError, match=r"y\.21o\.gz: no 'END OF HEADER'"):
        read_rinex_obs(cut)


def _lines() -> list[str]:
    return FIXTURE.read_text().splitlines(keepends=True)


def test_bad_number_skips_line_and_names_it(tmp_path):
    lines = _lines()
    i = next(k for k, l in enumerate(lines) if l.startswith("G12"))
    lines[i] = lines[i][:8] + "x" + lines[i][9:]
    p = _write(tmp_path, "".join(lines))
    with pytest.warns(UserWarning, match=rf"x\.21o:{i + 1}: unreadable number"):
        raw = read_rinex_obs(p)
    assert raw.skipped["sat_lines_bad_number"] == 1
    assert len(raw.frame) == len(read_rinex_obs(FIXTURE).frame) - 1


def test_bad_epoch_line_is_error_with_line(tmp_path):
    lines = _lines()
    i = next(k for k, l in enumerate(lines) if l.startswith(">"))
    lines[i] = lines[i].replace(" 04 ", " 4x ", 1)
    with pytest.raises(DataError, match=rf"x\.21o:{i + 1}: cannot read epoch line"):
        read_rinex_obs(_write(tmp_path, "".join(lines)))


def test_truncated_final_record_is_counted(tmp_path):
    p = _write(tmp_path, "".join(_lines()[:-3]))
    with pytest.warns(UserWarning, match="truncated"):
        raw = read_rinex_obs(p)
    assert raw.skipped["records_truncated"] == 1
    assert raw.n_epochs == 4


def _records(text: str) -> tuple[list[str], list[str]]:
    """The fixture's header lines and its epoch records, each record's lines joined."""
    lines = text.splitlines(keepends=True)
    starts = [k for k, l in enumerate(lines) if l.startswith(">")]
    return lines[:starts[0]], ["".join(lines[a:b]) for a, b in zip(starts, starts[1:] + [len(lines)])]


@pytest.mark.parametrize("version", [3, 2])
def test_a_record_written_twice_or_time_going_back_is_skipped_and_counted(tmp_path, version):
    """Epoch 1 written twice, then epochs 0-1 again after epoch 3: the file's first word on each epoch stands,
    the three others are counted with a warning naming the first one's line, and every good epoch is kept."""
    head, rec = _records(FIXTURE.read_text())
    text = "".join(head + [rec[0], rec[1], rec[1], rec[2], rec[3], rec[0], rec[1], rec[4]])
    if version == 2:
        text = _to_v2(text)
    line = len(head) + rec[0].count("\n") + rec[1].count("\n") + 1 if version == 3 else r"\d+"
    with pytest.warns(UserWarning, match=rf"x\.21o:{line}: epoch not later than one before it.*3 such record"):
        raw = read_rinex_obs(_write(tmp_path, text))
    ref = read_rinex_obs(FIXTURE)
    assert raw.skipped.get("epochs_not_later") == 3 and raw.n_epochs == 5
    assert raw.frame.equals(ref.frame)


@pytest.mark.parametrize("version", [3, 2])
def test_an_epoch_record_without_satellites_is_counted(tmp_path, version):
    """An epoch record announcing no satellite leaves no row: it is counted, not lost from the totals."""
    head, rec = _records(FIXTURE.read_text())
    empty = rec[2].splitlines(keepends=True)[0]
    empty = empty[:32] + "  0" + empty[35:]
    text = "".join(head + [rec[0], rec[1], empty, rec[3], rec[4]])
    raw = read_rinex_obs(_write(tmp_path, _to_v2(text) if version == 2 else text))
    assert raw.skipped.get("epochs_no_satellites") == 1 and raw.n_epochs == 4


def test_event_and_power_failure_flags(tmp_path):
    lines = _lines()
    epochs = [k for k, l in enumerate(lines) if l.startswith(">")]
    # Epoch 3 becomes a power-failure epoch; an event record (flag 5, one comment line) precedes epoch 2.
    lines[epochs[3]] = lines[epochs[3]][:31] + "1" + lines[epochs[3]][32:]
    event = ">                              5  1\n" + "SOME EVENT".ljust(60) + "COMMENT\n"
    lines.insert(epochs[2], event)
    raw = read_rinex_obs(_write(tmp_path, "".join(lines)))
    assert raw.skipped["event_records"] == 1 and raw.n_epochs == 5
    reset = raw.frame.groupby("t_ns").clock_reset.first().to_numpy()
    assert list(reset) == [False, False, False, True, False]


def test_garbage_header_only_and_rinex2(tmp_path):
    with pytest.raises(DataError, match="END OF HEADER"):
        read_rinex_obs(_write(tmp_path, bytes(range(256)) * 10))
    head = "".join(l for l in _lines() if not l.startswith((">", "G", "R", "E")) or "OBS TYPES" in l
                   or "SLOT" in l)
    head = head[:head.index("END OF HEADER") + 73]
    with pytest.raises(DataError, match="no epoch records"):
        read_rinex_obs(_write(tmp_path, head))
    v1 = "     1.00           OBSERVATION DATA    M (MIXED)           RINEX VERSION / TYPE\n" + \
         "                                                            END OF HEADER\n"
    with pytest.raises(DataError, match=r"x\.21o:1: RINEX version 1\.0 "):
        read_rinex_obs(_write(tmp_path, v1))
    crx = "1.0                 COMPACT RINEX FORMAT                    CRINEX VERS   / TYPE\n" + v1
    with pytest.raises(DataError, match="Hatanaka"):
        read_rinex_obs(_write(tmp_path, crx))
    with pytest.raises(DataError, match="missing.21o: RINEX observation file not found"):
        read_rinex_obs(tmp_path / "missing.21o")


def test_full_pixel5_file(shared_data):
    path = shared_data / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5/supplemental/Pixel5_GnssLog.21o"
    raw = read_rinex_obs(path)
    assert raw.n_epochs == 1985
    assert set(raw.frame.signal) == {"GPS_L1", "GPS_L5", "GLO_G1", "GAL_E1", "GAL_E5A"}
    ok = raw.frame.pr_m.notna()
    assert ((raw.frame.pr_m[ok] > 1.9e7) & (raw.frame.pr_m[ok] < 3e7)).all()


def test_cut_inside_last_line_is_truncated_not_misread(tmp_path):
    text = FIXTURE.read_text()
    cut = text[:text.rstrip().rfind(".") - 2]  # inside the last number of the last line
    with pytest.warns(UserWarning, match="truncated"):
        raw = read_rinex_obs(_write(tmp_path, cut))
    assert raw.skipped["records_truncated"] == 1 and raw.n_epochs == 4


def test_a_complete_last_line_without_a_newline_is_kept(tmp_path):
    """Many writers end the file without a newline: a last line that ends at a field's edge or after a value
    is read (RINEX 3 and 2), one that ends inside a value is not (the test above)."""
    ref = read_rinex_obs(FIXTURE)
    for name, text in (("x.21o", FIXTURE.read_text()), ("v2.21o", _to_v2(FIXTURE.read_text()))):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            raw = read_rinex_obs(_write(tmp_path, text.rstrip("\n"), name))
        assert raw.frame.equals(ref.frame) and raw.skipped == ref.skipped


def test_published_mixed_types_sample_keeps_its_last_epoch(shared_data):
    path = shared_data / "android_samples" / "rinex_obs_mixed_types.20o"
    assert path.read_bytes()[-1:] != b"\n"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        raw = read_rinex_obs(path)
    assert raw.n_epochs == 5 and "records_truncated" not in raw.skipped
    last = raw.frame[raw.frame.t_ns == raw.frame.t_ns.max()]
    e30 = last[(last.const == "E") & (last.svid == 30)]       # the last line, with its two signals
    assert len(e30) == 2 and e30.pr_m.notna().all()


def test_glonass_channels_fill_missing_header_slots(tmp_path):
    lines = [l for l in _lines() if "GLONASS SLOT / FRQ #" not in l]
    path = _write(tmp_path, "".join(lines))
    plain = read_rinex_obs(path, slot_table=False)
    glo = plain.frame[plain.frame.const == "R"]
    assert len(glo) and (glo.glo_k == -99).all() and glo.prr_mps.isna().all() and glo.pr_m.notna().any()
    assert plain.skipped["glonass_no_channel_doppler_phase"] > 0
    filled = read_rinex_obs(path, glonass_channels={9: -2, 20: 2, 21: 4}, slot_table=False)
    g = filled.frame[filled.frame.const == "R"]
    ref = read_rinex_obs(FIXTURE).frame
    assert g.reset_index(drop=True).equals(ref[ref.const == "R"].reset_index(drop=True))
    assert "glonass_no_channel_doppler_phase" not in filled.skipped
    assert filled.skipped["glonass_rows_channel_from_navigation"] == len(g)
    # without navigation, the slot table gives the same channels (it agrees with this phone's header)
    table = read_rinex_obs(path)
    assert table.frame[table.frame.const == "R"].reset_index(drop=True).equals(g.reset_index(drop=True))
    assert table.skipped["glonass_rows_channel_from_slot_table"] == len(g)
    # navigation wins over the table; the header wins over both
    nav = read_rinex_obs(path, glonass_channels={9: 3})
    assert (nav.frame.query("const == 'R' and svid == 9").glo_k == 3).all()
    assert (read_rinex_obs(FIXTURE, glonass_channels={9: 3}).frame.query("const == 'R' and svid == 9").glo_k == -2).all()
    # The header wins over the caller.
    assert (read_rinex_obs(FIXTURE, glonass_channels={21: -5}).frame.query("svid == 21 and const == 'R'").glo_k == 4).all()


def test_glonass_header_list_read_whole():
    from fusion.io.rinex_obs import _parse_header
    # GnssToRinex writes " 6 R05  1 R09 -2 ...": the list starts a column early.
    assert _parse_header(FIXTURE.read_bytes(), FIXTURE).glo_k == {5: 1, 9: -2, 12: -1, 20: 2, 21: 4, 22: -3}


def _obs_file(tmp_path: Path) -> Path:
    """A survey-receiver-like RINEX 3.04 file: BeiDou, QZSS, SBAS, NavIC, GPS L2 (C2X ours, C2W not), and
    GPS observation types continued on a second header line."""
    g = "C1C L1C D1C S1C C2W L2W C5Q L5Q D5Q S5Q C2X L2X S2X C1W".split()
    types = {"G": g, "C": "C2I L2I D2I S2I".split(), "J": "C1C L1C D1C S1C C5Q L5Q D5Q S5Q".split(),
             "S": ["C1C", "L1C"], "I": ["C5A", "L5A"]}
    head = ["     3.04           OBSERVATION DATA    M                   RINEX VERSION / TYPE",
            "".join(f"{v:14.4f}" for v in (-2.7e6, -4.3e6, 3.85e6)).ljust(60) + "APPROX POSITION XYZ"]
    for s, t in types.items():
        head.append(f"{s}  {len(t):3d} " + " ".join(t[:13]).ljust(53) + "SYS / # / OBS TYPES")
        if len(t) > 13:
            head.append("       " + " ".join(t[13:]).ljust(53) + "SYS / # / OBS TYPES")
    head.append("  2021     4    28    22    19   22.0000000     GPS         TIME OF FIRST OBS")
    head.append(" " * 60 + "END OF HEADER")
    f = lambda v, lli=" ": f"{v:14.3f}{lli}5"  # noqa: E731
    body = ["> 2021 04 28 22 19 22.0000000  0  5",
            "G07" + "".join(f(2.1e7 + i) for i in range(len(g))),
            "C05" + f(3.8e7) + f(2.0e8, "1") + f(-1000.5) + f(40.25),
            "J01" + f(3.7e7) + f(1.9e8) + f(250.0) + f(42.0) + f(3.7e7 + 2) + f(1.4e8) + f(190.0) + f(45.0),
            "S31" + f(3.9e7) + f(2.1e8),
            "I03" + f(3.6e7) + f(1.5e8)]
    p = tmp_path / "SURV00USA_R_20211182219_01H_01S_MO.rnx"
    p.write_text("\n".join(head + body) + "\n")
    return p


def test_other_constellations_and_codes(tmp_path):
    raw = read_rinex_obs(_obs_file(tmp_path))
    f = raw.frame.set_index(["sat_id", "signal"])
    assert sorted(f.index) == [(1007, "GPS_L1"), (1007, "GPS_L2"), (1007, "GPS_L5"), (4193, "QZS_J1"),
                               (4193, "QZS_J5"), (5005, "BDS_B1I")]
    assert np.allclose(raw.approx_pos, [-2.7e6, -4.3e6, 3.85e6])
    assert f.loc[(1007, "GPS_L5"), "pr_m"] == 2.1e7 + 6  # C5Q is the 7th type
    b = f.loc[(5005, "BDS_B1I")]
    assert b.pr_m == 3.8e7 and b.cn0 == 40.25 and b.adr_slip and b.carrier_hz == 1561.098e6
    assert b.adr_m == pytest.approx(2.0e8 * C / 1561.098e6) and b.prr_mps == pytest.approx(1000.5 * C / 1561.098e6)
    assert f.loc[(4193, "QZS_J5"), "carrier_hz"] == 1176.45e6
    # L2C (C2X, the 11th type) is a signal of its own, at the L2 carrier
    l2 = f.loc[(1007, "GPS_L2")]
    assert l2.pr_m == 2.1e7 + 10 and l2.carrier_hz == 1227.60e6 and l2.adr_m == pytest.approx((2.1e7 + 11) * C / 1227.60e6)
    # P(Y) (C2W/C1W) is not one of ours; SBAS and NavIC lines are dropped; all counted.
    assert raw.skipped == {"obs_other_signals": 1, "sat_lines_sbas_not_used": 1, "sat_lines_unsupported_system": 1}


def test_a_system_missing_from_the_header_is_counted(tmp_path):
    """A BeiDou line in a file whose header lists no BeiDou observation types cannot be decoded:
    dropped and counted, not lost silently."""
    p = _obs_file(tmp_path)
    p.write_text("".join(l for l in p.read_text().splitlines(True) if not l.startswith("C    4 C2I")))
    raw = read_rinex_obs(p)
    assert raw.skipped["sat_lines_system_not_in_header"] == 1
    assert "BDS_B1I" not in set(raw.frame.signal)


def test_repeated_satellite_line_is_counted_once(tmp_path):
    lines = _lines()
    e = next(k for k, l in enumerate(lines) if l.startswith(">"))
    lines[e] = lines[e][:32] + f"{int(lines[e][32:35]) + 1:3d}" + lines[e][35:]
    lines.insert(e + 2, lines[e + 1])
    raw = read_rinex_obs(_write(tmp_path, "".join(lines)))
    assert raw.skipped["duplicate_observations"] >= 1
    assert raw.frame.equals(read_rinex_obs(FIXTURE).frame)



def _to_v2(r3: str) -> str:
    """The fixture's RINEX 3 text (G/R/E, 8 types) rewritten as RINEX 2.11, value for value."""
    lines = r3.splitlines()
    end = next(i for i, l in enumerate(lines) if "END OF HEADER" in l)
    keep = [l for l in lines[:end] if l[60:].strip() in ("GLONASS SLOT / FRQ #", "TIME OF FIRST OBS")]
    head = ["     2.11           OBSERVATION DATA    M (MIXED)           RINEX VERSION / TYPE",
            "     8    C1    L1    D1    S1    C5    L5    D5    S5      # / TYPES OF OBSERV"] + keep + [lines[end]]
    out, i, body = [], 0, lines[end + 1:]
    while i < len(body):
        e = body[i]
        y, mo, d, h, mi = (int(x) for x in e[2:18].split())
        sec, flag, n = float(e[18:29]), int(e[29:32]), int(e[32:35])
        ids = [l[:3] for l in body[i + 1:i + 1 + n]]
        out.append(f" {y % 100:02d} {mo:2d} {d:2d} {h:2d} {mi:2d}{sec:11.7f}  {flag:1d}{n:3d}" + "".join(ids[:12]))
        out += [" " * 32 + "".join(ids[k:k + 12]) for k in range(12, n, 12)]
        for l in body[i + 1:i + 1 + n]:
            f = l[3:].ljust(128)
            out += [f[:80].rstrip(), f[80:128].rstrip()]  # 5 observations per line
        i += 1 + n
    return "\n".join(head + out) + "\n"


def test_rinex2_same_as_rinex3(tmp_path):
    v2 = _to_v2(FIXTURE.read_text())
    assert "G25R09R21E01E13E15E21\n" + " " * 32 + "E26E27" in v2  # satellite list continued
    raw = read_rinex_obs(_write(tmp_path, v2, "x.21o"))
    ref = read_rinex_obs(FIXTURE)
    assert raw.frame.equals(ref.frame) and raw.skipped == ref.skipped


def test_rinex2_malformed(tmp_path):
    lines = _to_v2(FIXTURE.read_text()).splitlines(keepends=True)
    with pytest.warns(UserWarning, match="truncated"):
        raw = read_rinex_obs(_write(tmp_path, "".join(lines[:-2])))
    assert raw.skipped["records_truncated"] == 1 and raw.n_epochs == 4
    i = next(k for k, l in enumerate(lines) if l.startswith(" 21"))
    bad = lines[:i] + [lines[i][:29] + " x" + lines[i][31:]] + lines[i + 1:]
    with pytest.raises(DataError, match=rf"x\.21o:{i + 1}: cannot read epoch line"):
        read_rinex_obs(_write(tmp_path, "".join(bad)))
    with pytest.raises(DataError, match="header only"):
        read_rinex_obs(_write(tmp_path, "".join(lines[:i])))
    j = i + 2  # the first satellite's first observation line
    garbled = lines[:j] + [lines[j].replace("23738869.070", "2373886?.070")] + lines[j + 1:]
    with pytest.warns(UserWarning, match=rf"x\.21o:{j + 1}: unreadable number"):
        raw = read_rinex_obs(_write(tmp_path, "".join(garbled)))
    assert raw.skipped["sat_lines_bad_number"] == 1


def test_satellite_lines_read_in_blocks_as_in_one(tmp_path, monkeypatch):
    """The body is gathered and parsed PARSE_BLOCK_LINES satellite lines at a time: any block size
    gives the same frame and counts, with an unreadable number in a later block."""
    import warnings

    import fusion.io.rinex_obs as ro

    lines = FIXTURE.read_text().splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln)
    sat = [i for i, ln in enumerate(lines) if i > end and ln[:1] != ">" and ln.strip()]
    bad = sat[-3]
    lines[bad] = lines[bad][:10] + "x" + lines[bad][11:]
    path = _write(tmp_path, "\n".join(lines) + "\n")
    frames = []
    for block in (1, 7, len(sat) - 1, 10**6):
        monkeypatch.setattr(ro, "PARSE_BLOCK_LINES", block)
        with warnings.catch_warnings(record=True):
            warnings.simplefilter("always")
            frames.append(read_rinex_obs(path))
    for other in frames[1:]:
        assert other.frame.equals(frames[0].frame) and other.skipped == frames[0].skipped
    assert frames[0].skipped["sat_lines_bad_number"] == 1 and len(frames[0].frame) > 20


def _beidou_file(tmp_path: Path, version: str, types: str) -> Path:
    """One epoch of one BeiDou satellite with the observation types ``types`` (C L D S per signal)."""
    t = types.split()
    head = [f"{version:>9s}           OBSERVATION DATA    M                   RINEX VERSION / TYPE",
            f"C  {len(t):3d} " + " ".join(t).ljust(53) + "SYS / # / OBS TYPES",
            "  2021     4    28    22    19   22.0000000     GPS         TIME OF FIRST OBS",
            " " * 60 + "END OF HEADER"]
    f = lambda v: f"{v:14.3f} 5"  # noqa: E731
    body = ["> 2021 04 28 22 19 22.0000000  0  1", "C30" + "".join(f(3.8e7 + i) for i in range(len(t)))]
    p = tmp_path / f"bds{version}.21o"
    p.write_text("\n".join(head + body) + "\n")
    return p


def test_beidou_b1c_and_b2a(tmp_path):
    """RINEX 3.04's BeiDou-3 codes: B1C on band 1 (pilot P first, then X, then data D), B2a on band 5, each a
    signal of its own beside B1I at its carrier; before 3.04 (in 3.01 band 1 was B1I) C1X is no B1C."""
    raw = read_rinex_obs(_beidou_file(tmp_path, "3.04", "C2I L2I D2I S2I C1D C1P L1P D1P S1P C5X L5X D5X S5X"))
    f = raw.frame.set_index("signal")
    assert sorted(f.index) == ["BDS_B1C", "BDS_B1I", "BDS_B2A"]
    assert f.loc["BDS_B1C", "pr_m"] == 3.8e7 + 5 and f.loc["BDS_B1C", "carrier_hz"] == 1575.42e6     # C1P, not C1D
    assert f.loc["BDS_B1C", "adr_m"] == pytest.approx((3.8e7 + 6) * C / 1575.42e6)
    assert f.loc["BDS_B2A", "pr_m"] == 3.8e7 + 9 and f.loc["BDS_B2A", "carrier_hz"] == 1176.45e6
    assert f.loc["BDS_B2A", "cn0"] == 3.8e7 + 12
    assert raw.skipped == {"obs_other_signals": 1}                                            # C1D
    assert set(read_rinex_obs(_beidou_file(tmp_path, "3.04", "C1X L1X")).frame.signal) == {"BDS_B1C"}
    for version in ("3.01", "3.03"):
        old = read_rinex_obs(_beidou_file(tmp_path, version, "C1I L1I C1X L1X"))
        assert set(old.frame.signal) == {"BDS_B1I"} and old.frame.pr_m.tolist() == [3.8e7]
        assert old.skipped == {"obs_other_signals": 1}
