"""Google Smartphone Decimeter Challenge (GSDC) loaders: files -> :class:`fusion.trace.Trace`.

Formats (detected from the folder's files, ``.csv`` or ``.csv.gz``):

- GSDC 2021 (``<collection>/<phone>/<phone>_derived.csv`` + ``ground_truth.csv``, optional
  ``supplemental/SPAN_<phone>_10Hz.nmea``).
- GSDC 2022/2023 (``<collection>/<phone>/device_gnss.csv`` + ``ground_truth.csv``).

Traps handled here (see the shared data README):

1. GSDC 2021 ``millisSinceGpsEpoch`` is one epoch (1000 ms) late. ``Trace.t_ms`` is the true
   receive time. Rather than subtracting 1000 ms blindly, each row's own receive time
   ``receivedSvTimeInGpsNanos + rawPrM / c`` picks the whole second it belongs to: a few rows
   (and a few whole epochs) in the real files are *not* shifted, and subtracting 1000 ms from
   them would mix measurements taken one second apart (35 m at highway speed, more from clock
   drift) into one epoch.
2. GSDC 2021 truth heights are ~63.1 m too high (geoid sign error). With SPAN NMEA present it
   is the truth; otherwise :data:`GSDC2021_TRUTH_HEIGHT_ERROR_M` is subtracted. We use a fixed
   63.1 m rather than 2x the local geoid separation because the package ships no geoid model
   and every GSDC 2021 drive is in the San Francisco Bay Area, where 2|N| = 63.10-63.18 m was
   measured against SPAN; a warning is raised for truth outside that area.
3. Receiver clock discontinuities: 2022/23 ``HardwareClockDiscontinuityCount`` changes set
   ``clock_reset``; 2021 derived files carry no such column (estimators detect jumps).

Bad input raises :class:`DataError` naming the file and problem; recoverable defects (rows with
missing values, duplicates, epochs with too few satellites) are dropped and counted in
``Trace.skipped``.
"""
from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError, GnssfuseError
from fusion.geometry import C_LIGHT, geodetic2ecef
from fusion.gpstime import unix_ms_to_gps_ms
from fusion.io_nmea import read_span_nmea
from fusion.trace import SIGNALS, Trace, count_skip, pack_rows

log = logging.getLogger(__name__)

#: GSDC 2021 derived timestamps are this much later than the true receive time [ms].
DERIVED_DELAY_MS = 1000
#: GSDC 2021 ground-truth height error [m] (truth minus SPAN, Bay Area), subtracted when fixing.
GSDC2021_TRUTH_HEIGHT_ERROR_M = 63.1
#: Truth rows are matched to epochs by nearest time within this tolerance [ms].
TRUTH_TOL_MS = 20
#: SPAN fixes are interpolated only across gaps up to this long [ms] (10 Hz log -> 100 ms).
NMEA_MAX_GAP_MS = 250
# Plausibility bounds (reject garbage, not outliers): MEO..GEO orbit radii, ranges from Earth.
_SAT_RADIUS_M = (1.0e7, 5.0e7)
_PR_RANGE_M = (1.0e7, 5.0e7)
# Where the 63.1 m figure was measured (centre of the GSDC 2021 drives) and how far it applies.
_BAY_AREA_LATLON = (37.5, -122.1)
_BAY_AREA_RADIUS_DEG = 1.5

_MEAS_COLS_2021 = {
    "t": "millisSinceGpsEpoch", "const": "constellationType", "svid": "svid", "signal": "signalType",
    "x": "xSatPosM", "y": "ySatPosM", "z": "zSatPosM", "clk": "satClkBiasM", "raw": "rawPrM",
    "unc": "rawPrUncM", "isrb": "isrbM", "iono": "ionoDelayM", "tropo": "tropoDelayM",
}
_VEL_COLS_2021 = ("xSatVelMps", "ySatVelMps", "zSatVelMps")
_MEAS_COLS_2022 = {
    "t": "utcTimeMillis", "const": "ConstellationType", "svid": "Svid", "signal": "SignalType",
    "x": "SvPositionXEcefMeters", "y": "SvPositionYEcefMeters", "z": "SvPositionZEcefMeters",
    "clk": "SvClockBiasMeters", "raw": "RawPseudorangeMeters", "unc": "RawPseudorangeUncertaintyMeters",
    "isrb": "IsrbMeters", "iono": "IonosphericDelayMeters", "tropo": "TroposphericDelayMeters",
}
_VEL_COLS_2022 = ("SvVelocityXEcefMetersPerSecond", "SvVelocityYEcefMetersPerSecond",
                  "SvVelocityZEcefMetersPerSecond")
