"""RINEX 3.0x / 4.0x and 2.10-2.12 observation files (``.obs``, ``.YYo``, ``*_MO.rnx``; gzip and
Hatanaka-compressed ``.crx`` / ``.YYd`` too, told by content) -> :class:`RawObs`.

Every constellation is read; observation codes are mapped onto :data:`fusion.trace.SIGNALS`
(:data:`SIGNAL_CODES`), other signals are dropped and counted. Units: C metres, L cycles
(-> metres with the carrier wavelength), D Hz (-> pseudorange rate ``-wavelength * D``), S dB-Hz.
RINEX writes a missing observation as blank or 0.0; both read as NaN. LLI bit 0 (lost lock since
the previous observation) on a phase sets ``adr_slip``. Epoch flag 1 (power failure) sets
``clock_reset``; flags 2-5 (event / header records) and 6 (cycle-slip records) are skipped and
counted. RINEX 2 records are located by :mod:`fusion.io.rinex2_obs` and their two-character types
mapped to RINEX 3 codes; RINEX 4 observation records are RINEX 3.05's (its new header lines are
ignored); other versions are refused with a one-line error. Hatanaka (CRINEX)
files are expanded first (:mod:`fusion.io.text_open`, PyPI ``hatanaka``).

Speed: the body is read as one byte buffer and every observation field is gathered into a
column-major byte array (:mod:`fusion.io.fixed_width`), so numbers are parsed with array
arithmetic; the Pixel5 phone log (4 MB, 2000 epochs) reads in about 0.1-0.2 s
(``benchmarks/bench_rinex.py``).
"""
from __future__ import annotations

import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.io.fixed_width import (char_matrix, cut_inside_a_number, gather_fields, line_bounds, parse_decimal,
                                   parse_float, parse_float_columns, parse_int)
from fusion.io.rinex2_obs import satellite_fields, walk_records
from fusion.io.text_open import read_bytes
from fusion.io.nav_records import SLOT_CHANNEL
from fusion.io.raw import GLO_G1_STEP_HZ, GLO_K_UNKNOWN, SIGNAL_CARRIER_HZ, RawObs, empty_raw, finish_raw
from fusion.trace import count_skip

#: System letter -> [(signal, band digit, tracking attributes in priority order)].
#: Second frequencies: GPS / QZSS L2C (L, M or combined X tracking; P(Y) semi-codeless W is not
#: L2C and stays out), Galileo E5b, BeiDou B2I (band 7 in every RINEX 3 version). BeiDou-3's B1C
#: (band 1, pilot, data or both) and B2a (band 5) since RINEX 3.04.
SIGNAL_CODES: dict[str, list[tuple[str, str, str]]] = {
    "G": [("GPS_L1", "1", "C"), ("GPS_L5", "5", "QIX"), ("GPS_L2", "2", "LXS")],
    "R": [("GLO_G1", "1", "C")],
    "E": [("GAL_E1", "1", "CXB"), ("GAL_E5A", "5", "QXI"), ("GAL_E5B", "7", "QXI")],
    # RINEX 3.01 wrote BeiDou B1I as C1I; 3.02 on as C2I.
    "C": [("BDS_B1I", "2", "I"), ("BDS_B1I", "1", "I"), ("BDS_B2I", "7", "IXQ"),
          ("BDS_B1C", "1", "PXD"), ("BDS_B2A", "5", "PXD")],
    "J": [("QZS_J1", "1", "C"), ("QZS_J5", "5", "QXI"), ("QZS_J2", "2", "LXS")],
}
#: Codes read only from a RINEX version on: BeiDou's band 1 was B1I in 3.01 (C1X its I + Q) and B1C from 3.04,
#: so a C1X in between is another converter's B1 and not read as B1C (counted as another signal).
_CODE_SINCE = {("C", "1X"): 3.04}
#: RINEX satellite number -> Android svid offset (QZSS J01 is svid 193, SBAS S20 is 120).
_SVID_OFFSET = {"J": 192, "S": 100}
#: Time systems whose seconds are GPS seconds, and BeiDou time's offset from GPS [s].
_GPS_LIKE = {"GPS", "GAL", "QZS", ""}
_BDT_OFFSET_S = 14
_FIELD = 16  # F14.3 + LLI + SSI
_GPS_EPOCH_DAYS = 723_125  # 1980-01-06 in days since 0000-03-01 (proleptic Gregorian)


