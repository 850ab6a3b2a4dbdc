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
    # in blocks: one (B,) bool mask of a 4 MB file is 4 MB of fresh memory to touch
    block = 1 << 19
    nl = np.concatenate([np.flatnonzero(buf[a:a + block] == 10) + a for a in range(0, buf.size, block)]
                        or [np.zeros(0, np.int64)])
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
    if buf.size == 0:
        return np.full((starts.size, width), SPACE, np.uint8)
    # Positions past a line's end read the buffer's last byte, then become spaces (no padded copy of
    # the whole buffer); int32 halves the index traffic.
    pos_t = np.int32 if buf.size < 2**31 - 1 else np.int64
    idx = starts.astype(pos_t)[:, None] + np.arange(width, dtype=pos_t)[None, :]
    past = idx >= ends.astype(pos_t)[:, None]
    out = np.take(buf, np.minimum(idx, pos_t(buf.size - 1)))
    out[past] = SPACE
    return out


def parse_decimal(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read right- or left-justified decimal numbers (``-123.456``, ``42``) from fixed fields.

    chars: (N, w) uint8, one field per row.  Returns
    ``(mantissa, decimals, blank, bad)``, each (N,): the value is ``mantissa / 10**decimals``
    exactly (int64 mantissa, so seconds or cycles keep every written digit); ``blank`` marks
    all-space fields; ``bad`` marks anything else that is not one optional leading minus, digits
    (at most 19, within int64) and at most one point, without inner spaces (bad and blank rows hold mantissa 0).
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
    bad = (inner_space | stray).any(axis=1) | (dot.sum(axis=1, dtype=np.int16) > 1) | (n_dig == 0) | (n_dig > 19)
    has_dot = dot.any(axis=1)
    dot_at = np.where(has_dot, np.argmax(dot, axis=1), last + 1)
    decimals = np.where(has_dot, last - dot_at, 0)
    # Power of ten of each digit in the integer mantissa: the count of digits to its right.
    right = np.cumsum(digit[:, ::-1], axis=1, dtype=np.int8)[:, ::-1] - digit
    value = np.where(digit, chars - np.uint8(48), np.uint8(0))
    mantissa = (value * _POW10[np.minimum(right, 18)]).sum(axis=1)
    bad |= mantissa < 0  # a 19-digit number past the int64 range wrapped around
    mantissa = np.where(chars[np.arange(chars.shape[0]), first] == 45, -mantissa, mantissa)
    mantissa[bad] = 0
    return mantissa, decimals, bad


def parse_float(chars: np.ndarray, dot_col: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fixed fields -> (N,) float64 values (NaN where blank or bad) and the (N,) bad mask.

    chars: (N, w) uint8.  dot_col: where the format puts the decimal point (Fortran Fw.d:
    ``w - d - 1``); fields that follow it take a fast path, the others the general parser.
    Dividing an exact integer mantissa by an exact power of ten rounds once, so the result
    equals Python's ``float(text)``.
    """
    return parse_float_columns(np.ascontiguousarray(chars.T), dot_col)


def parse_float_columns(columns: np.ndarray, dot_col: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`parse_float` on column-major fields: columns (w, N) uint8, character j of field i
    at ``[j, i]`` (the layout the fast path wants, so readers can gather straight into it)."""
    n = columns.shape[1]
    value, bad, rest = np.full(n, np.nan), np.zeros(n, bool), np.ones(n, bool)
    if dot_col is not None:
        fast, fast_value = _parse_fixed_point(columns, dot_col)
        value[fast] = fast_value[fast]
        rest = ~fast
    rows = np.flatnonzero(rest)
    if rows.size:
        mantissa, decimals, blank, bad_rest = parse_decimal(columns[:, rows].T)
        v = mantissa / 10.0 ** decimals
        v[blank | bad_rest] = np.nan
        value[rows], bad[rows] = v, bad_rest
    return value, bad


def _parse_fixed_point(c: np.ndarray, dot_col: int) -> tuple[np.ndarray, np.ndarray]:
    """Fast path for fields written exactly to format (optional spaces, optional minus, digits,
    the point at ``dot_col``, digits to the end) and blank fields (NaN). c: (w, N) uint8 column-major fields (reductions
    over a field's w characters are then w elementwise passes over N). Returns (N,) bool
    "parsed here" and (N,) values."""
    w = c.shape[0]
    space = c == SPACE
    digit = (c - np.uint8(48)) < 10  # uint8 wrap-around sends everything below '0' high
    minus = c == 45
    blank = space.all(axis=0)
    allowed = digit | space | minus
    allowed[dot_col] = (c[dot_col] == 46) | blank
    # Text must be one run: no filled -> space step; a minus only right after the leading spaces.
    filled_before = ~space[:-1]
    ok = (allowed.all(axis=0) & ~(space[1:] & filled_before).any(axis=0)
          & ~(minus[1:] & filled_before).any(axis=0) & ~minus[dot_col] & (digit.any(axis=0) | blank))
    dec = w - 1 - dot_col
    power = np.concatenate((np.arange(dot_col - 1, -1, -1) + dec, [0], np.arange(dec - 1, -1, -1)))
    weight = np.where(np.arange(w) == dot_col, 0.0, 10.0 ** power)
    # Digits times exact powers of ten sum exactly in float64 while the mantissa is < 2**53, in any
    # order: with at most 15 digits it always is, and a row at a time then gives the matrix product's
    # bits without its (w, N) float64 copy of the digits (8 bytes per character: the largest array of
    # a RINEX read, and fresh memory is slow to touch)
    digits = np.where(digit, c - np.uint8(48), np.uint8(0))
    if w - 1 <= 15:
        mantissa = np.zeros(c.shape[1])
        for j in np.flatnonzero(weight):
            mantissa += digits[j] * weight[j]
    else:
        mantissa = weight @ digits.astype(np.float64)
    value = np.where(minus.any(axis=0), -mantissa, mantissa) / 10.0 ** dec
    value[blank] = np.nan
    return ok & (mantissa < 2.0 ** 53), value


def gather_fields(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, offsets: np.ndarray,
                  width: int) -> np.ndarray:
    """Characters of fields at ``offsets`` in every line, column-major, space-padded.

    buf: (B,) uint8.  starts, ends: (N,) line offsets.  offsets: (K,) field start columns.
    Returns (width, N, K) uint8: character j of field k of line i at ``[j, i, k]``.
    """
    offsets = np.asarray(offsets, np.int64)
    if starts.size == 0 or offsets.size == 0:
        return np.full((width, starts.size, offsets.size), SPACE, np.uint8)
    lines = line_matrix(buf, starts, ends, int(offsets.max()) + width)        # (N, W)
    cols = (offsets[:, None] + np.arange(width)[None, :]).ravel()            # (K * width,)
    run = np.array_equal(cols, np.arange(cols[0], cols[0] + cols.size))    # side by side: a slice, no copy
    fields = lines[:, cols[0]:cols[0] + cols.size] if run else lines[:, cols]
    return np.ascontiguousarray(fields.reshape(starts.size, offsets.size, width).transpose(2, 0, 1))


def line_matrix(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, width: int) -> np.ndarray:
    """:func:`char_matrix` for wide lines: (N, width) uint8, lines cut at ``width`` or padded with spaces.

    Each line is sliced from the bytes and padded by Python's ``bytes.ljust`` and the lot laid out
    by numpy's fixed-width bytes dtype (which cuts longer lines), one C pass; the index arithmetic of
    :func:`char_matrix` costs three (N, width) integer arrays, twice the time on a phone's RINEX body
    (4 MB, 33,000 satellite lines of 131 characters).
    """
    if starts.size == 0:
        return np.zeros((0, width), np.uint8)
    ends = np.maximum(ends, starts)                    # an empty line, never a backward slice
    lo = int(starts.min())
    raw = buf[lo:int(ends.max())].tobytes()           # the lines' span only: readers call this per block
    padded = [raw[a:b].ljust(width) for a, b in zip((starts - lo).tolist(), (ends - lo).tolist())]
    return np.array(padded, dtype=f"S{width}").view(np.uint8).reshape(len(padded), width)


def parse_int(chars: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fixed integer fields -> (N,) int64 (0 where blank) and the (N,) bad mask (decimals are bad).

    chars: (N, w) uint8.
    """
    mantissa, decimals, _, bad = parse_decimal(chars)
    return mantissa, bad | (decimals != 0)


def parse_int_text(text: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integers in delimited text (CSV cells) -> exact int64.

    text: (N,) fixed-width bytes (dtype ``S<w>``), NUL-padded.  Returns (N,) int64 values
    (0 where empty or bad), (N,) bool empty, (N,) bool bad (anything but optional spaces, an
    optional minus and 1-19 digits in one run, or a value outside int64).
    """
    w = text.dtype.itemsize
    c = np.ascontiguousarray(np.frombuffer(text.tobytes(), np.uint8).reshape(-1, w).T)  # (w, N)
    space = (c == SPACE) | (c == 0)
    digit = (c - np.uint8(48)) < 10
    minus = c == 45
    empty = space.all(axis=0)
    runs = (~space[0]).astype(np.int16) + (~space[1:] & space[:-1]).sum(axis=0, dtype=np.int16)
    n_dig = digit.sum(axis=0, dtype=np.int16)
    ok = ((digit | space | minus).all(axis=0) & (runs == 1) & ~(minus[1:] & ~space[:-1]).any(axis=0)
          & (n_dig >= 1) & (n_dig <= 19))
    value = np.zeros(text.size, np.int64)
    try:
        value[ok] = text[ok].astype(np.int64)
    except OverflowError:  # a 19-digit value past int64: the exact parser finds which
        chars = np.where(c.T == 0, np.uint8(SPACE), c.T)
        value, bad_slow = parse_int(chars)
        ok &= ~bad_slow
        value[~ok] = 0
    return value, empty, ~ok & ~empty


def cut_inside_a_number(length: int, first_col: int, field: int = 16, number: int = 14) -> bool:
    """Whether a line of ``length`` characters whose fields of ``field`` characters (a ``number``-wide value,
    then flags) start at ``first_col`` ends inside a value: a file's last line without a newline may have been
    cut there, and the cut value would still parse, wrongly. A line ending at a field's edge or after a
    value is complete as far as it goes (writers trim blank trailing fields and flags)."""
    into = (length - first_col) % field
    return length > first_col and 0 < into < number
