"""Ionospheric and tropospheric delays for single-frequency pseudoranges.

Ionosphere: the GPS broadcast Klobuchar model (IS-GPS-200 20.3.3.5.2.5) from the navigation
header's alpha/beta, computed for L1 and scaled by ``(f_L1 / f)^2`` to each carrier (the delay
is dispersive: BeiDou's own BDSA/BDSB and Galileo's NeQuick are not used; Klobuchar removes
about half of the delay on any of them).

Troposphere: Saastamoinen's zenith delay (hydrostatic + wet) for a standard atmosphere at the
receiver's height (pressure from the 1976 standard atmosphere, 15 degC at sea level with the
standard lapse rate, 70 % relative humidity, as RTKLIB's ``tropmodel``), mapped with
``1.001 / sqrt(0.002001 + sin^2 el)`` (the simple mapping of the ESA GNSS Data Processing book,
A.2; within ~1 % of Niell's above 10 degrees, with no seasonal or latitude tables).
"""
from __future__ import annotations

import numpy as np

from fusion.geometry import C_LIGHT

F_L1 = 1575.42e6


def klobuchar_l1(klob: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray, az_deg: np.ndarray,
                 el_deg: np.ndarray, tow_s: np.ndarray) -> np.ndarray:
    """L1 ionospheric delay [m].

    klob: (8,) alpha0..3 [s, s/sc, s/sc^2, s/sc^3], beta0..3 [s, ...]. lat_deg, lon_deg: receiver
    (...); az_deg, el_deg: (...) satellite azimuth / elevation; tow_s: (...) GPS time of week [s].
    All broadcast together; returns (...).
    """
    alpha, beta = np.asarray(klob[:4], float), np.asarray(klob[4:], float)
    e = np.asarray(el_deg, float) / 180.0                         # semicircles
    az = np.radians(az_deg)
    psi = 0.0137 / (e + 0.11) - 0.022                             # earth angle [sc]
    phi_i = np.clip(np.asarray(lat_deg) / 180.0 + psi * np.cos(az), -0.416, 0.416)
    lam_i = np.asarray(lon_deg) / 180.0 + psi * np.sin(az) / np.cos(phi_i * np.pi)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * np.pi)      # geomagnetic latitude [sc]
    t = np.mod(43200.0 * lam_i + np.asarray(tow_s, float), 86400.0)
    f = 1.0 + 16.0 * (0.53 - e) ** 3                              # obliquity
    amp = np.maximum(np.polyval(alpha[::-1], phi_m), 0.0)
    per = np.maximum(np.polyval(beta[::-1], phi_m), 72000.0)
    x = 2.0 * np.pi * (t - 50400.0) / per
    night = 5e-9
    day = amp * (1.0 - x**2 / 2.0 + x**4 / 24.0)
    return C_LIGHT * f * (night + np.where(np.abs(x) < 1.57, day, 0.0))


def iono_scale(carrier_hz: np.ndarray) -> np.ndarray:
    """(f_L1 / f)^2 per carrier frequency (...) [Hz]: the L1 delay -> the delay on that carrier."""
    return (F_L1 / np.asarray(carrier_hz, float)) ** 2


def saastamoinen_zenith(lat_deg: np.ndarray, height_m: np.ndarray, humidity: float = 0.7) -> np.ndarray:
    """Total zenith tropospheric delay [m] for a standard atmosphere; (...) inputs -> (...)."""
    h = np.clip(np.asarray(height_m, float), 0.0, 10_000.0)      # phones report silly heights at times
    pres = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568              # hPa
    temp = 15.0 - 6.5e-3 * h + 273.16                             # K
    e = 6.108 * humidity * np.exp((17.15 * temp - 4684.0) / (temp - 38.45))
    lat = np.radians(lat_deg)
    hyd = 0.0022768 * pres / (1.0 - 0.00266 * np.cos(2.0 * lat) - 0.00028 * h / 1e3)
    wet = 0.002277 * (1255.0 / temp + 0.05) * e
    return hyd + wet


def tropo_mapping(el_deg: np.ndarray) -> np.ndarray:
    """Slant / zenith ratio (...) at elevation (...) [deg]; finite down to 0 degrees."""
    s = np.sin(np.radians(np.maximum(el_deg, 0.0)))
    return 1.001 / np.sqrt(0.002001 + s * s)


def tropo_delay(lat_deg: np.ndarray, height_m: np.ndarray, el_deg: np.ndarray) -> np.ndarray:
    """Slant tropospheric delay [m]: receiver (...) lat/height, satellite elevation (...)."""
    return saastamoinen_zenith(lat_deg, height_m) * tropo_mapping(el_deg)
