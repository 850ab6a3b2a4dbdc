"""NovAtel SPAN reference trajectories in NMEA 0183 (GSDC 2021 ``supplemental/SPAN_*_10Hz.nmea``).

Only GGA (position) and RMC (date) sentences are used. GGA carries UTC *time of day* only, so
the calendar date comes from the RMC sentences, or, where a file has none, from a reference
GPS time the caller knows (e.g. the first measurement epoch of the same drive).

Heights: GGA gives the altitude above mean sea level and the geoid separation N; the WGS-84
ellipsoidal height is ``altitude + N``. This is the quantity the GSDC 2021 ground-truth CSV got
wrong (it used ``altitude - N``: about 2 |N| = 63.1 m too high in the Bay Area).
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.gpstime import DAY_MS, gps_ms_to_unix_ms, unix_ms_to_gps_ms
from fusion.io.nmea_fields import SentenceFields, to_float
from fusion.io.text_open import read_lines
from fusion.trace import count_skip

#: Columns of :func:`read_span_nmea`'s result.
NMEA_COLUMNS = ("t_ms", "lat_deg", "lon_deg", "height_m", "alt_msl_m", "geoid_sep_m", "quality", "n_sats")


#: Longest line taken for a sentence (NMEA 0183 allows 82 characters; SPAN logs stay under 100):
#: longer lines are not sentences.
MAX_SENTENCE = 200


def _read_lines(path: Path) -> list[str]:
    """The file's lines, stripped."""
    return list(map(str.strip, read_lines(path, "NMEA")))


def _sentences(lines: list[str], kind: str) -> Iterator[str]:
    """The lines that are sentences of ``kind`` ("GGA", "RMC") from any talker ("$GPGGA", "$GNGGA"), lazily."""
    return (ln for ln in lines if ln[3:6] == kind and ln[:1] == "$")


def _tod_ms(v: np.ndarray) -> np.ndarray:
    """'hhmmss.ss' values (N,) -> milliseconds of the day (float, NaN where malformed)."""
    hh, rest = np.divmod(v, 10000.0)
    mm, ss = np.divmod(rest, 100.0)
    tod = np.round((hh * 3600.0 + mm * 60.0 + ss) * 1000.0)
    tod[(hh > 23) | (mm > 59) | (ss >= 61)] = np.nan
    return tod


def _deg(v: np.ndarray, negative: np.ndarray) -> np.ndarray:
    """NMEA 'dddmm.mmmm' values (N,) + (N,) bool southern / western hemisphere -> signed decimal degrees."""
    d, m = np.divmod(v, 100.0)
    out = d + m / 60.0
    return np.where(negative, -out, out)


def read_span_nmea(path: str | Path, ref_gps_ms: int | None = None,
                   skipped: dict[str, int] | None = None) -> pd.DataFrame:
    """Read GGA fixes of a SPAN NMEA log into a DataFrame sorted by time.

    path:        ``.nmea`` or ``.nmea.gz``.
    ref_gps_ms:  any GPS time [ms] during the drive; used to pick the date when the file has no
                 valid RMC sentence (the date whose GGA times fall nearest to it).
    skipped:     optional dict that receives counts of dropped sentences by reason.
    Returns columns :data:`NMEA_COLUMNS`: t_ms (int64 GPS ms), lat/lon [deg], height_m (WGS-84
    ellipsoidal = altitude + geoid separation), alt_msl_m, geoid_sep_m, quality, n_sats.
    Sentences with a bad checksum, an invalid fix (quality 0) or unparsable fields are dropped
    and counted; a file with no usable GGA raises :class:`DataError`.
    """
    path = Path(path)
    skipped = {} if skipped is None else skipped
    lines = _read_lines(path)
    fix = _gga_fixes(list(_sentences(lines, "GGA")), path, skipped)
    # Day roll-over: time of day only ever wraps forward (23:59:59 -> 00:00:00).
    tod = fix.pop("tod")
    day = np.concatenate([[0], np.cumsum(np.diff(tod) < -DAY_MS / 2)])
    # the first valid RMC dates the file: the others are never looked at
    unix_day0 = _first_day_unix_ms(_sentences(lines, "RMC"), tod[0], ref_gps_ms, path)
    t_ms = unix_ms_to_gps_ms((unix_day0 + day * DAY_MS + tod).astype(np.int64))
    df = pd.DataFrame({
        "t_ms": t_ms, "lat_deg": fix["lat"], "lon_deg": fix["lon"], "height_m": fix["alt"] + fix["sep"],
        "alt_msl_m": fix["alt"], "geoid_sep_m": fix["sep"], "quality": fix["quality"].astype(np.int16),
        "n_sats": np.nan_to_num(fix["n_sats"], nan=-1).astype(np.int16),
    })
    return _unique_forward(df, path, skipped)


