"""What ``gnssfuse run`` and ``evaluate`` write per (trace, mode): ``estimates.csv`` and ``metrics.json``.

``estimates.csv`` columns: :data:`ESTIMATE_COLUMNS`, then :data:`SIGMA_COLUMNS` for modes with a covariance,
then ``bridged`` (0/1) for the graph modes: 1 where fewer than 4 satellites and no prior (the network's, which
reads those same satellites, aside) determined the epoch; then :data:`VELOCITY_COLUMNS` and
:data:`VELOCITY_SIGMA_COLUMNS` for the graph modes with velocity states (the default constant-velocity motion
model) on a trace with Doppler.

Heights are WGS84 ellipsoidal everywhere (``height_m``), as are the positions the exports
(:mod:`fusion.io.export`) write.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.geometry import ecef2geodetic, ecef2ned_cov, ecef2ned_vec
from fusion.run_types import ModeResult
from fusion.trace import Trace

ESTIMATE_COLUMNS = ["gps_millis", "lat_deg", "lon_deg", "height_m", "x_m", "y_m", "z_m"]
#: 1-sigma position uncertainty in the local north/east/down frame at the estimate, for modes with a
#: covariance (empty cells where an epoch has none).
SIGMA_COLUMNS = ["sigma_n_m", "sigma_e_m", "sigma_d_m"]
#: The graph's velocity at the epoch [m/s], north/east/down at the estimate, where its Doppler factors measure it
#: (empty cells elsewhere: the motion model's velocity alone is no better than a difference of the positions,
#: experiments/velocity_output.py).
VELOCITY_COLUMNS = ["vel_n_mps", "vel_e_mps", "vel_d_mps"]
#: Their 1-sigma [m/s] from the graph's marginals, where the banded recursion gives them (after the banded solver,
#: the default, and ISAM2; not where the band is too wide for the recursion). Raw marginals: no variance factor
#: scales them, as it does the positions'.
VELOCITY_SIGMA_COLUMNS = ["sigma_vn_mps", "sigma_ve_mps", "sigma_vd_mps"]
#: How estimates.csv writes floats: 10 significant digits (0.1 mm in ECEF, 1e-8 degree).
FLOAT_FORMAT = "%.10g"
#: The off-diagonal NED covariances [m^2] the RTKLIB .pos export needs (not in estimates.csv).
COVARIANCE_COLUMNS = ["cov_ne_m2", "cov_nd_m2", "cov_ed_m2"]
#: The same of the velocity [m^2/s^2], where :data:`VELOCITY_SIGMA_COLUMNS` are written (not in estimates.csv).
VELOCITY_COVARIANCE_COLUMNS = ["cov_vne_m2s2", "cov_vnd_m2s2", "cov_ved_m2s2"]


def ned_covariances(pos: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,3,3) covariances in the local NED frame at ``pos`` (N,3) ECEF from ECEF ones (N,3,3)."""
    return ecef2ned_cov(cov, pos) if len(pos) else np.zeros((0, 3, 3))


