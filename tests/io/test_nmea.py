"""The SPAN NMEA reader (:mod:`fusion.io.nmea`) and its vectorised sentence fields
(:mod:`fusion.io.nmea_fields`), checked against a per-sentence reference: the reader as it was
before it was vectorised (split each sentence, ``pd.to_numeric`` each column), on crafted and
random sentences with every defect the reader handles."""
from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pandas as pd
import pytest

from fusion.errors import DataError
from fusion.gpstime import GPS_EPOCH_UNIX_MS
from fusion.io import nmea
from fusion.io.nmea_fields import SentenceFields, plain_decimals

# ---------------------------------------------------------------- the per-sentence reference


def _ref_checksum_ok(lines: list[str]) -> np.ndarray:
    """(N,) bool, the checksum rule as an (N, L) byte matrix of the lines states it."""
    fits = np.array([len(ln) <= nmea.MAX_SENTENCE for ln in lines], bool)
    ok = np.zeros(len(lines), bool)
    if not fits.any():
        return ok
    raw = np.array([ln.encode("ascii", "replace") for ln, f in zip(lines, fits) if f])
    buf = raw.view(np.uint8).reshape(raw.size, -1)
    n = np.char.str_len(raw)
    rows, cols = np.arange(raw.size), np.arange(buf.shape[1])
    star = np.maximum(n - 3, 0)
    xor = np.bitwise_xor.reduce(np.where((cols >= 1) & (cols < star[:, None]), buf, 0), axis=1)
    hexval = {ord(c): int(c, 16) for c in "0123456789abcdefABCDEF"}
    hi = np.array([hexval.get(b, -1) for b in buf[rows, np.maximum(n - 2, 0)]])
    lo = np.array([hexval.get(b, -1) for b in buf[rows, np.maximum(n - 1, 0)]])
    shaped = ((n >= 4) & (buf[:, 0] == ord("$")) & (buf[rows, star] == ord("*"))
              & ((buf == ord("*")).sum(1) == 1) & (hi >= 0) & (lo >= 0))
    ok[fits] = shaped & (xor == hi * 16 + lo)
    return ok


def _ref_fields(sentences: list[str], n: int) -> list[np.ndarray]:
    """The first ``n`` fields of each sentence's body, as n (N,) object columns."""
    rows = [(s[1:s.rfind("*")] if "*" in s else s[1:]).split(",") for s in sentences]
    return [np.array(c, dtype=object) for c in zip(*[r[:n] + [""] * (n - len(r)) for r in rows])]


def _ref_number(column: np.ndarray) -> np.ndarray:
    return pd.to_numeric(column, errors="coerce").astype(float)


def _ref_gga_fixes(gga: list[str], skipped: dict[str, int]) -> dict[str, np.ndarray]:
    """The GGA sentences' fixes as the per-sentence reader read them (before dropping any)."""
    ok = _ref_checksum_ok(gga)
    skipped["nmea_bad_checksum"] = int((~ok).sum())
    f = _ref_fields([ln for ln, k in zip(gga, ok) if k], 12)
    return {"tod": nmea._tod_ms(_ref_number(f[1])), "lat": nmea._deg(_ref_number(f[2]), f[3] == "S"),
            "lon": nmea._deg(_ref_number(f[4]), f[5] == "W"), "quality": _ref_number(f[6]),
            "n_sats": _ref_number(f[7]), "alt": _ref_number(f[9]), "sep": _ref_number(f[11])}


