"""Android GnssLogger logs (``*_GnssLog.txt``, ``gnss_log.txt``): ``Raw,`` records -> :class:`RawObs`.

Column names come from the log's own ``# Raw,...`` header line (they differ between app
versions). Pseudoranges follow the Android ``GnssMeasurement`` definitions:

- receive time (GPS ns) ``t_rx = TimeNanos + TimeOffsetNanos - (FullBiasNanos + BiasNanos)``;
- ``ReceivedSvTimeNanos`` is the satellite's transmit time within its own period: GPS, Galileo
  and QZSS time of week; BeiDou time of week in BDT (GPS - 14 s); GLONASS time of day in
  GLONASS time (UTC + 3 h, so GPS - leap seconds + 3 h);
- ``pr = c * (t_rx mod period - ReceivedSvTimeNanos)``, unwrapped across the period boundary.

The transmit time is only unambiguous when the ``State`` bits say the time of week (GLONASS: time
of day) is decoded or known; otherwise ``pr_m`` is NaN (the row keeps its Doppler / phase) and
the row is counted in ``skipped['pr_state_invalid']``. ``t_ns`` is ``t_rx`` without
``TimeOffsetNanos`` and sub-nanosecond bias, rounded to the nanosecond: the epoch's time tag.
"""
from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.gpstime import GPS_EPOCH_UNIX_MS, leap_seconds_at_unix_ms
from fusion.io.fixed_width import parse_int_text
from fusion.io.raw import GLO_G1_STEP_HZ, GLO_K_UNKNOWN, RawObs, empty_raw, finish_raw
from fusion.io.text_open import read_bytes
from fusion.trace import count_skip

C_MPS = 299_792_458.0
WEEK_NS = 604_800 * 10**9
DAY_NS = 86_400 * 10**9
BDT_OFFSET_NS = 14 * 10**9

# GnssMeasurement.getState() bits.
STATE_TOW_DECODED = 8
STATE_GLO_TOD_DECODED = 128
STATE_TOW_KNOWN = 16384
STATE_GLO_TOD_KNOWN = 32768
# getAccumulatedDeltaRangeState() bits.
ADR_VALID, ADR_RESET, ADR_CYCLE_SLIP = 1, 2, 4

#: Android constellationType -> RINEX letter (SBAS, IRNSS and unknown are dropped).
_CONST_LETTER = {1: "G", 2: "S", 3: "R", 4: "J", 5: "C", 6: "E"}
#: (letter, band) -> signal; band "L1" ~1575 MHz, "L5" ~1176 MHz, "B1" 1561 MHz, "G1" ~1602 MHz.
_SIGNAL = {("G", "L1"): "GPS_L1", ("G", "L5"): "GPS_L5", ("R", "G1"): "GLO_G1", ("E", "L1"): "GAL_E1",
           ("E", "L5"): "GAL_E5A", ("C", "B1"): "BDS_B1I", ("J", "L1"): "QZS_J1", ("J", "L5"): "QZS_J5",
           ("G", "L2"): "GPS_L2", ("J", "L2"): "QZS_J2", ("E", "B2"): "GAL_E5B", ("C", "B2"): "BDS_B2I",
           ("C", "L1"): "BDS_B1C", ("C", "L5"): "BDS_B2A"}
_BANDS = (("L1", 1575.42e6), ("L5", 1176.45e6), ("B1", 1561.098e6), ("L2", 1227.60e6), ("B2", 1207.14e6))
#: Android ``CodeType`` values that are our second-frequency signals (GPS / QZSS L2C: L, M, X
#: and S (L2C(M)); Galileo E5b and BeiDou B2I: I, Q, X); others on those carriers (GPS P(Y),
#: BeiDou B2b) are other signals. Logs without CodeType are read by carrier alone.
_SECOND_CODES = {"GPS_L2": "LMSX", "QZS_J2": "LMSX", "GAL_E5B": "IQX", "BDS_B2I": "IQX"}
_INT_COLS = ("TimeNanos", "FullBiasNanos", "ReceivedSvTimeNanos")
_NEEDED = _INT_COLS + ("Svid", "ConstellationType", "State", "BiasNanos")
_OPTIONAL = ("TimeOffsetNanos", "ReceivedSvTimeUncertaintyNanos", "Cn0DbHz", "PseudorangeRateMetersPerSecond",
             "PseudorangeRateUncertaintyMetersPerSecond", "AccumulatedDeltaRangeState",
             "AccumulatedDeltaRangeMeters", "AccumulatedDeltaRangeUncertaintyMeters", "CarrierFrequencyHz",
             "HardwareClockDiscontinuityCount", "utcTimeMillis")
