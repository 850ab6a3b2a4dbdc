"""GNSS measurement simulator: pseudoranges (GPS L1 by default; GLONASS, Galileo, BeiDou on
request), C/N0, Doppler and carrier phase along any trajectory, anywhere on Earth, in open sky or
street canyons.

Pipeline (vectorised over all epochs of all traces at once, :mod:`fusion.sim.measurements`):
trajectory (t_ms, ECEF) -> nearest valid record per (epoch, satellite) -> satellite state at the
true transmit time -> elevation mask -> street canyon (LOS / NLOS / diffracted / blocked,
:mod:`fusion.sim.canyon`) and C/N0 (:mod:`fusion.sim.cn0`) -> random subset of at most ``max_sats``
-> pseudorange = |sagnac_rotate(sat_pos, rx) - rx| + receiver clock + noise (+ NLOS delay,
multipath). Settings: :class:`fusion.sim.config.SimConfig`; presets: :func:`scenario_config`.

The pseudorange is the *corrected* one of :class:`fusion.trace.Trace` (satellite clock, iono,
tropo already removed), so WLS, features and the graph consume simulated and real traces alike.
:func:`fusion.io.gsdc_write.write_gsdc2021` saves a result in the GSDC 2021 derived format with ``satClkBiasM``,
``ionoDelayM`` and ``tropoDelayM`` filled consistently, so that
``rawPrM + satClkBiasM - isrbM - ionoDelayM - tropoDelayM`` gives back the simulated
pseudorange (to the file's millimetre rounding).

Truth heights in the written ``ground_truth.csv`` carry the GSDC 2021 +63.1 m error
(:data:`fusion.sim.trajectory.GSDC2021_HEIGHT_ERROR_M`) by default, exactly like the real files, so
``load_trace(..., fix_truth_height=True)`` returns the simulated truth.
:func:`fusion.sim.write.write_device_gnss` writes the GSDC 2022/23 format instead, which carries
C/N0, Doppler and carrier phase, with a label file of the hidden truth per measurement.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.errors import DataError, GeometryError
from fusion.geometry import ecef2geodetic
from fusion.gpstime import format_gps_ms, gps_ms_from_calendar
from fusion.io.rinex_nav import Navigation, default_nav_path, read_nav, read_rinex_nav
from fusion.nav.orbits import GpsNav
from fusion.trace import OPTIONAL_SLOT_FIELDS, Trace
from fusion.sim.config import SCENARIOS, SimConfig, config_from_options, scenario_config
from fusion.sim.constellations import parse_systems
from fusion.sim.measurements import CHUNK_EPOCHS, PER_EPOCH, simulate_arrays, sky_for
from fusion.sim.write import FORMATS, write_gsdc2021, write_trace
from fusion.sim.trajectory import (Trajectory, check_rate,
                                   parse_origins, random_trajectories, random_trajectory)

__all__ = ["DEFAULT_ORIGIN", "DEFAULT_START_MS", "FORMATS", "SCENARIOS", "SimConfig", "SimResult",
           "config_from_options", "random_origins", "scenario_config", "simulate", "simulate_dataset",
           "simulate_trajectory", "write_gsdc2021", "write_trace"]

#: Default start: 2021-04-28 20:00:00 GPS time, inside the shipped nav file (2021 day 118).
DEFAULT_START_MS = gps_ms_from_calendar(2021, 4, 28, 20, 0, 0.0)
#: Default origin: Mountain View, CA (where the GSDC 2021 MTV drives are), ellipsoidal height.
DEFAULT_ORIGIN = (37.3958, -122.1030, -5.0)


@dataclass
class SimResult:
    """A simulated trace plus the hidden quantities that made it (for tests and training).

    trace:    the measurements (truth set, ``pr_sigma`` = the noise sigma).
    clock_m:  (E,) true receiver clock c*dt [m] (never an input to estimators).
    bias_m:   (E, S) NLOS bias added to each slot [m] (0 where none).
    noise_m:  (E, S) Gaussian noise added [m].
    elev_deg, az_deg: (E, S) at the true position.
    sat_clock_m, sat_clock_drift_mps: (E, S) c*dt_sv and its rate (broadcast model, L1 TGD in).
    flight_s: (E, S) true signal flight time [s].
    iono_m, tropo_m: (E, S) delays written to the derived file.
    rx_vel_mps: (E, 3) true receiver ECEF velocity, clock_drift_mps: (E,) true clock drift
              (with ``SimConfig.doppler``; else None).
    ambiguity_m: (E, S) true carrier ambiguity of each slot (with ``SimConfig.carrier``; else None).
    broadcast_m: (E, S) the code's error the broadcast corrections leave [m] (with ``SimConfig.broadcast_errors``;
              else None; :mod:`fusion.sim.broadcast_errors`).

    With a C/N0 model (``SimConfig.cn0``; else None): hidden labels for analysis, never model inputs:
    los_class: (E, S) int8 0 LOS, 1 NLOS, 2 diffracted (:data:`fusion.sim.canyon.CLASS_NAMES`).
    nlos_delay_m: (E, S) extra path of the reflected / diffracted signal [m] (>= 0; 0 for LOS).
    multipath_m: (E, S) LOS multipath code error [m].  prr_error_mps: (E, S) range-rate error of
    the received path (NLOS geometry + multipath) [m/s].  loss_db: (E, S) NLOS / diffraction power
    loss [dB].  street: (E,) street index along the drive (with a canyon).
    """

    trace: Trace
    clock_m: np.ndarray
    bias_m: np.ndarray
    noise_m: np.ndarray
    elev_deg: np.ndarray
    az_deg: np.ndarray
    sat_clock_m: np.ndarray
    sat_clock_drift_mps: np.ndarray
    flight_s: np.ndarray
    iono_m: np.ndarray
    tropo_m: np.ndarray
    rx_vel_mps: np.ndarray | None = None
    clock_drift_mps: np.ndarray | None = None
    ambiguity_m: np.ndarray | None = None
    broadcast_m: np.ndarray | None = None
    los_class: np.ndarray | None = None
    nlos_delay_m: np.ndarray | None = None
    multipath_m: np.ndarray | None = None
    prr_error_mps: np.ndarray | None = None
    loss_db: np.ndarray | None = None
    street: np.ndarray | None = None


def _to_result(arrs: dict[str, np.ndarray], t_ms: np.ndarray, rx: np.ndarray, sel: np.ndarray,
               name: str) -> SimResult:
    """Slice epochs ``sel`` (indices) of the flat arrays into one SimResult (padding trimmed)."""
    keep = sel[arrs["keep"][sel]]
    n_drop = sel.size - keep.size
    S = max(int(arrs["mask"][keep].sum(axis=1).max(initial=0)), 1)
    cut = {k: v[keep] if k in PER_EPOCH else v[keep][:, :S] for k, v in arrs.items()}
    optional = {k: cut[k] for k in OPTIONAL_SLOT_FIELDS if k in cut}
    if "adr_slip" in optional:
        # a dropped epoch hides whether the arc went on: break every chain across it
        gap = np.r_[True, np.diff(keep) > 1]
        optional["adr_slip"] = optional["adr_slip"] | (gap[:, None] & cut["mask"])
    trace = Trace(
        t_ms=t_ms[keep].copy(), sat_pos=cut["sat_pos"], sat_vel=cut["sat_vel"], pr=cut["pr"],
        pr_sigma=cut["pr_sigma"], sat_id=np.where(cut["mask"], cut["sat_id"], 0).astype(np.int32),
        signal=np.where(cut["mask"], cut["signal"], 0).astype(np.int8), mask=cut["mask"],
        clock_reset=np.zeros(keep.size, bool), truth=rx[keep].copy(), name=name, **optional,
    )
    trace.count_skip("sim_too_few_visible_sats", n_drop)
    return SimResult(
        trace=trace, clock_m=cut["clock"], bias_m=cut["bias"], noise_m=cut["noise"],
        elev_deg=cut["el"], az_deg=cut["az"], sat_clock_m=cut["sat_clock_m"],
        sat_clock_drift_mps=cut["sat_clock_drift_mps"], flight_s=cut["flight_s"],
        iono_m=cut["iono"], tropo_m=cut["tropo"], rx_vel_mps=cut.get("rx_vel"),
        clock_drift_mps=cut.get("clock_drift"), ambiguity_m=cut.get("ambiguity"), broadcast_m=cut.get("broadcast"),
        los_class=cut.get("cls"), nlos_delay_m=cut.get("nlos_delay"), multipath_m=cut.get("multipath"),
        prr_error_mps=cut.get("prr_error"), loss_db=cut.get("loss_db"), street=cut.get("street"),
    )


def _rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _nav(nav: GpsNav | Navigation | str | Path | None, cfg: SimConfig | None = None) -> GpsNav | Navigation:
    """Navigation data as given, or read from a path (default: the shipped GPS file). GPS-only
    settings read the file's GPS records; multi-constellation ones every system's."""
    if isinstance(nav, (GpsNav, Navigation)):
        return nav
    path = default_nav_path() if nav is None else nav
    systems = parse_systems(cfg.systems) if cfg is not None else ("G",)
    return read_rinex_nav(path) if systems == ("G",) else read_nav(path)


def _source(nav: GpsNav | Navigation) -> str:
    return ", ".join(nav.sources) if isinstance(nav, Navigation) else nav.source


def _toe_range(nav: GpsNav | Navigation) -> tuple[int, int]:
    """(first, last) reference time of the file's records [GPS ms] (default start-time range)."""
    toe = getattr(nav, "kepler", nav).toe_ms
    if isinstance(nav, Navigation) and len(nav.glonass):
        toe = np.r_[toe, nav.glonass.toe_ms]
    if toe.size == 0:
        raise DataError(f"{_source(nav)}: navigation data has no records")
    return int(toe.min()), int(toe.max())


