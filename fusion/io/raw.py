"""The raw-observation contract every raw reader (RINEX obs, GnssLogger) returns.

A raw frame is a pandas DataFrame in long format, one row per epoch x satellite x signal, with
exactly the columns of :data:`RAW_COLUMNS` (code against these names; they do not change):

=============  =======  ===================================================================
column         dtype    meaning
=============  =======  ===================================================================
t_ns           int64    receive time [GPS ns since 1980-01-06], the receiver's own time tag
                        (before the receiver clock bias is removed)
const          object   constellation letter: G R E C J S
svid           int64    satellite number within the constellation (GLONASS: slot 1..24)
sat_id         int64    ``1000 * Android constellationType + svid`` (GPS 1, SBAS 2,
                        GLONASS 3, QZSS 4, BDS 5, GAL 6), as in :class:`fusion.trace.Trace`
signal         object   name from :data:`fusion.trace.SIGNALS`; rows of other signals are
                        dropped by the readers and counted in ``skipped``
pr_m           float64  raw pseudorange [m] (no clock, iono or tropo correction); NaN if none
pr_sigma_m     float64  its 1-sigma [m]; NaN if unknown
prr_mps        float64  pseudorange rate ``-wavelength * doppler`` [m/s]; NaN if none.
                        NOT corrected for satellite clock drift
prr_sigma_mps  float64  its 1-sigma [m/s]; NaN if unknown
adr_m          float64  accumulated delta range (carrier phase) [m]; NaN if none
adr_sigma_m    float64  its 1-sigma [m]; NaN if unknown
adr_ok         bool     the carrier phase is valid
adr_slip       bool     reset, cycle slip or RINEX LLI bit 0 since this satellite/signal's
                        previous epoch: a carrier chain must break here
cn0            float64  carrier-to-noise density [dB-Hz]; NaN if none
glo_k          int64    GLONASS frequency channel -7..6; 0 for other constellations;
                        -99 where unknown
clock_reset    bool     epoch-level (same on every row of an epoch): the receiver clock
                        jumped since the previous epoch (HardwareClockDiscontinuityCount
                        change, RINEX epoch flag / clock event)
carrier_hz     float64  carrier frequency [Hz]
=============  =======  ===================================================================

Rows are sorted by ``t_ns``, then ``sat_id``, then ``signal`` (in :data:`fusion.trace.SIGNALS` order); a
(t_ns, sat_id, signal) triple appears at most once.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.trace import SIGNALS, count_skip

#: Column name -> numpy dtype kind required ("i" int, "f" float, "b" bool, "O" str).
RAW_COLUMNS: dict[str, str] = {
    "t_ns": "i", "const": "O", "svid": "i", "sat_id": "i", "signal": "O",
    "pr_m": "f", "pr_sigma_m": "f", "prr_mps": "f", "prr_sigma_mps": "f",
    "adr_m": "f", "adr_sigma_m": "f", "adr_ok": "b", "adr_slip": "b", "cn0": "f",
    "glo_k": "i", "clock_reset": "b", "carrier_hz": "f",
}

#: Constellation letter -> Android ``constellationType``.
CONSTELLATION_TYPE: dict[str, int] = {"G": 1, "S": 2, "R": 3, "J": 4, "C": 5, "E": 6}

#: Unknown GLONASS frequency channel.
GLO_K_UNKNOWN = -99

C_MPS = 299_792_458.0

#: Nominal carrier frequency [Hz] of each signal (GLONASS G1: the k = 0 centre; see
#: :func:`carrier_hz`).
SIGNAL_CARRIER_HZ: dict[str, float] = {
    "GPS_L1": 1575.42e6, "GPS_L5": 1176.45e6, "GLO_G1": 1602.0e6, "GAL_E1": 1575.42e6,
    "GAL_E5A": 1176.45e6, "BDS_B1I": 1561.098e6, "QZS_J1": 1575.42e6, "QZS_J5": 1176.45e6,
    "GPS_L2": 1227.60e6, "GAL_E5B": 1207.14e6, "BDS_B2I": 1207.14e6, "QZS_J2": 1227.60e6,
    "BDS_B1C": 1575.42e6, "BDS_B2A": 1176.45e6,
}
GLO_G1_STEP_HZ = 0.5625e6


def carrier_hz(signal: np.ndarray, glo_k: np.ndarray) -> np.ndarray:
    """Carrier frequency [Hz] per row.

    signal: (N,) str, names from SIGNALS.  glo_k: (N,) int, GLONASS channel (-99 unknown).
    Returns (N,) float64; NaN for GLONASS rows whose channel is unknown.
    """
    codes, names = pd.factorize(np.asarray(signal, dtype=object))
    f = np.array([SIGNAL_CARRIER_HZ.get(n, np.nan) for n in names] + [np.nan])[codes]
    glo = np.asarray(signal) == "GLO_G1"
    k = np.asarray(glo_k)
    f[glo] = np.where(k[glo] == GLO_K_UNKNOWN, np.nan, 1602.0e6 + k[glo] * GLO_G1_STEP_HZ)
    return f


@dataclass
class RawObs:
    """Raw observations of one receiver log.

    frame:      the long-format DataFrame described in this module's docstring.
    path:       the file it was read from.
    skipped:    counts of dropped rows / records by reason.
    approx_pos: (3,) float64 approximate receiver ECEF [m] from the file header, or None
                (phones write zeros there, which read as None).
    """

    frame: pd.DataFrame
    path: Path
    skipped: dict[str, int] = field(default_factory=dict)
    approx_pos: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_raw(self.frame, self.path)

    @property
    def n_epochs(self) -> int:
        return int(self.frame["t_ns"].nunique())


def empty_raw() -> pd.DataFrame:
    """A raw frame with the contract's columns and dtypes and no rows."""
    dtypes = {"i": np.int64, "f": np.float64, "b": bool, "O": object}
    return pd.DataFrame({c: np.array([], dtypes[k]) for c, k in RAW_COLUMNS.items()})


