"""GLONASS satellite states from broadcast state vectors (GLONASS ICD 2008, A.3.1.2).

A GLONASS record gives position, velocity and lunisolar acceleration in PZ-90 at ``toe``; the
state at another time is found by integrating the J2 equations of motion with fourth-order
Runge-Kutta. All queries are integrated together: each takes the same number of steps, sized so
that the longest one uses steps of at most :data:`MAX_STEP_S` (RTKLIB uses 60 s as well; the
integration error is then below a centimetre over the 15-minute half-interval).
"""
from __future__ import annotations

import numpy as np

from fusion.errors import DataError
from fusion.io.nav_records import GLONASS_VALID_MS as VALID_MS, GloNav

#: PZ-90 constants (GLONASS ICD 2008, 3.1.3).
MU_GLO = 3.9860044e14
J2_GLO = 1.0826257e-3
RE_GLO = 6378136.0
OMEGA_GLO = 7.292115e-5
#: Integration step bound [s].
MAX_STEP_S = 60.0


def select_glonass(nav: GloNav, sat_id: np.ndarray, t_ms: np.ndarray) -> np.ndarray:
    """(...) index of the record with the nearest toe within :data:`VALID_MS`, or -1.

    sat_id: (...) int; t_ms: (...) int GPS ms (broadcast together).
    """
    sat_id, t_ms = np.broadcast_arrays(np.asarray(sat_id, np.int64), np.asarray(t_ms, np.int64))
    if len(nav) == 0:
        return np.full(sat_id.shape, -1)
    big = np.int64(10**13)
    keys = nav.sat_id * big + nav.toe_ms
    right = np.searchsorted(keys, sat_id * big + t_ms)
    n = len(nav)
    cand = np.stack([np.clip(right - 1, 0, n - 1), np.clip(right, 0, n - 1)])
    dist = np.abs(nav.toe_ms[cand] - t_ms)
    ok = (nav.sat_id[cand] == sat_id) & (dist <= VALID_MS)
    dist = np.where(ok, dist, np.iinfo(np.int64).max)
    pick = np.argmin(dist, axis=0)
    idx = np.take_along_axis(cand, pick[None], axis=0)[0]
    return np.where(ok.any(axis=0), idx, -1)


def _derivative(state: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """d/dt of (N, 6) [position, velocity] in the rotating PZ-90 frame (ICD A.3.1.2)."""
    r = state[:, :3]
    v = state[:, 3:]
    r2 = np.sum(r * r, axis=1)
    r3 = r2 * np.sqrt(r2)
    a = 1.5 * J2_GLO * MU_GLO * RE_GLO**2 / (r2 * r3)
    b = 5.0 * r[:, 2] ** 2 / r2
    c = -MU_GLO / r3 - a * (1.0 - b)
    w2 = OMEGA_GLO**2
    ax = (c + w2) * r[:, 0] + 2.0 * OMEGA_GLO * v[:, 1] + acc[:, 0]
    ay = (c + w2) * r[:, 1] - 2.0 * OMEGA_GLO * v[:, 0] + acc[:, 1]
    az = (c - 2.0 * a) * r[:, 2] + acc[:, 2]
    return np.concatenate([v, np.stack([ax, ay, az], axis=1)], axis=1)


def glonass_state(nav: GloNav, idx: np.ndarray, t_ms: np.ndarray, dt_s: np.ndarray | float = 0.0
                  ) -> dict[str, np.ndarray]:
    """Position, velocity and clock of GLONASS satellites at GPS time ``t_ms / 1000 + dt_s``.

    idx: (N,) record indices (>= 0); t_ms: (N,) int GPS ms; dt_s: (N,) or scalar seconds.
    Returns ``pos`` (N, 3) [m], ``vel`` (N, 3) [m/s], ``clock_s`` (N,) [s] (``-TauN + GammaN
    (t - toe)``; GLONASS clocks need no separate relativistic term), ``clock_drift`` (N,) [s/s].
    """
    idx = np.asarray(idx)
    if np.any(idx < 0):
        raise DataError(f"{nav.source}: GLONASS state requested without a valid record")
    dt = (np.asarray(t_ms, np.int64) - nav.toe_ms[idx]) * 1e-3 + dt_s
    dt = np.broadcast_to(dt, idx.shape).astype(float)
    n_steps = max(int(np.ceil(np.max(np.abs(dt), initial=0.0) / MAX_STEP_S)), 1)
    h = (dt / n_steps)[:, None]
    x = np.concatenate([nav.pos[idx], nav.vel[idx]], axis=1)
    acc = nav.acc[idx]
    for _ in range(n_steps):
        k1 = _derivative(x, acc)
        k2 = _derivative(x + 0.5 * h * k1, acc)
        k3 = _derivative(x + 0.5 * h * k2, acc)
        k4 = _derivative(x + h * k3, acc)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    gamma = nav.gamma[idx]
    return {"pos": x[:, :3], "vel": x[:, 3:], "clock_s": nav.tau[idx] + gamma * dt,
            "clock_drift": gamma, "clock_rel_s": np.zeros_like(dt)}
