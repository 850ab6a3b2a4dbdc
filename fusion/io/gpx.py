"""Estimates as a GPX 1.1 track (one point per solved epoch), for map tools and GPS software.

Written with gpxpy (well kept, no dependencies, the reader most Python GPS tools use): 1.2 s for
100k points. ``<ele>`` is the WGS84 *ellipsoidal* height (the file's description says so): GPX does
not name its height datum and many tools assume mean sea level, which we cannot give without a
geoid model.
"""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import gpxpy.gpx
import pandas as pd

from fusion.gpstime import gps_ms_to_unix_ms

DESCRIPTION = "gnssfuse estimates; ele = WGS84 ellipsoidal height [m]; time = UTC"


def write_gpx(frame: pd.DataFrame, path: Path, name: str) -> Path:
    """One track, one segment, one point per row of ``frame`` (gps_millis, lat_deg, lon_deg, height_m)."""
    gpx = gpxpy.gpx.GPX()
    gpx.creator = "gnssfuse"
    gpx.name, gpx.description = name, DESCRIPTION
    track = gpxpy.gpx.GPXTrack(name=name, description=DESCRIPTION)
    segment = gpxpy.gpx.GPXTrackSegment()
    track.segments.append(segment)
    gpx.tracks.append(track)
    unix_s = gps_ms_to_unix_ms(frame["gps_millis"].to_numpy()) / 1000.0
    segment.points.extend(
        gpxpy.gpx.GPXTrackPoint(lat, lon, elevation=h, time=datetime.fromtimestamp(t, timezone.utc))
        for lat, lon, h, t in zip(frame["lat_deg"].tolist(), frame["lon_deg"].tolist(),
                                  frame["height_m"].tolist(), unix_s.tolist()))
    path.write_text(gpx.to_xml(version="1.1"))
    return path