def check_raw(frame: pd.DataFrame, path: str | Path = "raw frame") -> None:
    """Raise :class:`DataError` unless ``frame`` has exactly the contract's columns and dtypes,
    known signal names and constellation letters."""
    cols = list(frame.columns)
    if cols != list(RAW_COLUMNS):
        missing = [c for c in RAW_COLUMNS if c not in cols]
        extra = [c for c in cols if c not in RAW_COLUMNS]
        raise DataError(f"{path}: raw frame columns differ from the contract "
                        f"(missing {missing}, extra {extra}, or out of order)")
    for col, kind in RAW_COLUMNS.items():
        got = frame[col].dtype.kind
        if got != kind and not (kind == "O" and got in "OUS"):
            raise DataError(f"{path}: raw column {col} has dtype {frame[col].dtype}, expected kind {kind!r}")
    bad_sig = ~frame["signal"].isin(SIGNALS)
    if bad_sig.any():
        raise DataError(f"{path}: raw frame has unknown signal {frame['signal'][bad_sig].iloc[0]!r}")
    bad_const = ~frame["const"].isin(list(CONSTELLATION_TYPE))
    if bad_const.any():
        raise DataError(f"{path}: raw frame has unknown constellation {frame['const'][bad_const].iloc[0]!r}")


def finish_raw(columns: dict[str, np.ndarray], skipped: dict[str, int] | None = None) -> pd.DataFrame:
    """Assemble reader columns into a sorted contract frame; ``sat_id`` and ``carrier_hz``
    are derived here when absent. Repeated (t_ns, sat_id, signal) rows after the first are
    dropped and counted in ``skipped['duplicate_observations']``.

    columns: name -> (N,) array, every contract column except possibly sat_id / carrier_hz.
    """
    cols = dict(columns)
    const = np.asarray(cols["const"], dtype=object)
    if "sat_id" not in cols:
        codes, names = pd.factorize(const)
        ctype = np.array([CONSTELLATION_TYPE.get(n, 0) for n in names] + [0], np.int64)[codes]
        cols["sat_id"] = 1000 * ctype + np.asarray(cols["svid"], np.int64)
    if "carrier_hz" not in cols:
        cols["carrier_hz"] = carrier_hz(np.asarray(cols["signal"], dtype=object), cols["glo_k"])
    codes, names = pd.factorize(np.asarray(cols["signal"], dtype=object))
    sig = np.array([SIGNALS.index(n) if n in SIGNALS else len(SIGNALS) for n in names] + [-1])[codes]
    t_ns, sat_id = np.asarray(cols["t_ns"], np.int64), np.asarray(cols["sat_id"], np.int64)
    order = np.lexsort((sig, sat_id, t_ns))
    t_o, sat_o, sig_o = t_ns[order], sat_id[order], sig[order]
    dup = np.zeros(order.size, bool)
    dup[1:] = (t_o[1:] == t_o[:-1]) & (sat_o[1:] == sat_o[:-1]) & (sig_o[1:] == sig_o[:-1])
    if skipped is not None:
        count_skip(skipped, "duplicate_observations", dup)
    order = order[~dup]
    dtypes = {"i": np.int64, "f": np.float64, "b": bool, "O": object}
    # copy=False: the columns are fresh (indexed by ``order``), a second copy of each is only memory
    return pd.DataFrame({c: np.asarray(cols[c], dtype=dtypes[k])[order] for c, k in RAW_COLUMNS.items()}, copy=False)
