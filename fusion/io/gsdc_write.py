"""A trace in the GSDC 2021 derived format (``<phone>_derived.csv`` + ``ground_truth.csv``): what
``gnssfuse simulate`` writes, so a simulated drive loads like a real one (:mod:`fusion.io.gsdc`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np
import pandas as pd

from fusion.geometry import C_LIGHT, ecef2geodetic, ecef2ned_vec
from fusion.io.truth import GSDC2021_TRUTH_HEIGHT_ERROR_M as GSDC2021_HEIGHT_ERROR_M
from fusion.trace import SIGNALS, Trace


class SimulatedTrace(Protocol):
    """What the writer reads of a :class:`fusion.sim.simulate.SimResult` (named here by its fields so
    that ``fusion.io`` needs nothing above the shared vocabulary): the trace (with truth) and the
    (E, S) satellite clock [m], its drift [m/s], signal flight time [s], iono and tropo delays [m]."""

    trace: Trace
    sat_clock_m: np.ndarray
    sat_clock_drift_mps: np.ndarray
    flight_s: np.ndarray
    iono_m: np.ndarray
    tropo_m: np.ndarray


def write_gsdc2021(result: SimulatedTrace, out_dir: str | Path, collection: str, phone: str = "SimPhone",
                   *, height_error_m: float = GSDC2021_HEIGHT_ERROR_M) -> tuple[Path, Path]:
    """Save as ``<out>/<collection>/<phone>/<phone>_derived.csv`` + ``ground_truth.csv``.

    Derived rows follow GSDC 2021: ``millisSinceGpsEpoch`` is one second late (receive time +
    1000 ms), ``receivedSvTimeInGpsNanos`` is the transmit time on the satellite's clock,
    satellite states are at the true transmit time, and rawPrM carries the satellite clock,
    iono and tropo so that the standard correction gives back ``trace.pr``. Truth heights get
    ``+height_error_m`` (the real files' error; 0 writes true heights).
    Returns (derived path, ground-truth path).
    """
    tr = result.trace
    folder = Path(out_dir) / collection / phone
    folder.mkdir(parents=True, exist_ok=True)
    e, s = np.nonzero(tr.mask)
    t = tr.t_ms[e]
    clk = np.round(result.sat_clock_m[e, s], 3)
    iono = np.round(result.iono_m[e, s], 3)
    tropo = np.round(result.tropo_m[e, s], 3)
    # Use the rounded columns so the correction reproduces pr to the file's last digit.
    raw = np.round(tr.pr[e, s] - clk + iono + tropo, 3)
    tx_sv_ns = t * 1_000_000 - np.round((result.flight_s[e, s] - result.sat_clock_m[e, s] / C_LIGHT)
                                        * 1e9).astype(np.int64)
    pos, vel = np.round(tr.sat_pos[e, s], 3), np.round(tr.sat_vel[e, s], 3)
    derived = pd.DataFrame({
        "collectionName": collection, "phoneName": phone, "millisSinceGpsEpoch": t + 1000,
        "constellationType": tr.sat_id[e, s] // 1000, "svid": tr.sat_id[e, s] % 1000,
        "signalType": np.asarray(SIGNALS)[tr.signal[e, s]], "receivedSvTimeInGpsNanos": tx_sv_ns,
        "xSatPosM": pos[:, 0], "ySatPosM": pos[:, 1], "zSatPosM": pos[:, 2],
        "xSatVelMps": vel[:, 0], "ySatVelMps": vel[:, 1], "zSatVelMps": vel[:, 2],
        "satClkBiasM": clk, "satClkDriftMps": np.round(result.sat_clock_drift_mps[e, s], 3),
        "rawPrM": raw, "rawPrUncM": np.round(tr.pr_sigma[e, s], 3), "isrbM": 0.0,
        "ionoDelayM": iono, "tropoDelayM": tropo,
    })
    d_path = folder / f"{phone}_derived.csv"
    derived.to_csv(d_path, index=False)

    llh = ecef2geodetic(tr.truth)
    v = np.gradient(tr.truth, tr.t_ms * 1e-3, axis=0) if tr.n_epochs > 1 else np.zeros((1, 3))
    v_ned = ecef2ned_vec(v, tr.truth)
    gt = pd.DataFrame({
        "collectionName": collection, "phoneName": phone, "millisSinceGpsEpoch": tr.t_ms,
        "latDeg": np.round(llh[:, 0], 10), "lngDeg": np.round(llh[:, 1], 10),
        "heightAboveWgs84EllipsoidM": np.round(llh[:, 2] + height_error_m, 4),
        "timeSinceFirstFixSeconds": np.round((tr.t_ms - tr.t_ms[0]) * 1e-3, 3),
        "hDop": 0.5, "vDop": 0.0, "speedMps": np.round(np.hypot(v_ned[:, 0], v_ned[:, 1]), 3),
        "courseDegree": np.round(np.degrees(np.arctan2(v_ned[:, 1], v_ned[:, 0])) % 360.0, 2),
    })
    g_path = folder / "ground_truth.csv"
    gt.to_csv(g_path, index=False)
    return d_path, g_path
