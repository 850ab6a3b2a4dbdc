"""What ``gnssfuse run`` and ``evaluate`` write per (trace, mode): ``estimates.csv`` and ``metrics.json``.

``estimates.csv`` columns: :data:`ESTIMATE_COLUMNS`, then :data:`SIGMA_COLUMNS` for modes with a covariance,
then ``bridged`` (0/1) for the graph modes: 1 where fewer than 4 satellites and no prior determined the epoch.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.geometry import ecef2geodetic, ecef2ned_cov
from fusion.run_types import ModeResult
from fusion.trace import Trace

ESTIMATE_COLUMNS = ["gps_millis", "lat_deg", "lon_deg", "height_m", "x_m", "y_m", "z_m"]
#: 1-sigma position uncertainty in the local north/east/down frame at the estimate, for modes with a
#: covariance (empty cells where an epoch has none).
SIGMA_COLUMNS = ["sigma_n_m", "sigma_e_m", "sigma_d_m"]


def ned_sigmas(pos: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,3) 1-sigma [m] along north/east/down at ``pos`` (N,3) ECEF from ECEF covariances (N,3,3);
    NaN where the covariance is not finite or has a negative diagonal."""
    var = np.diagonal(ecef2ned_cov(cov, pos), axis1=1, axis2=2) if len(pos) else np.zeros((0, 3))
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(var) & (var >= 0), np.sqrt(np.abs(var)), np.nan)


def estimates_frame(trace: Trace, result: ModeResult) -> pd.DataFrame:
    """One row per solved epoch, in the CLI contract's columns (+ :data:`SIGMA_COLUMNS` when the mode
    gives a covariance)."""
    ok = result.valid & np.isfinite(result.pos).all(axis=1)
    pos = result.pos[ok]
    llh = ecef2geodetic(pos) if len(pos) else np.zeros((0, 3))
    cols = (trace.t_ms[ok], llh[:, 0], llh[:, 1], llh[:, 2], pos[:, 0], pos[:, 1], pos[:, 2])
    frame = pd.DataFrame(dict(zip(ESTIMATE_COLUMNS, cols, strict=True)))
    if result.cov is not None:
        sig = ned_sigmas(pos, np.asarray(result.cov, float)[ok])
        for i, name in enumerate(SIGMA_COLUMNS):
            frame[name] = sig[:, i]
    bridged = result.info.get("bridged")
    if isinstance(bridged, np.ndarray) and bridged.shape == ok.shape:
        # 1: fewer than 4 satellites and no prior, the motion model carried the epoch
        frame["bridged"] = bridged[ok].astype(int)
    return frame


def write_outputs(out_dir: Path, trace: Trace, mode: str, result: ModeResult, metrics: dict | None) -> dict:
    """Write estimates.csv (+ metrics.json when ``metrics``, the accuracy against truth, is given);
    return the run record (what metrics.json holds)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    estimates_frame(trace, result).to_csv(out_dir / "estimates.csv", index=False, float_format="%.10g")
    record = {
        "trace": trace.name, "mode": mode, "epochs_total": trace.n_epochs,
        "epochs_solved": int(result.valid.sum()), "skipped": dict(trace.skipped),
        "info": {k: v for k, v in result.info.items() if isinstance(v, (int, float, str, bool))},
        "metrics": metrics,
    }
    if metrics is not None:
        (out_dir / "metrics.json").write_text(json.dumps(record, indent=2))
    return record