@dataclass
class ObsHeader:
    """What the body reader needs from a RINEX 3 observation header."""

    version: float = 0.0
    obs_types: dict[str, list[str]] = field(default_factory=dict)
    glo_k: dict[int, int] = field(default_factory=dict)
    approx_pos: np.ndarray | None = None
    time_system: str = ""
    n_lines: int = 0
    #: slot -> where its channel came from when not from the header ("navigation", "slot_table")
    glo_source: dict[int, str] = field(default_factory=dict)


def read_rinex_obs(path: str | Path, glonass_channels: dict[int, int] | None = None, *,
                   slot_table: bool = True) -> RawObs:
    """Read a RINEX 3.0x / 4.0x (or 2.10-2.12) observation file (plain, gzip or Hatanaka) into the raw contract.

    glonass_channels: slot -> frequency channel k, for slots the header's ``GLONASS SLOT / FRQ #``
    lacks (e.g. from navigation records); ``slot_table``: then the known channel of each slot
    (:data:`fusion.io.nav_records.SLOT_CHANNEL`). Rows so filled are counted
    (``glonass_rows_channel_from_navigation`` / ``_from_slot_table``); without k a GLONASS row
    keeps its pseudorange but not its Doppler and phase (counted in ``skipped``).

    Raises :class:`DataError` naming the file (and line) for an unreadable / corrupt file, an
    unsupported version, a malformed header or epoch line, or a file without epoch records.
    Satellite lines with unreadable numbers and a truncated final record are skipped, counted in
    ``skipped`` and reported with a warning naming the first offending line.
    """
    path = Path(path)
    skipped: dict[str, int] = {}
    text = _read_bytes(path, skipped)
    header = _parse_header(text, path)
    header.glo_source = {s: "slot_table" for s in (SLOT_CHANNEL if slot_table else {})}
    header.glo_source |= {s: "navigation" for s in (glonass_channels or {})}
    header.glo_source = {s: v for s, v in header.glo_source.items() if s not in header.glo_k}
    header.glo_k = {**(SLOT_CHANNEL if slot_table else {}), **(glonass_channels or {}), **header.glo_k}
    body = np.frombuffer(text, np.uint8)[_body_offset(text):]
    if header.version < 3:
        frame = _v2_frame(body, header, path, skipped)
    else:
        epochs, sat_lines = _epoch_records(body, header, path, skipped)
        frame = _observations(body, sat_lines, epochs, header, path, skipped)
    return RawObs(frame=frame, path=path, skipped=skipped, approx_pos=header.approx_pos)


def _read_bytes(path: Path, skipped: dict[str, int]) -> bytes:
    return read_bytes(path, "RINEX observation", skipped, crinex=True).replace(b"\r\n", b"\n")


def _body_offset(text: bytes) -> int:
    end = text.find(b"END OF HEADER")
    nl = text.find(b"\n", end)
    return len(text) if nl < 0 else nl + 1


def _parse_header(text: bytes, path: Path) -> ObsHeader:
    """Version, observation types per system, GLONASS channels, approximate position."""
    end = text.find(b"END OF HEADER")
    if end < 0:
        raise DataError(f"{path}: no 'END OF HEADER' line: not a RINEX observation file (or truncated header)")
    lines = text[:end].decode("ascii", errors="replace").split("\n")
    head = ObsHeader(n_lines=len(lines))
    first = lines[0]
    try:
        head.version = float(first[:9])
    except ValueError:
        raise DataError(f"{path}:1: cannot read the RINEX version from {first[:9]!r}") from None
    if first[20:21] != "O":
        raise DataError(f"{path}:1: file type {first[20:21]!r} is not 'O' (observation)")
    if not (3.0 <= head.version < 5.0 or 2.10 <= head.version < 2.2):
        raise DataError(f"{path}:1: RINEX version {head.version} observation files are not supported "
                        "(RINEX 4.0x, 3.0x and 2.10-2.12; convert others with gfzrnx or RTKLIB convbin)")
    system, types_v2 = "", []
    for no, line in enumerate(lines, start=1):
        label = line[60:].strip()
        if label == "# / TYPES OF OBSERV":
            types_v2 += line[6:60].split()
        elif label == "SYS / # / OBS TYPES":
            system = line[0] if line[0] != " " else system
            head.obs_types.setdefault(system, []).extend(line[7:60].split())
        elif label == "GLONASS SLOT / FRQ #":
            # Some writers (GnssToRinex) start the list one column early: search the whole field.
            for slot, k in re.findall(r"R\s?(\d{1,2})\s+(-?\d+)", line[:60]):
                head.glo_k[int(slot)] = int(k)
        elif label == "APPROX POSITION XYZ":
            head.approx_pos = _approx_pos(line, path, no)
        elif label == "TIME OF FIRST OBS":
            head.time_system = line[48:51].strip()
    if head.version < 3 and types_v2:
        head.obs_types = {s: [v2_type_as_v3(s, t) for t in types_v2] for s in "GRESJC"}
    if not head.obs_types:
        raise DataError(f"{path}: header has no 'SYS / # / OBS TYPES' (RINEX 2: '# / TYPES OF OBSERV') lines")
    return head