def _same(a: np.ndarray, b: np.ndarray) -> None:
    """Equal bit for bit: NaN where NaN, and the sign of zero too."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.signbit(a), np.signbit(b))


def sentence(body: str) -> str:
    cs = 0
    for ch in body:
        cs ^= ord(ch)
    return f"${body}*{cs:02X}"


#: Field texts with every reading rule: plain decimals, signs, blanks, spaces, exponents, words,
#: too many digits for an exact double, non-ASCII digits and letters.
FIELD_CASES = ["3723.7482661", "12206.1789951", "-32.65", "26.74", "05", "14", "0", "1", "-0", "-0.0",
               "0.0", "", " 5", "5 ", "+5", "+5.5", "1e3", ".5", "5.", "-.5", "-5.", ".", "-", "--1",
               "1.2.3", "-12", "12345678901234567", "123456789012345", "1234567890123456", "0.000000000000001",
               "99999999999999999999999", "nan", "inf", "-inf", "abc", "N", "S", "W", "E", "s", "SS",
               "é1", "1\u00a0", "0x1A", "\u0661\u0662", "221452.00", "235959.99", "240000.00", "1_000"]


def _random_sentences(rng: np.random.Generator, n: int) -> list[str]:
    """GGA-like sentences from FIELD_CASES and random plain numbers, with right and wrong
    checksums, lowercase hex, missing or doubled stars, trailing NULs and over-long lines."""
    out = []
    for _ in range(n):
        k = int(rng.integers(0, 16))
        fields = [FIELD_CASES[i] if rng.random() < 0.5 else _random_plain(rng)
                  for i in rng.integers(0, len(FIELD_CASES), k)]
        s = sentence(",".join(["GPGGA"] + fields))
        r = rng.random()
        if r < 0.1:
            s = s[:-2] + ("00" if s[-2:] != "00" else "01")
        elif r < 0.15:
            s = s.lower()[0] + s[1:-2] + s[-2:].lower()
        elif r < 0.2:
            s = s[:-3]
        elif r < 0.25:
            s = s.replace(",", "*,", 1)
        elif r < 0.3:
            s = s + "\x00" * int(rng.integers(1, 3))
        elif r < 0.33:
            s = s + "," * 200
        out.append(s)
    return out


def _random_plain(rng: np.random.Generator) -> str:
    digits = "".join(rng.choice(list("0123456789"), int(rng.integers(1, 18))))
    cut = int(rng.integers(0, len(digits) + 1))
    text = digits if rng.random() < 0.3 else digits[:cut] + "." + digits[cut:]
    return ("-" if rng.random() < 0.3 else "") + text


# ---------------------------------------------------------------- the vectorised fields


def test_fields_checksums_and_numbers_match_the_per_sentence_reader():
    rng = np.random.default_rng(7)
    lines = _random_sentences(rng, 3000)
    f = SentenceFields(lines, 12)
    np.testing.assert_array_equal(f.checksum_ok(nmea.MAX_SENTENCE), _ref_checksum_ok(lines))
    np.testing.assert_array_equal(f.n_commas, [ln.count(",") for ln in lines])
    ref = _ref_fields(lines, 12)
    for rows in (np.arange(len(lines)), np.sort(rng.choice(len(lines), 200, replace=False))):
        for k in range(12):
            _same(f.number(k, rows), _ref_number(ref[k][rows]))
            for letter in "SW":
                np.testing.assert_array_equal(f.letter_is(k, letter, rows), ref[k][rows] == letter)


@pytest.mark.parametrize("column, expect", [
    (["5", "-0"], [5.0, 0.0]),          # pandas reads a column of integers as integers: -0 is 0
    (["5.5", "-0"], [5.5, -0.0]),       # one decimal makes it a float column: -0 keeps its sign
    (["", "-0"], [np.nan, -0.0]),       # so does a blank (NaN)
    (["-0.0", " 7"], [-0.0, 7.0]),
])
def test_numbers_read_each_column_as_pandas_does(column, expect):
    f = SentenceFields([sentence(f"GPGGA,{v}") for v in column], 2)
    got = f.number(1, np.arange(len(column)))
    _same(got, expect)
    _same(got, _ref_number(np.array(column, dtype=object)))


def test_plain_decimals_are_correctly_rounded():
    """Up to 15 digits, [-]digits[.digits] reads as Python's float() (correctly rounded) does."""
    rng = np.random.default_rng(3)
    texts = [t for t in (_random_plain(rng) for _ in range(20000)) if sum(c.isdigit() for c in t) <= 15]
    texts = [t for t in texts if "." in t or not t.startswith("-")]
    f = SentenceFields([sentence("X," + t) for t in texts], 2)
    plain, value, _ = plain_decimals(f.buf, f.start[:, 1], f.stop[:, 1])
    assert plain.all()
    _same(value, [float(t) for t in texts])


def test_empty_and_odd_inputs():
    f = SentenceFields([], 12)
    assert f.checksum_ok(200).shape == (0,) and f.number(3, np.arange(0)).shape == (0,)
    f = SentenceFields(["$", "$*", "$GPGGA,1,2", "x"], 3)
    assert not f.checksum_ok(200).any()
    _same(f.number(1, np.arange(4)), [np.nan, np.nan, 1.0, np.nan])
    _same(f.number(2, np.arange(4)), [np.nan, np.nan, 2.0, np.nan])


# ---------------------------------------------------------------- the reader


