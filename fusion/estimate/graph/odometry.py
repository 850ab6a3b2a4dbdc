"""Vehicle odometry in the fused graph: one displacement factor per step between consecutive
positions, from the body-frame speed and the integrated turn rate (``Trace.odometry``).

The odometry knows the heading only up to a constant and a slow drift (gyro bias): the heading at
epoch ``k`` is modelled as ``psi(k) = theta(k) + psi0 + b * tau(k)``, with ``theta`` the turn rate
integrated over the trace, ``tau`` the time from the trace's middle, and ``(psi0, b)`` first fitted
robustly to the initial (WLS) track (:func:`fit_heading`), then refined in the graph through one
extra state ``h = (d_psi0, d_b)`` (:func:`heading_key`). Each step factor is linear in
``(x(k), x(k-1), h)``: the displacement ``x(k) - x(k-1) = step(psi) + d step / d psi * (d_psi0 + d_b tau)``
with ``step`` the trapezoid of ``speed * dt`` along the heading, in one local east-north-up plane per
trace (fine for drives of tens of km; the heading states absorb a slow rotation), rotated to ECEF.
It is whitened and wrapped as a ``LinearContainerFactor`` (C++), like the constant-velocity link.

Noise per step [m], along / across / up: ``dt * sqrt(var_vx + floor^2)``, ``dt * sqrt(var_vy +
(speed * odom_heading_sigma_rad)^2)``, ``dt * sqrt(var_vz + (speed * odom_pitch_sigma_rad)^2)``; the
variances are the file's, the rest :class:`~fusion.estimate.graph.config.GraphConfig`.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.keys import pos_key
from fusion.geometry import ecef2ned_vec, ned_rotation
from fusion.trace import ODOMETRY_COLUMNS, Trace

_VX, _VY, _VZ, _WZ = (ODOMETRY_COLUMNS.index(c) for c in ("vx", "vy", "vz", "wz"))
_VAR_VX, _VAR_VY, _VAR_VZ = (ODOMETRY_COLUMNS.index(c) for c in ("var_vx", "var_vy", "var_vz"))
#: The least velocity variance a step across or up takes [m^2/s^2] (1 cm/s).
MIN_VAR_MPS2 = 1e-4
#: gyro biases tried by the heading fit [rad/s]: +-0.01 (0.6 deg/s, far beyond a car's yaw-rate
#: sensor) in steps of 2.5e-4 (a 4 deg heading change over a 5-minute drive)
BIAS_GRID_RADPS = np.linspace(-0.01, 0.01, 81)
_HUBER_K_M = 10.0      # robust scale of the heading fit's track residuals (WLS in a street canyon)


def heading_key() -> int:
    """Key of the heading correction ``(d_psi0 [rad], d_b [rad/s])``, a 2-vector (one per trace)."""
    return gtsam.symbol("h", 0)


@dataclass
class OdometryFactors:
    """The trace's odometry factors. epoch (F,) int: the later epoch of each factor's step (the first
    one's also carries the heading state's prior); factors (F,) list; values: the heading state's
    initial value, to insert with the first factor; counts: steps used / skipped, for the report."""

    epoch: np.ndarray
    factors: list
    values: gtsam.Values
    counts: dict


def integrated_turn(t: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """(E,) heading change [rad] since the first epoch: trapezoid of the turn rate ``rate`` (E,) [rad/s]
    over times ``t`` (E,) [s] (missing rates count as 0)."""
    w = np.nan_to_num(rate)
    return np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]


def steps_en(speed: np.ndarray, psi: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(..., E) complex east + i north displacement of each step since the previous epoch (0 first):
    trapezoid of ``speed`` (E,) [m/s] along heading ``psi`` (..., E) [rad, counter-clockwise from east]."""
    v = speed * np.exp(1j * psi)
    out = np.zeros(psi.shape, complex)
    out[..., 1:] = 0.5 * (v[..., 1:] + v[..., :-1]) * dt[1:]
    return out


