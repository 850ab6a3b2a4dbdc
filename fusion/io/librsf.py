"""libRSF text files (TU Chemnitz's robust sensor fusion library; the smartLoc data set's format):
one measurement per line, whitespace-separated, the first token naming its type.

The types and their field counts after the tag (``readme.txt`` of smartLoc):

- ``pseudorange3``: time [s], pseudorange [m], its variance [m^2], satellite ECEF x, y, z [m],
  satellite id, system (1 GPS, 2 SBAS, 4 GLONASS, 8 Galileo, 16 QZSS, 32 BeiDou), elevation [deg],
  C/N0 [dB-Hz] (10 numbers);
- ``odom3``: time, body velocity x, y, z [m/s], turn rate x, y, z [rad/s], the six variances (13);
- ``point3``: time, ECEF x, y, z [m], a 3x3 covariance in row-major order (13).

:func:`read_librsf` keeps what it can: a line with the wrong field count, a non-numeric or non-finite
value, or an unknown type is skipped and counted (``lines_<reason>:<type>``), and a warning names the
file and the first such line. Blank lines and ``#`` comments are ignored.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.io.clean import read_text
from fusion.trace import count_skip

#: numbers after the tag, per libRSF type
FIELDS: dict[str, int] = {"pseudorange3": 10, "odom3": 13, "point3": 13}


def read_librsf(path: str | Path, what: str, skipped: dict[str, int]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every known type in the file -> (values (N, FIELDS[type]) float64, line (N,) 1-based line numbers).

    Types absent from the file are absent from the result. Raises :class:`DataError` (via
    :func:`fusion.io.clean.read_text`) for a missing, empty, binary or corrupt-gzip file.
    """
    path = Path(path)
    text = read_text(path, what, skipped)
    lines = pd.Series(text.splitlines()).str.strip()
    number = np.arange(1, lines.size + 1)
    keep = (lines != "") & ~lines.str.startswith("#")
    lines, number = lines[keep], number[keep.to_numpy()]
    tag = lines.str.split(n=1).str[0]
    first_bad: list[tuple[int, str]] = []
    unknown = ~tag.isin(list(FIELDS)).to_numpy()
    if unknown.any():
        for name, n in tag[unknown].value_counts().items():
            count_skip(skipped, f"lines_unknown_type:{name[:20]}", n)
        first_bad.append((int(number[unknown][0]), f"unknown type {tag[unknown].iloc[0][:20]!r}"))
    out = {}
    for name, n_fields in FIELDS.items():
        sel = (tag == name).to_numpy()
        if sel.any():
            vals, ok, why = _numbers(lines[sel], n_fields)
            for reason, bad in why.items():
                count_skip(skipped, f"lines_{reason}:{name}", bad)
                if bad.any():
                    first_bad.append((int(number[sel][bad][0]), f"{name} line: {reason.replace('_', ' ')}"))
            out[name] = (vals[ok], number[sel][ok])
    if first_bad:
        line, why = min(first_bad)
        warnings.warn(f"{path}:{line}: {why}; skipped (and counted) with every other bad line", stacklevel=3)
    return out


def _numbers(lines: pd.Series, n_fields: int) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(N, n_fields) numbers after the tag of each line, (N,) bool lines usable, and the bad ones by
    reason (each line counted once: a wrong field count first, then non-numeric, then non-finite)."""
    parts = lines.str.split(expand=True)
    count = parts.notna().sum(axis=1).to_numpy() - 1
    wrong = count != n_fields
    cols = parts.reindex(columns=range(1, n_fields + 1))
    vals = cols.apply(pd.to_numeric, errors="coerce").to_numpy(np.float64)
    nonnumeric = ~wrong & np.isnan(vals).any(axis=1)
    nonfinite = ~wrong & ~nonnumeric & ~np.isfinite(vals).all(axis=1)
    why = {"wrong_field_count": wrong, "nonnumeric": nonnumeric, "nonfinite": nonfinite}
    return vals, ~(wrong | nonnumeric | nonfinite), why
