"""Vectorised fixed-width number parsing: equal to Python's float() on written numbers, bad text flagged."""
from __future__ import annotations

import numpy as np

from fusion.io.fixed_width import char_matrix, line_bounds, parse_float, parse_int, parse_int_text


def _fields(texts: list[bytes], width: int) -> np.ndarray:
    return np.array([list(t.ljust(width)) for t in texts], np.uint8)


def test_fast_and_general_paths_equal_python_float():
    rng = np.random.default_rng(7)
    x = np.concatenate([np.round(rng.uniform(-1e9, 1e9, 3000), 3), np.round(rng.normal(0, 5, 1000), 3)])
    texts = [(b"%14.3f" % v) for v in x]
    want = np.array([float(t) for t in texts])
    m = _fields(texts, 14)
    for dot_col in (10, None):
        got, bad = parse_float(m, dot_col=dot_col)
        assert not bad.any() and np.array_equal(got, want)


CASES = {  # text -> value (None: bad)
    b"  23738869.070": 23738869.07, b"       -0.000": 0.0, b"    -61.912   ": -61.912, b"-5": -5.0,
    b"  7": 7.0, b"          .500": 0.5, b"          -.50": -0.5, b"   -12345.6789": -12345.6789,
    b"12 3.4": None, b"1.2.3": None, b"abc": None, b"5-": None, b"--5": None, b"       --1.000": None,
    b"      - 1.000": None, b"       1-1.000": None, b"  1 345678.000": None, b"      12\xff.000": None,
}


def test_edge_cases_both_paths():
    m = _fields(list(CASES), 14)
    for dot_col in (10, None):
        got, bad = parse_float(m, dot_col=dot_col)
        for (text, want), g, b in zip(CASES.items(), got, bad):
            assert b == (want is None), text
            assert (np.isnan(g) if want is None else g == want), text


def test_blank_is_nan_not_bad_and_ints():
    got, bad = parse_float(_fields([b"", b"    "], 6), dot_col=3)
    assert np.isnan(got).all() and not bad.any()
    v, bad = parse_int(_fields([b" 12", b"-3", b"1.5", b"x", b"   "], 3))
    assert list(v[:2]) == [12, -3] and list(bad) == [False, False, True, True, False]


def test_char_matrix_pads_and_cuts():
    buf = np.frombuffer(b"abc\n\nlonger line\nxy", np.uint8)
    s, e = line_bounds(buf)
    m = char_matrix(buf, s, e, 5)
    assert [bytes(r) for r in m] == [b"abc  ", b"     ", b"longe", b"xy   "]


def test_parse_int_text():
    text = np.array([b"-1378148348376188193", b" 42 ", b"", b"1.5", b"1_000", b"+5", b"4 2", b"-",
                     b"9223372036854775807", b"9999999999999999999", b"5-"], dtype="S24")
    value, empty, bad = parse_int_text(text)
    assert list(value[:3]) == [-1378148348376188193, 42, 0] and value[8] == 2**63 - 1
    assert list(empty) == [False, False, True] + [False] * 8
    assert list(bad) == [False, False, False, True, True, True, True, True, False, True, True]
