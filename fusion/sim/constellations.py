"""Which satellites the simulator sees: broadcast records from a file where it has them, synthetic
Walker constellations where it has none.

Systems are named by RINEX letter: ``G`` GPS, ``R`` GLONASS, ``E`` Galileo, ``C`` BeiDou.
A requested system takes its records from the navigation file when the file carries any of that
system (real GLONASS state vectors included), and otherwise from a synthetic circular Walker
constellation (:data:`WALKER`), the nominal design of that system:

======  =====  ================  ===========  ==================
system  T/P/F  semi-major axis   inclination  svid
======  =====  ================  ===========  ==================
R       24/3/1 25,508 km         64.8 deg     1..24
E       24/3/1 29,600 km         56.0 deg     1..24
C       24/3/1 27,906 km         55.0 deg     19..42 (MEO only)
G       24/6/1 26,560 km         55.0 deg     1..24 (only when no GPS file is given)
======  =====  ================  ===========  ==================

A synthetic satellite flies a Keplerian circle whose plane is fixed in inertial space (no J2
precession, no harmonic terms); its node longitudes and mean anomalies at :data:`WALKER_EPOCH_MS`
follow the Walker delta pattern, its clock is a fixed offset and drift drawn once from a
system-specific seed (the same sky in every run). BeiDou's GEO and IGSO satellites, QZSS and SBAS
are not synthesised. Records are valid forever, so any date works.

The records are stored in :class:`fusion.io.nav_records.GpsNav` layout with ``sat_id`` =
``1000 * constellationType + svid`` (GLONASS type 3 takes GPS's constants, which is fine for a
synthetic orbit), so :func:`fusion.nav.orbits.sat_state` computes their states like real ones.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.errors import DataError
from fusion.gpstime import WEEK_S, gps_ms_from_calendar
from fusion.nav.glonass import GloNav, glonass_state, select_glonass
from fusion.nav.orbits import GpsNav, sat_state, select_ephemeris
from fusion.trace import SIGNALS

#: Android constellation type per system letter.
CTYPE = {"G": 1, "R": 3, "C": 5, "E": 6, "J": 4}
#: The signal each system's satellites are simulated on (index into SIGNALS by name).
PRIMARY_SIGNAL = {1: "GPS_L1", 3: "GLO_G1", 4: "QZS_J1", 5: "BDS_B1I", 6: "GAL_E1"}
#: The second-frequency signal of dual-frequency simulations, per constellation type.
SECOND_SIGNAL = {1: "GPS_L5", 4: "QZS_J5", 6: "GAL_E5A"}
#: GPS PRNs broadcasting L5 in 2021 (Block IIF and GPS III); synthetic GPS satellites: all.
GPS_L5_PRNS = (1, 3, 4, 6, 8, 9, 10, 14, 18, 23, 24, 25, 26, 27, 30, 32)
#: Synthetic constellations: (satellites, planes, phasing, semi-major axis [m], inclination [deg], first svid).
WALKER = {
    "G": (24, 6, 1, 26_560_000.0, 55.0, 1),
    "R": (24, 3, 1, 25_508_000.0, 64.8, 1),
    "E": (24, 3, 1, 29_600_000.0, 56.0, 1),
    "C": (24, 3, 1, 27_906_000.0, 55.0, 19),
}
#: Reference epoch of the synthetic orbits (2021-01-03 00:00 GPS time, a week start).
WALKER_EPOCH_MS = gps_ms_from_calendar(2021, 1, 3, 0, 0, 0.0)
_FOREVER_H = 2.0e5                      # fit interval of synthetic records [h] (~23 years)
_L5 = np.array([name in ("GPS_L5", "GAL_E5A", "QZS_J5") for name in SIGNALS])
_NAMES = {"GPS": "G", "GLO": "R", "GLONASS": "R", "GAL": "E", "GALILEO": "E", "BDS": "C", "BEIDOU": "C"}


def parse_systems(text: str | tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``"GPS,GLO,GAL,BDS"`` (or letters ``G,R,E,C``, or ``all``) -> sorted unique letters, GPS first.

    ValueError naming the unknown entry otherwise.
    """
    items = text.split(",") if isinstance(text, str) else list(text)
    out = set()
    for item in (s.strip().upper() for s in items):
        if item == "ALL":
            out |= set(WALKER)
        elif item in WALKER:
            out.add(item)
        elif item in _NAMES:
            out.add(_NAMES[item])
        else:
            raise ValueError(f"unknown constellation {item!r}; use GPS, GLO, GAL, BDS (or G, R, E, C, all)")
    if not out:
        raise ValueError("no constellation given")
    return tuple(sorted(out, key="GREC".index))


