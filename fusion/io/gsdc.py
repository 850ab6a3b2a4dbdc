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
2. GSDC 2021 truth heights are ~63.1 m too high (geoid sign error): :mod:`fusion.io.truth`.
3. Receiver clock discontinuities: 2022/23 ``HardwareClockDiscontinuityCount`` changes set
   ``clock_reset``; 2021 derived files carry no such column (estimators detect jumps).

Bad input raises :class:`DataError` naming the file and problem; recoverable defects (rows with
missing values, duplicates, epochs with too few satellites) are dropped and counted in
``Trace.skipped``.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.geometry import C_LIGHT
from fusion.gpstime import unix_ms_to_gps_ms
from fusion.io.device_optional import optional_row_columns
from fusion.io.nmea import read_span_nmea
from fusion.io.clean import ROW, coerce_numeric, epochs_with_enough_rows, require_rows, sort_rows
from fusion.io.tables import read_csv_table
from fusion.io.truth import (GSDC2021_TRUTH_HEIGHT_ERROR_M, TRUTH_TOL_MS, check_overlap, interp_gapped,
                             llh_ecef, match_nearest, read_truth_csv, warn_outside_bay_area)
from fusion.trace import SIGNALS, Trace, count_skip, flags_since_previous, pack_rows, resolve_signals, signal_index

log = logging.getLogger(__name__)

