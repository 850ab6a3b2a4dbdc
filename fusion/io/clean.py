"""Keep the good part of an imperfect measurement file: the generic cleaning steps every reader shares.

A reader calls, in this order (see :func:`fusion.io.tables.read_csv_table` for the CSV case):

1. :func:`read_text` - the file's text, plain or gzipped. A gzip stream cut short keeps what was
   decompressed (counted ``truncated_gzip``, with a warning); a corrupt gzip, binary garbage or an
   empty file is refused with one line naming the file.
2. :func:`drop_truncated_final_line` - a final line without its newline *and* with fewer fields than
   the header is a write that was cut off: skipped, counted ``truncated_final_line``, warned about.
   (A cut inside the last field of a line cannot be told from a short number, and is kept.)
3. :func:`drop_exact_duplicates` - rows identical in every column: the first is kept, the rest counted.
4. :func:`coerce_numeric` - required columns to numbers; a row with an empty, unparseable or
   non-finite value is dropped and counted once, under ``rows_<missing|nonnumeric|nonfinite>:<column>``
   for the first bad column in the order given.
5. :func:`sort_rows` - rows in time (and satellite) order; out-of-order files are re-ordered, not refused.

Counts go into the ``skipped`` dict the reader hands on to ``Trace.skipped`` (report, metrics.json).
Only when nothing usable is left does a reader refuse the file (:func:`require_rows`).
"""
from __future__ import annotations

import csv
import io
import logging
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.io.text_open import read_bytes
from fusion.trace import count_skip

log = logging.getLogger(__name__)

#: Column holding each row's 1-based data-row number in the file (for messages).
ROW = "_row"


def read_text(path: str | Path, what: str, skipped: dict[str, int]) -> str:
    """The text of ``path`` (plain or gzipped: :func:`fusion.io.text_open.read_bytes`).

    Raises :class:`DataError` when the file is missing, empty, not gzip-decodable or not text.
    """
    path = Path(path)
    raw = read_bytes(path, what, skipped)
    if not raw.strip():
        raise DataError(f"{path}: {what} file is empty")
    nul = raw.find(b"\x00")
    if nul >= 0:
        raise DataError(f"{path}: {what} file is not text (binary data at byte {nul})")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: {what} file is not text (binary data at byte {exc.start})") from exc


def drop_truncated_final_line(text: str, n_fields: int, path: Path, skipped: dict[str, int],
                              key: str = "truncated_final_line") -> str:
    """``text`` without a final line that was cut off (no newline and < ``n_fields`` fields)."""
    if text.endswith(("\n", "\r")):
        return text
    cut = text.rfind("\n") + 1
    last = text[cut:]
    fields = next(csv.reader([last]), [])
    if cut == 0 or len(fields) >= n_fields:
        return text
    count_skip(skipped, key, 1)
    warnings.warn(f"{path}: final line is truncated ({len(fields)} of {n_fields} fields); skipped",
                  stacklevel=3)
    return text[:cut]


def drop_exact_duplicates(df: pd.DataFrame, skipped: dict[str, int], key: str = "duplicate_rows") -> pd.DataFrame:
    """Rows equal in every column but :data:`ROW` removed (first kept), counted under ``key``."""
    cols = [c for c in df.columns if c != ROW]
    dup = df.duplicated(cols).to_numpy()
    count_skip(skipped, key, dup)
    return df[~dup] if dup.any() else df


def coerce_numeric(df: pd.DataFrame, cols: Sequence[str], skipped: dict[str, int], prefix: str = "",
                   required: bool = True) -> pd.DataFrame:
    """``cols`` converted to float; with ``required``, rows with a bad value are dropped and counted.

    Each dropped row is counted once, as ``{prefix}rows_{missing|nonnumeric|nonfinite}:{column}``
    for the first of ``cols`` (in order) where it is bad. Without ``required`` bad cells become NaN.
    """
    df = df.copy()
    bad_any = np.zeros(len(df), bool)
    for c in cols:
        s = df[c]
        v = pd.to_numeric(s, errors="coerce").astype(float)
        vals = v.to_numpy()
        missing = s.isna().to_numpy()
        nonnum = np.isnan(vals) & ~missing
        nonfinite = np.isinf(vals)
        df[c] = vals
        if not required:
            df.loc[nonfinite, c] = np.nan
            continue
        for kind, sel in (("missing", missing), ("nonnumeric", nonnum), ("nonfinite", nonfinite)):
            count_skip(skipped, f"{prefix}rows_{kind}:{c}", sel & ~bad_any)
            bad_any |= sel
    return df[~bad_any] if bad_any.any() else df


def sort_rows(df: pd.DataFrame, keys: Sequence[str], path: Path) -> pd.DataFrame:
    """Rows ordered by ``keys`` (stable: rows with equal keys keep their file order)."""
    t = df[keys[0]].to_numpy()
    if t.size > 1 and np.any(np.diff(t) < 0):
        log.info("%s: rows are not in time order; re-ordered", path)
    return df.sort_values(list(keys), kind="stable")


def require_rows(df: pd.DataFrame, path: Path, what: str, skipped: dict[str, int]) -> None:
    """Refuse the file when cleaning left no row, naming the commonest reason."""
    if len(df):
        return
    worst = max(skipped.items(), key=lambda kv: kv[1], default=None)
    why = f" (most rows dropped for {worst[0]}: {worst[1]})" if worst else ""
    raise DataError(f"{path}: no usable {what} row is left after cleaning{why}")


def epochs_with_enough_rows(t: np.ndarray, min_rows: int, skipped: dict[str, int], path: Path,
                           what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows grouped into epochs by their time ``t`` (N,); epochs with fewer than ``min_rows`` rows are
    dropped and counted, and a file with none left is refused (``what`` names the rows counted).

    Returns (keep (N,) bool per row, epoch (K,) index of each kept row into the kept epochs,
    kept epoch times (E,)).
    """
    t_unique, epoch, counts = np.unique(t, return_inverse=True, return_counts=True)
    keep_epoch = counts >= min_rows
    count_skip(skipped, f"epochs_lt{min_rows}_sats", (~keep_epoch).sum())
    if not keep_epoch.any():
        raise DataError(f"{path}: no epoch has >= {min_rows} {what}; largest has {int(counts.max(initial=0))}")
    keep = keep_epoch[epoch]
    return keep, (np.cumsum(keep_epoch) - 1)[epoch[keep]], t_unique[keep_epoch]


def read_csv_text(text: str, path: Path, what: str) -> pd.DataFrame:
    """Parse cleaned CSV text (every column as read; numbers converted later by :func:`coerce_numeric`)."""
    try:
        df = pd.read_csv(io.StringIO(text), low_memory=False)
    except pd.errors.EmptyDataError as exc:
        raise DataError(f"{path}: {what} file is empty") from exc
    except (pd.errors.ParserError, ValueError) as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{path}: cannot parse {what} file ({msg})") from exc
    df.columns = [str(c).strip().lstrip("\ufeff") for c in df.columns]
    return df.assign(**{ROW: np.arange(1, len(df) + 1)})