def simulate_trajectory(traj: Trajectory, *, nav: GpsNav | Navigation | str | Path | None = None,
                        config: SimConfig | None = None,
                        seed: int | np.random.Generator | None = 0) -> SimResult:
    """Simulate GPS L1 measurements along ``traj`` (receive times and true ECEF positions).

    Raises DataError when the trajectory's times lie outside the nav file's validity, and
    GeometryError when no epoch has ``min_sats`` visible satellites; epochs with too few are
    otherwise skipped and counted in ``trace.skipped``.
    """
    cfg = config or SimConfig()
    nav = _nav(nav, cfg)
    seg = np.zeros(len(traj), bool); seg[0] = True
    arrs = simulate_arrays(traj.t_ms, traj.ecef, seg, nav, cfg, _rng(seed))
    if not arrs["keep"].any():
        llh = ecef2geodetic(traj.ecef[0])
        names = "/".join({"G": "GPS", "R": "GLONASS", "E": "Galileo", "C": "BeiDou"}[s]
                         for s in parse_systems(cfg.systems))
        raise GeometryError(
            f"{traj.name}: fewer than {cfg.min_sats} {names} satellites received above {cfg.elev_mask_deg} deg "
            f"at every epoch (first epoch {format_gps_ms(int(traj.t_ms[0]))} at lat {llh[0]:.4f}, "
            f"lon {llh[1]:.4f}, h {llh[2]:.1f} m); nothing to simulate")
    return _to_result(arrs, traj.t_ms, traj.ecef, np.arange(len(traj)), traj.name)