#: RINEX 2 two-character types -> the RINEX 3 tracking attribute our signal table expects, by
#: (system, band); anything else gets "?" and is dropped as another signal.
_V2_ATTR = {("G", "1"): "C", ("G", "5"): "X", ("R", "1"): "C", ("E", "1"): "X", ("E", "5"): "X",
            ("J", "1"): "C", ("J", "5"): "X", ("C", "2"): "I", ("G", "2"): "X", ("E", "7"): "X",
            ("C", "7"): "I", ("J", "2"): "X"}


def v2_type_as_v3(system: str, code: str) -> str:
    """RINEX 2 observation type (``C1``, ``L5``, ``P2``) -> a RINEX 3 code for ``system``
    (``C1C``, ``L5X``; P code -> ``C<band>P``, never one of our signals)."""
    if code[:1] == "P":
        return f"C{code[1:2]}P"
    return f"{code[:2]}{_V2_ATTR.get((system, code[1:2]), '?')}"


def _approx_pos(line: str, path: Path, no: int) -> np.ndarray | None:
    try:
        xyz = np.array([float(line[14 * i: 14 * (i + 1)]) for i in range(3)])
    except ValueError:
        raise DataError(f"{path}:{no}: cannot read APPROX POSITION XYZ from {line[:42]!r}") from None
    # Phones write zeros: no approximate position rather than the Earth's centre.
    return xyz if np.linalg.norm(xyz) > 1e5 else None


