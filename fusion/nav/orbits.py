"""Satellite orbits and clocks from Keplerian broadcast ephemerides: GPS and QZSS (IS-GPS-200,
Table 20-IV; IS-QZSS-PNT), Galileo (OS SIS ICD 5.1.1) and BeiDou MEO/IGSO/GEO (BDS-SIS-ICD 5.2.4).
GLONASS state vectors are in :mod:`fusion.nav.glonass`.

Everything is vectorised over arbitrary shapes of (epoch, satellite) queries. Times are split
into an integer GPS millisecond part ``t_ms`` and a float offset ``dt_s`` so that differences
to ``toe`` / ``toc`` stay exact to well below a nanosecond (a float64 second count since 1980
would only resolve ~0.2 us, i.e. ~70 m of light travel).
"""
from __future__ import annotations

import numpy as np

from fusion.errors import DataError
from fusion.geometry import C_LIGHT, OMEGA_E, line_of_sight
from fusion.io.nav_records import GpsNav

#: WGS-84 gravitational constant used by GPS [m^3/s^2] (IS-GPS-200).
MU_GPS = 3.986005e14
#: Relativistic clock correction constant F [s/sqrt(m)] (IS-GPS-200 20.3.3.3.3.1); Galileo's and
#: BeiDou's (-2 sqrt(mu) / c^2 with their mu) differ by 1e-7 relative, below a picosecond.
F_REL = -4.442807633e-10
#: Gravitational constant and Earth rotation rate per Android constellation type:
#: GPS 1, QZSS 4 (IS-GPS-200); BeiDou 5 (CGCS2000); Galileo 6 (GTRF).
_MU = {1: MU_GPS, 4: MU_GPS, 5: 3.986004418e14, 6: 3.986004418e14}
_OMEGA = {1: OMEGA_E, 4: OMEGA_E, 5: 7.292115e-5, 6: 7.2921151467e-5}


_POS_KEYS = ("sqrt_a", "delta_n", "e", "m0", "omega", "cus", "cuc", "crs", "crc", "i0", "cis", "cic",
             "idot", "omega_dot", "omega0", "toe_sow")


def orbit_constants(nav: GpsNav) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per record (N,): gravitational constant, Earth rotation rate, BeiDou GEO flag (C01-C05 and
    C59-C63 fly geostationary orbits whose ephemeris is rotated differently)."""
    ctype = nav.sat_id // 1000
    mu = np.full(len(nav), MU_GPS)
    we = np.full(len(nav), OMEGA_E)
    for c in np.unique(ctype):
        mu[ctype == c], we[ctype == c] = _MU.get(int(c), MU_GPS), _OMEGA.get(int(c), OMEGA_E)
    geo = (ctype == 5) & ((nav.prn <= 5) | (nav.prn >= 59))
    return mu, we, geo


def select_ephemeris(nav: GpsNav, prn: np.ndarray, t_ms: np.ndarray, *, by_sat_id: bool = False,
                     msg: np.ndarray | int = 0) -> np.ndarray:
    """Index of the record with the nearest ``toe`` whose fit interval covers each query.

    prn: (...) int GPS PRNs, or ``sat_id`` values with ``by_sat_id``; t_ms: (...) GPS ms;
    msg: (...) or scalar message wanted (:class:`GpsNav`; 1 = Galileo F/NAV) (broadcast
    together). Returns (...) int index into ``nav`` or -1 where no healthy record of that
    satellite and message is valid at that time.
    """
    prn = np.asarray(prn, np.int64)
    if not by_sat_id:
        prn = prn + 1000
    prn, t_ms, msg = np.broadcast_arrays(prn, np.asarray(t_ms, np.int64), np.asarray(msg, np.int64))
    if len(nav) == 0:
        return np.full(prn.shape, -1)
    # nav is sorted by (sat_id, msg, toe): one searchsorted on a combined key finds both neighbours.
    big = np.int64(10**13)  # > any GPS ms count this century
    keys = (nav.sat_id * 2 + nav.msg) * big + nav.toe_ms
    q = (prn * 2 + msg) * big + t_ms
    right = np.searchsorted(keys, q, side="left")
    n = len(nav)
    cand = np.stack([np.clip(right - 1, 0, n - 1), np.clip(right, 0, n - 1)], axis=0)
    ok = (nav.sat_id[cand] == prn) & (nav.msg[cand] == msg) & (nav.valid_from_ms[cand] <= t_ms) \
        & (t_ms <= nav.valid_to_ms[cand])
    dist = np.where(ok, np.abs(nav.toe_ms[cand] - t_ms), np.iinfo(np.int64).max)
    pick = np.argmin(dist, axis=0)
    idx = np.take_along_axis(cand, pick[None], axis=0)[0]
    return np.where(ok.any(axis=0), idx, -1)


def _kepler(m: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Eccentric anomaly from mean anomaly by Newton from E = M.

    The error squares each step (times ~e/2): for GPS (e < 0.05) three steps reach 1e-20 rad.
    """
    ea = m.copy()
    for _ in range(3):
        ea = ea - (ea - e * np.sin(ea) - m) / (1.0 - e * np.cos(ea))
    return ea