def fit_heading(t: np.ndarray, speed: np.ndarray, theta: np.ndarray, track: np.ndarray, ok: np.ndarray,
                comp: np.ndarray) -> tuple[float, float]:
    """Heading offset ``psi0`` [rad] and gyro bias ``b`` [rad/s] that best rotate the dead-reckoned
    path onto ``track`` (E,) complex east + i north [m] where ``ok`` (E,) bool; each motion component
    ``comp`` (E,) has its own translation. Robust (Huber on the residuals); ``b`` from a grid.

    t (E,) [s], speed (E,) [m/s], theta (E,) integrated turn [rad].
    """
    tau, dt = t - 0.5 * (t[0] + t[-1]), np.r_[0.0, np.diff(t)]
    psi = theta[None, :] + BIAS_GRID_RADPS[:, None] * tau[None, :]
    step = np.where(np.r_[False, comp[1:] == comp[:-1]], steps_en(speed, psi, dt), 0)
    path = np.cumsum(step, axis=1)                                    # (B, E)
    w = np.broadcast_to(ok.astype(float), path.shape).copy()
    n_comp = int(comp.max()) + 1
    for _ in range(4):                                                # IRLS
        d, p = _centred(path, w, comp, n_comp), _centred(np.broadcast_to(np.nan_to_num(track), path.shape), w, comp, n_comp)
        rot = np.exp(1j * np.angle(np.sum(w * np.conj(d) * p, axis=1)))
        r = np.abs(p - rot[:, None] * d)
        w = np.where(ok, 1.0 / np.maximum(1.0, r / _HUBER_K_M), 0.0)
    cost = np.sum(np.where(ok, np.where(r < _HUBER_K_M, 0.5 * r ** 2, _HUBER_K_M * (r - 0.5 * _HUBER_K_M)), 0), axis=1)
    best = int(np.argmin(cost))
    return float(np.angle(rot[best])), float(BIAS_GRID_RADPS[best])


def _centred(z: np.ndarray, w: np.ndarray, comp: np.ndarray, n_comp: int) -> np.ndarray:
    """(B, E) complex ``z`` minus its ``w``-weighted mean over each component of ``comp`` (E,)."""
    out = np.empty_like(z)
    for i in range(z.shape[0]):                                       # the bias grid, not epochs
        sw = np.bincount(comp, w[i], n_comp)
        mean = (np.bincount(comp, w[i] * z[i].real, n_comp) + 1j * np.bincount(comp, w[i] * z[i].imag, n_comp))
        out[i] = z[i] - (mean / np.maximum(sw, 1e-12))[comp]
    return out


def odometry_factors(trace: Trace, init_pos: np.ndarray, init_ok: np.ndarray, pos_link: np.ndarray,
                     comp: np.ndarray, keep: np.ndarray, cfg: GraphConfig) -> OdometryFactors | None:
    """Every odometry step factor of the trace (None when it has no usable odometry step).

    init_pos (E,3) ECEF initial positions, init_ok (E,) bool where they are solved (the heading fit
    uses only those), pos_link (E,) bool epoch linked to the previous one, comp (E,) motion
    component, keep (E,) bool epochs in the graph.
    """
    if trace.odometry is None:
        raise GeometryError(f"{trace.name}: odometry was asked for, but the trace carries none")
    odo = trace.odometry
    have = np.isfinite(odo).all(axis=1)
    step_ok = np.r_[False, pos_link[1:] & keep[1:] & keep[:-1] & have[1:] & have[:-1]]
    counts = {"odometry_steps": int(step_ok.sum()), "odometry_steps_missing": int((pos_link & ~step_ok).sum())}
    if not step_ok.any() or not init_ok.any():
        return None
    t = (trace.t_ms - trace.t_ms[0]) / 1000.0
    speed = np.nan_to_num(odo[:, _VX])
    ref = init_pos[init_ok].mean(axis=0)
    ned = ecef2ned_vec(init_pos - ref, ref)
    theta = integrated_turn(t, odo[:, _WZ])
    psi0, bias = fit_heading(t, speed, theta, ned[:, 1] + 1j * ned[:, 0], init_ok, comp)
    tau = t - 0.5 * (t[0] + t[-1])
    psi = theta + psi0 + bias * tau
    dt = np.r_[0.0, np.diff(t)]
    step = steps_en(speed, psi, dt)
    factors = _step_factors(np.flatnonzero(step_ok), step, speed, psi, tau, dt, odo, ned_rotation(ref), cfg)
    values = gtsam.Values()
    values.insert(heading_key(), np.zeros(2))
    prior = gtsam.PriorFactorVector(heading_key(), np.zeros(2), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.odom_heading_prior_rad, cfg.odom_gyro_bias_prior_radps])))
    epochs = np.flatnonzero(step_ok)
    counts.update(odometry_heading_deg=round(float(np.degrees(psi0)), 2),
                  odometry_gyro_bias_deg_s=round(float(np.degrees(bias)), 4))
    return OdometryFactors(epoch=np.r_[epochs[0], epochs], factors=[prior] + factors, values=values,
                           counts=counts)


