"""Broadcast navigation files: RINEX 4 (the IGS merged ``BRD400DLR_S_*_MN.rnx``), RINEX 3 mixed /
single-system (``*_MN.rnx``, ``*_GN.rnx``, a BeiDou ``.21f``, ...), RINEX 2 GPS (``.n``) and GLONASS
(``.g``), gzip too (files are found by their header, :mod:`fusion.io.discover`).

RINEX 4 wraps each record in a frame (``> EPH G01 LNAV``, ``> ION G01 LNAV``, ``> STO ...``, ``> EOP ...``)
whose ephemeris body is RINEX 3's; the Klobuchar coefficients move from the header into GPS ``ION`` frames.
The messages modelled here are those RINEX 3 carries (GPS / QZSS LNAV, Galileo I/NAV and F/NAV, BeiDou D1 /
D2, GLONASS FDMA); the modernised ones (CNAV, CNV1-3) and SBAS / NavIC are skipped and counted.

:func:`read_nav` keeps every system we model: Keplerian records of GPS, QZSS, Galileo and BeiDou
in one :class:`~fusion.io.nav_records.GpsNav` (keyed by ``sat_id``), GLONASS state vectors in a
:class:`~fusion.io.nav_records.GloNav`, plus the header's GPS Klobuchar coefficients and leap
seconds. SBAS and IRNSS records are skipped and counted. :func:`read_rinex_nav` is the GPS-only
view the simulator uses.

Times: every ``*_ms`` is absolute GPS milliseconds since 1980-01-06. BeiDou epochs (BDT) are
moved by +14 s, GLONASS epochs (UTC) by the leap seconds. The week of ``toe`` is resolved against
the clock epoch ``toc`` rather than trusted, because some writers store it modulo 1024.
Galileo I/NAV and F/NAV records are both kept (``GpsNav.msg``, from the data-source field): their
clocks serve different signal pairs. Group delays are kept per signal class
(:func:`group_delays`): ``tgd`` (L1 class: GPS/QZSS TGD, Galileo E1, BeiDou TGD1), ``tgd_l5``
(L5 / E5a) and ``tgd_l2`` (GPS/QZSS L2, Galileo E5b, BeiDou TGD2 for B2I).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.errors import DataError
from fusion.gpstime import WEEK_S, gps_ms_from_calendar, leap_seconds_at_unix_ms, GPS_EPOCH_UNIX_MS
from fusion.io.nav_records import GLONASS_VALID_MS as GLO_VALID_MS, GloNav, GpsNav
from fusion.io.text_open import read_lines
from fusion.trace import count_skip

#: Fit interval [h] by system when a record leaves it blank (GPS: IS-GPS-200, 4 h); Galileo and
#: BeiDou carry none: RTKLIB's limits (4 h, 6 h either side of toe) are used.
DEFAULT_FIT_H = {"G": 4.0, "J": 4.0, "E": 8.0, "C": 12.0}
#: Lines per record (first line included) in RINEX 3 navigation files, by system letter.
_R3_RECORD_LINES = {"G": 8, "E": 8, "C": 8, "J": 8, "I": 8, "R": 4, "S": 4}
#: RINEX 4 ephemeris messages whose body is the RINEX 3 record above, by system letter.
_V4_MESSAGES = {"G": ("LNAV",), "J": ("LNAV",), "E": ("INAV", "FNAV"), "C": ("D1", "D2"), "R": ("FDMA",)}
_KEPLER = ("G", "J", "E", "C")
#: Android constellation type and svid offset per RINEX system letter.
_CTYPE = {"G": 1, "R": 3, "J": 4, "C": 5, "E": 6}
_SVID_OFFSET = {"J": 192}
#: (f_L1 / f_L5)^2, the L5 / E5a group-delay scale; (f_L1 / f_L2)^2 for GPS / QZSS L2 and
#: (f_E1 / f_E5b)^2 for Galileo E5b.
GAMMA_L5 = (1575.42 / 1176.45) ** 2
GAMMA_L2 = (1575.42 / 1227.60) ** 2
GAMMA_E5B = (1575.42 / 1207.14) ** 2

#: Broadcast-orbit fields in file order (lines 1-7 of a Keplerian record, 4 per line); Galileo
#: and BeiDou put their group delays in the ``tgd`` / ``iodc`` slots.
_ORBIT_FIELDS = (
    "iode", "crs", "delta_n", "m0",
    "cuc", "e", "cus", "sqrt_a",
    "toe_sow", "cic", "omega0", "cis",
    "i0", "crc", "omega", "omega_dot",
    "idot", "l2_codes", "week", "l2p_flag",
    "accuracy", "health", "tgd", "iodc",
    "t_transmit", "fit_h",
)
_NAMES = ("af0", "af1", "af2") + _ORBIT_FIELDS
_KEEP = tuple(f for f in _NAMES if f not in ("l2_codes", "l2p_flag"))
#: GLONASS record fields in file order.
_GLO_FIELDS = ("tau", "gamma", "tk", "x", "vx", "ax", "health", "y", "vy", "ay", "k", "z", "vz", "az", "age")


@dataclass
class Navigation:
    """Everything read from one or more navigation files.

    kepler:  GPS / QZSS / Galileo / BeiDou records (may be empty).
    glonass: GLONASS records (may be empty).
    klobuchar: (8,) GPS alpha0..3, beta0..3 from a header, or None.
    leap_s:  GPS - UTC [s] from a header, or None.
    """

    kepler: GpsNav
    glonass: GloNav
    klobuchar: np.ndarray | None = None
    leap_s: int | None = None
    sources: list[str] = field(default_factory=list)
    skipped: dict[str, int] = field(default_factory=dict)
    #: file -> constellation letters it has records of (what each file covers, for the user)
    file_systems: dict[str, set[str]] = field(default_factory=dict)
    #: file -> (first, last) record reference time [ms, its systems' own times: to the minute] (which day a
    #: file is of, when several were given)
    file_spans: dict[str, tuple[int, int]] = field(default_factory=dict)

    def records_text(self, path: str) -> str | None:
        """"records <first> to <last>" of a navigation file (to the minute; None: it has none)."""
        from fusion.gpstime import format_gps_ms

        span = self.file_spans.get(path)
        return None if span is None else f"records {format_gps_ms(span[0])[:16]} to {format_gps_ms(span[1])[:16]}"

    def systems(self) -> set[str]:
        """Constellation letters with at least one record."""
        inv = {v: k for k, v in _CTYPE.items()}
        out = {inv[int(c)] for c in np.unique(self.kepler.sat_id // 1000)}
        return out | ({"R"} if len(self.glonass) else set())

    def span_ms(self) -> tuple[int, int] | None:
        """Earliest and latest instant any record is valid for [GPS ms], or None without records."""
        spans = [self.kepler.span_ms()] if len(self.kepler) else []
        if len(self.glonass):
            spans.append((int(self.glonass.toe_ms.min()) - GLO_VALID_MS, int(self.glonass.toe_ms.max()) + GLO_VALID_MS))
        return (min(s[0] for s in spans), max(s[1] for s in spans)) if spans else None

    def glonass_channels(self) -> dict[int, int]:
        """GLONASS slot -> frequency channel k from the records (the latest record's per slot)."""
        g = self.glonass
        return {int(s): int(k) for s, k in zip(g.svid, g.k)}  # sorted by (slot, toe): the last wins


@dataclass
class _Header:
    version: float
    file_type: str
    system: str
    body: int
    klobuchar: np.ndarray | None
    leap_s: int | None
    frames: list | None = None          # RINEX 4: the body's frames (:func:`_frames`)


# ---------------------------------------------------------------------------- lines and header
def _read_lines(path: Path) -> list[str]:
    return read_lines(path, "navigation")


def _num(text: str, path: Path, line_no: int) -> float:
    try:
        # float() skips surrounding whitespace itself: only a failure needs the blank check
        return float(text.replace("D", "E").replace("d", "e"))
    except ValueError:
        text = text.strip()
        if not text:
            return 0.0
        raise DataError(f"{path}:{line_no}: cannot read number {text!r}") from None


def _header(lines: list[str], path: Path) -> _Header:
    """Version, file type, system, first body line, Klobuchar coefficients and leap seconds."""
    if not lines or "RINEX VERSION" not in lines[0]:
        raise DataError(f"{path}:1: not a RINEX file (no 'RINEX VERSION / TYPE' header line)")
    try:
        version = float(lines[0][:9])
    except ValueError:
        raise DataError(f"{path}:1: cannot read RINEX version {lines[0][:9]!r}") from None
    if version >= 5 or version < 2:
        raise DataError(f"{path}:1: RINEX navigation version {version} is not supported (2.x, 3.x or 4.x)")
    file_type = lines[0][20:21].upper()
    # RINEX 2: type N is GPS, G is GLONASS; RINEX 3: type N with the system in column 41.
    system = {"N": "G", "G": "R"}.get(file_type, "") if version < 3 else (lines[0][40:41].upper() or "M")
    if file_type not in ("N", "G") or (version >= 3 and file_type != "N"):
        raise DataError(f"{path}:1: RINEX type {file_type!r} is not navigation data")
    alpha = beta = leap = None
    for no, ln in enumerate(lines):
        label = ln[60:].strip()
        if label == "END OF HEADER":
            klob = np.r_[alpha, beta] if alpha is not None and beta is not None else None
            frames = _frames(lines, no + 1, path) if version >= 4 else None
            if frames is not None:
                # RINEX 4 moved the coefficients into ION frames; a writer that kept the header lines too
                # still counts where the body has none
                ion = _v4_klobuchar(frames, path)
                klob = ion if ion is not None else klob
            return _Header(version, file_type, system, no + 1, klob, leap, frames)
        if label in ("ION ALPHA", "ION BETA") or (label == "IONOSPHERIC CORR" and ln[:4] in ("GPSA", "GPSB")):
            start = 2 if label.startswith("ION ") else 5
            vals = np.array([_num(ln[start + 12 * k: start + 12 * (k + 1)], path, no + 1) for k in range(4)])
            if label == "ION ALPHA" or ln[:4] == "GPSA":
                alpha = vals
            else:
                beta = vals
        elif label == "LEAP SECONDS" and ln[:6].strip():
            leap = int(_num(ln[:6], path, no + 1))
    raise DataError(f"{path}: no 'END OF HEADER' line")


# ---------------------------------------------------------------------------- records
def _records(lines: list[str], head: _Header, path: Path, skipped: dict[str, int]
             ) -> list[tuple[str, int, int, list[float]]]:
    """(system letter, svid, toc in the system's own time [ms], values) per Keplerian or GLONASS
    record; other systems are skipped and counted."""
    if head.frames is not None:
        return _v4_records(head.frames, path, skipped)
    out, bad = [], []
    i, n = head.body, len(lines)
    while i < n:
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if head.version >= 3:
            sys_letter = line[0].upper()
            if sys_letter not in _R3_RECORD_LINES:
                raise DataError(f"{path}:{i + 1}: unknown satellite system {line[0]!r} in record")
        else:
            sys_letter = head.system
        n_lines = _R3_RECORD_LINES[sys_letter]
        span = _record_span(lines, i, n_lines) if head.version >= 3 else min(n_lines, n - i)
        if span < n_lines:
            bad.append(f"{path}:{i + 1}: truncated ephemeris record ({span} of {n_lines} lines present)")
        elif sys_letter in _KEPLER or sys_letter == "R":
            _read_record(out, bad, lines[i:i + n_lines], sys_letter, head.version, path, i + 1)
        else:
            count_skip(skipped, f"records_{sys_letter}_not_modelled", 1)
        i += span
    _skip_unreadable(bad, skipped, out)
    return out


def _read_record(out: list, bad: list[str], rec: list[str], sys_letter: str, version: float, path: Path,
                 line_no: int) -> None:
    """:func:`_record` appended to ``out``, or its error to ``bad``: one broken record costs itself alone."""
    try:
        out.append(_record(rec, sys_letter, version, path, line_no))
    except DataError as exc:
        bad.append(str(exc))


def _skip_unreadable(bad: list[str], skipped: dict[str, int], read: list) -> None:
    """One warning naming the first record that could not be read, and their count (``records_unreadable``);
    a file none of whose records could be read (``read`` empty) is refused, by the first one's error."""
    if bad and not read:
        raise DataError(f"{bad[0]} (no ephemeris record of the file could be read)")
    if bad:
        warnings.warn(f"{bad[0]}; {len(bad)} ephemeris record(s) skipped", stacklevel=4)
        count_skip(skipped, "records_unreadable", len(bad))


def _frames(lines: list[str], body: int, path: Path) -> list[tuple[int, list[str], list[str]]]:
    """RINEX 4 frames from line ``body`` on: (0-based line of the marker, marker fields such as
    ``["EPH", "G01", "LNAV"]``, the lines up to the next marker). A blank line inside a frame stays (a
    record's spare fields may be written as one); blank lines at a frame's end are dropped."""
    out: list[tuple[int, list[str], list[str]]] = []
    for i in range(body, len(lines)):
        line = lines[i]
        if line.startswith(">"):
            out.append((i, line[1:].split(), []))
        elif out:
            out[-1][2].append(line)
        elif line.strip():
            raise DataError(f"{path}:{i + 1}: expected a RINEX 4 record marker ('> EPH ...'), got {line[:20]!r}")
    for _, _, frame in out:
        while frame and not frame[-1].strip():
            frame.pop()
    return out


def _v4_records(frames: list, path: Path, skipped: dict[str, int]) -> list[tuple[str, int, int, list[float]]]:
    """The modelled ephemerides of RINEX 4 frames (:data:`_V4_MESSAGES`), read as RINEX 3 records (a
    GLONASS FDMA body of 4.01 on carries a fifth line, read past here); other messages skipped and counted."""
    out, bad = [], []
    for i, fields, body in frames:
        if not fields or fields[0] != "EPH":
            continue                      # ION (read by the header), STO, EOP: nothing to model
        if len(fields) < 3 or not fields[1][:1].isalpha():
            raise DataError(f"{path}:{i + 1}: cannot read the record marker {'> ' + ' '.join(fields)!r}")
        sys_letter, msg = fields[1][0].upper(), fields[2].upper()
        if msg not in _V4_MESSAGES.get(sys_letter, ()):
            count_skip(skipped, f"records_{sys_letter}_{msg}_not_modelled", 1)
            continue
        n_lines = _R3_RECORD_LINES[sys_letter]
        if len(body) < n_lines:
            bad.append(f"{path}:{i + 1}: truncated ephemeris record ({len(body)} of {n_lines} lines present)")
            continue
        if body[0][:3].replace(" ", "0").upper() != fields[1].upper():
            raise DataError(f"{path}:{i + 2}: record of {body[0][:3]!r} under the marker for {fields[1]!r}")
        _read_record(out, bad, body[:n_lines], sys_letter, 3.0, path, i + 2)
    _skip_unreadable(bad, skipped, out)
    return out


def _v4_klobuchar(frames: list, path: Path) -> np.ndarray | None:
    """(8,) GPS alpha0..3, beta0..3 of the first GPS LNAV ``ION`` frame, or None. Its first line is the
    transmission time and three coefficients (from column 24), then four and one (from column 5)."""
    for i, fields, body in frames:
        if fields[:1] == ["ION"] and len(fields) >= 3 and fields[1][:1].upper() == "G" and fields[2].upper() == "LNAV":
            if len(body) < 3:
                raise DataError(f"{path}:{i + 1}: truncated ION record ({len(body)} of 3 lines present)")
            vals = _fields(body[0], 23, 3, path, i + 2) + _fields(body[1], 4, 4, path, i + 3) + \
                _fields(body[2], 4, 1, path, i + 4)
            return np.array(vals)
    return None


def _record_span(lines: list[str], i: int, n_lines: int) -> int:
    """Lines of the RINEX 3 record starting at line ``i``: up to the next line that starts with a
    system letter (RINEX 3.05 GLONASS records carry a fifth line, read past here)."""
    j = i + 1
    while j < len(lines) and (lines[j][:1] == " " or not lines[j].strip()):
        j += 1
    return j - i


def _record(rec: list[str], sys_letter: str, version: float, path: Path, line_no: int
            ) -> tuple[str, int, int, list[float]]:
    head = rec[0]
    if version >= 3:
        prn_txt, date_txt, clk_col, cont = head[1:3], head[4:23].split(), 23, 4
    else:
        prn_txt, date_txt, clk_col, cont = head[0:2], head[3:22].split(), 22, 3
    try:
        svid = int(prn_txt) + _SVID_OFFSET.get(sys_letter, 0)
        y, mo, d, hh, mi = (int(v) for v in date_txt[:5])
        sec = float(date_txt[5])
    except (ValueError, IndexError):
        raise DataError(f"{path}:{line_no}: cannot read PRN / epoch from {head[:23]!r}") from None
    if version < 3:
        y += 2000 if y < 80 else 1900
    try:
        toc = gps_ms_from_calendar(y, mo, d, hh, mi, sec)
    except ValueError as exc:
        raise DataError(f"{path}:{line_no}: invalid epoch ({exc})") from None
    vals = _fields(head, clk_col, 3, path, line_no)
    for k, ln in enumerate(rec[1:], 1):
        vals += _fields(ln, cont, 4, path, line_no + k)
    return sys_letter, svid, toc, vals


def _fields(line: str, start: int, count: int, path: Path, line_no: int) -> list[float]:
    """``count`` 19-character numeric fields starting at column ``start`` (blank -> 0)."""
    line = line.rstrip("\n").ljust(start + 19 * count)
    return [_num(line[start + 19 * k: start + 19 * (k + 1)], path, line_no) for k in range(count)]


# ---------------------------------------------------------------------------- tables
def _kepler_table(recs: list, path: str, skipped: dict[str, int]) -> GpsNav:
    """Keplerian records -> healthy, de-duplicated :class:`GpsNav` sorted by (sat_id, toe)."""
    recs = [r for r in recs if r[0] in _KEPLER]
    if not recs:
        return GpsNav(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                      {k: np.zeros(0) for k in _KEEP + ("tgd_l5", "tgd_l2")}, path, skipped, np.zeros(0, np.int64))
    letters = np.array([r[0] for r in recs])
    svid = np.array([r[1] for r in recs], np.int64)
    table = np.asarray([r[3] for r in recs], float)
    params = {name: table[:, k] for k, name in enumerate(_NAMES) if name in _KEEP}
    msg = galileo_message(letters, table[:, _NAMES.index("l2_codes")])
    params.update(group_delays(letters, msg, params["tgd"], params["iodc"]))
    default_fit = np.array([DEFAULT_FIT_H[s] for s in letters])
    # QZSS writes a fit flag (0/1), Galileo and BeiDou no fit interval at all.
    use_file_fit = np.isin(letters, ["G"]) & (params["fit_h"] > 1)
    params["fit_h"] = np.where(use_file_fit, params["fit_h"], default_fit)
    # BeiDou times are BDT = GPST - 14 s; the week-of-toe logic runs in the system's own time.
    offset_ms = np.where(letters == "C", 14_000, 0)
    toc_sys = np.array([r[2] for r in recs], np.int64)
    toe_sow = params["toe_sow"]
    week = np.round((toc_sys / 1000.0 - toe_sow) / WEEK_S)
    toe_ms = (week * WEEK_S * 1000).astype(np.int64) + np.round(toe_sow * 1000).astype(np.int64) + offset_ms
    toc_ms = toc_sys + offset_ms
    sat_id = np.array([_CTYPE[s] for s in letters], np.int64) * 1000 + svid
    keep = _healthy_unique(sat_id * 2 + msg, toe_ms, params["health"], skipped) & _plausible_orbits(
        params, letters, svid, path, skipped)
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((toe_ms[sel], msg[sel], sat_id[sel]))]
    return GpsNav(prn=svid[sel], toc_ms=toc_ms[sel], toe_ms=toe_ms[sel],
                  params={k: v[sel] for k, v in params.items()}, source=path, skipped=skipped,
                  sat_id=sat_id[sel], msg=msg[sel])


