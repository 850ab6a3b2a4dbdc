"""What ``gnssfuse run`` and ``evaluate`` write per (trace, mode): ``estimates.csv`` and ``metrics.json``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.geometry import ecef2geodetic
from fusion.run_types import ModeResult
from fusion.trace import Trace

ESTIMATE_COLUMNS = ["gps_millis", "lat_deg", "lon_deg", "height_m", "x_m", "y_m", "z_m"]


def estimates_frame(trace: Trace, result: ModeResult) -> pd.DataFrame:
    """One row per solved epoch, in the CLI contract's columns."""
    ok = result.valid & np.isfinite(result.pos).all(axis=1)
    pos = result.pos[ok]
    llh = ecef2geodetic(pos) if len(pos) else np.zeros((0, 3))
    cols = (trace.t_ms[ok], llh[:, 0], llh[:, 1], llh[:, 2], pos[:, 0], pos[:, 1], pos[:, 2])
    return pd.DataFrame(dict(zip(ESTIMATE_COLUMNS, cols, strict=True)))


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
