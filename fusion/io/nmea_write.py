"""Estimates as NMEA 0183 (GGA + RMC per solved epoch), the format every GNSS viewer and logger reads.

Times are UTC (GPS time minus the leap seconds), with milliseconds. GGA's altitude field is the
height above mean sea level and its separation field the geoid height N (ellipsoidal = altitude + N);
with no geoid model we write the WGS84 ellipsoidal height as the altitude and N = 0, which keeps
``altitude + N`` equal to the ellipsoidal height for readers that add them (as :mod:`fusion.io.nmea`
does). Fix quality 1 (autonomous GPS), and RMC's mode A, for every mode, but 6 and E (estimated, dead
reckoning) at the graph's ``bridged`` epochs, where fewer than four satellites and no prior fixed the position
and the motion model carried it; HDOP is left empty. RMC's speed over ground
[knots] and course [degrees true] are the graph's velocity where the frame has it (``vel_n_mps``, ``vel_e_mps``:
the graph modes, at epochs whose Doppler measures it), else they come from the track itself
(:func:`ground_velocity`), empty where an epoch has no neighbour within :data:`MAX_SPEED_GAP_S`; course is empty
below :data:`MIN_COURSE_MPS`, where it is noise.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from fusion.geometry import ecef2ned_vec, geodetic2ecef
from fusion.gpstime import gps_ms_to_unix_ms
from fusion.io.estimates import VELOCITY_COLUMNS, bridged_rows

TALKER = "GN"    # any constellation
KNOTS_PER_MPS = 3600.0 / 1852.0
#: neighbours further apart than this [s] give no speed (a gap in the track, not motion across it)
MAX_SPEED_GAP_S = 5.0
#: below this ground speed [m/s] the course is the direction of the position noise: left empty
MIN_COURSE_MPS = 0.5


def sentences(bodies: list[str]) -> list[str]:
    """``$body*hh`` for each body, the checksums computed at once over an (N, L) byte matrix
    (zero-padded: 0 is neutral for XOR)."""
    if not bodies:
        return []
    raw = np.array([b.encode("ascii") for b in bodies])
    xor = np.bitwise_xor.reduce(raw.view(np.uint8).reshape(len(bodies), -1), axis=1)
    return [f"${b}*{x:02X}" for b, x in zip(bodies, xor.tolist())]


def checksum(body: str) -> str:
    """Two hex digits: the XOR of the bytes between ``$`` and ``*``."""
    return sentences([body])[0][-2:]


def _angle(deg: np.ndarray, width: int, hemis: str) -> tuple[list[str], np.ndarray]:
    """Signed degrees (N,) -> 'ddmm.mmmmmmm' strings (``width`` degree digits) and hemisphere letters."""
    a = np.abs(deg)
    d = np.floor(a)
    m = (a - d) * 60.0
    carry = np.round(m, 7) >= 60.0            # 59.99999999 min must not print as 60
    d, m = np.where(carry, d + 1, d), np.where(carry, 0.0, m)
    text = [f"{int(di):0{width}d}{mi:010.7f}" for di, mi in zip(d, m)]
    return text, np.where(deg < 0, hemis[1], hemis[0])


def ground_velocity(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Speed over ground [m/s] and course [deg true, 0..360) per row (N,), from the central difference of
    the track (gps_millis, lat_deg, lon_deg, height_m) over the neighbours within MAX_SPEED_GAP_S (one-sided
    at an end or a gap); NaN where a row has neither, and course NaN below MIN_COURSE_MPS."""
    n = len(frame)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    t = frame["gps_millis"].to_numpy(np.int64) / 1000.0
    xyz = geodetic2ecef(frame[["lat_deg", "lon_deg", "height_m"]].to_numpy(float))
    i = np.arange(n)
    gap = np.diff(t) > MAX_SPEED_GAP_S
    a = np.where((i > 0) & ~np.r_[True, gap], i - 1, i)
    b = np.where((i < n - 1) & ~np.r_[gap, True], i + 1, i)
    dt = np.where(b > a, t[b] - t[a], np.nan)
    ned = ecef2ned_vec((xyz[b] - xyz[a]) / dt[:, None], xyz)
    return speed_course(ned[:, 0], ned[:, 1])


def speed_course(north: np.ndarray, east: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Speed over ground [m/s] and course [deg true, 0..360) (N,) of velocities (N,) north and east [m/s];
    course NaN below :data:`MIN_COURSE_MPS`."""
    speed = np.hypot(north, east)
    course = np.degrees(np.arctan2(east, north)) % 360.0
    return speed, np.where(speed >= MIN_COURSE_MPS, course, np.nan)


def rmc_velocity(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Speed [m/s] and course [deg] per row for RMC: the frame's velocity columns where they are finite (the
    graph's own velocity), :func:`ground_velocity` of the track elsewhere."""
    speed, course = ground_velocity(frame)
    if set(VELOCITY_COLUMNS[:2]) <= set(frame.columns):
        north, east = (frame[c].to_numpy(float) for c in VELOCITY_COLUMNS[:2])
        own = np.isfinite(north) & np.isfinite(east)
        s_own, c_own = speed_course(north, east)
        speed, course = np.where(own, s_own, speed), np.where(own, c_own, course)
    return speed, course


def _fields_or_empty(values: np.ndarray, fmt: str) -> list[str]:
    """Each value formatted with ``fmt``, or "" where it is NaN."""
    return ["" if not np.isfinite(v) else format(v, fmt) for v in values.tolist()]


def nmea_lines(frame: pd.DataFrame) -> list[str]:
    """Two sentences (GGA, RMC) per row of ``frame`` (gps_millis, lat_deg, lon_deg, height_m[, n_sats])."""
    iso = np.datetime_as_string(gps_ms_to_unix_ms(frame["gps_millis"].to_numpy()).astype("datetime64[ms]"),
                                unit="ms").tolist()                    # 'YYYY-MM-DDTHH:MM:SS.mmm', UTC
    lat, ns = _angle(frame["lat_deg"].to_numpy(float), 2, "NS")
    lon, ew = _angle(frame["lon_deg"].to_numpy(float), 3, "EW")
    n_sats = (frame["n_sats"] if "n_sats" in frame else pd.Series(0, index=frame.index)).astype(int).tolist()
    speed, course = rmc_velocity(frame)
    sog, cog = _fields_or_empty(speed * KNOTS_PER_MPS, ".3f"), _fields_or_empty(course, ".2f")
    bridged = bridged_rows(frame)
    bodies = []
    for t, la, n, lo, e, h, k, v, c, dr in zip(iso, lat, ns.tolist(), lon, ew.tolist(), frame["height_m"].tolist(),
                                               n_sats, sog, cog, bridged.tolist()):
        hms, dmy = t[11:13] + t[14:16] + t[17:23], t[8:10] + t[5:7] + t[2:4]
        pos = f"{la},{n},{lo},{e}"
        bodies += [f"{TALKER}GGA,{hms},{pos},{6 if dr else 1},{k:02d},,{h:.3f},M,0.000,M,,",
                   f"{TALKER}RMC,{hms},A,{pos},{v},{c},{dmy},,,{'E' if dr else 'A'}"]
    return sentences(bodies)


def write_nmea(frame: pd.DataFrame, path: Path, name: str = "") -> Path:
    """Write :func:`nmea_lines` with CR LF line ends (NMEA 0183's)."""
    with open(path, "w", newline="\r\n", encoding="ascii") as fh:
        fh.write("\n".join(nmea_lines(frame)) + ("\n" if len(frame) else ""))
    return path
