"""Frames and line-of-sight geometry shared by WLS, features, the simulator and the graph.

All functions are vectorised over arbitrary leading dimensions ``(...)``. Frame names follow
pymap3d: ``ecef``, ``ned`` (north, east, down), ``geodetic`` (degrees, ellipsoidal height).
"""
from __future__ import annotations

import numpy as np
import pymap3d

#: Speed of light [m/s] (IS-GPS-200).
C_LIGHT = 299_792_458.0
#: WGS-84 Earth rotation rate [rad/s] (IS-GPS-200).
OMEGA_E = 7.2921151467e-5


def ecef2geodetic(xyz: np.ndarray) -> np.ndarray:
    """ECEF (..., 3) [m] -> (..., 3) latitude [deg], longitude [deg], ellipsoidal height [m]."""
    xyz = np.asarray(xyz, float)
    lat, lon, h = pymap3d.ecef2geodetic(xyz[..., 0], xyz[..., 1], xyz[..., 2])
    return np.stack(np.broadcast_arrays(lat, lon, h), axis=-1)


def geodetic2ecef(llh: np.ndarray) -> np.ndarray:
    """(..., 3) latitude [deg], longitude [deg], ellipsoidal height [m] -> ECEF (..., 3) [m]."""
    llh = np.asarray(llh, float)
    x, y, z = pymap3d.geodetic2ecef(llh[..., 0], llh[..., 1], llh[..., 2])
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ned_rotation(ref_ecef: np.ndarray) -> np.ndarray:
    """Rotation matrices taking ECEF vectors into the NED frame at ``ref_ecef``.

    ref_ecef: (..., 3) ECEF [m]. Returns (..., 3, 3) R with ``v_ned = R @ v_ecef``.
    """
    llh = ecef2geodetic(ref_ecef)
    lat, lon = np.radians(llh[..., 0]), np.radians(llh[..., 1])
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl)
    return np.stack([
        np.stack([-sl * co, -sl * so, cl], axis=-1),
        np.stack([-so, co, zero], axis=-1),
        np.stack([-cl * co, -cl * so, -sl], axis=-1),
    ], axis=-2)


def ecef2ned_vec(v_ecef: np.ndarray, ref_ecef: np.ndarray) -> np.ndarray:
    """Rotate ECEF vectors (..., 3) into the NED frame at ``ref_ecef`` (broadcastable (..., 3))."""
    return np.einsum("...ij,...j->...i", ned_rotation(ref_ecef), v_ecef)


def ned2ecef_vec(v_ned: np.ndarray, ref_ecef: np.ndarray) -> np.ndarray:
    """Rotate NED vectors (..., 3) at ``ref_ecef`` back into ECEF (inverse of :func:`ecef2ned_vec`)."""
    return np.einsum("...ji,...j->...i", ned_rotation(ref_ecef), v_ned)


def ecef2ned_cov(cov_ecef: np.ndarray, ref_ecef: np.ndarray) -> np.ndarray:
    """Rotate ECEF covariances (..., 3, 3) into the NED frame at ``ref_ecef`` (..., 3): R C R^T."""
    R = ned_rotation(ref_ecef)
    return R @ cov_ecef @ np.swapaxes(R, -1, -2)


def ned2ecef_cov(cov_ned: np.ndarray, ref_ecef: np.ndarray) -> np.ndarray:
    """NED covariances (..., 3, 3) at ``ref_ecef`` (..., 3) -> ECEF: R^T C R (inverse of
    :func:`ecef2ned_cov`)."""
    R = ned_rotation(ref_ecef)
    return np.swapaxes(R, -1, -2) @ np.asarray(cov_ned, float) @ R


def ned2ecef_diag(var_ned: np.ndarray, ref_ecef: np.ndarray) -> np.ndarray:
    """(..., 3, 3) ECEF covariances of diagonal NED ones given by their variances (..., 3) at ``ref_ecef``
    (..., 3). A function of its own: three epochs' variances (3, 3) are not one covariance matrix."""
    return ned2ecef_cov(np.asarray(var_ned, float)[..., :, None] * np.eye(3), ref_ecef)


