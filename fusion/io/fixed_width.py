"""Vectorised fixed-width text parsing: many lines of one byte buffer at once.

Fortran-style formats (RINEX) put every field at a known column, so a block of ``N`` lines can be
laid out as an ``(N, W)`` byte matrix and each field read with array arithmetic, instead of
slicing and ``float()``-ing value by value in Python (which is what makes generic RINEX readers
take tens of seconds on a phone log).
"""
from __future__ import annotations

import numpy as np

SPACE = 32
_POW10 = 10 ** np.arange(19, dtype=np.int64)


def line_bounds(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive, newline not included) offsets of every line.

    buf: (B,) uint8, the text.  Returns two (L,) int64 arrays; a final line without a newline
    counts, an empty tail after the last newline does not.
    """
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate(([0], nl + 1))
    ends = np.concatenate((nl, [buf.size]))
    if starts[-1] >= buf.size:
        starts, ends = starts[:-1], ends[:-1]
    return starts.astype(np.int64), ends.astype(np.int64)


def char_matrix(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, width: int) -> np.ndarray:
    """Lines as a space-padded byte matrix.

    buf: (B,) uint8.  starts, ends: (N,) int64 line offsets.  Returns (N, width) uint8; longer
    lines are cut at ``width``, shorter ones padded with spaces (RINEX writers strip trailing
    blanks, which mean "missing").
    """
    cols = np.arange(width, dtype=np.int64)
    idx = starts[:, None] + cols[None, :]
    inside = idx < ends[:, None]
    out = np.full((starts.size, width), SPACE, np.uint8)
    out[inside] = buf[idx[inside]]
    return out


def parse_decimal(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read right- or left-justified decimal numbers (``-123.456``, ``42``) from fixed fields.

    chars: (N, w) uint8, one field per row.  Returns
    ``(mantissa, decimals, blank, bad)``, each (N,): the value is ``mantissa / 10**decimals``
    exactly (int64 mantissa, so seconds or cycles keep every written digit); ``blank`` marks
    all-space fields; ``bad`` marks anything else that is not one optional leading minus, digits
    and at most one point, without inner spaces (bad and blank rows hold mantissa 0).
    """
    n = chars.shape[0]
    blank = ~(chars != SPACE).any(axis=1)
    mantissa, decimals, bad = np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, bool)
    # Phone logs leave many fields blank: parse only the filled ones.
    rows = np.flatnonzero(~blank)
    if rows.size:
        mantissa[rows], decimals[rows], bad[rows] = _parse_filled(chars[rows])
    return mantissa, decimals, blank, bad


def _parse_filled(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """parse_decimal on (N, w) uint8 fields that are not all blank -> mantissa, decimals, bad."""
    w = chars.shape[1]
    digit = (chars >= 48) & (chars <= 57)
    dot, minus, space = chars == 46, chars == 45, chars == SPACE
    filled = ~space
    first = np.argmax(filled, axis=1)
    last = w - 1 - np.argmax(filled[:, ::-1], axis=1)
    j = np.arange(w)[None, :]
    n_dig = digit.sum(axis=1, dtype=np.int16)
    inner_space = space & (j > first[:, None]) & (j < last[:, None])
    stray = ~(digit | dot | space) & ~(minus & (j == first[:, None]))
    bad = (inner_space | stray).any(axis=1) | (dot.sum(axis=1, dtype=np.int16) > 1) | (n_dig == 0) | (n_dig > 18)
    has_dot = dot.any(axis=1)
    dot_at = np.where(has_dot, np.argmax(dot, axis=1), last + 1)
    decimals = np.where(has_dot, last - dot_at, 0)
    # Power of ten of each digit in the integer mantissa: the count of digits to its right.
    right = np.cumsum(digit[:, ::-1], axis=1, dtype=np.int8)[:, ::-1] - digit
    value = np.where(digit, chars - np.uint8(48), np.uint8(0))
    mantissa = (value * _POW10[np.minimum(right, 18)]).sum(axis=1)
    mantissa = np.where(chars[np.arange(chars.shape[0]), first] == 45, -mantissa, mantissa)
    mantissa[bad] = 0
    return mantissa, decimals, bad


def parse_float(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fixed fields -> (N,) float64 values (NaN where blank or bad) and the (N,) bad mask.

    chars: (N, w) uint8.  Dividing the exact integer mantissa by an exact power of ten rounds
    once, so the result equals Python's ``float(text)``.
    """
    mantissa, decimals, blank, bad = parse_decimal(chars)
    value = mantissa / 10.0 ** decimals
    value[blank | bad] = np.nan
    return value, bad


def parse_int(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fixed integer fields -> (N,) int64 (0 where blank) and the (N,) bad mask (decimals are bad).

    chars: (N, w) uint8.
    """
    mantissa, decimals, _, bad = parse_decimal(chars)
    return mantissa, bad | (decimals != 0)
