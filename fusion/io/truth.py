"""Ground truth: the GSDC truth CSVs (2021 and 2022/23 columns), matching and interpolating truth
at epoch times, and the GSDC 2021 height fix.

GSDC 2021 truth heights are ~63.1 m too high (geoid sign error). With a SPAN NMEA log present it
is the truth; otherwise :data:`GSDC2021_TRUTH_HEIGHT_ERROR_M` is subtracted. We use a fixed 63.1 m
rather than 2x the local geoid separation because the package ships no geoid model and every GSDC
2021 drive is in the San Francisco Bay Area, where 2|N| = 63.10-63.18 m was measured against
SPAN; a warning is raised for truth outside that area.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.geometry import geodetic2ecef
from fusion.gpstime import unix_ms_to_gps_ms
from fusion.io.nmea import read_span_nmea
from fusion.io.clean import coerce_numeric, require_rows, sort_rows
from fusion.io.tables import read_csv_table
from fusion.trace import count_skip

#: GSDC 2021 ground-truth height error [m] (truth minus SPAN, Bay Area), subtracted when fixing.
GSDC2021_TRUTH_HEIGHT_ERROR_M = 63.1
#: Truth rows are matched to epochs by nearest time within this tolerance [ms].
TRUTH_TOL_MS = 20
#: SPAN fixes are interpolated only across gaps up to this long [ms] (10 Hz log -> 100 ms).
NMEA_MAX_GAP_MS = 250
# Where the 63.1 m figure was measured (centre of the GSDC 2021 drives) and how far it applies.
_BAY_AREA_LATLON = (37.5, -122.1)
_BAY_AREA_RADIUS_DEG = 1.5
_TRUTH_COLS_2021 = ("millisSinceGpsEpoch", "latDeg", "lngDeg", "heightAboveWgs84EllipsoidM")
_TRUTH_COLS_2022 = ("UnixTimeMillis", "LatitudeDegrees", "LongitudeDegrees", "AltitudeMeters")


def read_truth_csv(path: str | Path, skipped: dict[str, int] | None = None) -> pd.DataFrame:
    """Ground truth of either format -> DataFrame t_ms (GPS ms), lat_deg, lon_deg, height_m.

    Heights are as in the file (GSDC 2021's are ~63 m too high; :func:`load_derived_2021` fixes
    them). Cleaning as in :mod:`fusion.io.clean`, counts prefixed ``truth_``: exact duplicates and
    rows with a bad value are dropped, rows are put in time order, and of several rows at one time
    the first is kept (``truth_conflicting_duplicate_rows``).
    """
    path = Path(path)
    skipped = {} if skipped is None else skipped
    df = read_csv_table(path, [], "ground truth", skipped, prefix="truth_")
    if all(c in df.columns for c in _TRUTH_COLS_2021):
        cols, unix = _TRUTH_COLS_2021, False
    elif all(c in df.columns for c in _TRUTH_COLS_2022):
        cols, unix = _TRUTH_COLS_2022, True
    else:
        raise DataError(f"{path}: ground truth file lacks columns: need either {', '.join(_TRUTH_COLS_2021)} "
                        f"(GSDC 2021) or {', '.join(_TRUTH_COLS_2022)} (GSDC 2022/23)")
    df = coerce_numeric(df, cols, skipped, prefix="truth_")
    require_rows(df, path, "ground truth", {k: v for k, v in skipped.items() if k.startswith("truth_")})
    df = sort_rows(df, [cols[0]], path)
    t = df[cols[0]].to_numpy(np.int64)
    t = unix_ms_to_gps_ms(t) if unix else t
    out = pd.DataFrame({"t_ms": t, "lat_deg": df[cols[1]].to_numpy(float),
                        "lon_deg": df[cols[2]].to_numpy(float), "height_m": df[cols[3]].to_numpy(float)})
    dup = out.duplicated("t_ms").to_numpy()
    count_skip(skipped, "truth_conflicting_duplicate_rows", dup.sum())
    return out[~dup].reset_index(drop=True)


def llh_ecef(df: pd.DataFrame) -> np.ndarray:
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


def check_overlap(t_ms: np.ndarray, truth_t: np.ndarray, matched: np.ndarray,
                   meas: Path, truth: Path) -> None:
    if not np.isfinite(matched).all(axis=1).any():
        raise DataError(f"{meas}: epoch times {t_ms.min()}..{t_ms.max()} (GPS ms) do not overlap the "
                        f"ground truth {truth} times {truth_t.min()}..{truth_t.max()}")


def warn_outside_bay_area(truth: pd.DataFrame, path: Path) -> None:
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
