"""Estimates as KML for Google Earth and GIS tools: the track as a line string, and one placemark per
solved epoch with its time and, where the mode gives one, the 1-sigma horizontal error.

Written as text from a template (the document is a handful of element kinds; only the name needs
escaping): simplekml took 9.8 s for 100k placemarks and ElementTree 1.1 s, the template a fraction
of that. Geometries use KML's default ``clampToGround``: viewers drape the track on their terrain,
so the height written (WGS84 ellipsoidal; KML's own absolute heights are above the EGM96 geoid) is
informative only.
"""
from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np
import pandas as pd

from fusion.gpstime import GPS_EPOCH_UNIX_MS, gps_ms_to_unix_ms

HEAD = """<?xml version="1.0" encoding="UTF-8"?>
<kml xmlns="http://www.opengis.net/kml/2.2">
<Document>
<name>{name}</name>
<description>gnssfuse estimates; heights WGS84 ellipsoidal [m]; placemark names in GPS time</description>
<Style id="epoch"><IconStyle><scale>0.4</scale><Icon><href>http://maps.google.com/mapfiles/kml/shapes/shaded_dot.png</href></Icon></IconStyle><LabelStyle><scale>0</scale></LabelStyle></Style>
<Placemark><name>{name} track</name><LineString><coordinates>{line}</coordinates></LineString></Placemark>
<Folder><name>epochs</name>
"""
MARK = ("<Placemark><name>{gps}</name><TimeStamp><when>{utc}Z</when></TimeStamp><description>GPS time {gps}"
        "{sigma}</description><styleUrl>#epoch</styleUrl><Point><coordinates>{c}</coordinates></Point></Placemark>\n")
TAIL = "</Folder>\n</Document>\n</kml>\n"


def horizontal_sigma(frame: pd.DataFrame) -> np.ndarray | None:
    """(N,) 1-sigma horizontal error [m], sqrt(sigma_n^2 + sigma_e^2); None when the frame has none."""
    if "sigma_n_m" not in frame:
        return None
    return np.hypot(frame["sigma_n_m"].to_numpy(float), frame["sigma_e_m"].to_numpy(float))


def iso_ms(unix_ms: np.ndarray) -> np.ndarray:
    """(N,) ms since 1970 (UTC, or GPS time counted from the GPS epoch) -> 'YYYY-MM-DDTHH:MM:SS.mmm'."""
    return np.datetime_as_string(np.asarray(unix_ms, np.int64).astype("datetime64[ms]"), unit="ms")


def write_kml(frame: pd.DataFrame, path: Path, name: str) -> Path:
    """``Document`` with a ``LineString`` track and a ``Folder`` of per-epoch ``Point`` placemarks
    (frame: gps_millis, lat_deg, lon_deg, height_m[, sigma_n_m, sigma_e_m])."""
    coords = [f"{a:.9f},{b:.9f},{c:.3f}" for a, b, c in
              zip(frame["lon_deg"].tolist(), frame["lat_deg"].tolist(), frame["height_m"].tolist())]
    t = frame["gps_millis"].to_numpy(np.int64)
    gps = np.char.replace(iso_ms(t + GPS_EPOCH_UNIX_MS), "T", " ")      # GPS time (no leap seconds)
    utc = iso_ms(gps_ms_to_unix_ms(t))                                  # KML's TimeStamp (time slider)
    sigma = horizontal_sigma(frame)
    sig_text = ([f"; 1-sigma horizontal error {s:.2f} m" if np.isfinite(s) else "" for s in sigma.tolist()]
                if sigma is not None else [""] * len(frame))
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(HEAD.format(name=escape(name), line=" ".join(coords)))
        fh.writelines(MARK.format(gps=g, utc=u, sigma=s, c=c) for g, u, s, c in zip(gps, utc, sig_text, coords))
        fh.write(TAIL)
    return path