def sat_state(nav: GpsNav, idx: np.ndarray, t_ms: np.ndarray, dt_s: np.ndarray | float = 0.0,
              *, position_only: bool = False) -> dict[str, np.ndarray]:
    """Satellite ECEF position, velocity and clock at GPS time ``t_ms / 1000 + dt_s``.

    idx: (...) record indices from :func:`select_ephemeris` (must be >= 0).
    t_ms: (...) int GPS ms; dt_s: (...) float seconds added to it (e.g. minus the flight time).
    Returns dict with ``pos`` (..., 3) [m] and ``vel`` (..., 3) [m/s] in the ECEF frame *at
    that time*, ``clock_s`` (...) satellite clock offset dt_sv [s] (af0/af1/af2 + relativistic
    - the L1-class group delay ``tgd``: GPS/QZSS TGD, Galileo BGD(E1,E5b), BeiDou TGD1),
    ``clock_rel_s`` (...) the relativistic part alone, ``clock_drift`` (...) [s/s]. With
    ``position_only`` only ``pos`` is computed. Records of every Keplerian system (GPS, QZSS,
    Galileo, BeiDou MEO/IGSO/GEO) are handled, each with its own constants (:func:`orbit_constants`).
    """
    idx = np.asarray(idx)
    if np.any(idx < 0):
        raise DataError(f"{nav.source}: satellite state requested without a valid ephemeris")
    need = _POS_KEYS if position_only else nav.params.keys()
    p = {k: nav.params[k][idx] for k in need}
    mu, we, geo = (a[idx] for a in orbit_constants(nav))
    t_ms = np.asarray(t_ms, np.int64)
    tk = (t_ms - nav.toe_ms[idx]) * 1e-3 + dt_s
    orb = _orbit(p, tk, mu, we)
    pos = orb["pos"]
    if geo.any():
        pos = np.where(geo[..., None], _geo_position(p, tk, mu, we), pos)
    if position_only:
        return {"pos": pos}
    vel = _orbit_velocity(p, orb, we)
    if geo.any():
        # BeiDou GEO: the rotation chain has no tidy derivative; a 1 s central difference of
        # the position is exact to ~1e-6 m/s for a near-stationary orbit.
        dv = (_geo_position(p, tk + 0.5, mu, we) - _geo_position(p, tk - 0.5, mu, we))
        vel = np.where(geo[..., None], dv, vel)
    tc = (t_ms - nav.toc_ms[idx]) * 1e-3 + dt_s
    clock, rel, drift = _clock(p, tc, orb)
    return {"pos": pos, "vel": vel, "clock_s": clock, "clock_rel_s": rel, "clock_drift": drift}


def _orbit(p: dict[str, np.ndarray], tk: np.ndarray, mu: np.ndarray, we: np.ndarray,
           inertial: bool = False) -> dict[str, np.ndarray]:
    """Keplerian orbit with harmonic corrections (IS-GPS-200 Table 20-IV), (...)-shaped inputs.

    ``inertial``: omit the Earth-rotation terms in the node longitude (BeiDou GEO's first step).
    Returns the intermediate quantities the velocity and clock need, and ``pos`` (..., 3).
    """
    a = p["sqrt_a"] ** 2
    n = np.sqrt(mu / a**3) + p["delta_n"]
    e = p["e"]
    ea = _kepler(p["m0"] + n * tk, e)
    sin_e, cos_e = np.sin(ea), np.cos(ea)
    one_m_ecos = 1.0 - e * cos_e
    sq = np.sqrt(1.0 - e * e)
    phi = np.arctan2(sq * sin_e, cos_e - e) + p["omega"]
    s2, c2 = np.sin(2 * phi), np.cos(2 * phi)
    u = phi + p["cus"] * s2 + p["cuc"] * c2
    r = a * one_m_ecos + p["crs"] * s2 + p["crc"] * c2
    inc = p["i0"] + p["cis"] * s2 + p["cic"] * c2 + p["idot"] * tk
    om_dot = p["omega_dot"] if inertial else p["omega_dot"] - we
    om = p["omega0"] + om_dot * tk - we * p["toe_sow"]
    xp, yp = r * np.cos(u), r * np.sin(u)
    so, co, si, ci = np.sin(om), np.cos(om), np.sin(inc), np.cos(inc)
    x = xp * co - yp * ci * so
    y = xp * so + yp * ci * co
    z = yp * si
    return dict(a=a, n=n, e=e, sin_e=sin_e, cos_e=cos_e, one_m_ecos=one_m_ecos, sq=sq, s2=s2, c2=c2,
                u=u, xp=xp, yp=yp, so=so, co=co, si=si, ci=ci, om_dot=om_dot, x=x, y=y,
                pos=np.stack([x, y, z], axis=-1))


