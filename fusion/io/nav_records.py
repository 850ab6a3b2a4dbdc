"""Navigation records as the readers of :mod:`fusion.io` fill them: the parsing layer's contract for
navigation files (as :mod:`fusion.io.raw` is for observations), which :mod:`fusion.nav` reads to compute
satellite states.

- :class:`GpsNav`: Keplerian broadcast ephemerides (GPS, QZSS, Galileo, BeiDou);
- :class:`GloNav`: GLONASS broadcast state vectors, with :data:`GLONASS_VALID_MS` and the slot -> frequency
  channel table :data:`SLOT_CHANNEL`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Frequency channel of each orbital slot (GLONASS ICD 2008 3.3.1.1: antipodal slots share a
#: channel; the assignment has been stable since 2005, slots keep theirs when a satellite is
#: replaced). For files whose header omits ``GLONASS SLOT / FRQ #`` and without GLONASS
#: navigation records; a navigation record's own channel number wins over this table.
SLOT_CHANNEL: dict[int, int] = {
    1: 1, 2: -4, 3: 5, 4: 6, 5: 1, 6: -4, 7: 5, 8: 6, 9: -2, 10: -7, 11: 0, 12: -1,
    13: -2, 14: -7, 15: 0, 16: -1, 17: 4, 18: -3, 19: 3, 20: 2, 21: 4, 22: -3, 23: 3, 24: 2,
}
#: A record is used up to this far from its toe [ms] (records come every 30 minutes).
GLONASS_VALID_MS = 1_800_000


@dataclass
class GpsNav:
    """Healthy Keplerian broadcast ephemerides, one entry per distinct (satellite, toe).

    The name is historical: records of GPS, QZSS, Galileo and BeiDou share this layout; ``sat_id``
    says which (``1000 * constellationType + svid``, as in :class:`fusion.trace.Trace`; None means
    GPS, ``1000 + prn``). Times of every system are GPS ms (BeiDou's BDT + 14 s). Sorted by
    (sat_id, toe).

    prn:    (N,) int, satellite number within its constellation (Android svid: QZSS 193..).
    toc_ms: (N,) int64 clock reference time, GPS ms.   toe_ms: (N,) int64 ephemeris reference time.
    params: name -> (N,) float64 (af0, af1, af2, crs, delta_n, m0, cuc, e, cus, sqrt_a, toe_sow,
            cic, omega0, cis, i0, crc, omega, omega_dot, idot, week, accuracy, health, tgd, iodc,
            iode, t_transmit, fit_h) in IS-GPS-200 units (s, m, rad, rad/s).
    source: file path, for error messages.
    skipped: counts of dropped records by reason.
    msg:    (N,) int8 navigation message: 0 the system's default (Galileo I/NAV), 1 Galileo F/NAV
            (None: all 0). Galileo broadcasts both, with clocks for different signal pairs; the
            table keeps both and is sorted by (sat_id, msg, toe).
    """

    prn: np.ndarray
    toc_ms: np.ndarray
    toe_ms: np.ndarray
    params: dict[str, np.ndarray]
    source: str
    skipped: dict[str, int]
    sat_id: np.ndarray | None = None
    msg: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.sat_id is None:
            self.sat_id = 1000 + np.asarray(self.prn, np.int64)
        self.sat_id = np.asarray(self.sat_id, np.int64)
        self.msg = np.zeros(self.sat_id.shape, np.int8) if self.msg is None else np.asarray(self.msg, np.int8)

    def __len__(self) -> int:
        return int(self.prn.shape[0])

    @property
    def valid_from_ms(self) -> np.ndarray:
        """(N,) start of each record's fit interval [GPS ms]."""
        return self.toe_ms - (self.params["fit_h"] * 1800e3).astype(np.int64)

    @property
    def valid_to_ms(self) -> np.ndarray:
        """(N,) end of each record's fit interval [GPS ms]."""
        return self.toe_ms + (self.params["fit_h"] * 1800e3).astype(np.int64)

    def span_ms(self) -> tuple[int, int]:
        """Earliest and latest instant covered by any record's fit interval [GPS ms]."""
        return int(self.valid_from_ms.min()), int(self.valid_to_ms.max())


@dataclass
class GloNav:
    """Healthy GLONASS broadcast records, sorted by (sat_id, toe).

    svid: (N,) slot number 1..24; sat_id: (N,) ``3000 + svid``; toe_ms: (N,) int64 GPS ms.
    pos, vel, acc: (N, 3) PZ-90 ECEF position [m], velocity [m/s], lunisolar acceleration [m/s^2].
    tau: (N,) clock bias ``-TauN`` [s] as RINEX writes it; gamma: (N,) relative frequency bias.
    k: (N,) int frequency channel -7..6.
    """

    svid: np.ndarray
    toe_ms: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    tau: np.ndarray
    gamma: np.ndarray
    k: np.ndarray
    source: str = ""

    @property
    def sat_id(self) -> np.ndarray:
        return 3000 + np.asarray(self.svid, np.int64)

    def __len__(self) -> int:
        return int(self.svid.shape[0])
