"""GNSS measurement simulator: GPS L1 pseudoranges along any trajectory, anywhere on Earth.

Pipeline (vectorised over all epochs of all traces at once):
trajectory (t_ms, ECEF) -> nearest valid broadcast ephemeris per (epoch, PRN) -> satellite
state at the true transmit time -> elevation mask -> random subset of at most ``max_sats`` ->
pseudorange = |sagnac_rotate(sat_pos, rx) - rx| + receiver clock + noise (+ NLOS bias).

The pseudorange is the *corrected* one of :class:`fusion.trace.Trace` (satellite clock, iono,
tropo already removed), so WLS, features and the graph consume simulated and real traces alike.
:func:`fusion.io.gsdc_write.write_gsdc2021` saves a result in the GSDC 2021 format with ``satClkBiasM``,
``ionoDelayM`` and ``tropoDelayM`` filled consistently, so that
``rawPrM + satClkBiasM - isrbM - ionoDelayM - tropoDelayM`` gives back the simulated
pseudorange (to the file's millimetre rounding).

Truth heights in the written ``ground_truth.csv`` carry the GSDC 2021 +63.1 m error
(:data:`fusion.sim.trajectory.GSDC2021_HEIGHT_ERROR_M`) by default, exactly like the real files, so
``load_trace(..., fix_truth_height=True)`` returns the simulated truth.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.errors import DataError, GeometryError
from fusion.geometry import (C_LIGHT, ecef2geodetic, elevation_azimuth, line_of_sight, ned_rotation,
                             sagnac_rotate)
from fusion.gpstime import format_gps_ms, gps_ms_from_calendar
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.nav.orbits import GpsNav, sat_state, select_ephemeris, transmit_states
from fusion.trace import OPTIONAL_SLOT_FIELDS, SIGNALS, Trace
from fusion.sim.doppler_carrier import doppler_carrier_arrays
from fusion.sim.trajectory import (Trajectory, check_rate,
                                   parse_origins, random_trajectories, random_trajectory)

#: Default start: 2021-04-28 20:00:00 GPS time, inside the shipped nav file (2021 day 118).
DEFAULT_START_MS = gps_ms_from_calendar(2021, 4, 28, 20, 0, 0.0)
#: Default origin: Mountain View, CA (where the GSDC 2021 MTV drives are), ellipsoidal height.
DEFAULT_ORIGIN = (37.3958, -122.1030, -5.0)
#: Visibility is evaluated once per block of this many milliseconds (see _simulate_arrays).
_BLOCK_MS = 30_000
#: Flight-time iterations from the block's guess (each shrinks the error by ~1e-5).
_TAU_ITER = 2


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
    carrier:         also simulate carrier phase (``Trace.adr``), 1-sigma ``adr_sigma_m``, with a
                     random cycle slip per satellite and epoch at probability ``slip_prob``, each a
                     jump of the ambiguity by +-U[``slip_jump_m``] (see fusion.sim.doppler_carrier).
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


def _check_coverage(nav: GpsNav, prns: np.ndarray, t_ms: np.ndarray, min_sats: int) -> np.ndarray:
    """(E, P) ephemeris indices; DataError if any epoch lies outside the nav file's validity."""
    idx = select_ephemeris(nav, prns[None, :], t_ms[:, None])
    n_valid = (idx >= 0).sum(axis=1)
    bad = np.flatnonzero(n_valid < min_sats)
    if bad.size:
        lo, hi = nav.span_ms()
        k = bad[0]
        raise DataError(
            f"{nav.source}: epoch {k} (GPS ms {int(t_ms[k])}, {format_gps_ms(int(t_ms[k]))}) is outside the "
            f"validity of the navigation file (only {int(n_valid[k])} GPS ephemerides valid; file "
            f"covers {format_gps_ms(lo)} .. {format_gps_ms(hi)} GPS time); {bad.size} epoch(s) affected")
    return idx