def ned_sigmas(pos: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,3) 1-sigma [m] along north/east/down at ``pos`` (N,3) ECEF from ECEF covariances (N,3,3);
    NaN where the covariance is not finite or has a negative diagonal."""
    var = np.diagonal(ned_covariances(pos, cov), axis1=1, axis2=2)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(var) & (var >= 0), np.sqrt(np.abs(var)), np.nan)


def _solved(result: ModeResult) -> np.ndarray:
    return result.valid & np.isfinite(result.pos).all(axis=1)


def estimates_frame(trace: Trace, result: ModeResult) -> pd.DataFrame:
    """One row per solved epoch, in the CLI contract's columns (+ :data:`SIGMA_COLUMNS` when the mode
    gives a covariance)."""
    ok = _solved(result)
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
    _add_velocity(frame, result.info, ok, pos)
    return frame


def _add_velocity(frame: pd.DataFrame, info: dict, ok: np.ndarray, pos: np.ndarray) -> None:
    """:data:`VELOCITY_COLUMNS` (and :data:`VELOCITY_SIGMA_COLUMNS` where the solver gave marginals) into
    ``frame``, the rows of the solved epochs ``ok`` (E,) at their positions ``pos`` (N,3), where ``info``'s
    ``doppler_epochs`` say Doppler measured the velocity; nothing without a velocity or any such epoch."""
    vel, measured, vel_cov = info.get("vel"), info.get("doppler_epochs"), info.get("vel_cov")
    if not (isinstance(vel, np.ndarray) and vel.shape == (len(ok), 3) and isinstance(measured, np.ndarray)
            and measured.shape == ok.shape and measured.any()):
        return
    columns = [(VELOCITY_COLUMNS, ecef2ned_vec(vel[ok], pos) if len(pos) else np.zeros((0, 3)))]
    if isinstance(vel_cov, np.ndarray) and vel_cov.shape == (len(ok), 3, 3):
        columns.append((VELOCITY_SIGMA_COLUMNS, ned_sigmas(pos, vel_cov[ok])))
    for names, values in columns:
        values[~measured[ok]] = np.nan
        for i, name in enumerate(names):
            frame[name] = values[:, i]


def export_frame(trace: Trace, result: ModeResult) -> pd.DataFrame:
    """:func:`estimates_frame` + ``n_sats`` (satellites measured at the epoch) + :data:`COVARIANCE_COLUMNS`
    when the mode gives a covariance (+ :data:`VELOCITY_COVARIANCE_COLUMNS` where the velocity has sigmas):
    what the writers of :mod:`fusion.io.export` read."""
    ok = _solved(result)
    frame = estimates_frame(trace, result)
    frame["n_sats"] = trace.mask[ok].sum(axis=1)
    pos = result.pos[ok]
    if result.cov is not None:
        _add_off_diagonal(frame, COVARIANCE_COLUMNS, pos, np.asarray(result.cov, float)[ok])
    if VELOCITY_SIGMA_COLUMNS[0] in frame:
        _add_off_diagonal(frame, VELOCITY_COVARIANCE_COLUMNS, pos, result.info["vel_cov"][ok])
        frame.loc[frame[VELOCITY_SIGMA_COLUMNS[0]].isna(), VELOCITY_COVARIANCE_COLUMNS] = np.nan
    return frame


def bridged_rows(frame: pd.DataFrame) -> np.ndarray:
    """(N,) bool: the rows the motion model carried (``bridged`` = 1), none where the frame has no such column."""
    if "bridged" not in frame:
        return np.zeros(len(frame), bool)
    return frame["bridged"].fillna(0).to_numpy(float) == 1


def _add_off_diagonal(frame: pd.DataFrame, names: list[str], pos: np.ndarray, cov: np.ndarray) -> None:
    """The NE, ND and ED terms of the ECEF covariances ``cov`` (N,3,3) at ``pos`` (N,3) as ``names``."""
    ned = ned_covariances(pos, cov)
    for name, (i, j) in zip(names, ((0, 1), (0, 2), (1, 2)), strict=True):
        frame[name] = ned[:, i, j]


def run_record(trace: Trace, mode: str, result: ModeResult, metrics: dict | None) -> dict:
    """What metrics.json holds: the trace, the mode, epoch counts, what the loader skipped, the mode's
    scalar ``info`` (fault detection, guard and graph counts) and the accuracy (None without truth)."""
    return {
        "trace": trace.name, "mode": mode, "epochs_total": trace.n_epochs,
        "epochs_solved": int(result.valid.sum()), "skipped": dict(trace.skipped),
        "info": {k: v for k, v in result.info.items() if isinstance(v, (int, float, str, bool))},
        "metrics": metrics, "covariance": result.cov is not None,
    }


def write_outputs(out_dir: Path, trace: Trace, mode: str, result: ModeResult, metrics: dict | None) -> dict:
    """Write estimates.csv and metrics.json (with ``metrics``, the accuracy against truth, null when
    there is no truth); return the run record (what metrics.json holds)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(estimates_frame(trace, result), out_dir / "estimates.csv")
    record = run_record(trace, mode, result, metrics)
    (out_dir / "metrics.json").write_text(json.dumps(record, indent=2))
    return record


def write_csv(frame: pd.DataFrame, path: Path) -> None:
    """``frame.to_csv(path, index=False, float_format=FLOAT_FORMAT)``, byte for byte, without pandas' per-cell
    formatting machinery (it takes three times as long): integer and float columns; a frame with other
    columns, or with names a CSV must quote, is left to pandas."""
    cols = [frame[c].to_numpy() for c in frame.columns]
    names = [str(c) for c in frame.columns]
    if any(v.dtype.kind not in "iuf" for v in cols) or any(set(n) & set(',"\r\n') for n in names):
        frame.to_csv(path, index=False, float_format=FLOAT_FORMAT)
        return
    lines = [",".join(names), *map(",".join, zip(*map(_cells, cols)))]
    with open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(os.linesep.join(lines) + os.linesep)


def _cells(values: np.ndarray) -> list[str]:
    """(N,) int or float column -> its N CSV cells as pandas writes them (NaN empty, floats in FLOAT_FORMAT)."""
    if values.dtype.kind != "f":
        return [str(v) for v in values.tolist()]
    cells = [FLOAT_FORMAT % v for v in values.tolist()]
    for i in np.flatnonzero(np.isnan(values)):
        cells[i] = ""
    return cells
