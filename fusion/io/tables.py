"""CSV tables with one-line errors: read (plain or gzipped), convert to numbers, drop rows with
missing values (counted), check that times do not go backwards."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.trace import count_skip

def read_csv_table(path: Path, required: Sequence[str], what: str) -> pd.DataFrame:
    """Read a CSV (optionally gzipped), checking it exists, is not empty, has ``required``."""
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    try:
        df = pd.read_csv(path, low_memory=False)
    except pd.errors.EmptyDataError as exc:
        raise DataError(f"{path}: {what} file is empty") from exc
    except (pd.errors.ParserError, UnicodeDecodeError, OSError, EOFError) as exc:
        raise DataError(f"{path}: cannot parse {what} file ({type(exc).__name__}: {exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DataError(f"{path}: {what} file lacks column(s) {', '.join(missing)}")
    if df.empty:
        raise DataError(f"{path}: {what} file has a header but no data rows")
    return df


def to_numeric(df: pd.DataFrame, cols: Sequence[str], path: Path) -> None:
    """Convert ``cols`` to numbers in place; a non-numeric cell raises naming column and row."""
    for c in cols:
        s = df[c]
        if pd.api.types.is_numeric_dtype(s):
            continue
        v = pd.to_numeric(s, errors="coerce")
        bad = (v.isna() & s.notna()).to_numpy()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DataError(f"{path}: column {c!r}, data row {i + 1}: non-numeric value {s.iloc[i]!r}")
        df[c] = v


def drop_nan_rows(df: pd.DataFrame, cols: Sequence[str], path: Path, what: str,
                   skipped: dict[str, int], key: str) -> pd.DataFrame:
    bad = df[list(cols)].isna().any(axis=1).to_numpy()
    if bad.all():
        raise DataError(f"{path}: every {what} row has a missing value in {', '.join(cols)}")
    count_skip(skipped, key, bad.sum())
    return df[~bad]


def check_increasing(t: np.ndarray, row: np.ndarray, path: Path, what: str) -> None:
    """Times must never decrease down the file (rows of one epoch share a time).

    row: (N,) 1-based data row numbers in the file, for the message."""
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = int(back[0])
        raise DataError(f"{path}: {what} times are not increasing: data row {row[i + 1]} has time "
                        f"{t[i + 1]} after {t[i]} (data row {row[i]})")