#: Every GNSS orbit's semi-major axis lies within these [m] (GPS 26,560 km ... GEO / IGSO / QZSS 42,164 km), and
#: its eccentricity below ORBIT_E_MAX (QZSS: 0.075): a record outside is a corrupt one.
ORBIT_A_RANGE_M = (1.0e7, 5.0e7)
ORBIT_E_MAX = 0.2


def _plausible_orbits(params: dict[str, np.ndarray], letters: np.ndarray, svid: np.ndarray, path: str,
                      skipped: dict[str, int]) -> np.ndarray:
    """(N,) bool: Keplerian records whose orbit a GNSS satellite can fly; the others skipped and counted
    (``records_implausible_orbit``), with a warning naming their satellites."""
    a = params["sqrt_a"] ** 2
    ok = (a > ORBIT_A_RANGE_M[0]) & (a < ORBIT_A_RANGE_M[1]) & (params["e"] >= 0) & (params["e"] < ORBIT_E_MAX)
    if not ok.all():
        sats = sorted({f"{c}{n % 1000:02d}" for c, n in zip(letters[~ok], svid[~ok])})
        warnings.warn(f"{path}: {int((~ok).sum())} ephemeris record(s) with an orbit no GNSS satellite flies "
                      f"(semi-major axis outside 10,000-50,000 km, or eccentricity >= {ORBIT_E_MAX}) skipped: "
                      f"{', '.join(sats)}", stacklevel=4)
        count_skip(skipped, "records_implausible_orbit", ~ok)
    return ok


