"""Estimates in RTKLIB's solution format (``.pos``, as ``rnx2rtkp`` writes it with its defaults), so
RTKLIB's plotting and comparison tools (rtkplot, pos2kml, ...) and every reader of that format open it.

Columns: GPS week and time of week, latitude, longitude (deg), WGS84 ellipsoidal height (m), Q
(solution quality: 5 = single, which every gnssfuse mode is: no ambiguity is fixed; 7 = dead reckoning, RTKLIB's
own code, at the graph's ``bridged`` epochs, which the motion model carried), ns (satellites
measured at the epoch), then sdn, sde, sdu and the signed square roots of the NE, EU and UN
covariances (RTKLIB's convention), age and ratio. Where the mode gives no covariance the
standard deviations are written as 0, as RTKLIB does for an unknown value.

Where the graph's Doppler measured a velocity (the ``vel_*`` columns of ``estimates.csv``), the columns that
``rnx2rtkp`` adds with ``out-outvel = on`` follow: vn, ve, vu [m/s], sdvn, sdve, sdvu and the signed square
roots of the NE, EU and UN velocity covariances. An epoch without one gets zeros there, RTKLIB's unknown.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from fusion.gpstime import format_gps_ms
from fusion.io.estimates import (COVARIANCE_COLUMNS, SIGMA_COLUMNS, VELOCITY_COLUMNS, VELOCITY_COVARIANCE_COLUMNS,
                                 VELOCITY_SIGMA_COLUMNS, bridged_rows)

WEEK_MS = 604_800_000
Q_SINGLE = 5
Q_DEAD_RECKONING = 7
HEADER = ("%  GPST          latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)"
          "  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio")
VELOCITY_HEADER = "    vn(m/s)    ve(m/s)    vu(m/s)      sdvn     sdve     sdvu    sdvne    sdveu    sdvun"


def _signed_sqrt(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.sqrt(np.abs(x))


def enu_sigmas(frame: pd.DataFrame, sigmas: list[str], covariances: list[str]) -> np.ndarray:
    """(N, 6) the north, east, up sigmas and the signed square roots of the NE, EU, UN covariances (RTKLIB's
    order) from the frame's NED ``sigmas`` and NE / ND / ED ``covariances`` columns (up = -down flips the sign
    of the EU and UN terms); 0 where unknown."""
    out = np.zeros((len(frame), 6))
    if sigmas[0] in frame:
        out[:, :3] = frame[sigmas].to_numpy(float)
    if covariances[0] in frame:
        ne, nd, ed = frame[covariances].to_numpy(float).T
        out[:, 3:] = _signed_sqrt(np.stack([ne, -ed, -nd], axis=1))
    return np.where(np.isfinite(out), out, 0.0)


def pos_sigmas(frame: pd.DataFrame) -> np.ndarray:
    """(N, 6) sdn, sde, sdu, sdne, sdeu, sdun [m] (:func:`enu_sigmas` of the position)."""
    return enu_sigmas(frame, SIGMA_COLUMNS, COVARIANCE_COLUMNS)


def velocity_fields(frame: pd.DataFrame) -> list[str]:
    """One string per row: vn, ve, vu [m/s] and their :func:`enu_sigmas` in ``rnx2rtkp``'s widths (zeros where
    the epoch has no velocity); none without :data:`VELOCITY_COLUMNS`."""
    if VELOCITY_COLUMNS[0] not in frame:
        return [""] * len(frame)
    vel = frame[VELOCITY_COLUMNS].to_numpy(float) * np.array([1.0, 1.0, -1.0])
    vel = np.where(np.isfinite(vel), vel, 0.0)
    sig = enu_sigmas(frame, VELOCITY_SIGMA_COLUMNS, VELOCITY_COVARIANCE_COLUMNS)
    return [f" {v[0]:10.5f} {v[1]:10.5f} {v[2]:10.5f} {s[0]:9.5f}" + "".join(f" {x:8.5f}" for x in s[1:])
            for v, s in zip(vel.tolist(), sig.tolist())]


def pos_lines(frame: pd.DataFrame, name: str = "") -> list[str]:
    """The header comments and one line per row of ``frame`` (gps_millis, lat_deg, lon_deg, height_m
    [, n_sats, sigma_*_m, cov_*_m2, vel_*_mps, sigma_v*_mps, cov_v*_m2s2])."""
    t = frame["gps_millis"].to_numpy(np.int64)
    lines = ["% program   : gnssfuse", f"% inp file  : {name}"]
    if len(t):
        lines += [f"% obs start : {format_gps_ms(int(t[0]))} GPST", f"% obs end   : {format_gps_ms(int(t[-1]))} GPST"]
    lines += ["%", "% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,7:dr,"
              "ns=# of satellites)", HEADER + (VELOCITY_HEADER if VELOCITY_COLUMNS[0] in frame else "")]
    n_sats = frame["n_sats"].to_numpy() if "n_sats" in frame else np.zeros(len(frame), int)
    sig = pos_sigmas(frame)
    quality = np.where(bridged_rows(frame), Q_DEAD_RECKONING, Q_SINGLE)
    rows = zip(t // WEEK_MS, (t % WEEK_MS) / 1000.0, frame["lat_deg"].tolist(), frame["lon_deg"].tolist(),
               frame["height_m"].tolist(), quality.tolist(), n_sats.tolist(), sig.tolist(), velocity_fields(frame))
    for week, tow, lat, lon, h, q, ns, s, vel in rows:
        lines.append(f"{week:4d} {tow:10.3f} {lat:14.9f} {lon:14.9f} {h:10.4f} {q:3d} {ns:3d}"
                     + "".join(f" {v:8.4f}" for v in s) + "   0.00    0.0" + vel)
    return lines


def read_pos_at(path: Path, t_ms: np.ndarray) -> np.ndarray:
    """(E, k) the numeric columns after the time (latitude, longitude, height, Q, ns, sdn, ...) of a .pos file in
    GPS week / time-of-week form, as this module or ``rnx2rtkp`` writes it, at the epochs ``t_ms`` (E,) [GPS ms,
    increasing] within 1 ms of a line's time; NaN rows where none is."""
    rows = _pos_rows(Path(path))
    out = np.full((t_ms.size, max(rows.shape[1] - 2, 0)), np.nan)
    if not len(rows) or not t_ms.size:
        return out
    t = np.round(rows[:, 0] * WEEK_MS + rows[:, 1] * 1000).astype(np.int64)
    idx = np.clip(np.searchsorted(t_ms, t), 0, t_ms.size - 1)
    ok = np.abs(t_ms[idx] - t) <= 1
    out[idx[ok]] = rows[ok, 2:]
    return out


def _pos_rows(path: Path) -> np.ndarray:
    """(N, k) the data lines of a .pos file as numbers."""
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("%")]
    return np.array(lines, float) if lines else np.zeros((0, 2))


def write_pos(frame: pd.DataFrame, path: Path, name: str = "") -> Path:
    path.write_text("\n".join(pos_lines(frame, name)) + "\n")
    return path
