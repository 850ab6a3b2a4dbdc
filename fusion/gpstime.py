"""GPS time <-> Unix (UTC) time in integer milliseconds, with the leap-second table.

GPS time started at 1980-01-06 00:00:00 UTC and has no leap seconds; UTC has gained 18 since
then (the last on 2017-01-01), so ``gps = unix - GPS_EPOCH_UNIX_MS + 1000 * leap(unix)``.
"""
from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np

#: Unix time [ms] of the GPS epoch, 1980-01-06 00:00:00 UTC.
GPS_EPOCH_UNIX_MS = 315_964_800_000
#: The GPS epoch as a naive calendar instant (GPS time scale).
GPS_EPOCH = datetime(1980, 1, 6)
DAY_MS = 86_400_000
#: Seconds in a GPS week.
WEEK_S = 604_800

# Unix ms at which GPS-UTC stepped to 1, 2, ... 18 s (IERS Bulletin C; none since 2017-01-01).
_LEAP_UNIX_MS = np.array([
    362_793_600, 394_329_600, 425_865_600, 489_024_000, 567_993_600, 631_152_000,
    662_688_000, 709_948_800, 741_484_800, 773_020_800, 820_454_400, 867_715_200,
    915_148_800, 1_136_073_600, 1_230_768_000, 1_341_100_800, 1_435_708_800, 1_483_228_800,
], np.int64) * 1000


def leap_seconds_at_unix_ms(unix_ms: np.ndarray) -> np.ndarray:
    """GPS - UTC in whole seconds at the given Unix times [ms] (any shape)."""
    return np.searchsorted(_LEAP_UNIX_MS, np.asarray(unix_ms), side="right")


def unix_ms_to_gps_ms(unix_ms: np.ndarray) -> np.ndarray:
    """Unix (UTC) milliseconds -> GPS milliseconds (int64, any shape)."""
    unix_ms = np.asarray(unix_ms, np.int64)
    return unix_ms - GPS_EPOCH_UNIX_MS + 1000 * leap_seconds_at_unix_ms(unix_ms)


def gps_ms_to_unix_ms(gps_ms: np.ndarray) -> np.ndarray:
    """GPS milliseconds -> Unix (UTC) milliseconds (int64, any shape); inverse of the above
    except inside the leap second itself, which Unix time cannot represent."""
    gps_ms = np.asarray(gps_ms, np.int64)
    approx = gps_ms + GPS_EPOCH_UNIX_MS
    # GPS-UTC at the UTC instant: try the leap count at approx - leap, which converges in one step.
    leap = leap_seconds_at_unix_ms(approx - 1000 * leap_seconds_at_unix_ms(approx))
    return approx - 1000 * leap


def gps_ms_from_calendar(year: int, month: int, day: int, hour: int, minute: int, sec: float) -> int:
    """Calendar date in GPS time -> GPS milliseconds since 1980-01-06 (no leap seconds)."""
    whole = int(sec)
    dt = datetime(year, month, day, hour, minute, whole) - GPS_EPOCH
    return int(dt.days) * DAY_MS + int(dt.seconds) * 1000 + int(round((sec - whole) * 1000))


def format_gps_ms(t_ms: int) -> str:
    """GPS milliseconds -> ``'YYYY-MM-DD HH:MM:SS[.ffffff]'`` in GPS time (for messages and names)."""
    return str(GPS_EPOCH + timedelta(milliseconds=int(t_ms)))
