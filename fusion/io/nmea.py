"""NovAtel SPAN reference trajectories in NMEA 0183 (GSDC 2021 ``supplemental/SPAN_*_10Hz.nmea``).

Only GGA (position) and RMC (date) sentences are used. GGA carries UTC *time of day* only, so
the calendar date comes from the RMC sentences, or, where a file has none, from a reference
GPS time the caller knows (e.g. the first measurement epoch of the same drive).

Heights: GGA gives the altitude above mean sea level and the geoid separation N; the WGS-84
ellipsoidal height is ``altitude + N``. This is the quantity the GSDC 2021 ground-truth CSV got
wrong (it used ``altitude - N``: about 2 |N| = 63.1 m too high in the Bay Area).
"""
from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.gpstime import DAY_MS, gps_ms_to_unix_ms, unix_ms_to_gps_ms
from fusion.trace import count_skip

#: Columns of :func:`read_span_nmea`'s result.
NMEA_COLUMNS = ("t_ms", "lat_deg", "lon_deg", "height_m", "alt_msl_m", "geoid_sep_m", "quality", "n_sats")


def _read_lines(path: Path) -> pd.Series:
    if not path.is_file():
        raise DataError(f"{path}: NMEA file not found")
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rt", encoding="ascii", errors="replace") as fh:
            text = fh.read()
    except (OSError, EOFError) as exc:
        raise DataError(f"{path}: cannot read NMEA file ({exc})") from exc
    lines = pd.Series(text.splitlines(), dtype=object).str.strip()
    return lines[lines.str.len() > 0]


def _checksum_ok(lines: pd.Series) -> np.ndarray:
    """(N,) bool: the ``*hh`` checksum equals the XOR of the bytes between ``$`` and ``*``.

    Vectorised: bodies are padded into an (N, L) uint8 array (0 is neutral for XOR).
    """
    parts = lines.str.extract(r"^\$([^*]*)\*([0-9A-Fa-f]{2})$")
    ok = parts[0].notna().to_numpy().copy()
    if not ok.any():
        return ok
    bodies = parts[0][ok].to_numpy(dtype=str)
    raw = np.char.encode(bodies, "ascii", errors="replace")
    width = max(int(np.char.str_len(bodies).max()), 1)
    buf = np.frombuffer(raw.astype(f"S{width}").tobytes(), np.uint8).reshape(-1, width)
    xor = np.bitwise_xor.reduce(buf, axis=1)
    want = parts[1][ok].map(lambda h: int(h, 16)).to_numpy(np.uint8)
    ok[ok] = xor == want
    return ok


def _tod_ms(hhmmss: pd.Series) -> np.ndarray:
    """'hhmmss.ss' strings -> milliseconds of the day (float, NaN where malformed)."""
    v = pd.to_numeric(hhmmss, errors="coerce").to_numpy(float)
    hh, rest = np.divmod(v, 10000.0)
    mm, ss = np.divmod(rest, 100.0)
    tod = np.round((hh * 3600.0 + mm * 60.0 + ss) * 1000.0)
    tod[(hh > 23) | (mm > 59) | (ss >= 61)] = np.nan
    return tod


def _deg(value: pd.Series, hemi: pd.Series, neg: str) -> np.ndarray:
    """NMEA 'dddmm.mmmm' + hemisphere -> signed decimal degrees."""
    v = pd.to_numeric(value, errors="coerce").to_numpy(float)
    d, m = np.divmod(v, 100.0)
    out = d + m / 60.0
    return np.where(hemi.to_numpy(dtype=str) == neg, -out, out)


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
    is_rmc = lines.str.startswith("$") & (lines.str.slice(3, 6) == "RMC")
    fix = _gga_fixes(lines, path, skipped)
    # Day roll-over: time of day only ever wraps forward (23:59:59 -> 00:00:00).
    tod = fix.pop("tod")
    day = np.concatenate([[0], np.cumsum(np.diff(tod) < -DAY_MS / 2)])
    unix_day0 = _first_day_unix_ms(lines[is_rmc], tod[0], ref_gps_ms, path)
    t_ms = unix_ms_to_gps_ms((unix_day0 + day * DAY_MS + tod).astype(np.int64))
    df = pd.DataFrame({
        "t_ms": t_ms, "lat_deg": fix["lat"], "lon_deg": fix["lon"], "height_m": fix["alt"] + fix["sep"],
        "alt_msl_m": fix["alt"], "geoid_sep_m": fix["sep"], "quality": fix["quality"].astype(np.int16),
        "n_sats": np.nan_to_num(fix["n_sats"], nan=-1).astype(np.int16),
    })
    return _unique_forward(df, path, skipped)


