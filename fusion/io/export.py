"""``gnssfuse run --export``: the estimates in the formats a user opens elsewhere.

Each writer takes the frame of :func:`fusion.io.estimates.export_frame` (one row per solved epoch:
gps_millis, lat_deg, lon_deg, height_m (WGS84 ellipsoidal), n_sats, the NED sigmas and
covariances when the mode has them, and the graph's NED velocity where Doppler measures it), a path and a
name, and writes ``OUT/estimates.<format>``.
Adding a format is one writer module and one line here.
"""
from __future__ import annotations

import importlib
from pathlib import Path

import pandas as pd

from fusion.errors import GnssfuseError

#: format -> "module:function" (imported only when asked for: gpxpy is not needed otherwise)
WRITERS: dict[str, str] = {
    "gpx": "fusion.io.gpx:write_gpx",
    "kml": "fusion.io.kml:write_kml",
    "nmea": "fusion.io.nmea_write:write_nmea",
    "pos": "fusion.io.rtklib_pos:write_pos",
}


def parse_formats(text: str) -> tuple[str, ...]:
    """``"gpx,kml"`` -> ("gpx", "kml"); an unknown name is an error naming ``--export``."""
    names = tuple(dict.fromkeys(s.strip().lower() for s in text.split(",") if s.strip()))
    bad = [n for n in names if n not in WRITERS]
    if bad or not names:
        raise GnssfuseError(f"--export {text!r}: choose from {','.join(WRITERS)} (comma-separated)")
    return names


def write_exports(frame: pd.DataFrame, out_dir: Path, formats: tuple[str, ...], name: str) -> list[Path]:
    """``out_dir/estimates.<format>`` for each format; the paths written."""
    paths = []
    for fmt in formats:
        module, func = WRITERS[fmt].split(":")
        write = getattr(importlib.import_module(module), func)
        paths.append(write(frame, Path(out_dir) / f"estimates.{fmt}", name))
    return paths
