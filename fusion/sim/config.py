"""Simulator settings: :class:`SimConfig` and the scenario presets (open sky, suburban, urban canyon, deep high-rise canyon).

The default :class:`SimConfig` is the original GPS-L1 simulator (fixed noise sigma, no C/N0, no
buildings); :func:`scenario_config` returns the multi-constellation settings with C/N0, C/N0-driven
code noise, Doppler and (suburban / urban) street canyons.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, replace

from fusion.sim.canyon import CanyonModel, MultipathModel
from fusion.sim.cn0 import Cn0Model
from fusion.sim.constellations import parse_systems

@dataclass
class SimConfig:
    """Measurement model. Units: metres, seconds, degrees.

    sigma_m:         1-sigma Gaussian pseudorange noise (at zenith when ``elevation_noise``).
    elevation_noise: scale sigma by 1/sin(elevation) (low satellites noisier).
    elev_mask_deg:   satellites below this elevation are not visible.
    max_sats:        cap per epoch (random subset of the visible ones); None = all visible.
    min_sats:        epochs with fewer visible satellites are skipped and counted.
    nlos:            multipath/NLOS scenario: per epoch Poisson(``nlos_rate``) satellites get a
                     positive bias U[``nlos_bias_m``].
    clock_bias0_m:   receiver clock c*dt at the first epoch, drawn uniformly in this range.
    clock_drift0_mps: initial clock drift c*ddt/dt, uniform in this range.
    clock_bias_rw_m / clock_drift_rw_mps: random-walk densities per sqrt(second).
    iono_zenith_m / tropo_zenith_m: zenith delays written to the derived file (they cancel in
                     the corrected pseudorange; only the raw pseudorange carries them).
    doppler:         also simulate pseudorange rates (``Trace.prr``), 1-sigma ``prr_sigma_mps``.
    systems:         constellation letters (G GPS, R GLONASS, E Galileo, C BeiDou), see
                     :mod:`fusion.sim.constellations`.
    dual_frequency:  also simulate GPS L5 and Galileo E5a (a second column per satellite that has it).
    cn0:             C/N0 model (:mod:`fusion.sim.cn0`); None = no C/N0 (``Trace.cn0`` None).
    noise_from_cn0:  pseudorange noise sigma from the DLL model at each signal's C/N0 instead of
                     ``sigma_m`` (needs ``cn0``); Doppler noise scales with C/N0 as well.
    canyon:          street-side buildings (:mod:`fusion.sim.canyon`; needs ``cn0``); None = open sky.
    multipath:       line-of-sight code multipath growing as C/N0 falls (needs ``cn0``); None = none.
    carrier:         also simulate carrier phase (``Trace.adr``), 1-sigma ``adr_sigma_m``, with a
                     random cycle slip per satellite and epoch at probability ``slip_prob``, each a
                     jump of the ambiguity by +-U[``slip_jump_m``] (see fusion.sim.doppler_carrier); with
                     ``slip_on_class_change`` a flagged slip wherever a satellite's signal turns reflected or
                     bent, or back (a tracking loop loses lock there).
    broadcast_errors: also the slowly varying range errors the broadcast corrections leave (orbit and clock,
                     ionosphere, troposphere; :mod:`fusion.sim.broadcast_errors`) on code and carrier.
    """

    sigma_m: float = 6.0
    elevation_noise: bool = False
    elev_mask_deg: float = 5.0
    max_sats: int | None = 10
    min_sats: int = 4
    nlos: bool = False
    nlos_rate: float = 1.0
    nlos_bias_m: tuple[float, float] = (50.0, 200.0)
    clock_bias0_m: tuple[float, float] = (-1.0e5, 1.0e5)
    clock_drift0_mps: tuple[float, float] = (-100.0, 100.0)
    clock_bias_rw_m: float = 0.3
    clock_drift_rw_mps: float = 0.05
    iono_zenith_m: float = 4.0
    tropo_zenith_m: float = 2.4
    doppler: bool = False
    prr_sigma_mps: float = 0.2
    carrier: bool = False
    adr_sigma_m: float = 0.003
    slip_prob: float = 0.0
    slip_jump_m: tuple[float, float] = (5.0, 100.0)
    slip_on_class_change: bool = True
    broadcast_errors: bool = False
    systems: tuple[str, ...] = ("G",)
    dual_frequency: bool = False
    cn0: Cn0Model | None = None
    noise_from_cn0: bool = False
    canyon: CanyonModel | None = None
    multipath: MultipathModel | None = None

    def validate(self) -> None:
        if self.sigma_m < 0:
            raise ValueError(f"sigma_m must be >= 0, got {self.sigma_m}")
        if self.max_sats is not None and self.max_sats < self.min_sats:
            raise ValueError(f"max_sats ({self.max_sats}) < min_sats ({self.min_sats})")
        if self.min_sats < 1:
            raise ValueError(f"min_sats must be >= 1, got {self.min_sats}")
        lo, hi = self.nlos_bias_m
        if not (0 <= lo <= hi) or self.nlos_rate < 0:
            raise ValueError(f"bad NLOS settings: rate {self.nlos_rate}, bias range {self.nlos_bias_m}")
        if not (self.prr_sigma_mps > 0 and self.adr_sigma_m > 0 and 0 <= self.slip_prob <= 1):
            raise ValueError(f"bad Doppler/carrier settings: prr_sigma_mps {self.prr_sigma_mps}, "
                             f"adr_sigma_m {self.adr_sigma_m}, slip_prob {self.slip_prob}")
        if not 0 <= self.slip_jump_m[0] <= self.slip_jump_m[1]:
            raise ValueError(f"slip_jump_m must be (lo, hi) with 0 <= lo <= hi, got {self.slip_jump_m}")
        self.systems = parse_systems(self.systems)
        if self.cn0 is None and (self.noise_from_cn0 or self.canyon is not None or self.multipath is not None):
            raise ValueError("noise_from_cn0, canyon and multipath need a C/N0 model (cn0)")
        for part in (self.cn0, self.canyon):
            if part is not None:
                part.validate()


#: Scenario presets: building statistics and LOS multipath strength per environment.
SCENARIOS = {
    "open": dict(canyon=None, multipath=MultipathModel(scale_m=0.5)),
    "suburban": dict(canyon=CanyonModel(height_m=(6.0, 18.0), width_m=(18.0, 35.0), gap_prob=0.35),
                     multipath=MultipathModel(scale_m=1.0)),
    "urban": dict(canyon=CanyonModel(height_m=(15.0, 60.0), width_m=(15.0, 35.0), gap_prob=0.15),
                  multipath=MultipathModel(scale_m=1.5)),
    # a high-rise core: most of the sky blocked, often fewer than four satellites in view
    "deep": dict(canyon=CanyonModel(height_m=(30.0, 100.0), width_m=(12.0, 25.0), gap_prob=0.1),
                 multipath=MultipathModel(scale_m=1.5)),
}


def scenario_config(name: str, **overrides) -> SimConfig:
    """The :class:`SimConfig` of scenario ``name`` (``open``, ``suburban``, ``urban``, ``deep``): GPS, GLONASS,
    Galileo and BeiDou with GPS L5 and Galileo E5a (a dual-frequency phone), all tracked signals
    (no cap), C/N0 with DLL code noise, Doppler, 10 deg elevation mask, plus the scenario's
    buildings and multipath; ``overrides`` replace any field."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}")
    cfg = SimConfig(systems=("G", "R", "E", "C"), max_sats=None, elev_mask_deg=10.0, cn0=Cn0Model(),
                    noise_from_cn0=True, doppler=True, dual_frequency=True, **copy.deepcopy(SCENARIOS[name]))
    cfg = replace(cfg, **overrides)
    cfg.validate()
    return cfg


def config_from_options(scenario: str | None = None, constellations: str | None = None, *,
                        sigma_m: float | None = None, elevation_noise: bool = False,
                        elev_mask_deg: float | None = None, max_sats: int | None = None,
                        nlos: bool = False, carrier: bool = False, broadcast_errors: bool = False) -> SimConfig:
    """The settings a command line asks for: the scenario preset (None: the GPS-only default), with
    every option given (not None / True) replacing the preset's value. ``max_sats`` 0 = no cap;
    ``constellations`` as :func:`fusion.sim.constellations.parse_systems` reads it."""
    cfg = scenario_config(scenario) if scenario is not None else SimConfig()
    over: dict = {k: v for k, v in (("sigma_m", sigma_m), ("elev_mask_deg", elev_mask_deg)) if v is not None}
    if max_sats is not None:
        over["max_sats"] = max_sats or None
    if constellations is not None:
        over["systems"] = parse_systems(constellations)
    if elevation_noise:
        over["elevation_noise"] = True
    if nlos:
        over["nlos"] = True
    if carrier:
        over["carrier"] = True
    if broadcast_errors:
        over["broadcast_errors"] = True
    cfg = replace(cfg, **over)
    cfg.validate()
    return cfg
