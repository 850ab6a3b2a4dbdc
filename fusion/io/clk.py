"""RINEX clock files (``*.clk``, ``*_CLK.CLK``, gzip too): satellite clock biases (``AS`` records).

Receiver (``AR``) and other records are ignored. Epochs must be in GPS time (the IGS / MGEX
products are). Satellites are named as in SP3 (``"G01"``, ``"E11"``, ``"C20"``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.errors import DataError
from fusion.gpstime import gps_ms_from_calendar
from fusion.io.text_open import read_lines


@dataclass
class PreciseClocks:
    """t_ms: (T,) GPS ms; sats: (N,) names; bias: (T, N) satellite clock offset [s], NaN if missing."""

    t_ms: np.ndarray
    sats: np.ndarray
    bias: np.ndarray
    source: str


def _lines(path: Path) -> list[str]:
    return read_lines(path, "clock")


def read_clk(path: str | Path) -> PreciseClocks:
    """Satellite clock biases of a RINEX 2/3 clock file. Raises :class:`DataError` naming the
    file and line for a file that is not a clock file, a non-GPS time system or a bad record."""
    path = Path(path)
    lines = _lines(path)
    if not lines or "RINEX VERSION" not in lines[0] or "C" not in lines[0][19:23]:
        raise DataError(f"{path}:1: not a RINEX clock file (no 'C' in RINEX VERSION / TYPE)")
    body = next((i + 1 for i, ln in enumerate(lines) if "END OF HEADER" in ln), None)
    if body is None:
        raise DataError(f"{path}: no 'END OF HEADER' line")
    for ln in lines[:body]:
        if "TIME SYSTEM ID" in ln and ln[:10].strip() not in ("GPS", ""):
            raise DataError(f"{path}: clock time system {ln[:10].strip()!r} is not GPS")
    epochs: dict[str, int] = {}
    recs: list[tuple[int, str, float]] = []
    for no in range(body, len(lines)):
        ln = lines[no]
        if not ln.startswith("AS "):
            continue
        f = ln.split()
        try:
            key = " ".join(f[2:8])
            if key not in epochs:
                epochs[key] = gps_ms_from_calendar(int(f[2]), int(f[3]), int(f[4]), int(f[5]), int(f[6]), float(f[7]))
            recs.append((epochs[key], f[1], float(f[9].replace("D", "E"))))
        except (ValueError, IndexError):
            raise DataError(f"{path}:{no + 1}: cannot read satellite clock record {ln[:60]!r}") from None
    if not recs:
        raise DataError(f"{path}: no satellite clock (AS) records")
    t = np.array([r[0] for r in recs], np.int64)
    names = np.array([r[1] for r in recs])
    t_u, ti = np.unique(t, return_inverse=True)
    s_u, si = np.unique(names, return_inverse=True)
    bias = np.full((t_u.size, s_u.size), np.nan)
    bias[ti, si] = [r[2] for r in recs]
    return PreciseClocks(t_u, s_u, bias, str(path))