def galileo_message(letters: np.ndarray, data_source: np.ndarray) -> np.ndarray:
    """(N,) int8: 1 for Galileo F/NAV records, else 0 (I/NAV, and every other system).

    data_source: (N,) the RINEX 3 Galileo "data sources" field (bit 0 I/NAV E1-B, 1 F/NAV E5a-I,
    2 I/NAV E5b-I, 8 clock for E5a,E1, 9 clock for E5b,E1); other systems' values are ignored.
    """
    src = np.nan_to_num(data_source).astype(np.int64)
    fnav = ((src & 0b10) != 0) | (((src & 256) != 0) & ((src & 512) == 0) & ((src & 0b101) == 0))
    return ((letters == "E") & fnav).astype(np.int8)


def group_delays(letters: np.ndarray, msg: np.ndarray, tgd: np.ndarray, iodc: np.ndarray
                 ) -> dict[str, np.ndarray]:
    """Group delays [s] per signal class of each record (N,): ``tgd`` (L1 class: GPS/QZSS L1,
    Galileo E1, BeiDou B1I and B1C), ``tgd_l5`` (L5 / E5a; BeiDou B2a: 0), ``tgd_l2`` (GPS/QZSS L2,
    Galileo E5b, BeiDou B2I), each what that signal's user subtracts from the record's clock. A D1 / D2
    record has no group delay for B1C or B2a (CNAV-1 / CNAV-2 carry them): B1C takes TGD1, of the nearest
    carrier that has one, and B2a none; the graph's bias state per signal takes their common part.

    tgd / iodc: the record's two group-delay slots (GPS TGD / IODC; Galileo BGD(E1,E5a) /
    BGD(E1,E5b); BeiDou TGD1 / TGD2). Galileo's I/NAV clock serves E1 and E5b with BGD(E1,E5b),
    its F/NAV clock E1 and E5a with BGD(E1,E5a) (OS SIS ICD 5.1.5). The other pairings follow
    from both clocks giving the same E1 clock: on I/NAV, E5a subtracts BGD_b + (g5 - 1) BGD_a;
    on F/NAV (which carries no BGD_b), E5b subtracts g7 BGD_a, taking BGD_b as BGD_a.
    """
    gal, bds, fnav = letters == "E", letters == "C", msg == 1
    bgd_a, bgd_b = tgd, iodc
    l1 = np.where(gal, np.where(fnav, bgd_a, bgd_b), tgd)
    l5 = np.where(gal, np.where(fnav, GAMMA_L5 * bgd_a, bgd_b + (GAMMA_L5 - 1) * bgd_a), GAMMA_L5 * tgd)
    l2 = np.where(gal, np.where(fnav, GAMMA_E5B * bgd_a, GAMMA_E5B * bgd_b), GAMMA_L2 * tgd)
    l5 = np.where(bds, 0.0, l5)
    l2 = np.where(bds, iodc, l2)
    return {"tgd": l1, "tgd_l5": l5, "tgd_l2": l2}


