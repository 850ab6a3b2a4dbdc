"""The fields of many NMEA sentences at once: checksums, letters and numbers read with array
arithmetic over one byte buffer, instead of splitting and converting sentence by sentence.

The rules are those of a per-sentence reader: a sentence's body runs from after its first
character to its last ``*`` (or its end) and splits at commas (``""`` past its last field); a
field's number is what ``pd.to_numeric(column, errors="coerce")`` makes of the whole column.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

#: Most digits of a plain decimal read here (as an integer < 2^53: exact in a double); longer
#: numbers, and anything that is not ``[-]digits[.digits]``, are left to pandas.
EXACT_DIGITS = 15
_POW10 = np.array([float(10 ** k) for k in range(EXACT_DIGITS + 3)])
#: A character's code as :func:`plain_decimals` reads it: its byte minus '0' (uint8, wrapping).
_CODE = {c: np.uint8((ord(c) - ord("0")) % 256) for c in ".- "}


def _hex_table() -> np.ndarray:
    """(256,) int: the value of each ASCII hex digit, -1 for every other byte."""
    table = np.full(256, -1, np.int16)
    for i, ch in enumerate("0123456789ABCDEF"):
        table[ord(ch)] = table[ord(ch.lower())] = i
    return table


_HEX = _hex_table()


class SentenceFields:
    """N sentences joined in one byte buffer, with the offsets of their first ``n_fields`` fields.

    ``start``, ``stop``: (N, n_fields) field k of sentence i is ``text[start[i, k]:stop[i, k]]``
    (empty where stop <= start). ``n_commas``: (N,) commas in each whole sentence.
    """

    def __init__(self, sentences: list[str], n_fields: int):
        self.sentences = sentences
        self.text = "\n".join(sentences)
        # 'replace' maps every non-ASCII character to one '?': byte offsets stay character offsets
        self.buf = np.frombuffer(self.text.encode("ascii", "replace"), np.uint8)
        self._padded = np.append(self.buf, np.uint8(0))
        self.lens = np.fromiter(map(len, sentences), np.int64, len(sentences))
        self.line0 = np.cumsum(self.lens + 1) - (self.lens + 1)
        line_end = self.line0 + self.lens
        stars = np.flatnonzero(self.buf == ord("*"))
        self.n_stars = np.searchsorted(stars, line_end) - np.searchsorted(stars, self.line0)
        last = stars[np.maximum(np.searchsorted(stars, line_end) - 1, 0)] if stars.size else line_end
        body0, body_end = self.line0 + 1, np.where(self.n_stars > 0, last, line_end)
        # a comma past the buffer's end keeps the lookups below in range
        commas = np.append(np.flatnonzero(self.buf == ord(",")), self.buf.size)
        self.n_commas = np.searchsorted(commas, line_end) - np.searchsorted(commas, self.line0)
        # the commas of sentence i's body are commas[lo[i]:hi[i]]; field k ends at the k-th of them
        lo, hi = np.searchsorted(commas, body0), np.searchsorted(commas, body_end)
        bounds = np.empty((len(sentences), n_fields + 1), np.int64)
        bounds[:, 0] = body0 - 1
        for k in range(n_fields):
            at = lo + k
            bounds[:, k + 1] = np.where(at < hi, commas[np.minimum(at, commas.size - 1)], body_end)
        self.start, self.stop = bounds[:, :-1] + 1, bounds[:, 1:]

    def _byte(self, pos: np.ndarray) -> np.ndarray:
        """(N,) the buffer's bytes at ``pos`` (N,), 0 past its end."""
        return self._padded[np.minimum(pos, self.buf.size)]

    def checksum_ok(self, max_len: int) -> np.ndarray:
        """(N,) bool: the sentence is ``$body*hh``, at most ``max_len`` characters, and ``hh`` (hex)
        is the XOR of the body's bytes. As in a numpy byte string, trailing NULs do not count."""
        n = self.lens.copy()
        nul = np.flatnonzero(self.buf == 0)
        for i in np.unique(np.searchsorted(self.line0, nul, "right") - 1):
            n[i] = len(self.sentences[i].rstrip("\x00"))
        l0, long = self.line0, n >= 4
        hi, lo = _HEX[self._byte(l0 + np.maximum(n - 2, 0))], _HEX[self._byte(l0 + np.maximum(n - 1, 0))]
        shaped = (long & (self._byte(l0) == ord("$")) & (self._byte(l0 + np.maximum(n - 3, 0)) == ord("*"))
                  & (self.n_stars == 1) & (hi >= 0) & (lo >= 0))
        # XOR of buf[l0 + 1 : l0 + n - 3], each sentence's segment one reduceat slot (empty: 0)
        ends = np.where(long, l0 + n - 3, 0)
        marks = np.stack([np.where(long, l0 + 1, 0), ends], axis=1).ravel()
        xor = np.bitwise_xor.reduceat(self.buf, marks)[0::2] if self.buf.size else np.zeros(0, np.uint8)
        xor = np.where(ends > l0 + 1, xor, 0)
        return (self.lens <= max_len) & shaped & (xor == hi * 16 + lo)

    def letter_is(self, k: int, letter: str, rows: np.ndarray) -> np.ndarray:
        """(R,) bool: field ``k`` of the sentences ``rows`` (R,) is exactly ``letter``."""
        start, stop = self.start[rows, k], self.stop[rows, k]
        return ((stop - start) == 1) & (self._byte(start) == ord(letter))

    def number(self, k: int, rows: np.ndarray) -> np.ndarray:
        """(R,) float: field ``k`` of the sentences ``rows`` (R,), as ``pd.to_numeric(errors="coerce")``
        reads that column (NaN where it is not a number)."""
        start, stop = self.start[rows, k], self.stop[rows, k]
        plain, value, dotted = plain_decimals(self.buf, start, stop)
        out = np.where(plain, value, np.nan)
        rest = np.flatnonzero(~plain)
        if rest.size:
            strings = [self.text[a:b] for a, b in zip(start[rest], stop[rest])]
            # pandas reads a column of integers as integers ("-0" -> 0) and one with any decimal
            # as floats ("-0" -> -0.0): a decimal among the plain fields sets that context
            context = ["0.5"] if (plain & dotted).any() else []
            out[rest] = to_float(np.array(strings + context, dtype=object))[:rest.size]
        return out