def _receiver_clock(t_ms: np.ndarray, seg_start: np.ndarray, cfg: SimConfig,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(E,) c*dt [m] and (E,) its drift [m/s]: bias + integrated drift random walk, restarted at
    each segment start (seg_start (E,) bool)."""
    E = t_ms.shape[0]
    seg = np.cumsum(seg_start) - 1                                        # segment id per epoch
    n_seg = int(seg[-1]) + 1
    b0 = rng.uniform(*cfg.clock_bias0_m, n_seg)
    d0 = rng.uniform(*cfg.clock_drift0_mps, n_seg)
    dt = np.r_[0.0, np.diff(t_ms) * 1e-3]
    dt[seg_start] = 0.0
    w_d = rng.standard_normal(E) * cfg.clock_drift_rw_mps * np.sqrt(dt)
    w_b = rng.standard_normal(E) * cfg.clock_bias_rw_m * np.sqrt(dt)

    def seg_cumsum(x: np.ndarray) -> np.ndarray:
        c = np.cumsum(x)
        return c - (c - x)[np.flatnonzero(seg_start)][seg]               # restart per segment

    drift = d0[seg] + seg_cumsum(w_d)
    drift_prev = np.r_[0.0, drift[:-1]]
    return b0[seg] + seg_cumsum(drift_prev * dt + w_b), drift


def _visibility_guess(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray, nav: GpsNav,
                      idx: np.ndarray, R: np.ndarray, cfg: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pass 1: (E,P) bool candidates (maybe above the mask) and (E,P) flight-time guesses [s].

    Satellites move < 0.012 deg/s on the sky (a car's few hundred metres shift them by < 0.01 deg),
    so elevations are computed once per 30 s block of each segment, at a nominal 75 ms flight time,
    and kept with a 1 deg margin. The flight-time guess is good to ~0.1 ms, which the iterations of
    pass 2 make exact. A PRN whose ephemeris starts inside a block stays a candidate.
    t_ms (E,), rx (E,3), seg_start (E,) bool, idx (E,P) ephemeris indices, R (E,3,3) NED rotations.
    """
    seg_id = np.cumsum(seg_start) - 1
    t0_seg = t_ms[np.flatnonzero(seg_start)][seg_id]
    block = seg_id.astype(np.int64) * 10**9 + (t_ms - t0_seg) // _BLOCK_MS
    first = np.r_[True, block[1:] != block[:-1]]
    samp = np.flatnonzero(first)                                         # (B,) sample epochs
    samp_of = np.cumsum(first) - 1                                       # (E,) -> index in samp
    Rs, rxs = R[samp], rx[samp]
    st = sat_state(nav, np.maximum(idx[samp], 0), t_ms[samp, None], -0.075, position_only=True)
    d = sagnac_rotate(st["pos"], rxs) - rxs[:, None, :]
    r = np.linalg.norm(d, axis=-1)
    el_s = np.degrees(np.arcsin(-np.einsum("bj,bpj->bp", Rs[:, 2], d) / r))
    maybe_up = (el_s >= cfg.elev_mask_deg - 1.0) | (idx[samp] < 0)
    return maybe_up[samp_of], (r / C_LIGHT)[samp_of]


def _satellite_states(t_ms: np.ndarray, rx: np.ndarray, nav: GpsNav, idx: np.ndarray, R: np.ndarray,
                      candidate: np.ndarray, tau_guess: np.ndarray) -> dict[str, np.ndarray]:
    """Pass 2, candidates only: exact transmit-time states, elevation and azimuth.

    t_ms (E,), rx (E,3), idx (E,P), R (E,3,3), candidate (E,P) bool, tau_guess (E,P) [s].
    Returns (E,P[,3]) arrays pos, vel, el (-90 where not computed), az, clk [s], drift [s/s], tau [s].
    """
    E, P = idx.shape
    ce, cp = np.nonzero((idx >= 0) & candidate)
    st, ta = transmit_states(nav, idx[ce, cp], rx[ce], t_ms[ce], tau_guess[ce, cp], n_iter=_TAU_ITER)
    d = sagnac_rotate(st["pos"][:, None, :], rx[ce]) - rx[ce][:, None, :]          # (N, 1, 3)
    e_, z_ = elevation_azimuth(d / np.linalg.norm(d, axis=-1, keepdims=True), rx[ce], R=R[ce])
    out = {"pos": np.zeros((E, P, 3)), "vel": np.zeros((E, P, 3)), "el": np.full((E, P), -90.0)}
    out.update({k: np.zeros((E, P)) for k in ("az", "clk", "drift", "tau")})
    out["pos"][ce, cp], out["vel"][ce, cp] = st["pos"], st["vel"]
    out["el"][ce, cp], out["az"][ce, cp] = e_[:, 0], z_[:, 0]
    out["clk"][ce, cp], out["drift"][ce, cp], out["tau"][ce, cp] = st["clock_s"], st["clock_drift"], ta
    return out


def _pick_satellites(eligible: np.ndarray, K: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random subset of at most K eligible (E,P) satellites per epoch, slots ordered by PRN.
    Returns pick (E,K) indices into P and mask (E,K) bool."""
    P = eligible.shape[1]
    keys = np.where(eligible, rng.random(eligible.shape), 2.0)
    pick = np.argsort(keys, axis=1, kind="stable")[:, :K]
    picked_ok = np.take_along_axis(eligible, pick, axis=1)
    order = np.argsort(np.where(picked_ok, pick, P + pick), axis=1, kind="stable")
    return np.take_along_axis(pick, order, axis=1), np.take_along_axis(picked_ok, order, axis=1)


def _pseudorange_errors(el_k: np.ndarray, mask: np.ndarray, cfg: SimConfig, rng: np.random.Generator
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E,K) sigma, Gaussian noise and NLOS bias [m] of the picked slots (el_k (E,K) [deg])."""
    E, K = el_k.shape
    sigma = np.full((E, K), float(cfg.sigma_m))
    if cfg.elevation_noise:
        sigma = sigma / np.sin(np.radians(np.clip(el_k, 1.0, 90.0)))
    noise = rng.standard_normal((E, K)) * sigma
    bias = np.zeros((E, K))
    if cfg.nlos:
        n_bad = np.minimum(rng.poisson(cfg.nlos_rate, E), mask.sum(axis=1))
        rank = np.argsort(np.argsort(np.where(mask, rng.random((E, K)), 2.0), axis=1), axis=1)
        hit = rank < n_bad[:, None]
        bias = np.where(hit, rng.uniform(*cfg.nlos_bias_m, (E, K)), 0.0)
    return sigma, noise, bias


def _simulate_arrays(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray, nav: GpsNav,
                     cfg: SimConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Core simulator on flat arrays. t_ms (E,), rx (E,3), seg_start (E,) bool (trace starts).

    Returns (E, K) slot arrays (K = max_sats or number of PRNs) and (E,) ``keep`` epochs.
    All random draws happen in a fixed order over all epochs, so a seed fixes the result; Doppler
    and carrier draw after everything else, so switching them on leaves the pseudoranges as they were.
    """
    cfg.validate()
    prns = np.unique(nav.prn)
    idx = _check_coverage(nav, prns, t_ms, min(cfg.min_sats, 4))
    P = idx.shape[1]
    K = P if cfg.max_sats is None else min(int(cfg.max_sats), P)
    R = ned_rotation(rx)                                                 # (E, 3, 3)
    candidate, tau_guess = _visibility_guess(t_ms, rx, seg_start, nav, idx, R, cfg)
    st = _satellite_states(t_ms, rx, nav, idx, R, candidate, tau_guess)
    pick, mask = _pick_satellites((idx >= 0) & (st["el"] >= cfg.elev_mask_deg), K, rng)

    def g(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(a, pick[..., None] if a.ndim == 3 else pick, axis=1)

    sat_pos, el_k = g(st["pos"]), g(st["el"])
    clock, clock_drift = _receiver_clock(t_ms, seg_start, cfg, rng)
    sigma, noise, bias = _pseudorange_errors(el_k, mask, cfg, rng)
    # Exactly the model a solver inverts (fusion.geometry.line_of_sight).
    rng_m = line_of_sight(sat_pos, rx)[0]
    # Plausible delays for the raw pseudorange of the derived file (they cancel when corrected).
    sin_el = np.sin(np.radians(np.clip(el_k, 1.0, 90.0)))
    tropo = cfg.tropo_zenith_m * 1.001 / np.sqrt(0.002001 + sin_el**2)
    iono = cfg.iono_zenith_m * (1.0 + 16.0 * (0.53 - np.clip(el_k, 0, 90) / 180.0) ** 3)
    out = dict(
        sat_pos=sat_pos, sat_vel=g(st["vel"]), pr=rng_m + clock[:, None] + noise + bias, mask=mask,
        sat_id=(1000 + prns[pick]).astype(np.int32), el=el_k, az=g(st["az"]), noise=noise, bias=bias,
        sat_clock_m=g(st["clk"]) * C_LIGHT, sat_clock_drift_mps=g(st["drift"]) * C_LIGHT,
        flight_s=g(st["tau"]), iono=iono, tropo=tropo, clock=clock,
    )
    out.update(doppler_carrier_arrays(t_ms, rx, seg_start, out, pick, P, clock_drift, rng_m, cfg, rng))
    zero = ~mask
    for k in ("sat_pos", "sat_vel", "pr", "el", "az", "noise", "bias", "sat_clock_m",
              "sat_clock_drift_mps", "flight_s", "iono", "tropo", "prr", "adr"):
        if k in out:
            out[k] = np.where(zero[..., None] if out[k].ndim == 3 else zero, 0.0, out[k])
    out["pr_sigma"] = np.where(zero, 1.0, sigma)
    out["keep"] = mask.sum(axis=1) >= cfg.min_sats
    return out


def _to_result(arrs: dict[str, np.ndarray], t_ms: np.ndarray, rx: np.ndarray, sel: np.ndarray,
               name: str) -> SimResult:
    """Slice epochs ``sel`` (indices) of the flat arrays into one SimResult (padding trimmed)."""
    keep = sel[arrs["keep"][sel]]
    n_drop = sel.size - keep.size
    S = max(int(arrs["mask"][keep].sum(axis=1).max(initial=0)), 1)
    per_epoch = ("clock", "keep", "rx_vel", "clock_drift")
    cut = {k: v[keep] if k in per_epoch else v[keep][:, :S] for k, v in arrs.items()}
    optional = {k: cut[k] for k in OPTIONAL_SLOT_FIELDS if k in cut}
    if "adr_slip" in optional:
        # a dropped epoch hides whether the arc went on: break every chain across it
        gap = np.r_[True, np.diff(keep) > 1]
        optional["adr_slip"] = optional["adr_slip"] | (gap[:, None] & cut["mask"])
    trace = Trace(
        t_ms=t_ms[keep].copy(), sat_pos=cut["sat_pos"], sat_vel=cut["sat_vel"], pr=cut["pr"],
        pr_sigma=cut["pr_sigma"], sat_id=np.where(cut["mask"], cut["sat_id"], 0).astype(np.int32),
        signal=np.full(cut["pr"].shape, SIGNALS.index("GPS_L1"), np.int8), mask=cut["mask"],
        clock_reset=np.zeros(keep.size, bool), truth=rx[keep].copy(), name=name, **optional,
    )
    trace.count_skip("sim_too_few_visible_sats", n_drop)
    return SimResult(
        trace=trace, clock_m=cut["clock"], bias_m=cut["bias"], noise_m=cut["noise"],
        elev_deg=cut["el"], az_deg=cut["az"], sat_clock_m=cut["sat_clock_m"],
        sat_clock_drift_mps=cut["sat_clock_drift_mps"], flight_s=cut["flight_s"],
        iono_m=cut["iono"], tropo_m=cut["tropo"], rx_vel_mps=cut.get("rx_vel"),
        clock_drift_mps=cut.get("clock_drift"), ambiguity_m=cut.get("ambiguity"),
    )


def _rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _nav(nav: GpsNav | str | Path | None) -> GpsNav:
    if isinstance(nav, GpsNav):
        return nav
    return read_rinex_nav(default_nav_path() if nav is None else nav)


def simulate_trajectory(traj: Trajectory, *, nav: GpsNav | str | Path | None = None,
                        config: SimConfig | None = None,
                        seed: int | np.random.Generator | None = 0) -> SimResult:
    """Simulate GPS L1 measurements along ``traj`` (receive times and true ECEF positions).

    Raises DataError when the trajectory's times lie outside the nav file's validity, and
    GeometryError when no epoch has ``min_sats`` visible satellites; epochs with too few are
    otherwise skipped and counted in ``trace.skipped``.
    """
    cfg = config or SimConfig()
    nav = _nav(nav)
    seg = np.zeros(len(traj), bool); seg[0] = True
    arrs = _simulate_arrays(traj.t_ms, traj.ecef, seg, nav, cfg, _rng(seed))
    if not arrs["keep"].any():
        llh = ecef2geodetic(traj.ecef[0])
        raise GeometryError(
            f"{traj.name}: fewer than {cfg.min_sats} GPS satellites above {cfg.elev_mask_deg} deg "
            f"at every epoch (first epoch {format_gps_ms(int(traj.t_ms[0]))} at lat {llh[0]:.4f}, "
            f"lon {llh[1]:.4f}, h {llh[2]:.1f} m); nothing to simulate")
    return _to_result(arrs, traj.t_ms, traj.ecef, np.arange(len(traj)), traj.name)


def simulate(origin_llh: tuple[float, ...] = DEFAULT_ORIGIN, n_epochs: int = 600, *,
             start_ms: int = DEFAULT_START_MS, rate_hz: float = 1.0,
             nav: GpsNav | str | Path | None = None, config: SimConfig | None = None,
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
                     nav: GpsNav | str | Path | None = None, config: SimConfig | None = None,
                     start_range_ms: tuple[int, int] | None = None, concatenate: bool = False,
                     results: bool = False) -> list[Trace] | Trace | list[SimResult] | SimResult:
    """Many short random drives at different origins and start times (training data).

    origins: (K, 2|3) lat, lon[, h]; trace i uses origins[i % K]; None = uniform over the Earth.
    start_range_ms: start times are uniform in it; default = the nav file's toe range.
    concatenate: return one Trace with the drives laid back to back in time (each marked by
    ``clock_reset``); they must then fit into ``start_range_ms`` one after the other.
    results: return the :class:`SimResult` (trace + hidden true clock etc.) instead of the bare Trace.
    All epochs of all traces go through the simulator in one vectorised pass.
    """
    if n_traces < 1 or epochs_per_trace < 1:
        raise ValueError(f"need n_traces >= 1 and epochs_per_trace >= 1, got {n_traces}, {epochs_per_trace}")
    rng = _rng(seed)
    nav = _nav(nav)
    cfg = config or SimConfig()
    step = check_rate(rate_hz)  # before any use: rate 0 must be a ValueError, not a ZeroDivisionError
    dur = step * (epochs_per_trace - 1)
    lo, hi = start_range_ms or (int(nav.toe_ms.min()), int(nav.toe_ms.max()))
    org = random_origins(n_traces, rng) if origins is None else parse_origins(origins)
    org = org[np.arange(n_traces) % org.shape[0]]
    if concatenate:
        gap = 10 * step
        total = n_traces * (dur + gap)
        if total > hi - lo:
            raise DataError(f"{nav.source}: {n_traces} traces of {epochs_per_trace} epochs do not fit "
                            f"back to back into {(hi - lo) / 3.6e6:.1f} h of valid ephemerides; "
                            "use concatenate=False or a longer nav file")
        starts = lo + rng.integers(0, hi - lo - total + 1) + np.arange(n_traces) * (dur + gap)
    else:
        if hi - lo < dur:
            raise DataError(f"{nav.source}: a trace of {epochs_per_trace} epochs is longer than the "
                            f"{(hi - lo) / 3.6e6:.1f} h the navigation file covers")
        starts = rng.integers(lo, hi - dur + 1, n_traces)
    starts = starts // step * step
    trajs = random_trajectories(org, epochs_per_trace, starts, rng, rate_hz=rate_hz)
    t_ms = np.concatenate([tr.t_ms for tr in trajs])
    rx = np.concatenate([tr.ecef for tr in trajs])
    seg = np.zeros(t_ms.size, bool); seg[::epochs_per_trace] = True
    arrs = _simulate_arrays(t_ms, rx, seg, nav, cfg, rng)
    if concatenate:
        res = _to_result(arrs, t_ms, rx, np.arange(t_ms.size), "sim/dataset")
        # a new trace starts a new receiver clock even when its first epochs were dropped
        sid = (np.cumsum(seg) - 1)[arrs["keep"]]
        res.trace.clock_reset = np.r_[False, np.diff(sid) != 0]
        return res if results else res.trace
    traces = []
    for i in range(n_traces):  # slicing only; all maths above was vectorised
        sel = np.arange(i * epochs_per_trace, (i + 1) * epochs_per_trace)
        if arrs["keep"][sel].any():
            r = _to_result(arrs, t_ms, rx, sel, trajs[i].name)
            traces.append(r if results else r.trace)
    if not traces:
        raise GeometryError("no simulated trace has an epoch with enough visible satellites")
    return traces