def _healthy_unique(sat_id: np.ndarray, toe_ms: np.ndarray, health: np.ndarray,
                    skipped: dict[str, int]) -> np.ndarray:
    """(N,) bool: healthy, first of its (sat_id, toe) (re-broadcasts carry the same orbit)."""
    keep = health == 0
    count_skip(skipped, "unhealthy_or_bad_prn", ~keep)
    key = sat_id * 10**13 + toe_ms
    order = np.lexsort((np.arange(len(key)), key))
    first = np.zeros(len(key), bool)
    k_sorted = key[order]
    first[order[np.r_[True, k_sorted[1:] != k_sorted[:-1]]]] = True
    count_skip(skipped, "duplicate_records", ~first & keep)
    return keep & first


def _glonass_table(recs: list, leap_s: int, path: str, skipped: dict[str, int]) -> GloNav:
    """GLONASS records (epochs in UTC) -> healthy, de-duplicated :class:`GloNav`."""
    recs = [r for r in recs if r[0] == "R"]
    t = np.array([r[2] for r in recs], np.int64) + 1000 * leap_s
    svid = np.array([r[1] for r in recs], np.int64)
    v = {k: np.asarray([r[3][i] for r in recs], float) for i, k in enumerate(_GLO_FIELDS)}
    keep = _healthy_unique(3000 + svid, t, v["health"] if recs else np.zeros(0), skipped) if recs else np.zeros(0, bool)
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((t[sel], svid[sel]))]
    xyz = lambda a, b, c: np.stack([v[a], v[b], v[c]], axis=1)[sel] * 1000.0 if recs else np.zeros((0, 3))  # noqa: E731
    return GloNav(svid=svid[sel], toe_ms=t[sel], pos=xyz("x", "y", "z"), vel=xyz("vx", "vy", "vz"),
                  acc=xyz("ax", "ay", "az"), tau=v["tau"][sel] if recs else np.zeros(0),
                  gamma=v["gamma"][sel] if recs else np.zeros(0),
                  k=v["k"][sel].astype(np.int64) if recs else np.zeros(0, np.int64), source=path)