@pytest.mark.filterwarnings("ignore:invalid value encountered in divmod:RuntimeWarning")  # "inf" fields
def test_gga_fixes_match_the_per_sentence_reader(tmp_path):
    rng = np.random.default_rng(11)
    good = [sentence(f"GPGGA,{22 + i // 36000:02d}{i // 600 % 60:02d}{i / 10 % 60:04.1f},3723.748{i % 10},"
                     f"{'NS'[i % 2]},12206.17{i % 100:02d},{'EW'[i % 3 > 0]},{i % 3},{i % 15:02d},0.9,"
                     f"{20 + i / 7:.2f},M,{-32.65 + i % 5:.2f},M,,") for i in range(400)]
    lines = good + _random_sentences(rng, 400)
    rng.shuffle(lines)
    got_skipped, ref_skipped = {}, {}
    ref = _ref_gga_fixes(lines, ref_skipped)
    keep = np.isfinite(ref["tod"]) & np.isfinite(ref["lat"]) & np.isfinite(ref["lon"]) & \
        np.isfinite(ref["alt"]) & np.isfinite(ref["sep"]) & (ref["quality"] > 0)
    got = nmea._gga_fixes(lines, tmp_path / "x.nmea", got_skipped)
    for k, v in got.items():
        _same(v, ref[k][keep])
    assert got_skipped["nmea_bad_checksum"] == ref_skipped["nmea_bad_checksum"]
    assert got_skipped["nmea_no_fix"] + got_skipped["nmea_bad_fields"] == (~keep).sum()


def _write(tmp_path, lines: list[str], name: str = "SPAN.nmea"):
    p = tmp_path / name
    p.write_bytes(("\r\n".join(lines) + "\r\n").encode("latin-1"))
    return p


GGA = "GPGGA,{},3720.0499537,{},12154.0145819,{},{},14,0.6,25.25,M,-32.64,M,,"
RMC = sentence("GPRMC,235959.00,A,3720.050,N,12154.015,W,0.0,45.3,280421,,,A")


def test_reader_counts_every_defect_and_rolls_over_midnight(tmp_path):
    lines = [RMC,
             sentence(GGA.format("235959.80", "S", "E", 1)),
             sentence(GGA.format("235959.90", "N", "W", 0)),                   # no fix
             sentence(GGA.format("235959.90", "N", "W", 2))[:-2] + "00",       # bad checksum
             sentence(GGA.format("235959.95", "N", "W", 1).replace("25.25", "")),  # no altitude
             sentence("GPGGA,235959.97,3720.0499537,N"),                       # missing fields
             sentence(GGA.format("000000.00", "N", "W", 1)),
             sentence(GGA.format("000000.00", "N", "W", 4)),                   # repeated time
             "\x85garbage \xe9", "", "   ",
             sentence(GGA.format("000000.10", "N", "W", 1))]
    skipped = {}
    df = nmea.read_span_nmea(_write(tmp_path, lines), skipped=skipped)
    assert skipped == {"nmea_bad_checksum": 1, "nmea_bad_fields": 2, "nmea_no_fix": 1, "nmea_duplicate_times": 1}
    t0 = round(datetime(2021, 4, 28, 23, 59, 59, 800000, tzinfo=timezone.utc).timestamp() * 1000
               - GPS_EPOCH_UNIX_MS + 18_000)
    np.testing.assert_array_equal(df["t_ms"], [t0, t0 + 200, t0 + 300])
    np.testing.assert_array_equal(df["quality"], [1, 1, 1])
    np.testing.assert_allclose(df["lat_deg"], np.array([-1, 1, 1]) * (37 + 20.0499537 / 60), rtol=0, atol=1e-12)
    np.testing.assert_allclose(df["lon_deg"], np.array([1, -1, -1]) * (121 + 54.0145819 / 60), rtol=0, atol=1e-12)
    np.testing.assert_allclose(df["height_m"], 25.25 - 32.64)


def test_reader_refuses_what_it_cannot_use(tmp_path):
    with pytest.raises(DataError, match="no valid GGA sentences"):
        nmea.read_span_nmea(_write(tmp_path, [RMC, sentence(GGA.format("000000.00", "N", "W", 1))[:-1] + "X"]))
    with pytest.raises(DataError, match="no GGA sentence with a valid fix"):
        nmea.read_span_nmea(_write(tmp_path, [RMC, sentence(GGA.format("000000.00", "N", "W", 0))]))
    with pytest.raises(DataError, match="go backwards after fix 1"):
        nmea.read_span_nmea(_write(tmp_path, [RMC, sentence(GGA.format("000001.00", "N", "W", 1)),
                                              sentence(GGA.format("000000.00", "N", "W", 1))]))
