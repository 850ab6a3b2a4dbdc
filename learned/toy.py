"""A tiny open-sky snapshot generator for unit tests and smoke runs (no orbits, no nav files).

Not the project simulator (that is :mod:`fusion.sim.simulate`): satellites are placed at random azimuth /
elevation on the GPS orbit sphere around each receiver, independently per epoch. Pseudoranges follow the
same transmit-time / Sagnac model as real data, so :func:`fusion.geometry.line_of_sight` at the truth
recovers the simulated range to well under a millimetre.
"""
from __future__ import annotations

import numpy as np

from fusion.geometry import C_LIGHT, OMEGA_E, geodetic2ecef, ned2ecef_vec
from fusion.trace import Trace, empty_trace

GPS_ORBIT_RADIUS = 26_560e3


def toy_trace(n_epochs: int = 200, *, seed: int | np.random.Generator = 0, n_sats: tuple[int, int] = (6, 10),
              sigma: float = 6.0, bias: bool = False, min_elev_deg: float = 12.0,
              clock_m: float = 1e5, name: str = "toy") -> Trace:
    """One Trace of ``n_epochs`` independent snapshots near one random origin.

    Per epoch ``n_sats`` (inclusive range) satellites above ``min_elev_deg``; Gaussian noise ``sigma``;
    with ``bias`` a Poisson(1) number of satellites gets +U(50, 200) m (paper's multipath scenario).
    Receiver clock: one random offset in +-``clock_m`` plus a slow drift.
    """
    rng = np.random.default_rng(seed)
    E, S = n_epochs, n_sats[1]
    origin = np.array([rng.uniform(-60, 60), rng.uniform(-180, 180), rng.uniform(0, 500)])
    # Smooth-ish drive: a random walk in NED around the origin (metres).
    steps = rng.normal(0, 10.0, (E, 3)) * np.array([1, 1, 0.05])
    truth = geodetic2ecef(origin) + ned2ecef_vec(np.cumsum(steps, 0), geodetic2ecef(origin)[None])
    az = rng.uniform(0, 2 * np.pi, (E, S))
    el = np.arcsin(rng.uniform(np.sin(np.radians(min_elev_deg)), 1.0, (E, S)))
    ned = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)], -1)
    u = ned2ecef_vec(ned, truth[:, None, :])
    xu = np.einsum("esj,ej->es", u, truth)
    rho = -xu + np.sqrt(xu ** 2 - (truth ** 2).sum(-1)[:, None] + GPS_ORBIT_RADIUS ** 2)
    p_rx = truth[:, None, :] + rho[..., None] * u
    # Undo the Earth rotation during flight: transmit-time ECEF is the receive-time one turned by +theta.
    theta = OMEGA_E * rho / C_LIGHT
    c, s = np.cos(theta), np.sin(theta)
    sat_pos = np.stack([c * p_rx[..., 0] - s * p_rx[..., 1], s * p_rx[..., 0] + c * p_rx[..., 1], p_rx[..., 2]], -1)
    n = rng.integers(n_sats[0], n_sats[1] + 1, E)
    mask = np.arange(S)[None, :] < n[:, None]
    clock = rng.uniform(-clock_m, clock_m) + np.cumsum(rng.normal(0, 0.5, E))
    pr = rho + clock[:, None] + rng.normal(0, sigma, (E, S))
    if bias:
        k = np.minimum(rng.poisson(1.0, E), n)
        order = np.argsort(rng.random((E, S)) + ~mask, axis=1)  # random real slots first
        hit = np.zeros((E, S), bool)
        np.put_along_axis(hit, order, np.arange(S)[None, :] < k[:, None], axis=1)
        pr = pr + hit * rng.uniform(50, 200, (E, S))
    kw = empty_trace(E, S, name=name, with_truth=True)
    kw.update(t_ms=np.arange(E, dtype=np.int64) * 1000 + 1_300_000_000_000,
              sat_pos=np.where(mask[..., None], sat_pos, 0.0),
              pr=np.where(mask, pr, 0.0), pr_sigma=np.full((E, S), sigma), mask=mask, truth=truth,
              sat_id=np.where(mask, 1001 + np.arange(S)[None, :], 0).astype(np.int32))
    return Trace(**kw)


def toy_dataset(n_traces: int, epochs_per_trace: int, *, seed: int = 0, bias: bool = False, **kw) -> list[Trace]:
    ss = np.random.SeedSequence(seed)
    return [toy_trace(epochs_per_trace, seed=np.random.default_rng(child), bias=bias, name=f"toy{i}", **kw)
            for i, child in enumerate(ss.spawn(n_traces))]