# ---------------------------------------------------------------------------- public API
def read_nav(paths: str | Path | list) -> Navigation:
    """Read one or more navigation files into one :class:`Navigation` (records of every file
    merged; header values from the first file that has them)."""
    paths = [Path(p) for p in (paths if isinstance(paths, (list, tuple)) else [paths])]
    if not paths:
        raise DataError("no navigation file given")
    skipped: dict[str, int] = {}
    recs: list = []
    klob = leap = None
    file_systems: dict[str, set[str]] = {}
    file_spans: dict[str, tuple[int, int]] = {}
    for path in paths:
        lines = _read_lines(path)
        head = _header(lines, path)
        mine = _records(lines, head, path, skipped)
        file_systems[str(path)] = {r[0] for r in mine}
        if mine:
            file_spans[str(path)] = (min(r[2] for r in mine), max(r[2] for r in mine))
        recs += mine
        klob = klob if klob is not None else head.klobuchar
        leap = leap if leap is not None else head.leap_s
    name = ", ".join(str(p) for p in paths)
    if not recs:
        raise DataError(f"{name}: no GPS, QZSS, Galileo, BeiDou or GLONASS records in navigation file")
    glo_leap = leap if leap is not None else _leap_at_gps_ms(min(r[2] for r in recs))
    return Navigation(kepler=_kepler_table(recs, name, skipped), glonass=_glonass_table(recs, glo_leap, name, skipped),
                      klobuchar=klob, leap_s=leap, sources=[str(p) for p in paths], skipped=skipped,
                      file_systems=file_systems, file_spans=file_spans)