def to_float(strings: np.ndarray) -> np.ndarray:
    """(N,) object array of str -> (N,) float as ``pd.to_numeric(errors="coerce")`` reads it."""
    return pd.to_numeric(strings, errors="coerce").astype(float)


def plain_decimals(buf: np.ndarray, start: np.ndarray, stop: np.ndarray):
    """Fields ``buf[start:stop]`` (N,) of the form ``[-]digits[.digits]`` (a sign only with a decimal
    point; 1 to :data:`EXACT_DIGITS` digits): (plain (N,) bool, value (N,) float, dotted (N,) bool).

    The digits as an integer (exact in a double) divided by an exact power of ten is one correctly
    rounded operation, as Python's and pandas' parsers round. The fields are right-aligned in a
    (W, N) matrix, one row per character position so that reductions run along contiguous rows: a
    digit's power of ten is its distance from the last row, less one left of the point.
    """
    length = np.maximum(stop - start, 0)
    width = int(min(length.max(initial=0), EXACT_DIGITS + 2))
    n = start.size
    if width == 0 or buf.size == 0:
        return np.zeros(n, bool), np.full(n, np.nan), np.zeros(n, bool)
    rows = np.arange(width)[:, None]
    pos = stop - width + rows
    outside = pos < start
    code = buf[np.clip(pos, 0, buf.size - 1)] - np.uint8(ord("0"))   # uint8: wraps below '0'
    code[outside] = _CODE[" "]
    digit, dot = code < 10, code == _CODE["."]
    n_dot, n_digits = np.count_nonzero(dot, axis=0), np.count_nonzero(digit, axis=0)
    neg = (length <= width) & (code[np.clip(width - length, 0, width - 1), np.arange(n)] == _CODE["-"])
    plain = ((length >= 1) & (length <= width) & (n_digits + n_dot + neg == length) & (n_dot <= 1)
             & (n_digits >= 1) & (n_digits <= EXACT_DIGITS) & ((n_dot == 1) | ~neg))
    dot_row = np.where(n_dot > 0, dot.argmax(0), -1)
    weight = np.where(rows < dot_row, _POW10[np.maximum(width - 2 - rows, 0)], _POW10[width - 1 - rows])
    mantissa = np.einsum("ij,ij->j", np.where(digit, code, np.uint8(0)), weight)
    value = mantissa / _POW10[np.where(n_dot > 0, width - 1 - dot_row, 0)]
    return plain, np.where(neg, -value, value), n_dot > 0