def _orbit_velocity(p: dict[str, np.ndarray], o: dict[str, np.ndarray], we: np.ndarray) -> np.ndarray:
    """(..., 3) ECEF velocity: analytic time derivative of :func:`_orbit`'s expressions."""
    ea_dot = o["n"] / o["one_m_ecos"]
    phi_dot = o["sq"] * ea_dot / o["one_m_ecos"]
    s2, c2 = o["s2"], o["c2"]
    u_dot = phi_dot * (1.0 + 2.0 * (p["cus"] * c2 - p["cuc"] * s2))
    r_dot = o["a"] * o["e"] * o["sin_e"] * ea_dot + 2.0 * phi_dot * (p["crs"] * c2 - p["crc"] * s2)
    i_dot = p["idot"] + 2.0 * phi_dot * (p["cis"] * c2 - p["cic"] * s2)
    xp, yp, so, co, si, ci = o["xp"], o["yp"], o["so"], o["co"], o["si"], o["ci"]
    xp_dot = r_dot * np.cos(o["u"]) - yp * u_dot
    yp_dot = r_dot * np.sin(o["u"]) + xp * u_dot
    vx = xp_dot * co - yp_dot * ci * so + yp * si * so * i_dot - o["om_dot"] * o["y"]
    vy = xp_dot * so + yp_dot * ci * co - yp * si * co * i_dot + o["om_dot"] * o["x"]
    vz = yp_dot * si + yp * ci * i_dot
    return np.stack([vx, vy, vz], axis=-1)


def _geo_position(p: dict[str, np.ndarray], tk: np.ndarray, mu: np.ndarray, we: np.ndarray) -> np.ndarray:
    """(..., 3) BeiDou GEO ECEF position (BDS-SIS-ICD 5.2.4.12): the orbit in a frame that does
    not turn with the Earth, tilted by -5 degrees about X, then turned by the Earth's rotation."""
    g = _orbit(p, tk, mu, we, inertial=True)["pos"]
    c5, s5 = np.cos(np.radians(-5.0)), np.sin(np.radians(-5.0))
    y = c5 * g[..., 1] + s5 * g[..., 2]
    z = -s5 * g[..., 1] + c5 * g[..., 2]
    ang = we * tk
    ca, sa = np.cos(ang), np.sin(ang)
    return np.stack([ca * g[..., 0] + sa * y, -sa * g[..., 0] + ca * y, z], axis=-1)


def _clock(p: dict[str, np.ndarray], tc: np.ndarray, o: dict[str, np.ndarray]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clock offset (polynomial + relativistic - L1 group delay) [s], relativistic term [s] and
    drift [s/s]; tc: (...) seconds since toc."""
    ea_dot = o["n"] / o["one_m_ecos"]
    rel = F_REL * o["e"] * p["sqrt_a"] * o["sin_e"]
    clock = p["af0"] + p["af1"] * tc + p["af2"] * tc**2 + rel - p["tgd"]
    drift = p["af1"] + 2.0 * p["af2"] * tc + F_REL * o["e"] * p["sqrt_a"] * o["cos_e"] * ea_dot
    return clock, rel, drift


def transmit_states(nav: GpsNav, idx: np.ndarray, rx_ecef: np.ndarray, t_rx_ms: np.ndarray,
                    tau0: np.ndarray | float = 0.075, n_iter: int = 2
                    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Satellite states at the true transmit time of signals received at ``t_rx_ms``.

    Iterates the flight time tau = |R(OMEGA_E tau) sat(t_rx - tau) - rx| / c. Each pass shrinks
    the error by about |range rate| / c ~ 1e-5, so from the default 75 ms guess two passes are
    at the micrometre level, and one pass suffices from a guess good to a few metres.

    Flat inputs: idx (N,) record indices (>= 0); rx_ecef (N, 3) receiver at receive time;
    t_rx_ms (N,) int GPS ms of reception; tau0 (N,) or scalar first guess [s].
    Returns (states with (N[,3]) arrays as :func:`sat_state`, tau (N,) [s]).
    """
    t = np.asarray(t_rx_ms, np.int64)
    tau = np.broadcast_to(np.asarray(tau0, float), np.shape(idx))
    for _ in range(n_iter):
        st = sat_state(nav, idx, t, -tau, position_only=True)
        tau = line_of_sight(st["pos"][:, None, :], rx_ecef)[0][:, 0] / C_LIGHT
    return sat_state(nav, idx, t, -tau), tau
