"""Vectorised fixed-width number parsing: equal to Python's float() on written numbers, bad text flagged."""
from __future__ import annotations

import numpy as np

from fusion.io.fixed_width import (char_matrix, gather_fields, line_bounds, parse_float, parse_int, parse_int_text)


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


# ---------------------------------------------------------------------------- line layout, against plain slicing
def _random_text(rng, n_lines: int) -> bytes:
    """Lines of digits, signs, points, blanks, tabs, NULs and letters, some empty, some long."""
    alphabet = np.frombuffer(b" 0123456789.-\x00abc\t", np.uint8)
    lines = [rng.choice(alphabet, size=rng.integers(0, 90)).tobytes() for _ in range(n_lines)]
    return b"\n".join(lines) + (b"\n" if rng.random() < 0.5 else b"")


def _padded(buf: bytes, start: int, end: int, width: int) -> bytes:
    return buf[start:end][:width].ljust(width)


def test_line_bounds_char_matrix_and_gather_equal_slicing():
    rng = np.random.default_rng(11)
    for trial in range(200):
        text = _random_text(rng, int(rng.integers(0, 30)))
        buf = np.frombuffer(text, np.uint8)
        starts, ends = line_bounds(buf)
        assert [text[a:b] for a, b in zip(starts, ends)] == text.split(b"\n")[:starts.size]
        pick = np.sort(rng.choice(starts.size, size=rng.integers(0, starts.size + 1), replace=False))
        starts, ends = starts[pick], ends[pick]
        width = int(rng.integers(1, 100))
        m = char_matrix(buf, starts, ends, width)
        assert m.shape == (starts.size, width) and m.dtype == np.uint8
        assert [bytes(r) for r in m] == [_padded(text, a, b, width) for a, b in zip(starts, ends)]
        w = int(rng.integers(1, 9))
        offsets = (np.sort(rng.integers(0, 60, int(rng.integers(1, 5)))) if trial % 2
                   else int(rng.integers(0, 4)) + w * np.arange(int(rng.integers(1, 5))))   # apart / side by side
        f = gather_fields(buf, starts, ends, offsets, w)
        assert f.shape == (w, starts.size, offsets.size) and f.flags.c_contiguous
        for i, (a, b) in enumerate(zip(starts, ends)):
            line = _padded(text, a, b, int(offsets.max()) + w)
            assert [bytes(f[:, i, k]) for k in range(offsets.size)] == [line[o:o + w] for o in offsets]


def test_line_bounds_across_its_blocks():
    """line_bounds scans a buffer in 512 kB blocks: a newline on either side of a block edge counts once."""
    block = 1 << 19
    text = bytearray(b"x" * (3 * block + 5))
    for pos in (block - 1, block, 2 * block + 1, 3 * block + 4):
        text[pos] = 10
    starts, ends = line_bounds(np.frombuffer(bytes(text), np.uint8))
    assert ends.tolist() == [block - 1, block, 2 * block + 1, 3 * block + 4]
    assert starts.tolist() == [0, block, block + 1, 2 * block + 2]


def test_wide_fixed_point_fields_take_the_exact_product():
    """Up to 15 digits the mantissa is summed a row at a time; wider fields keep the matrix product:
    both equal Python's float() where the digits fit a double exactly."""
    rng = np.random.default_rng(5)
    for width, dot_col in ((14, 10), (16, 12), (20, 16), (22, 10)):
        digits = width - 2
        mant = rng.integers(0, 10 ** min(digits, 15), 500)
        texts = [(b"%" + str(width).encode() + b"." + str(width - dot_col - 1).encode() + b"f")
                 % (int(v) / 10 ** (width - dot_col - 1) * s) for v, s in zip(mant, rng.choice([-1, 1], 500))]
        got, bad = parse_float(_fields(texts, width), dot_col=dot_col)
        assert not bad.any() and np.array_equal(got, [float(t) for t in texts]), width