def walker_records(system: str) -> GpsNav:
    """The synthetic constellation of ``system`` (a letter of :data:`WALKER`) as Keplerian records."""
    T, P, F, a, inc, svid0 = WALKER[system]
    k = np.arange(T)
    plane, slot = k // (T // P), k % (T // P)
    raan = 2 * np.pi * plane / P
    m0 = 2 * np.pi * slot / (T // P) + 2 * np.pi * F * plane / T
    # a fixed, system-specific draw: the same satellite clocks in every run
    g = np.random.default_rng(CTYPE[system] * 7919)
    zeros = np.zeros(T)
    toe_sow = (WALKER_EPOCH_MS // 1000) % WEEK_S
    params = {key: zeros.copy() for key in ("crs", "delta_n", "cuc", "e", "cus", "cic", "cis", "crc", "omega",
                                             "omega_dot", "idot", "af2", "health", "tgd", "iodc", "iode",
                                             "t_transmit", "accuracy", "tgd_l5")}
    params.update(sqrt_a=np.full(T, np.sqrt(a)), m0=m0, i0=np.full(T, np.radians(inc)),
                  # GPS convention: the node longitude at toe is omega0 - OMEGA_E * toe_sow
                  omega0=raan + 7.2921151467e-5 * toe_sow, toe_sow=np.full(T, float(toe_sow)),
                  af0=g.uniform(-5e-4, 5e-4, T), af1=g.uniform(-1e-11, 1e-11, T),
                  week=np.full(T, float(WALKER_EPOCH_MS // 1000 // WEEK_S)), fit_h=np.full(T, _FOREVER_H))
    t = np.full(T, WALKER_EPOCH_MS, np.int64)
    svid = svid0 + k
    return GpsNav(prn=svid, toc_ms=t, toe_ms=t.copy(), params=params, source=f"synthetic {system} Walker",
                  skipped={}, sat_id=CTYPE[system] * 1000 + svid)


def _concat(navs: list[GpsNav]) -> GpsNav:
    """One GpsNav of several, sorted by (sat_id, toe) as select_ephemeris needs."""
    sat_id = np.concatenate([n.sat_id for n in navs])
    toe = np.concatenate([n.toe_ms for n in navs])
    order = np.lexsort((toe, sat_id))
    keys = set.intersection(*(set(n.params) for n in navs))
    return GpsNav(prn=np.concatenate([n.prn for n in navs])[order],
                  toc_ms=np.concatenate([n.toc_ms for n in navs])[order], toe_ms=toe[order],
                  params={k: np.concatenate([n.params[k] for n in navs])[order] for k in keys},
                  source=" + ".join(n.source for n in navs), skipped={}, sat_id=sat_id[order])


@dataclass
class Sky:
    """The signals of one simulation and the records their satellites fly by: Keplerian records
    (real and synthetic) and real GLONASS.

    A column is one (satellite, signal). sat_ids: (P,) ``sat_id`` of each column, sorted by
    (sat_id, signal); signal: (P,) int8 index into SIGNALS; is_glo: (P,) bool, served by
    ``glonass`` (real state vectors) instead of ``kepler``; origin: system letter -> the file name
    or ``"synthetic Walker"``. Record indices (``select``) point into ``kepler`` or ``glonass``
    according to ``is_glo`` of their column.
    """

    kepler: GpsNav
    glonass: GloNav | None
    sat_ids: np.ndarray
    signal: np.ndarray
    is_glo: np.ndarray
    origin: dict[str, str]

    @property
    def from_file(self) -> np.ndarray:
        """(P,) bool: the column's satellite flies by records read from a file (not synthetic)."""
        letters = {v: k for k, v in CTYPE.items()}
        return np.array([self.origin.get(letters[int(c)]) != "synthetic Walker" for c in self.sat_ids // 1000])

    @property
    def source(self) -> str:
        return "; ".join(f"{s}: {o}" for s, o in self.origin.items())

    def signals(self) -> np.ndarray:
        """(P,) int8 signal index of each column."""
        return self.signal

    def select(self, t_ms: np.ndarray) -> np.ndarray:
        """(E, P) record index valid at each epoch t_ms (E,) for each satellite, -1 where none."""
        idx = select_ephemeris(self.kepler, self.sat_ids[None, :], t_ms[:, None], by_sat_id=True)
        if self.glonass is not None and self.is_glo.any():
            g = select_glonass(self.glonass, self.sat_ids[None, self.is_glo], t_ms[:, None])
            idx[:, self.is_glo] = g
        return idx

    def states(self, idx: np.ndarray, col: np.ndarray, t_ms: np.ndarray, dt_s: np.ndarray | float,
               position_only: bool = False) -> dict[str, np.ndarray]:
        """States of flat queries (N,): record idx (>= 0), satellite column col, GPS time t_ms + dt_s.

        Returns pos (N,3) and, unless ``position_only``, vel (N,3), clock_s (N,), clock_drift (N,).
        """
        glo = self.is_glo[col]
        dt = np.broadcast_to(np.asarray(dt_s, float), idx.shape)
        t_ms = np.broadcast_to(np.asarray(t_ms, np.int64), idx.shape)
        if not glo.any():               # the common case: no scatter needed
            return self._kepler_state(idx, t_ms, dt, position_only, self.signal[col])
        keys = ("pos",) if position_only else ("pos", "vel", "clock_s", "clock_drift")
        out = {k: np.zeros(idx.shape + ((3,) if k in ("pos", "vel") else ())) for k in keys}
        for rows, fn in ((~glo, self._kepler_state), (glo, self._glonass_state)):
            if rows.any():
                st = fn(idx[rows], t_ms[rows], dt[rows], position_only, self.signal[col[rows]])
                for k in keys:
                    out[k][rows] = st[k]
        return out

    def _kepler_state(self, idx, t_ms, dt, position_only, signal):
        st = sat_state(self.kepler, idx, t_ms, dt, position_only=position_only)
        if not position_only and _L5[signal].any():
            # sat_state removes the L1-class group delay; L5-class signals take theirs instead
            p = self.kepler.params
            st["clock_s"] = st["clock_s"] + np.where(_L5[signal], p["tgd"][idx] - p["tgd_l5"][idx], 0.0)
        return st

    def _glonass_state(self, idx, t_ms, dt, position_only, signal):
        return glonass_state(self.glonass, idx, t_ms, dt)

    def span_ms(self) -> tuple[int, int]:
        """Earliest and latest instant any record covers [GPS ms]."""
        lo, hi = self.kepler.span_ms() if len(self.kepler) else (2**62, -2**62)
        if self.glonass is not None and len(self.glonass):
            lo = min(lo, int(self.glonass.toe_ms.min()) - 1_800_000)
            hi = max(hi, int(self.glonass.toe_ms.max()) + 1_800_000)
        return lo, hi


def build_sky(nav, systems: tuple[str, ...] = ("G",), dual_frequency: bool = False) -> Sky:
    """The :class:`Sky` of ``systems`` (letters) from ``nav``: a :class:`GpsNav` (GPS records) or a
    :class:`fusion.io.rinex_nav.Navigation` (any system); systems without records are synthetic.
    ``dual_frequency`` adds GPS L5 (:data:`GPS_L5_PRNS`), Galileo E5a and QZSS L5 columns.
    """
    kepler = getattr(nav, "kepler", nav)
    glonass = getattr(nav, "glonass", None)
    have_kep = {c for c in np.unique(kepler.sat_id // 1000)} if len(kepler) else set()
    parts, origin, use_glo = [], {}, False
    for s in systems:
        if s == "R" and glonass is not None and len(glonass):
            origin[s], use_glo = glonass.source, True
        elif CTYPE[s] in have_kep:
            sel = np.flatnonzero(kepler.sat_id // 1000 == CTYPE[s])
            parts.append(_take(kepler, sel))
            origin[s] = kepler.source
        else:
            parts.append(walker_records(s))
            origin[s] = "synthetic Walker"
    if not parts and not use_glo:
        raise DataError(f"{kepler.source}: no satellites for systems {systems}")
    kep = _concat(parts) if parts else _take(kepler, np.zeros(0, np.int64))
    ids = [np.unique(kep.sat_id)] + ([np.unique(glonass.sat_id)] if use_glo else [])
    sat_ids, signal = _columns(np.unique(np.concatenate(ids)), dual_frequency, origin.get("G") == "synthetic Walker")
    return Sky(kepler=kep, glonass=glonass if use_glo else None, sat_ids=sat_ids, signal=signal,
               is_glo=(sat_ids // 1000 == 3) & use_glo, origin=origin)


def _columns(sat_ids: np.ndarray, dual: bool, synthetic_gps: bool) -> tuple[np.ndarray, np.ndarray]:
    """(P,) sat_id and signal of every column, sorted by (sat_id, signal)."""
    ctype = sat_ids // 1000
    sig = np.array([SIGNALS.index(PRIMARY_SIGNAL[int(c)]) for c in ctype], np.int8)
    if not dual:
        return sat_ids, sig
    l5 = np.isin(ctype, list(SECOND_SIGNAL))
    l5 &= (ctype != 1) | synthetic_gps | np.isin(sat_ids % 1000, GPS_L5_PRNS)
    sig2 = np.array([SIGNALS.index(SECOND_SIGNAL[int(c)]) for c in ctype[l5]], np.int8)
    ids, sigs = np.r_[sat_ids, sat_ids[l5]], np.r_[sig, sig2].astype(np.int8)
    order = np.lexsort((sigs, ids))
    return ids[order], sigs[order]


def _take(nav: GpsNav, sel: np.ndarray) -> GpsNav:
    return GpsNav(prn=nav.prn[sel], toc_ms=nav.toc_ms[sel], toe_ms=nav.toe_ms[sel],
                  params={k: v[sel] for k, v in nav.params.items()}, source=nav.source,
                  skipped=nav.skipped, sat_id=nav.sat_id[sel])