#: Text columns kept as they are.
_TEXT = ("CodeType",)


def read_gnss_log(path: str | Path, *, fixed_full_bias: bool = False) -> RawObs:
    """Read the ``Raw`` records of an Android GnssLogger text log into the raw contract.

    ``fixed_full_bias=False`` (default) uses each epoch's ``FullBiasNanos``, as GSDC 2021
    ``rawPrM`` does: ``t_ns`` then tracks GPS time and the receiver clock bias stays small.
    ``True`` uses the first record's for the whole log, as Google's gps-measurement-tools and
    GSDC 2023 ``RawPseudorangeMeters`` do (their reference epoch is the drive's first): the
    hardware clock's drift then accumulates in every pseudorange and in ``t_ns``. The two differ
    per epoch by one offset common to all satellites, which a receiver clock estimate absorbs.

    Raises :class:`DataError` naming the file for an unreadable file, a log without a
    ``# Raw,`` header or without ``Raw`` records, or missing essential columns. Records with a
    wrong number of fields (a truncated last line) or unreadable numbers are skipped, counted
    and reported with a warning naming the first offending line.
    """
    path = Path(path)
    skipped: dict[str, int] = {}
    table, line_no = _raw_table(path, skipped)
    cols = _numeric_columns(table, line_no, path, skipped)
    frame = _to_contract(cols, skipped, fixed_full_bias)
    return RawObs(frame=frame, path=path, skipped=skipped, approx_pos=None)


def _raw_table(path: Path, skipped: dict[str, int]) -> tuple[pd.DataFrame, np.ndarray]:
    """The ``Raw`` records with the columns we use (integer-nanosecond ones as text) and their
    (N,) file line numbers; records with the wrong number of fields are dropped and counted."""
    text = read_bytes(path, "GnssLogger", skipped).decode("utf-8", errors="replace")
    lines = text.splitlines()
    header = next((l for l in lines if l.startswith("# Raw,")), None)
    if header is None:
        raise DataError(f"{path}: no '# Raw,...' header line: not a GnssLogger log with raw measurements")
    names = [n.strip() for n in header[2:].split(",")][1:]
    missing = [c for c in _NEEDED if c not in names]
    if missing:
        raise DataError(f"{path}: the '# Raw' header lacks column(s) {', '.join(missing)}")
    line_no = np.array([i for i, l in enumerate(lines, start=1) if l.startswith("Raw,")], np.int64)
    if line_no.size == 0:
        raise DataError(f"{path}: no 'Raw,' records (header only?)")
    records = [lines[i - 1] for i in line_no]
    wrong = np.array([r.count(",") for r in records]) != len(names)
    _warn_first(path, line_no, wrong, "wrong number of fields")
    count_skip(skipped, "records_wrong_field_count", wrong)
    body = "\n".join(r[4:] for r, w in zip(records, wrong) if not w)
    use = [c for c in _NEEDED + _OPTIONAL + _TEXT if c in names]
    table = pd.read_csv(io.StringIO(body), header=None, names=names, usecols=use,
                        dtype={c: str for c in _INT_COLS + _TEXT}, skipinitialspace=True, low_memory=False)
    return table, line_no[~wrong]


def _warn_first(path: Path, line_no: np.ndarray, bad: np.ndarray, what: str) -> None:
    """Warn once, naming the first bad line. line_no, bad: (N,)."""
    if np.any(bad):
        warnings.warn(f"{path}:{line_no[np.flatnonzero(bad)[0]]}: {what}; "
                      f"{int(np.sum(bad))} record(s) skipped", stacklevel=4)