_TRUTH_COLS_2021 = ("millisSinceGpsEpoch", "latDeg", "lngDeg", "heightAboveWgs84EllipsoidM")
_TRUTH_COLS_2022 = ("UnixTimeMillis", "LatitudeDegrees", "LongitudeDegrees", "AltitudeMeters")


# ---------------------------------------------------------------------------- signals
def signal_index(names: Sequence[str] | pd.Series) -> np.ndarray:
    """Map GSDC signal names onto indices into :data:`SIGNALS` (int8, -1 where unknown).

    2021/2022 names are ours already (``GPS_L1``); 2023 adds a code suffix (``GPS_L1_CA``,
    ``GAL_E1_C_P``, ``GAL_E5A_Q``), which is dropped: the first two ``_`` tokens name the signal.
    """
    s = pd.Series(names, dtype=object)
    lookup = {}
    for name in s.dropna().unique():
        key = str(name).strip().upper()
        short = "_".join(key.split("_")[:2])
        lookup[name] = SIGNALS.index(key) if key in SIGNALS else (
            SIGNALS.index(short) if short in SIGNALS else -1)
    return s.map(lookup).fillna(-1).to_numpy(np.int8)


def resolve_signals(signals: Sequence[str] | str | None) -> np.ndarray:
    """User signal selection -> sorted unique indices into :data:`SIGNALS`.

    ``None``, ``"all"`` or a sequence containing ``"all"`` (any case) selects every known signal;
    names may use 2023 spellings.
    """
    if isinstance(signals, str):
        signals = [signals]
    if signals is None or any(str(s).strip().lower() == "all" for s in signals):
        return np.arange(len(SIGNALS))
    idx = signal_index(list(signals))
    unknown = [s for s, i in zip(signals, idx) if i < 0]
    if unknown or len(idx) == 0:
        raise GnssfuseError(f"unknown signal name(s) {unknown or list(signals)}; known: {', '.join(SIGNALS)}")
    return np.unique(idx)