def simulate(origin_llh: tuple[float, ...] = DEFAULT_ORIGIN, n_epochs: int = 600, *,
             start_ms: int = DEFAULT_START_MS, rate_hz: float = 1.0,
             nav: GpsNav | Navigation | str | Path | None = None, config: SimConfig | None = None,
             seed: int | np.random.Generator | None = 0, name: str = "sim") -> SimResult:
    """A random smooth drive at ``origin_llh`` (lat, lon[, h]) and its simulated measurements."""
    rng = _rng(seed)
    origin = tuple(origin_llh) + (0.0,) * (3 - len(origin_llh))
    traj = random_trajectory(origin, n_epochs, start_ms, rng, rate_hz=rate_hz, name=name)
    return simulate_trajectory(traj, nav=nav, config=config, seed=rng)


def random_origins(n: int, rng: np.random.Generator, height_range: tuple[float, float] = (-50.0, 500.0)
                   ) -> np.ndarray:
    """(n, 3) lat, lon [deg], ellipsoidal height [m] uniform over the sphere's surface."""
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    lon = rng.uniform(-180.0, 180.0, n)
    return np.stack([lat, lon, rng.uniform(*height_range, n)], axis=1)


def simulate_dataset(n_traces: int, epochs_per_trace: int, *, origins: np.ndarray | None = None,
                     seed: int | np.random.Generator | None = 0, rate_hz: float = 1.0,
                     nav: GpsNav | Navigation | str | Path | None = None, config: SimConfig | None = None,
                     start_range_ms: tuple[int, int] | None = None, concatenate: bool = False,
                     results: bool = False) -> list[Trace] | Trace | list[SimResult] | SimResult:
    """Many short random drives at different origins and start times (training data).

    origins: (K, 2|3) lat, lon[, h]; trace i uses origins[i % K]; None = uniform over the Earth.
    start_range_ms: start times are uniform in it; default = the nav file's toe range.
    concatenate: return one Trace with the drives laid back to back in time (each marked by
    ``clock_reset``); they must then fit into ``start_range_ms`` one after the other.
    results: return the :class:`SimResult` (trace + hidden true clock etc.) instead of the bare Trace.
    All epochs of all traces go through the simulator in one vectorised pass (with a C/N0 model:
    in passes of at most ``CHUNK_EPOCHS`` epochs, which bounds the memory).
    """
    if n_traces < 1 or epochs_per_trace < 1:
        raise ValueError(f"need n_traces >= 1 and epochs_per_trace >= 1, got {n_traces}, {epochs_per_trace}")
    rng = _rng(seed)
    cfg = config or SimConfig()
    nav = _nav(nav, cfg)
    step = check_rate(rate_hz)  # before any use: rate 0 must be a ValueError, not a ZeroDivisionError
    dur = step * (epochs_per_trace - 1)
    lo, hi = start_range_ms or _toe_range(nav)
    org = random_origins(n_traces, rng) if origins is None else parse_origins(origins)
    org = org[np.arange(n_traces) % org.shape[0]]
    if concatenate:
        gap = 10 * step
        total = n_traces * (dur + gap)
        if total > hi - lo:
            raise DataError(f"{_source(nav)}: {n_traces} traces of {epochs_per_trace} epochs do not fit "
                            f"back to back into {(hi - lo) / 3.6e6:.1f} h of valid ephemerides; "
                            "use concatenate=False or a longer nav file")
        starts = lo + rng.integers(0, hi - lo - total + 1) + np.arange(n_traces) * (dur + gap)
    else:
        if hi - lo < dur:
            raise DataError(f"{_source(nav)}: a trace of {epochs_per_trace} epochs is longer than the "
                            f"{(hi - lo) / 3.6e6:.1f} h the navigation file covers")
        starts = rng.integers(lo, hi - dur + 1, n_traces)
    starts = starts // step * step
    trajs = random_trajectories(org, epochs_per_trace, starts, rng, rate_hz=rate_hz)
    if concatenate:
        t_ms, rx, seg = _stack(trajs)
        arrs = simulate_arrays(t_ms, rx, seg, nav, cfg, rng)
        res = _to_result(arrs, t_ms, rx, np.arange(t_ms.size), "sim/dataset")
        # a new trace starts a new receiver clock even when its first epochs were dropped
        sid = (np.cumsum(seg) - 1)[arrs["keep"]]
        res.trace.clock_reset = np.r_[False, np.diff(sid) != 0]
        return res if results else res.trace
    traces = _per_trace(trajs, nav, cfg, rng)
    if not traces:
        raise GeometryError("no simulated trace has an epoch with enough visible satellites")
    return traces if results else [r.trace for r in traces]


