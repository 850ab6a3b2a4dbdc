"""The optional Trace fields (C/N0, Doppler, carrier phase) from GSDC 2022/2023 ``device_gnss.csv`` columns.

Semantics follow :class:`fusion.trace.Trace`: like the corrected pseudorange, Doppler and carrier
phase get the satellite clock removed (``prr = PseudorangeRateMetersPerSecond +
SvClockDriftMetersPerSecond``, ``adr = AccumulatedDeltaRangeMeters + SvClockBiasMeters``).
A group whose source columns are absent is left out (the Trace gets None for it), never faked.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd


# AccumulatedDeltaRangeState bits (android.location.GnssMeasurement).
ADR_VALID, ADR_RESET, ADR_CYCLE_SLIP = 1, 2, 4

_CN0 = ("Cn0DbHz",)
_DOPPLER = ("PseudorangeRateMetersPerSecond", "PseudorangeRateUncertaintyMetersPerSecond",
            "SvClockDriftMetersPerSecond")
_CARRIER = ("AccumulatedDeltaRangeMeters", "AccumulatedDeltaRangeUncertaintyMeters",
            "AccumulatedDeltaRangeState", "SvClockBiasMeters")


def optional_row_columns(df: pd.DataFrame, rows: np.ndarray, path: Path) -> dict[str, np.ndarray]:
    """Per-row optional Trace fields for the kept measurement rows.

    df:   the device_gnss table with a ``_row`` column (1-based file data row).
    rows: (N,) ``_row`` values of the kept rows, in their order.
    Returns Trace field name -> (N,) array, with the Trace's fillers already in place where a
    value is unusable (0 value / sigma 1 / flags False), for the groups whose columns exist.
    """
    have = lambda cols: all(c in df.columns for c in cols)  # noqa: E731
    wanted = [c for group in (_CN0, _DOPPLER, _CARRIER) if have(group) for c in group]
    if not wanted:
        return {}
    # an unreadable optional value only makes that measurement's Doppler / phase unusable (filler below)
    for c in wanted:
        df[c] = pd.to_numeric(df[c], errors="coerce")
    src = df.set_index("_row")[wanted].reindex(rows)
    col = {c: src[c].to_numpy(float) for c in wanted}
    out: dict[str, np.ndarray] = {}
    if have(_CN0):
        out["cn0"] = np.nan_to_num(col["Cn0DbHz"], nan=0.0)
    if have(_DOPPLER):
        prr = col["PseudorangeRateMetersPerSecond"] + col["SvClockDriftMetersPerSecond"]
        sigma = col["PseudorangeRateUncertaintyMetersPerSecond"]
        ok = np.isfinite(prr) & np.isfinite(sigma) & (sigma > 0)
        out |= {"prr": np.where(ok, prr, 0.0), "prr_sigma": np.where(ok, sigma, 1.0), "prr_ok": ok}
    if have(_CARRIER):
        out |= _carrier(col)
    return out


def _carrier(col: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Carrier-phase fields from the (N,) source columns."""
    state = np.nan_to_num(col["AccumulatedDeltaRangeState"], nan=0).astype(np.int64)
    adr = col["AccumulatedDeltaRangeMeters"] + col["SvClockBiasMeters"]
    sigma = col["AccumulatedDeltaRangeUncertaintyMeters"]
    ok = (state & ADR_VALID != 0) & np.isfinite(adr) & np.isfinite(sigma) & (sigma > 0)
    slip = ok & (state & (ADR_RESET | ADR_CYCLE_SLIP) != 0)
    return {"adr": np.where(ok, adr, 0.0), "adr_sigma": np.where(ok, sigma, 1.0), "adr_ok": ok, "adr_slip": slip}
