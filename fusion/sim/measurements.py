"""The simulator's measurement model on flat arrays: all epochs of all traces in one vectorised pass.

Pipeline: satellites of the :class:`~fusion.sim.constellations.Sky` -> record per (epoch,
satellite) -> states at the true transmit time -> elevation mask -> environment (street canyon
class, C/N0, tracking threshold; :func:`_environment`) -> random subset of at most ``max_sats``
-> pseudorange = |sagnac_rotate(sat_pos, rx) - rx| + receiver clock + noise (+ NLOS delay, LOS
multipath, legacy random NLOS bias) -> Doppler / carrier (:mod:`fusion.sim.doppler_carrier`).

Random draws: the original model (pick, clock, noise, legacy bias, Doppler, carrier) draws from the
caller's generator in a fixed order; everything the environment adds (streets, C/N0, multipath)
draws from a child generator spawned from it, so a seed fixes the result and the GPS-only default
gives the same numbers as before the environment existed.
"""
from __future__ import annotations

import numpy as np

from fusion.errors import DataError
from fusion.geometry import C_LIGHT, ecef2ned_vec, elevation_azimuth, line_of_sight, ned_rotation, sagnac_rotate
from fusion.gpstime import format_gps_ms
from fusion.io.rinex_nav import Navigation
from fusion.nav.orbits import GpsNav
from fusion.sim.broadcast_errors import broadcast_range_errors
from fusion.sim.canyon import BLOCKED, LOS, classify, los_multipath, street_layout
from fusion.sim.cn0 import CHIP_M, dll_sigma_m, doppler_sigma_scale, draw_cn0, los_cn0
from fusion.sim.config import SimConfig
from fusion.sim.constellations import Sky, build_sky
from fusion.sim.doppler_carrier import doppler_carrier_arrays, receiver_velocity
from fusion.trace import SIGNALS

#: Visibility is evaluated once per block of this many milliseconds (see _visibility_guess).
_BLOCK_MS = 30_000
#: Flight-time iterations from the block's guess (each shrinks the error by ~1e-5).
_TAU_ITER = 2
#: Epochs per pass of the simulator when it models C/N0 (see simulate_arrays).
CHUNK_EPOCHS = 5_000
#: Per-epoch (E,) / (E,3) outputs of the simulator (the others are (E, K) slot arrays).
PER_EPOCH = ("clock", "keep", "rx_vel", "clock_drift", "street")
#: Slot arrays set to 0 on padding.
_ZEROED = ("sat_pos", "sat_vel", "pr", "el", "az", "noise", "bias", "sat_clock_m", "sat_clock_drift_mps",
           "flight_s", "iono", "tropo", "prr", "adr", "cn0", "nlos_delay", "multipath", "prr_error", "loss_db",
           "broadcast")


def sky_for(nav, cfg: SimConfig) -> Sky:
    """The :class:`Sky` of ``cfg.systems`` from a GpsNav or Navigation (see build_sky)."""
    return build_sky(nav, cfg.systems, cfg.dual_frequency)


def _check_coverage(sky: Sky, t_ms: np.ndarray, min_sats: int) -> np.ndarray:
    """(E, P) record indices; DataError if any epoch lies outside the navigation file's validity
    (fewer than ``min_sats`` records of the systems read from a file; synthetic ones are always valid)."""
    idx = sky.select(t_ms)
    from_file = sky.from_file
    if not from_file.any():
        return idx
    n_valid = (idx[:, from_file] >= 0).sum(axis=1)
    bad = np.flatnonzero(n_valid < min_sats)
    if bad.size:
        lo, hi = sky.span_ms()
        k = bad[0]
        raise DataError(
            f"{sky.source}: epoch {k} (GPS ms {int(t_ms[k])}, {format_gps_ms(int(t_ms[k]))}) is outside the "
            f"validity of the navigation file (only {int(n_valid[k])} ephemerides valid; file "
            f"covers {format_gps_ms(lo)} .. {format_gps_ms(hi)} GPS time); {bad.size} epoch(s) affected")
    return idx