def norm3(v: np.ndarray) -> np.ndarray:
    """(...) Euclidean norms of float64 vectors (..., 3), bit for bit ``np.linalg.norm(v, axis=-1)``.

    numpy's norm squares and reduces along the last axis, in order: ``(x^2 + y^2) + z^2``. Written out
    on the three columns this is the same arithmetic, about six times faster on the (E, S, 3) arrays of
    every Gauss-Newton step (a reduction over a length-3 axis pays its loop overhead per vector);
    ``tests/test_geometry.py`` holds it to numpy's bits. Other dtypes go to numpy.
    """
    v = np.asarray(v)
    if v.dtype != np.float64 or v.shape[-1:] != (3,):
        return np.linalg.norm(v, axis=-1)
    sq = v * v
    return np.sqrt(sq[..., 0] + sq[..., 1] + sq[..., 2])


def sagnac_rotate(sat_pos: np.ndarray, rx_pos: np.ndarray) -> np.ndarray:
    """Rotate transmit-time satellite ECEF positions into the ECEF frame at receive time.

    The Earth turns by ``OMEGA_E * tau`` during the signal's flight time ``tau`` (~70 ms), which
    moves the satellite by ~100-140 m in the receive-time frame and changes the range by up to
    ~30 m; the angle is taken from the transmit-time range, whose error here is second order.

    sat_pos: (..., S, 3) ECEF at transmit time. rx_pos: (..., 3) receiver ECEF guess.
    Returns (..., S, 3).
    """
    theta = OMEGA_E * norm3(sat_pos - rx_pos[..., None, :]) / C_LIGHT
    c, s = np.cos(theta), np.sin(theta)
    x, y = sat_pos[..., 0], sat_pos[..., 1]
    out = np.empty(c.shape + (3,), np.result_type(c, sat_pos))   # what np.stack of the three made
    out[..., 0] = c * x + s * y
    out[..., 1] = -s * x + c * y
    out[..., 2] = sat_pos[..., 2]
    return out


def line_of_sight(sat_pos: np.ndarray, rx_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geometric ranges and unit vectors from receiver to satellites, Sagnac included.

    sat_pos: (..., S, 3) transmit-time ECEF. rx_pos: (..., 3).
    Returns ``(rng (..., S), los_ecef (..., S, 3))`` with ``los`` pointing receiver -> satellite.
    """
    rot = sagnac_rotate(sat_pos, rx_pos)
    d = rot - rx_pos[..., None, :]
    rng = norm3(d)
    return rng, d / np.maximum(rng, 1.0)[..., None]


def range_rate(sat_pos: np.ndarray, sat_vel: np.ndarray, rx_pos: np.ndarray, rx_vel: np.ndarray) -> np.ndarray:
    """Geometric range rate [m/s] with the first-order Earth-rotation term, the model of GTSAM's
    ``DopplerFactor`` (so simulated and fused Doppler agree to numerical precision).

    sat_pos, sat_vel: (..., S, 3) transmit-time ECEF [m], [m/s]. rx_pos, rx_vel: (..., 3).
    Returns (..., S): d/dt (|sat - rx| + OMEGA_E / c * (x_sat y_rx - y_sat x_rx)).
    """
    d = sat_pos - rx_pos[..., None, :]
    los = d / np.maximum(np.linalg.norm(d, axis=-1), 1.0)[..., None]
    dv = sat_vel - rx_vel[..., None, :]
    x, v = rx_pos[..., None, :], rx_vel[..., None, :]
    sagnac = (sat_vel[..., 0] * x[..., 1] + sat_pos[..., 0] * v[..., 1]
              - sat_vel[..., 1] * x[..., 0] - sat_pos[..., 1] * v[..., 0])
    return np.sum(los * dv, axis=-1) + OMEGA_E / C_LIGHT * sagnac


def elevation_azimuth(los_ecef: np.ndarray, rx_pos: np.ndarray,
                      R: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth [deg] of unit LOS vectors (..., S, 3) seen from ``rx_pos`` (..., 3).

    R: optional (..., 3, 3) ``ned_rotation(rx_pos)`` already computed by the caller (saves the
    geodetic conversion); ``rx_pos`` is then not used.
    """
    if R is None:
        R = ned_rotation(rx_pos)
    ned = np.einsum("...ij,...sj->...si", R, los_ecef)
    el = np.degrees(np.arcsin(np.clip(-ned[..., 2], -1.0, 1.0)))
    az = np.degrees(np.arctan2(ned[..., 1], ned[..., 0])) % 360.0
    return el, az
