"""Motion models linking consecutive epochs of the fused graph.

A model is built once per trace (its noise vectorised over epochs) and then asked, per epoch ``k``,
for the variables it adds and for the factors that tie ``k`` to ``k - 1`` (or that start a new
motion component at ``k``). :func:`motion_model` picks one from ``GraphConfig.motion``.
"""
from __future__ import annotations

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import velocity_prior_factor_v, zero_point
from fusion.estimate.graph.keys import pos_key, vel_key
from fusion.geometry import ned2ecef_diag, ned_rotation

#: Loose velocity prior at the start of a component [m/s] (cars stay well inside it).
START_VEL_SIGMA_MPS = 50.0
_ZERO3 = np.zeros(3)


class RandomWalkMotion:
    """Zero-mean position random walk: x(k) - x(k-1) ~ N(0, diag(h, h, v)^2 dt^2) in local NED.

    init_pos (E,3) ECEF sets each epoch's NED frame; dt (E,) [s] time since the previous epoch."""

    def __init__(self, init_pos: np.ndarray, dt: np.ndarray, cfg: GraphConfig):
        dt = np.maximum(dt, 1e-3)
        var_h, var_v = (cfg.rw_sigma_h_mps * dt) ** 2, (cfg.rw_sigma_v_mps * dt) ** 2
        self.cov = ned2ecef_diag(np.stack([var_h, var_h, var_v], axis=-1), init_pos)

    def add_values(self, k: int, values: gtsam.Values) -> None:
        """No variables beyond the position."""

    def link_factors(self, k: int, lin: gtsam.Values | None = None) -> list:
        """Factors tying epoch ``k`` to ``k - 1``."""
        return [gtsam.BetweenFactorPoint3(pos_key(k - 1), pos_key(k), _ZERO3,
                                          gtsam.noiseModel.Gaussian.Covariance(self.cov[k]))]

    def start_factors(self, k: int) -> list:
        """Factors at the first epoch of a motion component."""
        return []

    def level_factors(self, k: int, lin: gtsam.Values | None = None) -> list:
        """No vertical-velocity prior: this model has no velocity."""
        return []


class ConstantVelocityMotion:
    """Velocity states: x(k) = x(k-1) + v(k-1) dt + small noise; v(k) - v(k-1) a random walk.

    init_pos (E,3) ECEF (NED frames), init_vel (E,3) ECEF [m/s] initial velocities, dt (E,) [s];
    accel_scale (E,) or scalar: the walk's sigma into each epoch, in units of the configured one;
    level_sigma_mps: the zero-mean prior's sigma on each epoch's vertical velocity (0: none)."""

    def __init__(self, init_pos: np.ndarray, init_vel: np.ndarray, dt: np.ndarray, cfg: GraphConfig,
                 accel_scale: np.ndarray | float = 1.0, level_sigma_mps: float = 0.0):
        self.dt, self.init_vel = dt, init_vel
        dts = np.maximum(dt, 1e-3)
        walk = dts * np.asarray(accel_scale, float) ** 2
        var_h, var_v = cfg.cv_accel_h ** 2 * walk, cfg.cv_accel_v ** 2 * walk
        self.vel_cov = ned2ecef_diag(np.stack([var_h, var_h, var_v], axis=-1), init_pos)
        self.pos_sqrt_info = 1.0 / (cfg.cv_pos_sigma_m * np.sqrt(dts))
        # (E,3) ECEF down direction over the level prior's sigma: the prior's whitened row
        self.level_row = ned_rotation(init_pos)[:, 2, :] / level_sigma_mps if level_sigma_mps > 0 else None

    def add_values(self, k: int, values: gtsam.Values) -> None:
        values.insert(vel_key(k), self.init_vel[k])

    def link_factors(self, k: int, lin: gtsam.Values | None = None) -> list:
        """Factors tying epoch ``k`` to ``k - 1``; ``lin`` a Values with zero Point3s at the keys of the
        linear factor (shared by the whole graph; None: made here)."""
        # x_k - x_{k-1} - dt v_{k-1} = 0 is linear, so a whitened JacobianFactor wrapped for the
        # nonlinear graph is exact and runs in C++ (a Python CustomFactor would be far slower). With
        # an all-zero linearisation point its error is exactly A x - b.
        w, I3 = self.pos_sqrt_info[k], np.eye(3)
        keys = (pos_key(k), pos_key(k - 1), vel_key(k - 1))
        jf = gtsam.JacobianFactor(keys[0], w * I3, keys[1], -w * I3, keys[2], -w * self.dt[k] * I3,
                                  _ZERO3, gtsam.noiseModel.Unit.Create(3))
        return [gtsam.LinearContainerFactor(jf, zero_point(keys) if lin is None else lin),
                gtsam.BetweenFactorPoint3(vel_key(k - 1), vel_key(k), _ZERO3,
                                          gtsam.noiseModel.Gaussian.Covariance(self.vel_cov[k]))]

    def start_factors(self, k: int) -> list:
        return [velocity_prior_factor_v(k, self.init_vel[k], START_VEL_SIGMA_MPS)]

    def level_factors(self, k: int, lin: gtsam.Values | None = None) -> list:
        """The zero-mean prior on epoch ``k``'s vertical velocity (none where the config has no level sigma);
        linear, so exact as a whitened JacobianFactor (``lin`` as in :meth:`link_factors`)."""
        if self.level_row is None:
            return []
        jf = gtsam.JacobianFactor(vel_key(k), self.level_row[k][None, :], np.zeros(1), gtsam.noiseModel.Unit.Create(1))
        return [gtsam.LinearContainerFactor(jf, zero_point([vel_key(k)]) if lin is None else lin)]


def motion_model(init_pos: np.ndarray, init_vel: np.ndarray, dt: np.ndarray, cfg: GraphConfig,
                 motion_only: np.ndarray | None = None, level_sigma_mps: float = 0.0):
    """The motion model named by ``cfg.motion`` ("rw" or "cv") for a trace's epochs; ``motion_only`` (E,) bool
    the epochs nothing else places, whose velocity random walk into them is ``cfg.bridged_accel_scale`` x;
    ``level_sigma_mps`` the cv model's prior on the vertical velocity (0: none)."""
    if cfg.motion == "rw":
        return RandomWalkMotion(init_pos, dt, cfg)
    if cfg.motion == "cv":
        scale = 1.0 if motion_only is None else np.where(motion_only, cfg.bridged_accel_scale, 1.0)
        return ConstantVelocityMotion(init_pos, init_vel, dt, cfg, scale, level_sigma_mps)
    raise GeometryError(f"unknown motion model {cfg.motion!r}; choose rw or cv")