def _stack(trajs: list[Trajectory]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trajectories back to back: t_ms (E,), rx (E,3), trace starts (E,) bool."""
    t_ms = np.concatenate([tr.t_ms for tr in trajs])
    seg = np.zeros(t_ms.size, bool)
    seg[np.cumsum([0] + [len(tr) for tr in trajs[:-1]])] = True
    return t_ms, np.concatenate([tr.ecef for tr in trajs]), seg


def _per_trace(trajs: list[Trajectory], nav, cfg: SimConfig, rng: np.random.Generator) -> list[SimResult]:
    """One SimResult per trajectory with enough satellites. Without a C/N0 model all traces go
    through the simulator in one pass; with one (many signals per epoch), groups of traces of at
    most CHUNK_EPOCHS epochs in all, one after the other, so memory stays bounded."""
    sky = sky_for(nav, cfg)
    per = max(1, CHUNK_EPOCHS // len(trajs[0])) if cfg.cn0 is not None else len(trajs)
    out, n_streets = [], 0
    for c0 in range(0, len(trajs), per):
        group = trajs[c0:c0 + per]
        t_ms, rx, seg = _stack(group)
        arrs = simulate_arrays(t_ms, rx, seg, sky, cfg, rng)
        if "street" in arrs:                       # street ids unique over the whole data set
            arrs["street"] = arrs["street"] + n_streets
            n_streets = int(arrs["street"].max()) + 1
        first = np.flatnonzero(seg)
        for tr, a in zip(group, first):  # slicing only; all maths above was vectorised
            sel = np.arange(a, a + len(tr))
            if arrs["keep"][sel].any():
                out.append(_to_result(arrs, t_ms, rx, sel, tr.name))
    return out