def _step_factors(ks: np.ndarray, step: np.ndarray, speed: np.ndarray, psi: np.ndarray, tau: np.ndarray,
                  dt: np.ndarray, odo: np.ndarray, R: np.ndarray, cfg: GraphConfig) -> list:
    """One linear factor per step ``k`` in ``ks`` on (x(k), x(k-1), h); R (3,3) ECEF -> NED rotation."""
    s = 0.5 * (speed[ks] + speed[ks - 1])
    var = lambda c: 0.5 * (odo[ks, c] + odo[ks - 1, c])                          # noqa: E731
    sd_along = dt[ks] * np.sqrt(var(_VAR_VX) + cfg.odom_speed_sigma_floor_mps ** 2)
    # a standing car whose log reports no variance across or up would make these steps exact: a floor
    sd_across = dt[ks] * np.sqrt(np.maximum(var(_VAR_VY) + (s * cfg.odom_heading_sigma_rad) ** 2, MIN_VAR_MPS2))
    sd_up = dt[ks] * np.sqrt(np.maximum(var(_VAR_VZ) + (s * cfg.odom_pitch_sigma_rad) ** 2, MIN_VAR_MPS2))
    heading = 0.5 * (psi[ks] + psi[ks - 1])
    # rows: along, across, up in ENU; columns -> ECEF through NED
    along = np.stack([np.sin(heading), np.cos(heading), np.zeros_like(heading)], -1)   # NED of the unit heading
    across = np.stack([np.cos(heading), -np.sin(heading), np.zeros_like(heading)], -1)
    up = np.broadcast_to(np.array([0.0, 0.0, -1.0]), along.shape)
    frame = np.stack([along, across, up], 1) @ R                                     # (F,3,3) ECEF -> frame
    W = frame / np.stack([sd_along, sd_across, sd_up], -1)[..., None]                # whitened rows
    d_ned = np.stack([step[ks].imag, step[ks].real, np.zeros(ks.size)], -1)
    mean = d_ned @ R                                                                  # ECEF step (R^T d)
    d_dpsi = np.stack([step[ks].real, -step[ks].imag, np.zeros(ks.size)], -1)          # NED of i * step
    J = (d_dpsi @ R)[..., None] * np.stack(
        [np.ones(ks.size), 0.5 * (tau[ks] + tau[ks - 1])], -1)[:, None, :]          # (F,3,2)
    out = []
    for f, k in enumerate(ks):                                                        # one factor per step
        out.append(_linear_factor(int(k), W[f], W[f] @ mean[f], W[f] @ J[f]))
    return out


def _linear_factor(k: int, W: np.ndarray, b: np.ndarray, WJ: np.ndarray) -> gtsam.LinearContainerFactor:
    """``W (x(k) - x(k-1) - J h) = b`` as an exact linear factor (all-zero linearisation point)."""
    keys = (pos_key(k), pos_key(k - 1), heading_key())
    jf = gtsam.JacobianFactor(keys[0], W, keys[1], -W, keys[2], -WJ, b, gtsam.noiseModel.Unit.Create(3))
    lin = gtsam.Values()
    lin.insert(keys[0], np.zeros(3))
    lin.insert(keys[1], np.zeros(3))
    lin.insert(keys[2], np.zeros(2))
    return gtsam.LinearContainerFactor(jf, lin)