# ---------------------------------------------------------------------------- CSV reading
def _read_csv(path: Path, required: Sequence[str], what: str) -> pd.DataFrame:
    """Read a CSV (optionally gzipped), checking it exists, is not empty, has ``required``."""
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    try:
        df = pd.read_csv(path, low_memory=False)
    except pd.errors.EmptyDataError as exc:
        raise DataError(f"{path}: {what} file is empty") from exc
    except (pd.errors.ParserError, UnicodeDecodeError, OSError, EOFError) as exc:
        raise DataError(f"{path}: cannot parse {what} file ({type(exc).__name__}: {exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DataError(f"{path}: {what} file lacks column(s) {', '.join(missing)}")
    if df.empty:
        raise DataError(f"{path}: {what} file has a header but no data rows")
    return df


def _to_numeric(df: pd.DataFrame, cols: Sequence[str], path: Path) -> None:
    """Convert ``cols`` to numbers in place; a non-numeric cell raises naming column and row."""
    for c in cols:
        s = df[c]
        if pd.api.types.is_numeric_dtype(s):
            continue
        v = pd.to_numeric(s, errors="coerce")
        bad = (v.isna() & s.notna()).to_numpy()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DataError(f"{path}: column {c!r}, data row {i + 1}: non-numeric value {s.iloc[i]!r}")
        df[c] = v


def _drop_nan_rows(df: pd.DataFrame, cols: Sequence[str], path: Path, what: str,
                   skipped: dict[str, int], key: str) -> pd.DataFrame:
    bad = df[list(cols)].isna().any(axis=1).to_numpy()
    if bad.all():
        raise DataError(f"{path}: every {what} row has a missing value in {', '.join(cols)}")
    count_skip(skipped, key, bad.sum())
    return df[~bad]


def _check_increasing(t: np.ndarray, row: np.ndarray, path: Path, what: str) -> None:
    """Times must never decrease down the file (rows of one epoch share a time).

    row: (N,) 1-based data row numbers in the file, for the message."""
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = int(back[0])
        raise DataError(f"{path}: {what} times are not increasing: data row {row[i + 1]} has time "
                        f"{t[i + 1]} after {t[i]} (data row {row[i]})")


# ---------------------------------------------------------------------------- measurements
def _standard_rows(df: pd.DataFrame, cols: dict[str, str], vel_cols: Sequence[str], path: Path,
                   skipped: dict[str, int]) -> pd.DataFrame:
    """Source columns -> one standard row table, dropping (and counting) rows with missing values
    (a missing satellite velocity alone becomes zeros, the Trace's "unknown").

    Returns columns t, const, svid, signal_name, x, y, z, vx, vy, vz, pr, pr_sigma plus ``row``
    (1-based data row in the file, for messages).
    """
    numeric = [v for k, v in cols.items() if k != "signal"]
    vel = [c for c in vel_cols if c in df.columns]
    _to_numeric(df, numeric + vel, path)
    if "_row" not in df.columns:
        df = df.assign(_row=np.arange(1, len(df) + 1))
    # Satellite velocity feeds no estimator here, so a row missing only it keeps its pseudorange and
    # gets the Trace's "unknown" velocity (zeros) instead of being dropped.
    df = _drop_nan_rows(df, numeric + [cols["signal"]], path, "measurement", skipped, "rows_missing_values")
    if vel:
        df = df.assign(**{c: df[c].fillna(0.0) for c in vel})
    c = cols
    pr = df[c["raw"]] + df[c["clk"]] - df[c["isrb"]] - df[c["iono"]] - df[c["tropo"]]
    out = pd.DataFrame({
        "t": df[c["t"]].to_numpy(np.float64), "const": df[c["const"]].to_numpy(np.int64),
        "svid": df[c["svid"]].to_numpy(np.int64), "signal_name": df[c["signal"]].to_numpy(object),
        "x": df[c["x"]].to_numpy(float), "y": df[c["y"]].to_numpy(float), "z": df[c["z"]].to_numpy(float),
        "pr": pr.to_numpy(float), "pr_sigma": df[c["unc"]].to_numpy(float), "row": df["_row"].to_numpy(),
    })
    for k, vc in zip(("vx", "vy", "vz"), vel_cols):
        out[k] = df[vc].to_numpy(float) if vc in df.columns else 0.0
    return out


def _rows_to_trace(rows: pd.DataFrame, *, name: str, path: Path, signals, min_sats: int,
                   skipped: dict[str, int], clock_count: np.ndarray | None = None) -> dict:
    """Filter, de-duplicate and pack standard rows (``t`` already integer true GPS ms).

    Returns Trace keyword arguments (without truth).
    """
    sel = resolve_signals(signals)
    rows = rows.assign(signal=signal_index(rows["signal_name"]))
    if clock_count is not None:
        rows = rows.assign(clk_count=clock_count)
    rows = rows[np.isin(rows["signal"].to_numpy(), sel)]
    if rows.empty:
        raise DataError(f"{path}: no rows of signal(s) {', '.join(SIGNALS[i] for i in sel)}")

    r = np.sqrt(rows["x"] ** 2 + rows["y"] ** 2 + rows["z"] ** 2).to_numpy()
    pr, sig = rows["pr"].to_numpy(), rows["pr_sigma"].to_numpy()
    good = ((r > _SAT_RADIUS_M[0]) & (r < _SAT_RADIUS_M[1]) & (pr > _PR_RANGE_M[0]) & (pr < _PR_RANGE_M[1])
            & np.isfinite(sig) & (sig > 0))
    count_skip(skipped, "rows_bad_values", (~good).sum())
    rows = rows[good]

    rows = rows.sort_values(["t", "const", "svid", "signal"], kind="stable")
    dup = rows.duplicated(["t", "const", "svid", "signal"]).to_numpy()
    count_skip(skipped, "duplicate_rows", dup.sum())
    rows = rows[~dup]

    t_unique, epoch, counts = np.unique(rows["t"].to_numpy(np.int64), return_inverse=True, return_counts=True)
    keep_epoch = counts >= min_sats
    count_skip(skipped, f"epochs_lt{min_sats}_sats", (~keep_epoch).sum())
    if not keep_epoch.any():
        raise DataError(f"{path}: no epoch has >= {min_sats} satellites of the selected signal(s) "
                        f"({', '.join(SIGNALS[i] for i in sel)}); largest has {int(counts.max(initial=0))}")
    keep_row = keep_epoch[epoch]
    rows = rows[keep_row]
    new_index = np.cumsum(keep_epoch) - 1
    epoch = new_index[epoch[keep_row]]
    t_ms = t_unique[keep_epoch]
    E = t_ms.shape[0]

    packed = pack_rows(epoch, E, {
        "sat_pos": rows[["x", "y", "z"]].to_numpy(float),
        "sat_vel": rows[["vx", "vy", "vz"]].to_numpy(float),
        "pr": rows["pr"].to_numpy(float), "pr_sigma": rows["pr_sigma"].to_numpy(float),
        "sat_id": (1000 * rows["const"].to_numpy() + rows["svid"].to_numpy()).astype(np.int32),
        "signal": rows["signal"].to_numpy(np.int8),
    })
    clock_reset = np.zeros(E, bool)
    if clock_count is not None:
        # A change between consecutive *kept* epochs also flags jumps inside skipped epochs.
        per_epoch = np.full(E, -1, np.int64)
        np.maximum.at(per_epoch, epoch, rows["clk_count"].to_numpy(np.int64))
        clock_reset[1:] = np.diff(per_epoch) != 0
    return dict(t_ms=t_ms.astype(np.int64), clock_reset=clock_reset, name=name, **packed)


def _retime_derived(rows: pd.DataFrame, received_ns: np.ndarray | None) -> tuple[np.ndarray, int]:
    """GSDC 2021 derived time -> true receive time [GPS ms] per row; also the count of rows that
    were not stamped one epoch late (see module docstring, trap 1).

    The corrected pseudorange stands in for ``rawPrM``: they differ by the satellite clock and
    delays (< 1 ms of light time), which cannot move a row to another whole second."""
    t = rows["t"].to_numpy(np.int64) - DERIVED_DELAY_MS
    if received_ns is None:
        return t, 0
    rx_ms = received_ns / 1e6 + rows["pr"].to_numpy() / C_LIGHT * 1e3
    k = np.round((rx_ms - t) / 1000.0)
    # the files are at most one epoch off; a larger shift means a bad receivedSvTimeInGpsNanos
    # (0, time of week only, ...), which must not move the row to another day: keep the 1000 ms rule
    k = np.where(np.isfinite(k) & (np.abs(k) <= 1), k, 0).astype(np.int64)
    return t + 1000 * k, int(np.count_nonzero(k))


def _read_derived_rows(path: Path, skipped: dict[str, int]) -> pd.DataFrame:
    df = _read_csv(path, list(_MEAS_COLS_2021.values()), "GSDC 2021 derived")
    rows = _standard_rows(df, _MEAS_COLS_2021, _VEL_COLS_2021, path, skipped)
    _check_increasing(rows["t"].to_numpy(), rows["row"].to_numpy(), path, "millisSinceGpsEpoch")
    received = None
    if "receivedSvTimeInGpsNanos" in df.columns:
        # Optional column, used only to place rows in time; unparsable or implausible values fall
        # back to 1000 ms.
        rec = pd.to_numeric(df["receivedSvTimeInGpsNanos"], errors="coerce")
        received = rec.to_numpy(float)[rows["row"].to_numpy() - 1]
    t_true, n_moved = _retime_derived(rows, received)
    if n_moved:
        log.info("%s: %d rows were not stamped one epoch late; placed at their own receive time", path, n_moved)
    return rows.assign(t=t_true)


# ---------------------------------------------------------------------------- truth
def read_truth_csv(path: str | Path, skipped: dict[str, int] | None = None) -> pd.DataFrame:
    """Ground truth of either format -> DataFrame t_ms (GPS ms), lat_deg, lon_deg, height_m.

    Heights are as in the file (GSDC 2021's are ~63 m too high; :func:`load_derived_2021` fixes
    them). Rows with missing values are dropped and counted (``truth_rows_missing_values``).
    """
    path = Path(path)
    skipped = {} if skipped is None else skipped
    df = _read_csv(path, [], "ground truth")
    if all(c in df.columns for c in _TRUTH_COLS_2021):
        cols, unix = _TRUTH_COLS_2021, False
    elif all(c in df.columns for c in _TRUTH_COLS_2022):
        cols, unix = _TRUTH_COLS_2022, True
    else:
        raise DataError(f"{path}: ground truth file lacks columns: need either {', '.join(_TRUTH_COLS_2021)} "
                        f"(GSDC 2021) or {', '.join(_TRUTH_COLS_2022)} (GSDC 2022/23)")
    _to_numeric(df, cols, path)
    df = df.assign(_row=np.arange(1, len(df) + 1))
    df = _drop_nan_rows(df, cols, path, "ground truth", skipped, "truth_rows_missing_values")
    t = df[cols[0]].to_numpy(np.int64)
    t = unix_ms_to_gps_ms(t) if unix else t
    _check_increasing(t, df["_row"].to_numpy(), path, "ground truth")
    out = pd.DataFrame({"t_ms": t, "lat_deg": df[cols[1]].to_numpy(float),
                        "lon_deg": df[cols[2]].to_numpy(float), "height_m": df[cols[3]].to_numpy(float)})
    dup = out.duplicated("t_ms").to_numpy()
    count_skip(skipped, "truth_duplicate_rows", dup.sum())
    return out[~dup].reset_index(drop=True)


def _llh_ecef(df: pd.DataFrame) -> np.ndarray:
    return geodetic2ecef(df[["lat_deg", "lon_deg", "height_m"]].to_numpy(float))


def match_nearest(t_ms: np.ndarray, ref_t: np.ndarray, ref_val: np.ndarray,
                  tol_ms: float = TRUTH_TOL_MS) -> np.ndarray:
    """Value of the reference row nearest in time to each epoch, NaN beyond ``tol_ms``.

    t_ms: (E,), ref_t: (M,) increasing, ref_val: (M, k) -> (E, k).
    """
    out = np.full((t_ms.shape[0], ref_val.shape[1]), np.nan)
    if ref_t.size == 0:
        return out
    j = np.clip(np.searchsorted(ref_t, t_ms), 1, max(ref_t.size - 1, 1))
    lo = np.clip(j - 1, 0, ref_t.size - 1)
    hi = np.clip(j, 0, ref_t.size - 1)
    best = np.where(np.abs(ref_t[hi] - t_ms) < np.abs(ref_t[lo] - t_ms), hi, lo)
    ok = np.abs(ref_t[best] - t_ms) <= tol_ms
    out[ok] = ref_val[best[ok]]
    return out


def interp_gapped(t_ms: np.ndarray, ref_t: np.ndarray, ref_val: np.ndarray,
                  max_gap_ms: float = NMEA_MAX_GAP_MS) -> np.ndarray:
    """Linear interpolation of (M, k) ``ref_val`` at (E,) ``t_ms``; NaN outside the reference
    span or across gaps longer than ``max_gap_ms``."""
    out = np.full((t_ms.shape[0], ref_val.shape[1]), np.nan)
    if ref_t.size < 2:
        return match_nearest(t_ms, ref_t, ref_val, 0)
    hi = np.clip(np.searchsorted(ref_t, t_ms, side="right"), 1, ref_t.size - 1)
    lo = hi - 1
    span = (ref_t[hi] - ref_t[lo]).astype(float)
    w = (t_ms - ref_t[lo]) / span
    # a time exactly on a reference fix is that fix, whatever gap follows or precedes it
    ok = (t_ms >= ref_t[0]) & (t_ms <= ref_t[-1]) & ((span <= max_gap_ms) | (w == 0) | (w == 1))
    out[ok] = ref_val[lo[ok]] + w[ok, None] * (ref_val[hi[ok]] - ref_val[lo[ok]])
    return out


def _check_overlap(t_ms: np.ndarray, truth_t: np.ndarray, matched: np.ndarray,
                   meas: Path, truth: Path) -> None:
    if not np.isfinite(matched).all(axis=1).any():
        raise DataError(f"{meas}: epoch times {t_ms.min()}..{t_ms.max()} (GPS ms) do not overlap the "
                        f"ground truth {truth} times {truth_t.min()}..{truth_t.max()}")


def _warn_outside_bay_area(truth: pd.DataFrame, path: Path) -> None:
    lat, lon = np.nanmedian(truth["lat_deg"]), np.nanmedian(truth["lon_deg"])
    if np.hypot(lat - _BAY_AREA_LATLON[0], lon - _BAY_AREA_LATLON[1]) > _BAY_AREA_RADIUS_DEG:
        warnings.warn(f"{path}: truth is at ({lat:.2f}, {lon:.2f}), outside the Bay Area where the "
                      f"{GSDC2021_TRUTH_HEIGHT_ERROR_M} m height fix was measured; the true error there is "
                      f"2x the local geoid separation", stacklevel=3)


def gsdc2021_height_offsets(truth_csv: str | Path, nmea: str | Path) -> np.ndarray:
    """GSDC 2021 truth-CSV height minus SPAN ellipsoidal height at the CSV times [m] (NaN where
    the SPAN log has no fix); the figure behind :data:`GSDC2021_TRUTH_HEIGHT_ERROR_M`."""
    truth = read_truth_csv(truth_csv)
    span = read_span_nmea(nmea, ref_gps_ms=int(truth["t_ms"].iloc[0]))
    h = interp_gapped(truth["t_ms"].to_numpy(), span["t_ms"].to_numpy(), span[["height_m"]].to_numpy())
    return truth["height_m"].to_numpy() - h[:, 0]


# ---------------------------------------------------------------------------- loaders
def load_derived_2021(derived: str | Path, truth_csv: str | Path | None = None, nmea: str | Path | None = None,
                      *, signals=("GPS_L1",), fix_truth_height: bool = True, min_sats: int = 4,
                      truth_tol_ms: float = TRUTH_TOL_MS, name: str | None = None) -> Trace:
    """Load a GSDC 2021 ``*_derived.csv[.gz]`` file (and its truth) into a :class:`Trace`.

    truth_csv:        ``ground_truth.csv``; matched to epochs by nearest time within ``truth_tol_ms``.
    nmea:             SPAN NMEA log; when given (and ``fix_truth_height``) it is the truth, interpolated
                      to the epoch times, with the height-fixed CSV filling epochs it does not cover.
    fix_truth_height: remove the 63.1 m CSV height error (False: CSV heights as published, and the
                      NMEA log is used only when there is no ``truth_csv``).
    min_sats:         epochs with fewer measurements are skipped and counted (0 keeps every epoch).
    """
    derived = Path(derived)
    skipped: dict[str, int] = {}
    rows = _read_derived_rows(derived, skipped)
    kwargs = _rows_to_trace(rows, name=name or derived.stem, path=derived, signals=signals,
                            min_sats=min_sats, skipped=skipped)
    t_ms = kwargs["t_ms"]
    truth = None
    if truth_csv is not None:
        truth_csv = Path(truth_csv)
        tdf = read_truth_csv(truth_csv, skipped)
        if fix_truth_height:
            _warn_outside_bay_area(tdf, truth_csv)
            tdf = tdf.assign(height_m=tdf["height_m"] - GSDC2021_TRUTH_HEIGHT_ERROR_M)
        truth = match_nearest(t_ms, tdf["t_ms"].to_numpy(), _llh_ecef(tdf), truth_tol_ms)
        _check_overlap(t_ms, tdf["t_ms"].to_numpy(), truth, derived, truth_csv)
    if nmea is not None and (fix_truth_height or truth is None):
        nmea = Path(nmea)
        span = read_span_nmea(nmea, ref_gps_ms=int(t_ms[0]), skipped=skipped)
        span_truth = interp_gapped(t_ms, span["t_ms"].to_numpy(), _llh_ecef(span))
        _check_overlap(t_ms, span["t_ms"].to_numpy(), span_truth, derived, nmea)
        if truth is not None:
            covered = np.isfinite(span_truth).all(axis=1)
            span_truth[~covered] = truth[~covered]
        truth = span_truth
    return Trace(truth=truth, skipped=skipped, **kwargs)


def load_device_gnss(device_csv: str | Path, truth_csv: str | Path | None = None, *, signals=("GPS_L1",),
                     min_sats: int = 4, truth_tol_ms: float = TRUTH_TOL_MS, name: str | None = None) -> Trace:
    """Load a GSDC 2022/2023 ``device_gnss.csv[.gz]`` (and ``ground_truth.csv``) into a :class:`Trace`.

    Epoch time is ``utcTimeMillis`` converted to GPS ms; truth ``UnixTimeMillis`` is on the same
    clock (no shift) and its heights are ellipsoidal already. ``clock_reset`` marks epochs where
    ``HardwareClockDiscontinuityCount`` changed since the previous kept epoch.
    """
    device_csv = Path(device_csv)
    skipped: dict[str, int] = {}
    df = _read_csv(device_csv, list(_MEAS_COLS_2022.values()), "GSDC device_gnss")
    df = df.assign(_row=np.arange(1, len(df) + 1))
    if "MessageType" in df.columns:
        df = df[df["MessageType"].astype(str).str.strip() == "Raw"]
        if df.empty:
            raise DataError(f"{device_csv}: no 'Raw' measurement rows")
    has_clk = "HardwareClockDiscontinuityCount" in df.columns
    if has_clk:
        _to_numeric(df, ["HardwareClockDiscontinuityCount"], device_csv)
    rows = _standard_rows(df, _MEAS_COLS_2022, _VEL_COLS_2022, device_csv, skipped)
    _check_increasing(rows["t"].to_numpy(), rows["row"].to_numpy(), device_csv, "utcTimeMillis")
    rows = rows.assign(t=unix_ms_to_gps_ms(rows["t"].to_numpy(np.int64)))
    clk = None
    if has_clk:
        clk = df.set_index("_row")["HardwareClockDiscontinuityCount"].reindex(rows["row"]).to_numpy(float)
        clk = np.nan_to_num(clk, nan=-1).astype(np.int64)
    kwargs = _rows_to_trace(rows, name=name or device_csv.stem, path=device_csv, signals=signals,
                            min_sats=min_sats, skipped=skipped, clock_count=clk)
    truth = None
    if truth_csv is not None:
        truth_csv = Path(truth_csv)
        tdf = read_truth_csv(truth_csv, skipped)
        truth = match_nearest(kwargs["t_ms"], tdf["t_ms"].to_numpy(), _llh_ecef(tdf), truth_tol_ms)
        _check_overlap(kwargs["t_ms"], tdf["t_ms"].to_numpy(), truth, device_csv, truth_csv)
    return Trace(truth=truth, skipped=skipped, **kwargs)


# ---------------------------------------------------------------------------- folders
def _csv_name(p: Path) -> str:
    """'x.csv' or 'x.csv.gz' -> 'x', else ''."""
    n = p.name
    for suf in (".csv.gz", ".csv"):
        if n.endswith(suf):
            return n[: -len(suf)]
    return ""


def _measurement_files(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file()
             and ("_derived" in _csv_name(p) or _csv_name(p) == "device_gnss")]
    return sorted(files)


def _find_optional(folder: Path, stem: str) -> Path | None:
    for suf in (".csv", ".csv.gz"):
        if (folder / f"{stem}{suf}").is_file():
            return folder / f"{stem}{suf}"
    return None


def _span_file(folder: Path, phone: str) -> Path | None:
    sup = folder / "supplemental"
    if not sup.is_dir():
        return None
    cands = sorted(p for p in sup.iterdir() if p.name.startswith("SPAN_")
                   and (p.name.endswith(".nmea") or p.name.endswith(".nmea.gz")))
    if len(cands) > 1:
        cands = [p for p in cands if phone in p.name] or cands
        if len(cands) > 1:
            raise DataError(f"{sup}: several SPAN NMEA logs ({', '.join(p.name for p in cands)}); pass one")
    return cands[0] if cands else None


def load_trace(path: str | Path, signals=("GPS_L1",), fix_truth_height: bool = True, truth: str = "auto",
               *, min_sats: int = 4, truth_tol_ms: float = TRUTH_TOL_MS) -> Trace:
    """Load one trace: a ``<collection>/<phone>`` folder, or a measurement file inside one.

    Format is detected from the files (``*_derived.csv[.gz]`` -> GSDC 2021, ``device_gnss.csv[.gz]``
    -> GSDC 2022/23). ``truth``: ``"auto"`` (SPAN NMEA when present for 2021, else
    ``ground_truth.csv``, else none), ``"csv"`` (ignore NMEA), ``"nmea"`` (require it), ``"none"``.
    The trace is named ``<collection>/<phone>`` after its folder, or ``<folder>/<stem>`` when that
    folder holds several measurement files (e.g. ``samples/Pixel4_derived``).
    """
    path = Path(path)
    if truth not in ("auto", "csv", "nmea", "none"):
        raise GnssfuseError(f"truth must be 'auto', 'csv', 'nmea' or 'none', got {truth!r}")
    if path.is_dir():
        files = _measurement_files(path)
        if not files:
            raise DataError(f"{path}: no *_derived.csv[.gz] or device_gnss.csv[.gz] measurement file")
        if len(files) > 1:
            raise DataError(f"{path}: several measurement files ({', '.join(p.name for p in files)}); "
                            f"pass one of them")
        meas, folder = files[0], path
        single = True
    elif path.is_file():
        meas, folder = path, path.parent
        single = len(_measurement_files(folder)) == 1
    else:
        raise DataError(f"{path}: no such trace folder or file")
    name = f"{folder.parent.name}/{folder.name}" if single else f"{folder.name}/{_csv_name(meas)}"
    stem = _csv_name(meas)

    # Truth beside the file: '<x>_ground_truth' pairs with '<x>_derived'; else the folder's one.
    truth_csv = None
    if truth in ("auto", "csv"):
        paired = _find_optional(folder, stem.replace("_derived", "_ground_truth")) if "_derived" in stem else None
        truth_csv = paired or (_find_optional(folder, "ground_truth") if single else None)

    if stem == "device_gnss":
        if truth == "nmea":
            raise DataError(f"{folder}: truth='nmea' is only for GSDC 2021 traces with a SPAN log")
        return load_device_gnss(meas, truth_csv, signals=signals, min_sats=min_sats,
                                truth_tol_ms=truth_tol_ms, name=name)
    nmea = None
    if truth in ("auto", "nmea") and single:
        nmea = _span_file(folder, folder.name)
    if truth == "nmea":
        if nmea is None:
            raise DataError(f"{folder}: truth='nmea' but no supplemental/SPAN_*.nmea[.gz] file")
        if not fix_truth_height:
            raise GnssfuseError("truth='nmea' already has correct heights; fix_truth_height=False contradicts it")
    return load_derived_2021(meas, truth_csv, nmea, signals=signals, fix_truth_height=fix_truth_height,
                             min_sats=min_sats, truth_tol_ms=truth_tol_ms, name=name)


def find_traces(root: str | Path) -> list[Path]:
    """Every loadable trace under ``root`` (a Kaggle-layout folder such as ``train/``, or a trace).

    Returns ``<collection>/<phone>`` folders holding one measurement file; folders holding several
    (e.g. ``samples/``) contribute each file, which :func:`load_trace` also accepts. Sorted.
    Raises :class:`DataError` when ``root`` does not exist or holds no trace.
    """
    root = Path(root)
    if not root.exists():
        raise DataError(f"{root}: no such folder")
    if root.is_file():
        return [root]
    found: list[Path] = []
    for folder in sorted({root, *(p for p in root.rglob("*") if p.is_dir())}):
        files = _measurement_files(folder)
        found.extend([folder] if len(files) == 1 else files)
    if not found:
        raise DataError(f"{root}: no trace found (no *_derived.csv[.gz] or device_gnss.csv[.gz] below it)")
    return sorted(found)


def load_dataset(root: str | Path, signals=("GPS_L1",), fix_truth_height: bool = True, truth: str = "auto",
                 *, min_sats: int = 4, on_error: str = "raise") -> Iterator[Trace]:
    """Yield :func:`load_trace` of every trace :func:`find_traces` finds under ``root``.

    on_error: ``"raise"`` stops at the first bad trace; ``"skip"`` warns and goes on.
    """
    if on_error not in ("raise", "skip"):
        raise GnssfuseError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    for path in find_traces(root):
        try:
            yield load_trace(path, signals=signals, fix_truth_height=fix_truth_height, truth=truth,
                             min_sats=min_sats)
        except DataError as exc:
            if on_error == "raise":
                raise
            warnings.warn(f"skipping trace: {exc}", stacklevel=2)