def _gga_fixes(lines: pd.Series, path: Path, skipped: dict[str, int]) -> dict[str, np.ndarray]:
    """The GGA sentences with a good checksum, readable fields and a fix, as (F,) arrays
    tod (ms of day), lat, lon, quality, n_sats, alt, sep; the others dropped and counted."""
    is_gga = lines.str.startswith("$") & (lines.str.slice(3, 6) == "GGA")
    ok = _checksum_ok(lines)
    # RMC is read for its date only and its checksum is not enforced: every RMC sentence in the
    # GSDC 2021 SPAN logs has a wrong checksum (their GGA ones are right). The date is instead
    # cross-checked against ``ref_gps_ms`` when given.
    count_skip(skipped, "nmea_bad_checksum", int((is_gga & ~ok).sum()))
    gga = lines[is_gga & ok].str.split("*").str[0].str.split(",", expand=True)
    if gga.empty or gga.shape[1] < 12:
        raise DataError(f"{path}: no valid GGA sentences")
    num = lambda k: pd.to_numeric(gga[k], errors="coerce").to_numpy(float)  # noqa: E731
    fix = {"tod": _tod_ms(gga[1]), "lat": _deg(gga[2], gga[3], "S"), "lon": _deg(gga[4], gga[5], "W"),
           "quality": num(6), "n_sats": num(7), "alt": num(9), "sep": num(11)}
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


def _first_day_unix_ms(rmc_lines: pd.Series, first_tod: float, ref_gps_ms: int | None,
                       path: Path) -> float:
    """Unix ms of 00:00 UTC on the day of the first GGA fix."""
    if len(rmc_lines):
        rmc = rmc_lines.str.split("*").str[0].str.split(",", expand=True)
        if rmc.shape[1] > 9:
            dates = pd.to_datetime(rmc[9], format="%d%m%y", errors="coerce", utc=True)
            valid = dates.notna() & (rmc[2] == "A")
            if valid.any():
                i = int(np.flatnonzero(valid.to_numpy())[0])
                d_unix = dates[valid].iloc[0].value // 1_000_000
                # The dating RMC and the first kept GGA may sit on either side of midnight (an
                # RMC after it dates a GGA before it, or the GGA fixes before midnight had no
                # fix): move the date by the day the times of day imply.
                rmc_tod = _tod_ms(rmc[1].iloc[[i]])[0]
                if np.isfinite(rmc_tod) and rmc_tod < first_tod - DAY_MS / 2:
                    d_unix -= DAY_MS
                elif np.isfinite(rmc_tod) and rmc_tod > first_tod + DAY_MS / 2:
                    d_unix += DAY_MS
                if ref_gps_ms is not None:
                    ref_unix = float(gps_ms_to_unix_ms(np.int64(ref_gps_ms)))
                    if abs(d_unix + first_tod - ref_unix) > DAY_MS:
                        raise DataError(f"{path}: RMC date {rmc[9].iloc[i]} is more than a day from the "
                                        f"measurements (GPS ms {ref_gps_ms}): wrong NMEA file for this drive?")
                return float(d_unix)
    if ref_gps_ms is None:
        raise DataError(f"{path}: no valid RMC sentence to date the GGA fixes, and no reference time given")
    ref_unix = float(gps_ms_to_unix_ms(np.int64(ref_gps_ms)))
    day0 = np.floor(ref_unix / DAY_MS) * DAY_MS
    cands = day0 + np.array([-1, 0, 1]) * DAY_MS
    return float(cands[np.argmin(np.abs(cands + first_tod - ref_unix))])