def _int_column(text: pd.Series) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer nanoseconds exactly (a float64 would lose up to 256 ns of a 1e18 FullBiasNanos).

    text: (N,) strings or NaN.  Returns (N,) int64 values, (N,) bool empty, (N,) bool bad.
    """
    raw = text.fillna("").to_numpy(dtype="S24")
    value, empty, bad = parse_int_text(raw)
    return value, empty, bad | (np.char.str_len(raw) >= 24)


def _numeric_columns(table: pd.DataFrame, line_no: np.ndarray, path: Path,
                     skipped: dict[str, int]) -> dict[str, np.ndarray]:
    """Record columns -> numbers (integer-nanosecond columns exact int64).

    Returns name -> (N,) array over the records that parsed, plus ``line``. Empty fields read as
    NaN and are legal, except in TimeNanos / ReceivedSvTimeNanos; text that is not a number is not.
    """
    n = len(table)
    bad = np.zeros(n, bool)
    out: dict[str, np.ndarray] = {}
    for name in _INT_COLS:
        out[name], empty, b = _int_column(table[name])
        bad |= b | (empty if name != "FullBiasNanos" else False)
        if name == "FullBiasNanos":
            no_time = empty  # the phone has no GNSS time yet: no pseudorange can be formed
    for name in _NEEDED[len(_INT_COLS):] + _OPTIONAL:
        if name not in table:
            out[name] = np.full(n, np.nan)
            continue
        col = table[name]
        if pd.api.types.is_numeric_dtype(col):
            out[name] = col.to_numpy(float)
            continue
        v = pd.to_numeric(col, errors="coerce").to_numpy(float)
        bad |= np.isnan(v) & (col.fillna("").astype(str).str.strip() != "").to_numpy(bool)
        out[name] = v
    count_skip(skipped, "records_no_gnss_time", no_time)
    bad &= ~no_time
    _warn_first(path, line_no, bad, "unreadable number")
    count_skip(skipped, "records_bad_number", bad)
    # without these a record names no satellite, or no valid pseudorange
    blank = np.zeros(n, bool)
    for name in ("Svid", "ConstellationType", "State"):
        blank |= np.isnan(out[name])
    blank &= ~(bad | no_time)
    count_skip(skipped, "records_blank_svid_constellation_or_state", blank)
    keep = ~(bad | no_time | blank)
    out["CodeType"] = table["CodeType"].fillna("").astype(str).str.strip().to_numpy(object) \
        if "CodeType" in table else np.full(n, "", dtype=object)
    # An unreported sub-nanosecond BiasNanos is common to every satellite of the epoch: the
    # receiver clock estimate absorbs it, so it reads as 0 rather than costing the epoch.
    out["BiasNanos"] = np.nan_to_num(out["BiasNanos"])
    return {k: v[keep] for k, v in out.items()} | {"line": line_no[keep]}


def _signals(const: np.ndarray, freq_hz: np.ndarray, svid: np.ndarray,
             code: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Signal name (None where not one of ours) and GLONASS channel per record.

    const: (N,) RINEX letters.  freq_hz: (N,) CarrierFrequencyHz, NaN when not logged (old logs, which
    predate dual-frequency phones: L1 band assumed, B1I for BeiDou).  svid: (N,) Android svid (GLONASS
    93..106 = channel + 100, slot unknown).
    code: (N,) CodeType ('' when not logged), which tells L2C / B2I from other signals on their carriers.
    """
    band = np.full(const.size, "", dtype=object)
    f = np.where(np.isnan(freq_hz), np.where(const == "C", 1561.098e6, 1575.42e6), freq_hz)
    for name, centre in _BANDS:
        band[np.abs(f - centre) < 1e6] = name
    glo = const == "R"
    k = np.where(np.isnan(freq_hz), GLO_K_UNKNOWN, np.round((f - 1602e6) / GLO_G1_STEP_HZ)).astype(np.int64)
    glo_band = glo & ((k == GLO_K_UNKNOWN) | ((k >= -7) & (k <= 6)))
    band[glo_band] = "G1"
    k = np.where(glo & (svid >= 93) & (svid <= 106) & (k == GLO_K_UNKNOWN), svid - 100, k)
    keys = pd.Series(list(zip(const, band)), dtype=object)
    signal = keys.map(_SIGNAL).to_numpy(object)
    if code is not None:
        for name, codes in _SECOND_CODES.items():
            other = (signal == name) & (code != "") & ~pd.Series(code).isin(list(codes)).to_numpy()
            signal[other] = None
    return signal, np.where(glo, k, 0)