#: GSDC 2021 derived timestamps are this much later than the true receive time [ms].
DERIVED_DELAY_MS = 1000
# Plausibility bounds (reject garbage, not outliers): MEO..GEO orbit radii, ranges from Earth.
_SAT_RADIUS_M = (1.0e7, 5.0e7)
_PR_RANGE_M = (1.0e7, 5.0e7)

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
    sig = cols["signal"]
    missing_sig = df[sig].isna().to_numpy()
    count_skip(skipped, f"rows_missing:{sig}", missing_sig)
    df = coerce_numeric(df[~missing_sig], numeric, skipped)
    # Satellite velocity feeds no estimator here, so a row missing only it keeps its pseudorange and
    # gets the Trace's "unknown" velocity (zeros) instead of being dropped.
    df = coerce_numeric(df, vel, skipped, required=False)
    require_rows(df, path, "measurement", skipped)
    if vel:
        df = df.assign(**{c: df[c].fillna(0.0) for c in vel})
    c = cols
    pr = df[c["raw"]] + df[c["clk"]] - df[c["isrb"]] - df[c["iono"]] - df[c["tropo"]]
    out = pd.DataFrame({
        "t": df[c["t"]].to_numpy(np.float64), "const": df[c["const"]].to_numpy(np.int64),
        "svid": df[c["svid"]].to_numpy(np.int64), "signal_name": df[c["signal"]].to_numpy(object),
        "x": df[c["x"]].to_numpy(float), "y": df[c["y"]].to_numpy(float), "z": df[c["z"]].to_numpy(float),
        "pr": pr.to_numpy(float), "pr_sigma": df[c["unc"]].to_numpy(float), "row": df[ROW].to_numpy(),
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
    t_file = np.unique(rows["t"].to_numpy(np.int64))
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

    rows = sort_rows(rows, ["t", "const", "svid", "signal"], path)
    # exact duplicates are gone already (read_csv_table); these disagree on some value: first kept
    dup = rows.duplicated(["t", "const", "svid", "signal"]).to_numpy()
    count_skip(skipped, "conflicting_duplicate_rows", dup.sum())
    rows = rows[~dup]

    keep, epoch, t_ms = epochs_with_enough_rows(
        rows["t"].to_numpy(np.int64), min_sats, skipped, path,
        f"satellites of the selected signal(s) ({', '.join(SIGNALS[i] for i in sel)})")
    rows = rows[keep]
    E = t_ms.shape[0]

    packed = pack_rows(epoch, E, {
        "sat_pos": rows[["x", "y", "z"]].to_numpy(float),
        "sat_vel": rows[["vx", "vy", "vz"]].to_numpy(float),
        "pr": rows["pr"].to_numpy(float), "pr_sigma": rows["pr_sigma"].to_numpy(float),
        "sat_id": (1000 * rows["const"].to_numpy() + rows["svid"].to_numpy()).astype(np.int32),
        "signal": rows["signal"].to_numpy(np.int8),
    })
    # Optional Trace fields ride along as "opt_<field>" columns through the filters above.
    optional = {k[4:]: rows[k].to_numpy() for k in rows.columns if k.startswith("opt_")}
    if optional:
        packed |= {k: v for k, v in pack_rows(epoch, E, optional).items() if k != "mask"}
    if "adr_slip" in packed:
        # a dropped epoch may hide a cycle slip: no carrier chain across it
        _, gap = flags_since_previous(np.zeros(t_file.size, bool), np.searchsorted(t_file, t_ms))
        packed["adr_slip"] = packed["adr_slip"] | gap[:, None]
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
    df = read_csv_table(path, list(_MEAS_COLS_2021.values()), "GSDC 2021 derived", skipped)
    rows = _standard_rows(df, _MEAS_COLS_2021, _VEL_COLS_2021, path, skipped)
    received = None
    if "receivedSvTimeInGpsNanos" in df.columns:
        # Optional column, used only to place rows in time; unparsable or implausible values fall
        # back to 1000 ms.
        rec = pd.to_numeric(df.set_index(ROW)["receivedSvTimeInGpsNanos"], errors="coerce")
        received = rec.reindex(rows["row"]).to_numpy(float)
    t_true, n_moved = _retime_derived(rows, received)
    if n_moved:
        log.info("%s: %d rows were not stamped one epoch late; placed at their own receive time", path, n_moved)
    return rows.assign(t=t_true)


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
            warn_outside_bay_area(tdf, truth_csv)
            tdf = tdf.assign(height_m=tdf["height_m"] - GSDC2021_TRUTH_HEIGHT_ERROR_M)
        truth = match_nearest(t_ms, tdf["t_ms"].to_numpy(), llh_ecef(tdf), truth_tol_ms)
        check_overlap(t_ms, tdf["t_ms"].to_numpy(), truth, derived, truth_csv)
    if nmea is not None and (fix_truth_height or truth is None):
        nmea = Path(nmea)
        span = read_span_nmea(nmea, ref_gps_ms=int(t_ms[0]), skipped=skipped)
        span_truth = interp_gapped(t_ms, span["t_ms"].to_numpy(), llh_ecef(span))
        check_overlap(t_ms, span["t_ms"].to_numpy(), span_truth, derived, nmea)
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
    ``HardwareClockDiscontinuityCount`` changed since the previous kept epoch. The optional
    fields (cn0, Doppler, carrier phase) are filled when their columns are present
    (:mod:`fusion.io.device_optional`).
    """
    device_csv = Path(device_csv)
    skipped: dict[str, int] = {}
    df = read_csv_table(device_csv, list(_MEAS_COLS_2022.values()), "GSDC device_gnss", skipped)
    if "MessageType" in df.columns:
        df = df[df["MessageType"].astype(str).str.strip() == "Raw"]
        if df.empty:
            raise DataError(f"{device_csv}: no 'Raw' measurement rows")
    has_clk = "HardwareClockDiscontinuityCount" in df.columns
    if has_clk:
        df = coerce_numeric(df, ["HardwareClockDiscontinuityCount"], skipped, required=False)
    rows = _standard_rows(df, _MEAS_COLS_2022, _VEL_COLS_2022, device_csv, skipped)
    rows = rows.assign(t=unix_ms_to_gps_ms(rows["t"].to_numpy(np.int64)))
    optional = optional_row_columns(df, rows["row"].to_numpy(), device_csv)
    rows = rows.assign(**{f"opt_{k}": v for k, v in optional.items()})
    clk = None
    if has_clk:
        clk = df.set_index(ROW)["HardwareClockDiscontinuityCount"].reindex(rows["row"]).to_numpy(float)
        clk = np.nan_to_num(clk, nan=-1).astype(np.int64)
    kwargs = _rows_to_trace(rows, name=name or device_csv.stem, path=device_csv, signals=signals,
                            min_sats=min_sats, skipped=skipped, clock_count=clk)
    truth = None
    if truth_csv is not None:
        truth_csv = Path(truth_csv)
        tdf = read_truth_csv(truth_csv, skipped)
        truth = match_nearest(kwargs["t_ms"], tdf["t_ms"].to_numpy(), llh_ecef(tdf), truth_tol_ms)
        check_overlap(kwargs["t_ms"], tdf["t_ms"].to_numpy(), truth, device_csv, truth_csv)
    return Trace(truth=truth, skipped=skipped, **kwargs)


