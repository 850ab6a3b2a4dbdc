"""Carrier-to-noise density (C/N0) of simulated signals, and the code-tracking noise it implies.

C/N0 [dB-Hz] of a line-of-sight signal (every term a column of the model a network can learn)::

    cn0 = zenith_db[signal]                       signal power at zenith for an isotropic antenna
        + 20 log10(r_zenith / r)                  free-space loss of the longer low-elevation path
        + gain_horizon_db * (1 - sin el)^2        antenna pattern (0 dB at zenith, a few dB down at 5 deg)
        + receiver_offset                         per trace: the phone's antenna/front-end, U[receiver_db]
        + satellite_offset                        per trace and satellite: transmit power, body shadowing
        + N(0, noise_db^2)                        per measurement: fading and the C/N0 estimator's noise
        - loss_db                                 NLOS reflection / diffraction loss (from the canyon model)

Signals below ``track_db`` are not tracked (the measurement does not exist).

Code noise (delay-locked loop with a non-coherent early-minus-late power discriminator, the standard
thermal-noise formula, e.g. Kaplan & Hegarty, *Understanding GPS/GNSS*, 3rd ed., eq. 8.41)::

    sigma_dll [chips] = sqrt( B_L d / (2 C/N0) * (1 + 2 / (T (2 - d) C/N0)) )

with loop bandwidth ``B_L`` [Hz], correlator spacing ``d`` [chips], integration ``T`` [s] and C/N0
in linear Hz, times the chip length of the signal; a floor ``floor_m`` adds in quadrature (residual
multipath and quantisation that no tracking loop removes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.geometry import C_LIGHT
from fusion.trace import SIGNALS

#: Chip rate [chips/s] of the ranging code of each signal.
CHIP_RATE = {"GPS_L1": 1.023e6, "GPS_L5": 10.23e6, "GLO_G1": 0.511e6, "GAL_E1": 1.023e6,
             "GAL_E5A": 10.23e6, "BDS_B1I": 2.046e6, "QZS_J1": 1.023e6, "QZS_J5": 10.23e6,
             # second frequencies (L2C: CM and CL chips time-multiplexed at 1.023 Mcps)
             "GPS_L2": 1.023e6, "GAL_E5B": 10.23e6, "BDS_B2I": 2.046e6, "QZS_J2": 1.023e6,
             "BDS_B1C": 1.023e6, "BDS_B2A": 10.23e6}
#: Zenith C/N0 [dB-Hz] of each signal for an isotropic antenna at nominal received power
#: (GPS L1 C/A -158.5 dBW into a -204 dBW/Hz noise floor = 45.5; others relative to it).
ZENITH_DB = {"GPS_L1": 45.5, "GPS_L5": 47.5, "GLO_G1": 44.5, "GAL_E1": 44.5, "GAL_E5A": 46.5,
             "BDS_B1I": 43.5, "QZS_J1": 45.5, "QZS_J5": 47.5,
             # L2C -160 dBW (1.5 dB below L1 C/A), E5b as E5a, B2I as B1I
             "GPS_L2": 44.0, "GAL_E5B": 46.5, "BDS_B2I": 43.5, "QZS_J2": 44.0,
             # B1C -159 dBW (data + pilot), B2a -156 dBW (BDS-SIS-ICD-B1C / B2a 1.0)
             "BDS_B1C": 45.0, "BDS_B2A": 47.5}
#: Chip length [m] per signal index (index into SIGNALS).
CHIP_M = np.array([C_LIGHT / CHIP_RATE[s] for s in SIGNALS])
_ZENITH = np.array([ZENITH_DB[s] for s in SIGNALS])
_R_ZENITH_M = 20_200_000.0   # reference range for the path-loss term (GPS at zenith)


@dataclass
class Cn0Model:
    """Parameters of the C/N0 and code-noise model (see module docstring). dB, Hz, s, chips, m."""

    gain_horizon_db: float = -10.0
    receiver_db: tuple[float, float] = (-8.0, 4.0)
    satellite_sigma_db: float = 1.5
    noise_db: float = 1.0
    track_db: float = 18.0
    loop_bw_hz: float = 1.0
    spacing_chips: float = 0.5
    integration_s: float = 0.02
    floor_m: float = 0.5

    def validate(self) -> None:
        lo, hi = self.receiver_db
        if not (lo <= hi and self.satellite_sigma_db >= 0 and self.noise_db >= 0):
            raise ValueError(f"bad C/N0 spreads: receiver_db {self.receiver_db}, satellite_sigma_db "
                             f"{self.satellite_sigma_db}, noise_db {self.noise_db}")
        if not (self.loop_bw_hz > 0 and 0 < self.spacing_chips <= 1 and self.integration_s > 0 and self.floor_m >= 0):
            raise ValueError(f"bad DLL settings: loop_bw_hz {self.loop_bw_hz}, spacing_chips {self.spacing_chips}, "
                             f"integration_s {self.integration_s}, floor_m {self.floor_m}")


def los_cn0(signal: np.ndarray, el_deg: np.ndarray, range_m: np.ndarray, model: Cn0Model) -> np.ndarray:
    """Deterministic line-of-sight C/N0 [dB-Hz] (any shape, broadcast): signal power, path loss,
    antenna pattern; no receiver, satellite or noise terms."""
    s = np.sin(np.radians(np.clip(el_deg, 0.0, 90.0)))
    path = 20.0 * np.log10(_R_ZENITH_M / np.maximum(range_m, 1.0))
    return _ZENITH[signal] + path + model.gain_horizon_db * (1.0 - s) ** 2


def draw_cn0(base_db: np.ndarray, trace_of_epoch: np.ndarray, model: Cn0Model,
             rng: np.random.Generator) -> np.ndarray:
    """(E, P) C/N0 [dB-Hz]: ``base_db`` (E, P) plus the per-trace receiver offset, the per
    (trace, satellite) offset and per-measurement noise. trace_of_epoch (E,) int trace index."""
    E, P = base_db.shape
    n_tr = int(trace_of_epoch.max(initial=0)) + 1
    receiver = rng.uniform(*model.receiver_db, n_tr)
    sat = rng.standard_normal((n_tr, P)) * model.satellite_sigma_db
    noise = rng.standard_normal((E, P)) * model.noise_db
    return base_db + receiver[trace_of_epoch][:, None] + sat[trace_of_epoch] + noise


def dll_sigma_m(cn0_db: np.ndarray, signal: np.ndarray, model: Cn0Model) -> np.ndarray:
    """Code (pseudorange) noise 1-sigma [m] of the DLL at C/N0 ``cn0_db`` (any shape) for
    ``signal`` (indices into SIGNALS, broadcast), the floor added in quadrature."""
    c = 10.0 ** (np.asarray(cn0_db, float) / 10.0)
    d, T = model.spacing_chips, model.integration_s
    chips = np.sqrt(model.loop_bw_hz * d / (2.0 * c) * (1.0 + 2.0 / (T * (2.0 - d) * c)))
    return np.hypot(chips * CHIP_M[signal], model.floor_m)


def doppler_sigma_scale(cn0_db: np.ndarray, ref_db: float = 40.0) -> np.ndarray:
    """Factor on the Doppler (pseudorange-rate) noise at C/N0 ``cn0_db`` relative to ``ref_db``:
    frequency-loop jitter grows like 1 / sqrt(C/N0) (and faster near the tracking threshold,
    which the clip at 4x ignores)."""
    return np.clip(10.0 ** ((ref_db - np.asarray(cn0_db, float)) / 20.0), 0.5, 4.0)