def _gga_fixes(gga_lines: list[str], path: Path, skipped: dict[str, int]) -> dict[str, np.ndarray]:
    """The GGA sentences with a good checksum, readable fields and a fix, as (F,) arrays
    tod (ms of day), lat, lon, quality, n_sats, alt, sep; the others dropped and counted."""
    gga = SentenceFields(gga_lines, 12)
    ok = gga.checksum_ok(MAX_SENTENCE)
    # RMC is read for its date only and its checksum is not enforced: every RMC sentence in the
    # GSDC 2021 SPAN logs has a wrong checksum (their GGA ones are right). The date is instead
    # cross-checked against ``ref_gps_ms`` when given.
    count_skip(skipped, "nmea_bad_checksum", int((~ok).sum()))
    if not (ok & (gga.n_commas >= 11)).any():
        raise DataError(f"{path}: no valid GGA sentences")
    rows = np.flatnonzero(ok)
    fix = {"tod": _tod_ms(gga.number(1, rows)), "lat": _deg(gga.number(2, rows), gga.letter_is(3, "S", rows)),
           "lon": _deg(gga.number(4, rows), gga.letter_is(5, "W", rows)), "quality": gga.number(6, rows),
           "n_sats": gga.number(7, rows), "alt": gga.number(9, rows), "sep": gga.number(11, rows)}
    good = np.logical_and.reduce([np.isfinite(fix[k]) for k in ("tod", "lat", "lon", "alt", "sep")])
    count_skip(skipped, "nmea_bad_fields", int((~good).sum()))
    count_skip(skipped, "nmea_no_fix", good & ~(fix["quality"] > 0))
    keep = good & (fix["quality"] > 0)
    if not keep.any():
        raise DataError(f"{path}: no GGA sentence with a valid fix")
    return {k: v[keep] for k, v in fix.items()}


def _unique_forward(df: pd.DataFrame, path: Path, skipped: dict[str, int]) -> pd.DataFrame:
    """Drop (and count) repeated fix times; refuse times that go backwards."""
    dup = df.duplicated("t_ms")
    if dup.any():
        count_skip(skipped, "nmea_duplicate_times", dup.to_numpy())
        df = df[~dup]
    back = np.flatnonzero(np.diff(df["t_ms"].to_numpy()) < 0)
    if back.size:
        i = back[0]
        raise DataError(f"{path}: GGA times go backwards after fix {i + 1} "
                        f"(GPS ms {df['t_ms'].iat[i]} then {df['t_ms'].iat[i + 1]})")
    return df.reset_index(drop=True)


def _first_rmc_date(rmc_lines: Iterable[str]) -> tuple[int, float, str] | None:
    """(unix ms of 00:00 UTC of the date, ms of day, the date field) of the first RMC sentence
    with status A and a readable ``ddmmyy`` date; None when there is none."""
    for ln in rmc_lines:
        f = ln.split("*")[0].split(",")
        if len(f) <= 9 or f[2] != "A":
            continue
        try:
            date = datetime.strptime(f[9], "%d%m%y").replace(tzinfo=timezone.utc)
        except ValueError:
            continue
        return int(date.timestamp()) * 1000, float(_tod_ms(to_float(np.array([f[1]], dtype=object)))[0]), f[9]
    return None


def _first_day_unix_ms(rmc_lines: Iterable[str], first_tod: float, ref_gps_ms: int | None,
                       path: Path) -> float:
    """Unix ms of 00:00 UTC on the day of the first GGA fix."""
    rmc = _first_rmc_date(rmc_lines)
    ref_unix = None if ref_gps_ms is None else float(gps_ms_to_unix_ms(np.int64(ref_gps_ms)))
    if rmc is not None:
        d_unix, rmc_tod, date = rmc
        # The dating RMC and the first kept GGA may sit on either side of midnight (an RMC after it
        # dates a GGA before it, or the GGA fixes before midnight had no fix): move the date by the
        # day the times of day imply.
        if np.isfinite(rmc_tod) and rmc_tod < first_tod - DAY_MS / 2:
            d_unix -= DAY_MS
        elif np.isfinite(rmc_tod) and rmc_tod > first_tod + DAY_MS / 2:
            d_unix += DAY_MS
        if ref_unix is not None and abs(d_unix + first_tod - ref_unix) > DAY_MS:
            raise DataError(f"{path}: RMC date {date} is more than a day from the "
                            f"measurements (GPS ms {ref_gps_ms}): wrong NMEA file for this drive?")
        return float(d_unix)
    if ref_unix is None:
        raise DataError(f"{path}: no valid RMC sentence to date the GGA fixes, and no reference time given")
    day0 = np.floor(ref_unix / DAY_MS) * DAY_MS
    cands = day0 + np.array([-1, 0, 1]) * DAY_MS
    return float(cands[np.argmin(np.abs(cands + first_tod - ref_unix))])