def _epoch_records(body: np.ndarray, head: ObsHeader, path: Path,
                   skipped: dict[str, int]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Find epoch lines, read their times and flags, and the satellite lines that belong to them.

    body: (B,) uint8.  Returns ``epochs`` (arrays over kept epochs: ``t_ns``, ``clock_reset``)
    and ``sat_lines``: (M, 3) int64 rows ``(start, end, epoch index)`` of observation lines.
    """
    starts, ends = line_bounds(body)
    is_epoch = body[starts] == ord(">") if starts.size else np.zeros(0, bool)
    e_line = np.flatnonzero(is_epoch)
    if e_line.size == 0:
        raise DataError(f"{path}: no epoch records after the header (header only?)")
    line_no = head.n_lines + 1 + e_line  # 1-based file line numbers of epoch lines
    t_ns, flag, n_sat = epoch_fields(char_matrix(body, starts[e_line], ends[e_line], 35), head, path, line_no)
    n_lines = np.diff(np.append(e_line, starts.size)) - 1
    _trim_trailing_blank(n_lines, starts, ends)
    if body[-1] != 10 and n_lines[-1] > 0 and cut_inside_a_number(int(ends[-1] - starts[-1]), 3):
        n_lines[-1] -= 1              # the record then counts as truncated
    event = (flag >= 2) & (flag <= 6)
    count_skip(skipped, "event_records", (flag >= 2) & (flag <= 5))
    count_skip(skipped, "cycle_slip_records", flag == 6)
    wrong = (n_lines != n_sat)
    truncated = wrong & (np.arange(e_line.size) == e_line.size - 1) & (n_lines < n_sat)
    if truncated.any():
        warnings.warn(f"{path}:{line_no[-1]}: last epoch record is truncated "
                      f"({n_lines[-1]} of {n_sat[-1]} satellite lines); skipped", stacklevel=3)
    count_skip(skipped, "records_truncated", truncated)
    bad = wrong & ~truncated & ~event
    if bad.any():
        i = np.flatnonzero(bad)[0]
        warnings.warn(f"{path}:{line_no[i]}: epoch record announces {n_sat[i]} satellites but "
                      f"{n_lines[i]} lines follow; {bad.sum()} such record(s) skipped", stacklevel=3)
    count_skip(skipped, "records_bad_satellite_count", bad)
    keep = ~(event | wrong)
    kept = np.flatnonzero(keep)
    kept = kept[_later_epochs(t_ns[kept], line_no[kept], path, skipped)]
    count_skip(skipped, "epochs_no_satellites", n_sat[kept] == 0)     # an epoch with nothing in it leaves no row
    epoch_of = np.repeat(np.arange(kept.size), n_sat[kept])
    first = np.repeat(e_line[kept] + 1, n_sat[kept])
    sat = first + (np.arange(first.size) - np.repeat(np.cumsum(n_sat[kept]) - n_sat[kept], n_sat[kept]))
    epochs = {"t_ns": t_ns[kept], "clock_reset": flag[kept] == 1, "epoch_of": epoch_of,
              "line_no": head.n_lines + 1 + sat}
    return epochs, np.column_stack([starts[sat], ends[sat], epoch_of])


def _later_epochs(t_ns: np.ndarray, line_no: np.ndarray, path: Path, skipped: dict[str, int]) -> np.ndarray:
    """(K,) bool: the epoch records (times (K,), file lines (K,)) later than every record before them. A record
    written twice, or a stretch written again after later ones, is skipped and counted, with a warning naming the
    first such line: the file's first word on an epoch stands."""
    later = t_ns > np.maximum.accumulate(np.r_[np.iinfo(np.int64).min, t_ns[:-1]])
    if not later.all():
        first = line_no[np.flatnonzero(~later)[0]]
        warnings.warn(f"{path}:{first}: epoch not later than one before it (written twice, or time going back); "
                      f"{int((~later).sum())} such record(s) skipped", stacklevel=3)
    count_skip(skipped, "epochs_not_later", ~later)
    return later


def _v2_frame(body: np.ndarray, head: ObsHeader, path: Path, skipped: dict[str, int]) -> pd.DataFrame:
    """A RINEX 2 body (B,) uint8 -> contract frame (record layout: :mod:`fusion.io.rinex2_obs`)."""
    n_types = len(head.obs_types["G"])
    first_no = head.n_lines + 1
    epoch_line, n_sat, flag, obs_start = walk_records(body, n_types, first_no, path, skipped)
    if epoch_line.size == 0:
        raise DataError(f"{path}: no epoch records after the header (header only?)")
    starts, ends = line_bounds(body)
    t_ns, _, _ = epoch_fields(char_matrix(body, starts[epoch_line], ends[epoch_line], 35), head, path,
                              first_no + epoch_line)
    later = _later_epochs(t_ns, first_no + epoch_line, path, skipped)
    t_ns, epoch_line, n_sat, flag, obs_start = (a[later] for a in (t_ns, epoch_line, n_sat, flag, obs_start))
    count_skip(skipped, "epochs_no_satellites", n_sat == 0)
    epoch_of, system, prn_chars, fields, first = satellite_fields(body, epoch_line, n_sat, obs_start, n_types)
    prn, prn_bad = sat_number(prn_chars)
    epochs = {"t_ns": t_ns, "clock_reset": flag == 1, "epoch_of": epoch_of, "line_no": first_no + first}
    parsed = _parse_values(fields.shape[1], n_types, lambda a, b: fields[:, a:b])
    return observation_frame(system, prn, prn_bad, parsed, epochs, head, path, skipped)


def _trim_trailing_blank(n_lines: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> None:
    """Blank lines after the last record are not satellite lines (in place on ``n_lines``)."""
    tail = 0
    while tail < n_lines[-1] and ends[-1 - tail] - starts[-1 - tail] <= 0:
        tail += 1
    n_lines[-1] -= tail


#: Epoch-line columns (RINEX 3: ``> yyyy mm dd hh mm ss.sssssss  f nnn``; RINEX 2: 2-digit year,
#: no ``>``), seconds last.
EPOCH_COLUMNS = {
    3: {"year": (2, 6), "month": (7, 9), "day": (10, 12), "hour": (13, 15), "minute": (16, 18),
        "flag": (29, 32), "n_sat": (32, 35), "sec": (18, 29)},
    2: {"year": (1, 3), "month": (4, 6), "day": (7, 9), "hour": (10, 12), "minute": (13, 15),
        "flag": (28, 29), "n_sat": (29, 32), "sec": (15, 26)},
}


def epoch_fields(m: np.ndarray, head: ObsHeader, path: Path,
                 line_no: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Epoch lines -> receive time [GPS ns], epoch flag and satellite count, each (K,).

    m: (K, 35) uint8 epoch lines.  line_no: (K,) their file line numbers (for errors).
    """
    cols = dict(EPOCH_COLUMNS[min(int(head.version), 3)])    # RINEX 4 epoch lines are RINEX 3's
    sec_cols = cols.pop("sec")
    v, bad = {}, np.zeros(m.shape[0], bool)
    for name, (a, b) in cols.items():
        v[name], b_ = parse_int(m[:, a:b])
        bad |= b_
    if head.version < 3:  # two-digit years: 80-99 -> 19xx
        v["year"] = v["year"] + np.where(v["year"] < 80, 2000, 1900)
    sec, sec_bad = parse_float(m[:, sec_cols[0]:sec_cols[1]])
    mant, dec, _, _ = parse_decimal(m[:, sec_cols[0]:sec_cols[1]])
    bad |= sec_bad | (dec > 9) | ~np.isfinite(sec) | (v["month"] < 1) | (v["month"] > 12) | (v["day"] < 1) \
        | (v["day"] > 31) | (v["hour"] > 23) | (v["minute"] > 59) | (sec >= 61)
    # Event records (flags 2-5) may leave the time blank; they are skipped anyway.
    bad &= (v["flag"] < 2) | (v["flag"] > 5)
    bad |= (v["flag"] > 6) | (v["n_sat"] < 0)
    if bad.any():
        i = np.flatnonzero(bad)[0]
        text = bytes(m[i]).decode("ascii", errors="replace").rstrip()
        raise DataError(f"{path}:{line_no[i]}: cannot read epoch line {text!r}")
    days = _days_from_civil(v["year"], v["month"], v["day"]) - _GPS_EPOCH_DAYS
    sec_ns = mant * 10 ** (9 - np.minimum(dec, 9))
    t_ns = ((days * 24 + v["hour"]) * 60 + v["minute"]) * 60 * 10**9 + sec_ns
    if head.time_system == "BDT":
        t_ns = t_ns + _BDT_OFFSET_S * 10**9
    elif head.time_system not in _GPS_LIKE:
        raise DataError(f"{path}: time system {head.time_system!r} is not supported (GPS, GAL, QZS, BDT)")
    return t_ns.astype(np.int64), v["flag"], v["n_sat"]


def _days_from_civil(y: np.ndarray, m: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Days since 0000-03-01 of Gregorian dates (H. Hinnant's algorithm), vectorised; (K,) int64."""
    y = np.asarray(y, np.int64) - (m <= 2)
    era = np.floor_divide(y, 400)
    yoe = y - era * 400
    mp = (m + 9) % 12
    doy = (153 * mp + 2) // 5 + d - 1
    doe = yoe * 365 + yoe // 4 - yoe // 100 + doy
    return era * 146097 + doe


def _observations(body: np.ndarray, sat_lines: np.ndarray, epochs: dict[str, np.ndarray],
                  head: ObsHeader, path: Path, skipped: dict[str, int]) -> pd.DataFrame:
    """Satellite lines -> contract frame, one block of rows per (system, signal).

    sat_lines: (M, 3) int64 ``(start, end, epoch index)``.
    """
    if sat_lines.shape[0] == 0:
        return empty_raw()
    n_obs = max(len(t) for t in head.obs_types.values())
    starts, ends = sat_lines[:, 0], sat_lines[:, 1]
    m = char_matrix(body, starts, ends, 3)
    prn, prn_bad = sat_number(m[:, 1:3])
    # F14.3 value, LLI, SSI of every observation, gathered column-major and parsed a block of lines at a time
    offsets = 3 + _FIELD * np.arange(n_obs)
    parsed = _parse_values(starts.size, n_obs,
                           lambda a, b: gather_fields(body, starts[a:b], ends[a:b], offsets, _FIELD))
    return observation_frame(m[:, 0], prn, prn_bad, parsed, epochs, head, path, skipped)


def observation_frame(system: np.ndarray, prn: np.ndarray, prn_bad: np.ndarray,
                      parsed: tuple[np.ndarray, np.ndarray, np.ndarray], epochs: dict[str, np.ndarray],
                      head: ObsHeader, path: Path, skipped: dict[str, int]) -> pd.DataFrame:
    """Satellite records -> contract frame, one block of rows per (system, signal).

    system: (M,) uint8 letters.  prn, prn_bad: (M,) satellite numbers and their parse failures.
    parsed: :func:`_parse_values` of the records' fields: (M, n_obs) values, (M,) bad, (M, n_obs) LLI.
    """
    values, bad, lli = parsed
    bad = bad | prn_bad
    values[values == 0.0] = np.nan
    if bad.any():
        line_no = epochs["line_no"][np.flatnonzero(bad)[0]]
        warnings.warn(f"{path}:{line_no}: unreadable number in satellite line; "
                      f"{bad.sum()} such line(s) skipped", stacklevel=3)
    count_skip(skipped, "sat_lines_bad_number", bad)
    ok = ~bad
    unknown_sys = ok & ~np.isin(system, [ord(s) for s in SIGNAL_CODES])
    # SBAS ranging is left out (its GEO clocks and corrections are not modelled): counted apart
    count_skip(skipped, "sat_lines_sbas_not_used", unknown_sys & (system == ord("S")))
    count_skip(skipped, "sat_lines_unsupported_system", unknown_sys & (system != ord("S")))
    # a system the header lists no observation types for cannot be decoded
    unlisted = ok & ~unknown_sys & ~np.isin(system, [ord(s) for s in head.obs_types])
    count_skip(skipped, "sat_lines_system_not_in_header", unlisted)
    blocks = []
    for sys_letter, types in head.obs_types.items():
        rows = np.flatnonzero(ok & (system == ord(sys_letter)))
        if sys_letter in SIGNAL_CODES and rows.size:
            blocks += _system_blocks(sys_letter, types, rows, values, lli, prn, epochs, head, skipped)
    if not blocks:
        return empty_raw()
    cols = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}
    del blocks          # their memory serves the frame's columns (fresh memory is slow to touch)
    return finish_raw(cols, skipped)


#: Satellite lines gathered and parsed at a time: each block's arrays (the fields, a dozen
#: (14, lines x types) temporaries) stay small and in cache instead of tens of MB of fresh memory,
#: which is slow to touch (a third of a cold read of the Pixel5 log went to page faults).
PARSE_BLOCK_LINES = 4096


def _parse_values(n_lines: int, n_obs: int, fields_of: Callable[[int, int], np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The F14.3 + LLI + SSI fields of ``n_lines`` satellite lines -> (M, n_obs) values (NaN blank or bad),
    (M,) bool lines with an unreadable number and (M, n_obs) uint8 LLI characters. ``fields_of(a, b)`` gives
    lines a..b-1 as (16, b - a, n_obs) uint8; asked :data:`PARSE_BLOCK_LINES` lines at a time."""
    values, bad, lli = np.empty((n_lines, n_obs)), np.empty(n_lines, bool), np.empty((n_lines, n_obs), np.uint8)
    for a in range(0, n_lines, PARSE_BLOCK_LINES):
        b = min(a + PARSE_BLOCK_LINES, n_lines)
        block = fields_of(a, b)
        v, bad_chars = parse_float_columns(block[:14].reshape(14, -1), dot_col=10)
        values[a:b] = v.reshape(-1, n_obs)
        bad[a:b] = bad_chars.reshape(-1, n_obs).any(axis=1)
        lli[a:b] = block[14]
    return values, bad, lli


def _system_blocks(sys_letter: str, types: list[str], rows: np.ndarray, values: np.ndarray,
                   lli: np.ndarray, prn: np.ndarray, epochs: dict[str, np.ndarray], head: ObsHeader,
                   skipped: dict[str, int]) -> list[dict[str, np.ndarray]]:
    """Contract columns for one system's satellite lines, one dict per mapped signal.

    rows: (R,) indices into values (M, n_obs) / lli (M, n_obs) uint8 / prn (M,).
    """
    index = {t: i for i, t in enumerate(types)}
    used: set[str] = set()
    done: set[str] = set()
    blocks = []
    for signal, band, attrs in SIGNAL_CODES[sys_letter]:
        attrs = "".join(a for a in attrs if head.version >= _CODE_SINCE.get((sys_letter, band + a), 0.0))
        attr = next((a for a in attrs if f"C{band}{a}" in index or f"L{band}{a}" in index), None)
        if attr is None or signal in done:
            continue
        done.add(signal)
        code = band + attr
        used |= {k + code for k in "CLDS"}
        col = {k: values[rows, index[k + code]] if k + code in index else np.full(rows.size, np.nan) for k in "CLDS"}
        slip = (lli[rows, index["L" + code]] - 48) & 1 == 1 if "L" + code in index else np.zeros(rows.size, bool)
        have = ~(np.isnan(col["C"]) & np.isnan(col["L"]) & np.isnan(col["D"]))
        r = rows[have]
        blocks.append(_signal_columns(sys_letter, signal, r, {k: v[have] for k, v in col.items()},
                                      slip[have], prn, epochs, head, skipped))
    other = [index[t] for t in types if t not in used and t[0] in "CLD"]
    if other:
        count_skip(skipped, "obs_other_signals", np.isfinite(values[np.ix_(rows, other)]).any(axis=1))
    return blocks


def _signal_columns(sys_letter: str, signal: str, rows: np.ndarray, col: dict[str, np.ndarray],
                    slip: np.ndarray, prn: np.ndarray, epochs: dict[str, np.ndarray], head: ObsHeader,
                    skipped: dict[str, int]) -> dict[str, np.ndarray]:
    """Contract columns of one signal. col: C/L/D/S -> (R,) float values; slip: (R,) bool."""
    n = rows.size
    svid = prn[rows] + _SVID_OFFSET.get(sys_letter, 0)
    if sys_letter == "R":
        slots, inverse = np.unique(svid, return_inverse=True)
        glo_k = np.array([head.glo_k.get(int(s), GLO_K_UNKNOWN) for s in slots], np.int64)[inverse.ravel()]
        for origin in ("navigation", "slot_table"):
            filled = np.array([head.glo_source.get(int(s)) == origin for s in slots] + [False])[inverse.ravel()]
            count_skip(skipped, f"glonass_rows_channel_from_{origin}", filled)
    else:
        glo_k = np.zeros(n, np.int64)
    sig = np.full(n, signal, dtype=object)
    freq = (1602.0e6 + glo_k * GLO_G1_STEP_HZ) if signal == "GLO_G1" else np.full(n, SIGNAL_CARRIER_HZ[signal])
    freq = np.where(glo_k == GLO_K_UNKNOWN, np.nan, freq)
    wavelength = 299_792_458.0 / freq
    # Without the channel, cycles and Hz cannot become metres: Doppler and phase are dropped.
    count_skip(skipped, "glonass_no_channel_doppler_phase", np.isnan(wavelength) & ~(np.isnan(col["L"]) & np.isnan(col["D"])))
    adr = col["L"] * wavelength
    nan = np.full(n, np.nan)
    return {
        "t_ns": epochs["t_ns"][epochs["epoch_of"][rows]], "const": np.full(n, sys_letter, dtype=object),
        "svid": svid, "signal": sig, "pr_m": col["C"], "pr_sigma_m": nan,
        "prr_mps": -col["D"] * wavelength, "prr_sigma_mps": nan, "adr_m": adr, "adr_sigma_m": nan,
        "adr_ok": np.isfinite(adr), "adr_slip": slip & np.isfinite(adr), "cn0": col["S"], "glo_k": glo_k,
        "clock_reset": epochs["clock_reset"][epochs["epoch_of"][rows]], "carrier_hz": freq,
    }


def sat_number(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two-column satellite numbers ('05', ' 5') -> (M,) int64 and (M,) bad mask. m: (M, 2) uint8."""
    tens, ones = m[:, 0] - np.uint8(48), m[:, 1] - np.uint8(48)
    blank_tens = m[:, 0] == 32
    bad = ~((tens < 10) | blank_tens) | ~(ones < 10)
    return np.where(blank_tens, 0, tens).astype(np.int64) * 10 + ones, bad
