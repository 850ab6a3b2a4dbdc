"""Save a simulated trace: GSDC 2021 derived format (:func:`write_gsdc2021`, GPS-era columns, no
C/N0 or Doppler) or GSDC 2022/23 ``device_gnss.csv`` (:func:`write_device_gnss`) with truth and labels;
:func:`write_trace` picks by what the trace carries.

The device_gnss writer fills

``<out>/<collection>/<phone>/`` with

- ``device_gnss.csv``: one ``Raw`` row per measurement with the columns
  :func:`fusion.io.gsdc.load_device_gnss` reads: raw pseudorange and its uncertainty, satellite
  position / velocity / clock at transmit time, iono and tropo delays, ``Cn0DbHz``, Doppler as
  ``PseudorangeRateMetersPerSecond`` (+ uncertainty) and, when simulated, carrier phase as
  ``AccumulatedDeltaRangeMeters`` (+ uncertainty and state bits: valid, reset at each new arc).
  Corrections reproduce the simulated values: ``RawPseudorangeMeters + SvClockBiasMeters -
  IsrbMeters - IonosphericDelayMeters - TroposphericDelayMeters = trace.pr`` (to the millimetre),
  ``PseudorangeRateMetersPerSecond + SvClockDriftMetersPerSecond = trace.prr``.
  Times are ``utcTimeMillis`` (Unix ms of the GPS receive time, as the real files).
- ``ground_truth.csv``: ``UnixTimeMillis``, ``LatitudeDegrees``, ``LongitudeDegrees``,
  ``AltitudeMeters`` (ellipsoidal, no GSDC 2021 height error), speed and bearing.
- ``sim_labels.csv`` (with a C/N0 model): the hidden truth of every measurement: class (LOS, NLOS,
  DIFFRACTED), extra NLOS path, LOS multipath error, range-rate error, power loss, the true noise, and (with
  ``--broadcast-errors``) the error the broadcast corrections leave.
  It is for analysing results only: no loader reads it and no model may take it as input.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.geometry import C_LIGHT, ecef2geodetic, ecef2ned_vec
from fusion.gpstime import gps_ms_to_unix_ms
from fusion.io.gsdc_write import write_gsdc2021
from fusion.sim.canyon import CLASS_NAMES
from fusion.trace import SIGNALS

#: Name of the per-measurement label file (never read by a loader or a model).
LABELS_FILE = "sim_labels.csv"


def _measurement_table(result, e: np.ndarray, s: np.ndarray) -> pd.DataFrame:
    """device_gnss rows of the real slots (e, s) (N,) of a SimResult."""
    tr = result.trace
    t = tr.t_ms[e]
    clk = np.round(result.sat_clock_m[e, s], 3)
    iono, tropo = np.round(result.iono_m[e, s], 3), np.round(result.tropo_m[e, s], 3)
    raw = np.round(tr.pr[e, s] - clk + iono + tropo, 3)
    pos, vel = np.round(tr.sat_pos[e, s], 3), np.round(tr.sat_vel[e, s], 4)
    flight_sv_s = result.flight_s[e, s] - result.sat_clock_m[e, s] / C_LIGHT   # on the satellite's clock
    tx_ns = t * 1_000_000 - np.round(flight_sv_s * 1e9).astype(np.int64)
    df = pd.DataFrame({
        "MessageType": "Raw", "utcTimeMillis": gps_ms_to_unix_ms(t), "HardwareClockDiscontinuityCount":
            np.cumsum(tr.clock_reset)[e], "Svid": tr.sat_id[e, s] % 1000, "ConstellationType": tr.sat_id[e, s] // 1000,
        "SignalType": np.asarray(SIGNALS)[tr.signal[e, s]], "ReceivedSvTimeNanosSinceGpsEpoch": tx_ns,
        "RawPseudorangeMeters": raw, "RawPseudorangeUncertaintyMeters": np.round(tr.pr_sigma[e, s], 3),
        "SvPositionXEcefMeters": pos[:, 0], "SvPositionYEcefMeters": pos[:, 1], "SvPositionZEcefMeters": pos[:, 2],
        "SvElevationDegrees": np.round(result.elev_deg[e, s], 3), "SvAzimuthDegrees": np.round(result.az_deg[e, s], 3),
        "SvVelocityXEcefMetersPerSecond": vel[:, 0], "SvVelocityYEcefMetersPerSecond": vel[:, 1],
        "SvVelocityZEcefMetersPerSecond": vel[:, 2], "SvClockBiasMeters": clk,
        "SvClockDriftMetersPerSecond": np.round(result.sat_clock_drift_mps[e, s], 4), "IsrbMeters": 0.0,
        "IonosphericDelayMeters": iono, "TroposphericDelayMeters": tropo,
    })
    if tr.cn0 is not None:
        df["Cn0DbHz"] = np.round(tr.cn0[e, s], 2)
    if tr.prr is not None:
        ok = tr.prr_ok[e, s]
        prr = np.round(tr.prr[e, s] - df["SvClockDriftMetersPerSecond"], 4)
        df["PseudorangeRateMetersPerSecond"] = np.where(ok, prr, np.nan)
        df["PseudorangeRateUncertaintyMetersPerSecond"] = np.where(ok, np.round(tr.prr_sigma[e, s], 4), np.nan)
    if tr.adr is not None:
        ok = tr.adr_ok[e, s]
        df["AccumulatedDeltaRangeState"] = np.where(ok, 1, 0) | np.where(tr.adr_slip[e, s], 2, 0)
        df["AccumulatedDeltaRangeMeters"] = np.where(ok, np.round(tr.adr[e, s] - clk, 4), 0.0)
        df["AccumulatedDeltaRangeUncertaintyMeters"] = np.where(ok, tr.adr_sigma[e, s], 0.0)
    return df


def _truth_table(result) -> pd.DataFrame:
    tr = result.trace
    llh = ecef2geodetic(tr.truth)
    v = np.gradient(tr.truth, tr.t_ms * 1e-3, axis=0) if tr.n_epochs > 1 else np.zeros((1, 3))
    v_ned = ecef2ned_vec(v, tr.truth)
    return pd.DataFrame({
        "MessageType": "Fix", "Provider": "GT", "LatitudeDegrees": np.round(llh[:, 0], 10),
        "LongitudeDegrees": np.round(llh[:, 1], 10), "AltitudeMeters": np.round(llh[:, 2], 4),
        "SpeedMps": np.round(np.hypot(v_ned[:, 0], v_ned[:, 1]), 3), "AccuracyMeters": 0.1,
        "BearingDegrees": np.round(np.degrees(np.arctan2(v_ned[:, 1], v_ned[:, 0])) % 360.0, 2),
        "UnixTimeMillis": gps_ms_to_unix_ms(tr.t_ms),
    })


def label_table(result) -> pd.DataFrame | None:
    """Per-measurement hidden truth (see module docstring), None without a C/N0 model."""
    if result.los_class is None:
        return None
    tr = result.trace
    e, s = np.nonzero(tr.mask)
    df = pd.DataFrame({
        "utcTimeMillis": gps_ms_to_unix_ms(tr.t_ms[e]), "ConstellationType": tr.sat_id[e, s] // 1000,
        "Svid": tr.sat_id[e, s] % 1000, "SignalType": np.asarray(SIGNALS)[tr.signal[e, s]],
        "Class": np.asarray(CLASS_NAMES)[result.los_class[e, s]],
        "ExtraPathM": np.round(result.nlos_delay_m[e, s], 4), "MultipathM": np.round(result.multipath_m[e, s], 4),
        "NoiseM": np.round(result.noise_m[e, s], 4), "RangeRateErrorMps": np.round(result.prr_error_mps[e, s], 4),
        "PowerLossDb": np.round(result.loss_db[e, s], 2),
    })
    if result.street is not None:
        df["Street"] = result.street[e]
    if result.broadcast_m is not None:
        df["BroadcastErrorM"] = np.round(result.broadcast_m[e, s], 4)
    return df


def write_device_gnss(result, out_dir: str | Path, collection: str, phone: str = "SimPhone"
                      ) -> tuple[Path, Path, Path | None]:
    """Save ``result`` (a :class:`fusion.sim.simulate.SimResult`) under ``<out>/<collection>/<phone>/``.

    Returns (device_gnss.csv, ground_truth.csv, sim_labels.csv or None) paths.
    """
    tr = result.trace
    folder = Path(out_dir) / collection / phone
    folder.mkdir(parents=True, exist_ok=True)
    e, s = np.nonzero(tr.mask)
    d_path, g_path = folder / "device_gnss.csv", folder / "ground_truth.csv"
    _measurement_table(result, e, s).to_csv(d_path, index=False)
    _truth_table(result).to_csv(g_path, index=False)
    labels = label_table(result)
    l_path = None
    if labels is not None:
        l_path = folder / LABELS_FILE
        labels.to_csv(l_path, index=False)
    return d_path, g_path, l_path


#: Output formats of :func:`write_trace`.
FORMATS = ("auto", "gsdc2021", "device_gnss")


def write_trace(result, out_dir: str | Path, collection: str, phone: str = "SimPhone", fmt: str = "auto"
                ) -> list[Path]:
    """Save ``result`` as ``fmt``; ``auto`` writes device_gnss when the trace has C/N0, Doppler,
    carrier phase or a signal other than GPS L1 (which the 2021 derived format cannot all carry),
    else the GSDC 2021 derived format. Returns the written paths."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown output format {fmt!r}; choose one of {', '.join(FORMATS)}")
    tr = result.trace
    rich = tr.cn0 is not None or tr.prr is not None or tr.adr is not None or bool(
        np.any(tr.signal[tr.mask] != SIGNALS.index("GPS_L1")))
    device = fmt == "device_gnss" or (fmt == "auto" and rich)
    check_no_other_trace(Path(out_dir) / collection / phone, phone, device)
    if device:
        return [p for p in write_device_gnss(result, out_dir, collection, phone) if p is not None]
    return list(write_gsdc2021(result, out_dir, collection, phone))


def check_no_other_trace(folder: Path, phone: str, device: bool) -> None:
    """DataError when ``folder`` holds a simulated trace of the other format (its measurement file, or
    per-measurement labels the derived format has none of): written beside it, the folder would hold two
    measurement files (that no command reads) and one truth. The same format is overwritten."""
    other = [f"{phone}_derived.csv"] if device else ["device_gnss.csv", LABELS_FILE]
    found = [name for name in other if (folder / name).is_file()]
    if found:
        raise DataError(f"{folder}: already holds {', '.join(found)} of another simulation; pass another --out, "
                        f"--collection or --seed, or remove it")