def _leap_at_gps_ms(t_ms: int) -> int:
    """GPS - UTC [s] at a GPS time (the table in :mod:`fusion.gpstime`), when no header says."""
    return int(leap_seconds_at_unix_ms(np.int64(t_ms) + GPS_EPOCH_UNIX_MS))


def read_rinex_nav(path: str | Path) -> GpsNav:
    """GPS records only of a RINEX 2.x GPS or 3.x / 4.x (GPS / mixed) navigation file (the simulator's
    view). Raises :class:`DataError` (naming the file and line) for unreadable files, unsupported
    versions, or a file without a single healthy GPS record; a record cut short or unreadable is skipped and
    counted (``records_unreadable``), with a warning."""
    path = Path(path)
    lines = _read_lines(path)
    if lines and "RINEX VERSION" in lines[0] and lines[0][:9].strip().startswith("2") and lines[0][20:21] != "N":
        raise DataError(f"{path}:1: RINEX 2 type {lines[0][20:21]!r} file has no GPS records")
    head = _header(lines, path)
    skipped: dict[str, int] = {}
    recs = _records(lines, head, path, skipped)
    count_skip(skipped, "non_gps_records", sum(r[0] != "G" for r in recs))
    for k in [k for k in skipped if k.endswith("_not_modelled") and not k.startswith("records_G_")]:
        count_skip(skipped, "non_gps_records", skipped.pop(k))
    recs = [r for r in recs if r[0] == "G" and 1 <= r[1] <= 32]
    if not recs:
        raise DataError(f"{path}: no GPS records in navigation file (system {head.system!r})")
    nav = _kepler_table(recs, str(path), skipped)
    if not len(nav):
        raise DataError(f"{path}: no healthy GPS records in navigation file")
    return nav


def default_nav_path() -> Path:
    """The GPS broadcast navigation file shipped with gnssfuse (IGS hourly merge, 2021 day 118)."""
    return Path(__file__).resolve().parents[1] / "data" / "hour1180.21n"
