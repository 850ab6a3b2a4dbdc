"""Minimal SP3-c/d precise-orbit reader (positions and clocks), for checks and precise states.

SP3 positions are ECEF in km at the satellite centre of mass; epochs are in the file's time
system (GPS for the IGS/CODE products we use). Bad or missing values become NaN.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.errors import DataError
from fusion.gpstime import gps_ms_from_calendar
from fusion.io.text_open import read_lines


@dataclass
class Sp3Orbits:
    """t_ms: (T,) GPS ms; sats: (N,) ids like ``"G01"``; pos: (T, N, 3) ECEF [m], NaN if missing;
    clock: (T, N) satellite clock offset [s], NaN if missing (None from older callers)."""

    t_ms: np.ndarray
    sats: np.ndarray
    pos: np.ndarray
    source: str
    clock: np.ndarray | None = None


def read_sp3(path: str | Path) -> Sp3Orbits:
    """Read epoch (``*``) and position (``P``) records of an SP3 file (plain or gzipped). A position record cut
    short is skipped, and an epoch written again (two files joined: each day ends with the next one's first
    epoch) keeps its first block; both with a warning."""
    path = Path(path)
    lines = read_lines(path, "SP3")
    if not lines or not lines[0].startswith("#"):
        raise DataError(f"{path}:1: not an SP3 file")
    for ln in lines:
        if ln.startswith("%c") and ln[9:12].strip() not in ("GPS", "ccc", ""):
            raise DataError(f"{path}: time system {ln[9:12]!r} is not GPS")
        if ln.startswith("%c"):
            break
    times: list[int] = []
    short: list[int] = []
    recs: dict[tuple[int, str], tuple[float, float, float]] = {}
    clks: dict[tuple[int, str], float] = {}
    for no, ln in enumerate(lines, 1):
        if ln.startswith("* "):
            f = ln[1:].split()
            try:
                times.append(gps_ms_from_calendar(int(f[0]), int(f[1]), int(f[2]), int(f[3]),
                                                  int(f[4]), float(f[5])))
            except (ValueError, IndexError):
                raise DataError(f"{path}:{no}: cannot read epoch line {ln!r}") from None
        elif ln.startswith("P") and times:
            if len(ln.rstrip("\r\n")) < 46:           # cut inside its coordinates: z would read a few digits
                short.append(no)
                continue
            try:
                xyz = tuple(float(ln[4 + 14 * k: 18 + 14 * k]) for k in range(3))
            except ValueError:
                raise DataError(f"{path}:{no}: cannot read position record {ln[:46]!r}") from None
            recs[(len(times) - 1, ln[1:4].replace(" ", "0"))] = xyz
            try:
                clks[(len(times) - 1, ln[1:4].replace(" ", "0"))] = float(ln[46:60])
            except ValueError:  # a blank clock field is "no clock", not an error
                pass
    if not times:
        raise DataError(f"{path}: no epochs in SP3 file")
    sats = np.array(sorted({s for _, s in recs}))
    col = {s: k for k, s in enumerate(sats)}
    pos = np.full((len(times), len(sats), 3), np.nan)
    for (ti, s), xyz in recs.items():
        pos[ti, col[s]] = xyz
    # 0.000000 or 999999.999999 mark a missing position.
    bad = np.all(pos == 0.0, axis=-1) | np.any(np.abs(pos) > 999_999.0, axis=-1)
    pos[bad] = np.nan
    clock = np.full((len(times), len(sats)), np.nan)
    for (ti, sat), c in clks.items():
        clock[ti, col[sat]] = c
    # 999999.999999 (or more) marks a missing clock; values are microseconds.
    clock[~(np.abs(clock) < 999_999.0)] = np.nan
    if short:
        warnings.warn(f"{path}:{short[0]}: position record cut short; {len(short)} such record(s) skipped",
                      stacklevel=2)
    t = np.asarray(times, np.int64)
    first = _first_of_each_epoch(t, path)
    return Sp3Orbits(t[first], sats, pos[first] * 1000.0, str(path), clock[first] * 1e-6)


def _first_of_each_epoch(t: np.ndarray, path: Path) -> np.ndarray:
    """(T',) indices of the epochs (times (T,)) in time order, each time's first block only."""
    order = np.argsort(t, kind="stable")
    first = order[np.r_[True, np.diff(t[order]) > 0]]
    if first.size < t.size:
        warnings.warn(f"{path}: {t.size - first.size} epoch(s) written again (joined files?); the first block of "
                      f"each kept", stacklevel=3)
    return first