def _pseudorange(c: dict[str, np.ndarray], const: np.ndarray,
                 fixed_full_bias: bool) -> tuple[np.ndarray, np.ndarray]:
    """Raw pseudorange [m] (NaN where State says the transmit time is ambiguous) and t_ns.

    c: record columns, each (N,).  const: (N,) RINEX letters.  Returns two (N,) arrays.
    """
    full_bias = c["FullBiasNanos"][:1] if fixed_full_bias else c["FullBiasNanos"]
    whole = c["TimeNanos"] - full_bias  # GPS ns, exact in int64
    frac = np.nan_to_num(c["TimeOffsetNanos"]) - c["BiasNanos"]
    glo = const == "R"
    shift = np.where(const == "C", BDT_OFFSET_NS, 0)
    # GLONASS time = UTC + 3 h; GPS - UTC from the table (looked up at GPS time read as Unix time:
    # off by the 18 s only in the seconds around a leap second).
    leap = leap_seconds_at_unix_ms(whole // 10**6 + GPS_EPOCH_UNIX_MS)
    shift = np.where(glo, leap * 10**9 - 3 * 3600 * 10**9, shift)
    period = np.where(glo, DAY_NS, WEEK_NS)
    delta = np.mod(whole - shift, period) - c["ReceivedSvTimeNanos"]
    delta = np.where(delta > period // 2, delta - period, delta)
    delta = np.where(delta < -period // 2, delta + period, delta)
    state = c["State"].astype(np.int64)
    known = np.where(glo, state & (STATE_GLO_TOD_DECODED | STATE_GLO_TOD_KNOWN),
                     state & (STATE_TOW_DECODED | STATE_TOW_KNOWN)) != 0
    # TOW / TOD known implies code lock (Galileo E1 reports lock in its own bits, not bit 0).
    pr = np.where(known, (delta + frac) * (C_MPS * 1e-9), np.nan)
    t_ns = whole - np.round(c["BiasNanos"]).astype(np.int64)
    return pr, t_ns


def _to_contract(c: dict[str, np.ndarray], skipped: dict[str, int], fixed_full_bias: bool) -> pd.DataFrame:
    """Parsed record columns (each (N,)) -> the sorted contract frame."""
    if c["TimeNanos"].size == 0:
        return empty_raw()
    const = pd.Series(c["ConstellationType"]).map(_CONST_LETTER).to_numpy(object)
    svid = c["Svid"].astype(np.int64)
    signal, glo_k = _signals(const, c["CarrierFrequencyHz"], svid, c["CodeType"])
    glo_no_slot = (const == "R") & (svid > 24)
    keep = (signal != None) & ~glo_no_slot  # noqa: E711 (elementwise on object array)
    count_skip(skipped, "records_other_signals", signal == None)  # noqa: E711
    count_skip(skipped, "records_glonass_unknown_slot", (signal != None) & glo_no_slot)  # noqa: E711
    pr, t_ns = _pseudorange(c, const, fixed_full_bias)
    count_skip(skipped, "pr_state_invalid", keep & np.isnan(pr))
    state = np.nan_to_num(c["AccumulatedDeltaRangeState"]).astype(np.int64)
    adr_ok = (state & ADR_VALID != 0) & np.isfinite(c["AccumulatedDeltaRangeMeters"])
    reset = _clock_resets(c["TimeNanos"], c["HardwareClockDiscontinuityCount"])
    cols = {
        "t_ns": t_ns, "const": const, "svid": svid, "signal": signal, "pr_m": pr,
        "pr_sigma_m": c["ReceivedSvTimeUncertaintyNanos"] * (C_MPS * 1e-9),
        "prr_mps": c["PseudorangeRateMetersPerSecond"],
        "prr_sigma_mps": c["PseudorangeRateUncertaintyMetersPerSecond"],
        "adr_m": np.where(adr_ok, c["AccumulatedDeltaRangeMeters"], np.nan),
        "adr_sigma_m": np.where(adr_ok, c["AccumulatedDeltaRangeUncertaintyMeters"], np.nan),
        "adr_ok": adr_ok, "adr_slip": adr_ok & (state & (ADR_RESET | ADR_CYCLE_SLIP) != 0),
        "cn0": c["Cn0DbHz"], "glo_k": glo_k, "clock_reset": reset,
    }
    return finish_raw({k: v[keep] for k, v in cols.items()}, skipped)


def _clock_resets(time_nanos: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Per record: did HardwareClockDiscontinuityCount change since the previous epoch?

    time_nanos: (N,) int64 receiver hardware clock (one value per epoch).  count: (N,) float, NaN
    when not logged (then no reset is flagged).  Returns (N,) bool.
    """
    # Epochs in file order: after a discontinuity TimeNanos may even run backwards.
    starts = np.flatnonzero(np.diff(time_nanos, prepend=time_nanos[:1] - 1) != 0)
    epoch = np.cumsum(np.diff(time_nanos, prepend=time_nanos[:1] - 1) != 0) - 1
    per_epoch = count[starts]
    changed = np.zeros(starts.size, bool)
    changed[1:] = (per_epoch[1:] != per_epoch[:-1]) & np.isfinite(per_epoch[1:]) & np.isfinite(per_epoch[:-1])
    return changed[epoch]