def _visibility_guess(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray, sky: Sky,
                      idx: np.ndarray, R: np.ndarray, cfg: SimConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pass 1: (E,P) bool candidates (maybe above the mask) and (E,P) flight-time guesses [s].

    Satellites move < 0.012 deg/s on the sky (a car's few hundred metres shift them by < 0.01 deg),
    so elevations are computed once per 30 s block of each segment, at a nominal 75 ms flight time,
    and kept with a 1 deg margin. The flight-time guess is good to ~0.1 ms, which the iterations of
    pass 2 make exact. A satellite whose record starts inside a block stays a candidate.
    t_ms (E,), rx (E,3), seg_start (E,) bool, idx (E,P) record indices, R (E,3,3) NED rotations.
    """
    seg_id = np.cumsum(seg_start) - 1
    t0_seg = t_ms[np.flatnonzero(seg_start)][seg_id]
    block = seg_id.astype(np.int64) * 10**9 + (t_ms - t0_seg) // _BLOCK_MS
    first = np.r_[True, block[1:] != block[:-1]]
    samp = np.flatnonzero(first)                                         # (B,) sample epochs
    samp_of = np.cumsum(first) - 1                                       # (E,) -> index in samp
    Rs, rxs = R[samp], rx[samp]
    B, P = samp.size, idx.shape[1]
    cols = np.broadcast_to(np.arange(P), (B, P)).ravel()
    tt = np.broadcast_to(t_ms[samp, None], (B, P)).ravel()
    pos = sky.states(np.maximum(idx[samp], 0).ravel(), cols, tt, -0.075, position_only=True)["pos"]
    d = sagnac_rotate(pos.reshape(B, P, 3), rxs) - rxs[:, None, :]
    r = np.linalg.norm(d, axis=-1)
    el_s = np.degrees(np.arcsin(-np.einsum("bj,bpj->bp", Rs[:, 2], d) / r))
    maybe_up = (el_s >= cfg.elev_mask_deg - 1.0) | (idx[samp] < 0)
    return maybe_up[samp_of], (r / C_LIGHT)[samp_of]


def _transmit_states(sky: Sky, idx, col, rx, t_ms, tau):
    """Flat (N,) states at the true transmit time: tau = |R(OMEGA_E tau) sat(t - tau) - rx| / c."""
    for _ in range(_TAU_ITER):
        pos = sky.states(idx, col, t_ms, -tau, position_only=True)["pos"]
        tau = line_of_sight(pos[:, None, :], rx)[0][:, 0] / C_LIGHT
    return sky.states(idx, col, t_ms, -tau), tau


def _satellite_states(t_ms: np.ndarray, rx: np.ndarray, sky: Sky, idx: np.ndarray, R: np.ndarray,
                      candidate: np.ndarray, tau_guess: np.ndarray) -> dict[str, np.ndarray]:
    """Pass 2, candidates only: exact transmit-time states, elevation, azimuth and range.

    t_ms (E,), rx (E,3), idx (E,P), R (E,3,3), candidate (E,P) bool, tau_guess (E,P) [s].
    Returns (E,P[,3]) arrays pos, vel, el (-90 where not computed), az, clk [s], drift [s/s],
    tau [s], range [m].
    """
    E, P = idx.shape
    ce, cp = np.nonzero((idx >= 0) & candidate)
    st, ta = _transmit_states(sky, idx[ce, cp], cp, rx[ce], t_ms[ce], tau_guess[ce, cp])
    d = sagnac_rotate(st["pos"][:, None, :], rx[ce]) - rx[ce][:, None, :]          # (N, 1, 3)
    rng_m = np.linalg.norm(d, axis=-1)
    e_, z_ = elevation_azimuth(d / rng_m[..., None], rx[ce], R=R[ce])
    out = {"pos": np.zeros((E, P, 3)), "vel": np.zeros((E, P, 3)), "el": np.full((E, P), -90.0)}
    out.update({k: np.zeros((E, P)) for k in ("az", "clk", "drift", "tau", "range")})
    out["pos"][ce, cp], out["vel"][ce, cp] = st["pos"], st["vel"]
    out["el"][ce, cp], out["az"][ce, cp], out["range"][ce, cp] = e_[:, 0], z_[:, 0], rng_m[:, 0]
    out["clk"][ce, cp], out["drift"][ce, cp], out["tau"][ce, cp] = st["clock_s"], st["clock_drift"], ta
    return out


def _environment(rx: np.ndarray, vel: np.ndarray | None, seg_start: np.ndarray, sky: Sky,
                 st: dict[str, np.ndarray], cfg: SimConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """(E,P) canyon class, NLOS delay, Doppler error, power loss and C/N0, and ``receivable`` (E,P)
    bool (not blocked, C/N0 above the tracking threshold). Empty when ``cfg.cn0`` is None.

    rx (E,3), vel (E,3) ECEF receiver velocity (needed with a canyon), seg_start (E,) bool.
    """
    if cfg.cn0 is None:
        return {}
    E, P = st["el"].shape
    env = {"cls": np.zeros((E, P), np.int8), "nlos_delay": np.zeros((E, P)), "prr_error": np.zeros((E, P)),
           "loss_db": np.zeros((E, P))}
    if cfg.canyon is not None:
        layout = street_layout(rx, seg_start, cfg.canyon, rng)
        vel_ne = ecef2ned_vec(vel, rx)[:, :2]
        # classify only satellites above the horizon, as (N, 1) queries with their epoch's street
        ce, cp = np.nonzero(st["el"] > 0)
        sub = {k: v[ce] for k, v in layout.items() if k != "refl_u"} | {"refl_u": layout["refl_u"]}
        c = classify(st["el"][ce, cp, None], st["az"][ce, cp, None], sub, vel_ne[ce], cfg.canyon,
                     cols=sky.sat_ids[cp, None])
        env["cls"][:] = BLOCKED                                            # below the horizon
        for key, name in (("cls", "cls"), ("nlos_delay", "delay_m"), ("prr_error", "rate_err_mps"),
                          ("loss_db", "loss_db")):
            env[key][ce, cp] = c[name][:, 0]
        env["street"] = layout["street"]
    trace_of = np.cumsum(seg_start) - 1
    base = los_cn0(sky.signals()[None, :], st["el"], st["range"], cfg.cn0)
    env["cn0"] = draw_cn0(base - env["loss_db"], trace_of, cfg.cn0, rng)
    env["receivable"] = (env["cls"] != BLOCKED) & (env["cn0"] >= cfg.cn0.track_db)
    return env


def _pick_satellites(eligible: np.ndarray, K: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random subset of at most K eligible (E,P) satellites per epoch, slots ordered by sat_id.
    Returns pick (E,K) indices into P and mask (E,K) bool."""
    P = eligible.shape[1]
    keys = np.where(eligible, rng.random(eligible.shape), 2.0)
    pick = np.argsort(keys, axis=1, kind="stable")[:, :K]
    picked_ok = np.take_along_axis(eligible, pick, axis=1)
    order = np.argsort(np.where(picked_ok, pick, P + pick), axis=1, kind="stable")
    return np.take_along_axis(pick, order, axis=1), np.take_along_axis(picked_ok, order, axis=1)


def _pseudorange_errors(el_k: np.ndarray, mask: np.ndarray, cfg: SimConfig, rng: np.random.Generator,
                        sigma: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E,K) sigma, Gaussian noise and legacy random NLOS bias [m] of the picked slots.

    el_k (E,K) [deg]; sigma (E,K) overrides the fixed / elevation-scaled ``cfg.sigma_m``."""
    E, K = el_k.shape
    if sigma is None:
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


def _slot_environment(env: dict, pick: np.ndarray, mask: np.ndarray, t_ms: np.ndarray, seg_start: np.ndarray,
                      sig_k: np.ndarray, cfg: SimConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The environment's (E,K) arrays at the picked slots, plus LOS multipath and the DLL sigma."""
    if not env:
        return {}
    out = {k: np.take_along_axis(env[k], pick, axis=1) for k in ("cls", "nlos_delay", "prr_error", "loss_db", "cn0")}
    out["cls"] = np.where(mask, out["cls"], 0).astype(np.int8)
    out["multipath"] = np.zeros(pick.shape)
    if cfg.multipath is not None:
        trace_of = np.cumsum(seg_start) - 1
        t_s = (t_ms - t_ms[np.flatnonzero(seg_start)][trace_of]) * 1e-3
        mp, mp_rate = los_multipath(t_s, out["cn0"], trace_of, pick, cfg.multipath, rng)
        # a shorter chip bounds the code multipath error tighter (square-root scaling: a rough choice)
        short = np.sqrt(CHIP_M[sig_k] / CHIP_M[SIGNALS.index("GPS_L1")])
        mp, mp_rate = mp * short, mp_rate * short
        los = out["cls"] == LOS
        out["multipath"] = np.where(los, mp, 0.0)
        out["prr_error"] = out["prr_error"] + np.where(los, mp_rate, 0.0)
    if cfg.noise_from_cn0:
        out["sigma"] = dll_sigma_m(out["cn0"], sig_k, cfg.cn0)
        out["prr_scale"] = doppler_sigma_scale(out["cn0"])
    if "street" in env:
        out["street"] = env["street"]
    return out


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


def _visible(t_ms, rx, seg_start, sky: Sky, cfg: SimConfig, rng: np.random.Generator):
    """Satellite states (E,P) of every satellite, the environment, the receiver velocity (or None)
    and the (E,P) bool of satellites that can be picked (above the mask, received, tracked)."""
    idx = _check_coverage(sky, t_ms, min(cfg.min_sats, 4))
    R = ned_rotation(rx)                                                 # (E, 3, 3)
    candidate, tau_guess = _visibility_guess(t_ms, rx, seg_start, sky, idx, R, cfg)
    st = _satellite_states(t_ms, rx, sky, idx, R, candidate, tau_guess)
    eligible = (idx >= 0) & (st["el"] >= cfg.elev_mask_deg)
    vel = receiver_velocity(t_ms, rx, seg_start) if (cfg.doppler or cfg.canyon is not None) else None
    # spawning leaves `rng` untouched: the original model's draws stay as they were
    env = _environment(rx, vel, seg_start, sky, st, cfg, rng.spawn(1)[0]) if cfg.cn0 is not None else {}
    if env:
        eligible &= env["receivable"]
    return st, env, vel, eligible


def simulate_arrays(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray, nav: GpsNav | Navigation | Sky,
                    cfg: SimConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Core simulator on flat arrays. t_ms (E,), rx (E,3), seg_start (E,) bool (trace starts).

    Returns (E, K) slot arrays (K = max_sats or number of satellites) and (E,) ``keep`` epochs.
    All random draws happen in a fixed order over all epochs, so a seed fixes the result; Doppler
    and carrier draw after everything else, so switching them on leaves the pseudoranges as they were.
    With a C/N0 model (many signals per epoch) the traces go through in chunks of about
    :data:`CHUNK_EPOCHS` epochs (whole traces), one after the other from the same generator, which
    bounds the memory (about 0.4 GB per chunk with four constellations, two frequencies) and keeps
    the result fixed by the seed.
    """
    cfg.validate()
    sky = nav if isinstance(nav, Sky) else sky_for(nav, cfg)
    starts = np.flatnonzero(seg_start)
    if cfg.cn0 is None or t_ms.size <= CHUNK_EPOCHS or starts.size < 2:
        return _simulate_chunk(t_ms, rx, seg_start, sky, cfg, rng)
    cut = np.unique(np.r_[starts[np.searchsorted(starts, np.arange(0, t_ms.size, CHUNK_EPOCHS))], t_ms.size])
    parts = [_simulate_chunk(t_ms[a:b], rx[a:b], seg_start[a:b], sky, cfg, rng) for a, b in zip(cut[:-1], cut[1:])]
    if "street" in parts[0]:
        offset = np.cumsum([0] + [int(p["street"].max()) + 1 for p in parts[:-1]])
        for p, o in zip(parts, offset):
            p["street"] = p["street"] + o                  # street ids stay unique over the chunks
    S = max(p["mask"].shape[1] for p in parts)
    return {k: np.concatenate([p[k] if k in PER_EPOCH else _pad_slots(p[k], S, k) for p in parts]) for k in parts[0]}


def _keyed_child(rng: np.random.Generator, key: int) -> np.random.Generator:
    """A generator of its own, fixed by ``rng``'s seed, its spawn count so far and ``key``, that neither draws
    from ``rng`` nor spawns from it: a model switched on this way leaves every other array as the same seed gives
    it without the model (a spawn would shift the children of later chunks)."""
    seq = rng.bit_generator.seed_seq
    return np.random.default_rng([seq.entropy, *seq.spawn_key, seq.n_children_spawned, key])


def _pad_slots(a: np.ndarray, S: int, key: str) -> np.ndarray:
    """(E, s[, 3]) slot array padded to S slots with the Trace's filler (sigma 1, else 0 / False)."""
    widths = [(0, 0), (0, S - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
    return np.pad(a, widths, constant_values=1 if key.endswith("_sigma") else 0)


def _simulate_chunk(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray, sky: Sky, cfg: SimConfig,
                    rng: np.random.Generator) -> dict[str, np.ndarray]:
    """:func:`simulate_arrays` on epochs that start with a trace start (seg_start[0] True)."""
    st, env, vel, eligible = _visible(t_ms, rx, seg_start, sky, cfg, rng)
    P = eligible.shape[1]
    K = P if cfg.max_sats is None else min(int(cfg.max_sats), P)
    pick, mask = _pick_satellites(eligible, K, rng)

    def g(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(a, pick[..., None] if a.ndim == 3 else pick, axis=1)

    sat_pos, el_k, sig_k = g(st["pos"]), g(st["el"]), sky.signals()[pick]
    clock, clock_drift = _receiver_clock(t_ms, seg_start, cfg, rng)
    slot_env = _slot_environment(env, pick, mask, t_ms, seg_start, sig_k, cfg, rng.spawn(1)[0] if env else rng)
    sigma, noise, bias = _pseudorange_errors(el_k, mask, cfg, rng, slot_env.get("sigma"))
    rng_m = line_of_sight(sat_pos, rx)[0]          # exactly the model a solver inverts
    extra = slot_env.get("nlos_delay", 0.0) + slot_env.get("multipath", 0.0)
    # Plausible delays for the raw pseudorange of the written file (they cancel when corrected).
    sin_el = np.sin(np.radians(np.clip(el_k, 1.0, 90.0)))
    tropo = cfg.tropo_zenith_m * 1.001 / np.sqrt(0.002001 + sin_el**2)
    iono = cfg.iono_zenith_m * (1.0 + 16.0 * (0.53 - np.clip(el_k, 0, 90) / 180.0) ** 3)
    out = dict(
        sat_pos=sat_pos, sat_vel=g(st["vel"]), pr=rng_m + clock[:, None] + noise + bias + extra, mask=mask,
        sat_id=sky.sat_ids[pick].astype(np.int32), signal=sig_k, el=el_k, az=g(st["az"]), noise=noise,
        bias=bias, sat_clock_m=g(st["clk"]) * C_LIGHT, sat_clock_drift_mps=g(st["drift"]) * C_LIGHT,
        flight_s=g(st["tau"]), iono=iono, tropo=tropo, clock=clock,
    )
    out.update({k: v for k, v in slot_env.items() if k not in ("sigma", "prr_scale")})
    slots = dict(out, range=rng_m, clock_drift=clock_drift)
    out.update(doppler_carrier_arrays(t_ms, rx, seg_start, slots, pick, P, cfg, rng, env=dict(slot_env, vel=vel)))
    if cfg.broadcast_errors:
        code, carrier = broadcast_range_errors(t_ms, seg_start, out["sat_id"], sig_k, mask, iono, tropo,
                                               _keyed_child(rng, 0xB40AD))
        out["pr"] = out["pr"] + code
        out["broadcast"] = code
        if "adr" in out:
            out["adr"] = out["adr"] + carrier
    zero = ~mask
    for k in _ZEROED:
        if k in out:
            out[k] = np.where(zero[..., None] if out[k].ndim == 3 else zero, 0.0, out[k])
    out["pr_sigma"] = np.where(zero, 1.0, sigma)
    out["keep"] = mask.sum(axis=1) >= cfg.min_sats
    # real slots come first (see _pick_satellites): drop the columns no epoch uses
    S = max(int(mask.sum(axis=1).max(initial=0)), 1)
    return {k: v if k in PER_EPOCH else v[:, :S] for k, v in out.items()}
