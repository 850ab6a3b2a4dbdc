"""GPS broadcast ephemerides from RINEX 2 and 3 navigation files.

Only GPS (``G``) records are kept; other systems in a RINEX 3 mixed file are skipped by their
known record lengths. The result is a struct-of-arrays :class:`GpsNav` (one entry per record,
``N`` records) so that :mod:`fusion.nav.orbits` can evaluate many (epoch, satellite) pairs at once.

Times: ``toc_ms`` / ``toe_ms`` are absolute GPS milliseconds since the GPS epoch (1980-01-06).
The RINEX GPS week is resolved against the clock epoch ``toc`` rather than trusted, because
some writers store it modulo 1024.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fusion.errors import DataError
from fusion.gpstime import WEEK_S, gps_ms_from_calendar
from fusion.nav.orbits import GpsNav
from fusion.trace import count_skip
#: Fit interval used when a record leaves it blank or zero (IS-GPS-200: 4 hours).
DEFAULT_FIT_H = 4.0

#: Lines per record (first line included) in RINEX 3 navigation files, by system letter.
_R3_RECORD_LINES = {"G": 8, "E": 8, "C": 8, "J": 8, "I": 8, "R": 4, "S": 4}

#: Broadcast-orbit fields in file order (lines 1-7 of a GPS record, 4 per line).
_ORBIT_FIELDS = (
    "iode", "crs", "delta_n", "m0",
    "cuc", "e", "cus", "sqrt_a",
    "toe_sow", "cic", "omega0", "cis",
    "i0", "crc", "omega", "omega_dot",
    "idot", "l2_codes", "week", "l2p_flag",
    "accuracy", "health", "tgd", "iodc",
    "t_transmit", "fit_h",
)
_KEEP = ("af0", "af1", "af2") + tuple(f for f in _ORBIT_FIELDS if f not in ("l2_codes", "l2p_flag"))


def _num(text: str, path: Path, line_no: int) -> float:
    text = text.strip()
    if not text:
        return 0.0
    try:
        return float(text.replace("D", "E").replace("d", "e"))
    except ValueError:
        raise DataError(f"{path}:{line_no}: cannot read number {text!r}") from None


def _fields(line: str, start: int, count: int, path: Path, line_no: int) -> list[float]:
    """``count`` 19-character numeric fields starting at column ``start`` (blank -> 0)."""
    line = line.rstrip("\n").ljust(start + 19 * count)
    return [_num(line[start + 19 * k: start + 19 * (k + 1)], path, line_no) for k in range(count)]


def read_rinex_nav(path: str | Path) -> GpsNav:
    """Parse a RINEX 2.x GPS or 3.x (GPS / mixed) navigation file.

    Raises :class:`DataError` (naming the file and line) for unreadable files, unsupported
    versions, truncated records, or a file without a single healthy GPS record.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: navigation file not found")
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise DataError(f"{path}: cannot read navigation file ({exc})") from None
    if not lines or "RINEX VERSION" not in lines[0]:
        raise DataError(f"{path}:1: not a RINEX file (no 'RINEX VERSION / TYPE' header line)")
    try:
        version = float(lines[0][:9])
    except ValueError:
        raise DataError(f"{path}:1: cannot read RINEX version {lines[0][:9]!r}") from None
    file_type = lines[0][20:21].upper()
    system = lines[0][40:41].upper() if version >= 3 else "G"
    if file_type != "N":
        raise DataError(f"{path}: RINEX type {file_type!r} is not GPS navigation data (need 'N'); "
                        "no GPS records")
    if version >= 4 or version < 2:
        raise DataError(f"{path}: RINEX navigation version {version} is not supported (2.x or 3.x)")
    try:
        body = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    except StopIteration:
        raise DataError(f"{path}: no 'END OF HEADER' line") from None

    rows: list[list[float]] = []
    prns: list[int] = []
    tocs: list[int] = []
    i = body
    n = len(lines)
    skipped_other = 0
    while i < n:
        head = lines[i]
        if not head.strip():
            i += 1
            continue
        if version >= 3:
            sys_letter = head[0].upper()
            if sys_letter not in _R3_RECORD_LINES:
                raise DataError(f"{path}:{i + 1}: unknown satellite system {head[0]!r} in record")
            n_lines = _R3_RECORD_LINES[sys_letter]
            if sys_letter != "G":
                skipped_other += 1
                i += n_lines
                continue
            prn_txt, date_txt, clk_col, cont = head[1:3], head[4:23].split(), 23, 4
        else:
            n_lines = 8
            prn_txt, date_txt, clk_col, cont = head[0:2], head[3:22].split(), 22, 3
        if i + n_lines > n:
            raise DataError(f"{path}:{i + 1}: truncated ephemeris record "
                            f"({n - i} of {n_lines} lines present)")
        try:
            prn = int(prn_txt)
            y, mo, d, hh, mi = (int(v) for v in date_txt[:5])
            sec = float(date_txt[5])
        except (ValueError, IndexError):
            raise DataError(f"{path}:{i + 1}: cannot read PRN / epoch from {head[:23]!r}") from None
        if version < 3:
            y += 2000 if y < 80 else 1900
        try:
            toc = gps_ms_from_calendar(y, mo, d, hh, mi, sec)
        except ValueError as exc:
            raise DataError(f"{path}:{i + 1}: invalid epoch ({exc})") from None
        vals = _fields(head, clk_col, 3, path, i + 1)
        for k in range(1, 8):
            vals += _fields(lines[i + k], cont, 4, path, i + k + 1)
        rows.append(vals)
        prns.append(prn)
        tocs.append(toc)
        i += n_lines

    if not rows:
        raise DataError(f"{path}: no GPS records in navigation file (system {system!r})")
    names = ("af0", "af1", "af2") + _ORBIT_FIELDS
    table = np.asarray(rows, float)
    params = {name: table[:, k] for k, name in enumerate(names) if name in _KEEP}
    prn = np.asarray(prns, int)
    toc_ms = np.asarray(tocs, np.int64)
    params["fit_h"] = np.where(params["fit_h"] > 0, params["fit_h"], DEFAULT_FIT_H)

    # Resolve the week from toc: the toe lies within half a week of the clock epoch.
    toe_sow = params["toe_sow"]
    week = np.round((toc_ms / 1000.0 - toe_sow) / WEEK_S)
    toe_ms = (week * WEEK_S * 1000).astype(np.int64) + np.round(toe_sow * 1000).astype(np.int64)

    skipped: dict[str, int] = {}
    count_skip(skipped, "non_gps_records", skipped_other)
    keep = params["health"] == 0
    bad_prn = (prn < 1) | (prn > 32)
    keep &= ~bad_prn
    count_skip(skipped, "unhealthy_or_bad_prn", ~keep)
    # Duplicates (same PRN and toe, re-broadcast) carry the same orbit: keep the first.
    key = prn.astype(np.int64) * 10**13 + toe_ms
    order = np.lexsort((np.arange(len(prn)), key))
    first = np.zeros(len(prn), bool)
    k_sorted = key[order]
    first[order[np.r_[True, k_sorted[1:] != k_sorted[:-1]]]] = True
    count_skip(skipped, "duplicate_records", ~first & keep)
    keep &= first
    if not keep.any():
        raise DataError(f"{path}: no healthy GPS records in navigation file")
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((toe_ms[sel], prn[sel]))]
    return GpsNav(
        prn=prn[sel], toc_ms=toc_ms[sel], toe_ms=toe_ms[sel],
        params={k: v[sel] for k, v in params.items()}, source=str(path), skipped=skipped,
    )


def default_nav_path() -> Path:
    """The GPS broadcast navigation file shipped with gnssfuse (IGS hourly merge, 2021 day 118)."""
    return Path(__file__).resolve().parents[1] / "data" / "hour1180.21n"
