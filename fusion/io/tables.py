"""CSV tables with one-line errors: read (plain or gzipped) through the cleaning steps of
:mod:`fusion.io.clean`, and check the columns a reader needs."""
from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from fusion.errors import DataError
from fusion.io.clean import drop_exact_duplicates, drop_truncated_final_line, read_csv_text, read_text


def read_csv_table(path: Path, required: Sequence[str], what: str, skipped: dict[str, int] | None = None,
                   prefix: str = "") -> pd.DataFrame:
    """Read a CSV (optionally gzipped) keeping its good part.

    Refused (:class:`DataError`): missing / empty / binary / corrupt-gzip files, a missing
    ``required`` column, a header without data rows. Counted in ``skipped`` (keys start with
    ``prefix``): a truncated final line, a gzip stream cut short, exact duplicate rows.
    Returns every column as parsed plus ``_row`` (1-based data row in the file).
    """
    path = Path(path)
    skipped = {} if skipped is None else skipped
    local: dict[str, int] = {}
    text = read_text(path, what, local)
    header = text.lstrip("\ufeff").split("\n", 1)[0]
    n_fields = len(next(csv.reader([header]), []))
    text = drop_truncated_final_line(text, n_fields, path, local)
    df = read_csv_text(text, path, what)
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DataError(f"{path}: {what} file lacks column(s) {', '.join(missing)}")
    if df.empty:
        raise DataError(f"{path}: {what} file has a header but no data rows")
    df = drop_exact_duplicates(df, local)
    for k, v in local.items():
        skipped[prefix + k] = skipped.get(prefix + k, 0) + v
    return df
