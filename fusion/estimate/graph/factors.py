"""One small builder per factor kind of the fused graph, named like gtsam_gnss's factors: what is
measured, then the keys it ties (``x`` position, ``c`` clock, ``v`` velocity, ``i`` inter-system
bias; see :mod:`fusion.estimate.graph.keys`).

Sagnac: GTSAM 4.3's ``PseudorangeFactor`` already adds the Earth-rotation range term
``OMEGA_E / c * (x_sat * y_rx - y_sat * x_rx)`` to the geometric range (checked against
:func:`fusion.geometry.line_of_sight` in ``tests/test_graph.py``), which is the first-order form of
:func:`fusion.geometry.sagnac_rotate`. Satellite positions are therefore passed at transmit time,
unrotated: rotating them as well would apply the correction twice.
"""
from __future__ import annotations

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.keys import clock_key, isb_key, pos_key, vel_key
from fusion.geometry import C_LIGHT


def robust_model(kind: str, k: float, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """``base`` wrapped in a robust loss. GTSAM applies the M-estimator to the norm of the
    *whitened* error, i.e. to the Mahalanobis distance for a full-covariance ``base`` (checked in
    ``tests/test_graph.py``), so ``k`` is in sigmas whatever the covariance."""
    if kind == "none":
        return base
    if kind == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(k)
    elif kind == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    else:
        raise GeometryError(f"unknown robust loss {kind!r}; choose huber, cauchy or none")
    return gtsam.noiseModel.Robust.Create(est, base)


def prior_noise_model(cov: np.ndarray, robust: str = "none", robust_k: float = 1.0) -> gtsam.noiseModel.Base:
    """Noise model of one position prior: Gaussian with ``cov`` (3,3) (already cleaned by
    :func:`fusion.estimate.graph.priors.clean_priors`), wrapped in ``robust`` ("huber", "cauchy",
    "none") at ``robust_k`` sigmas."""
    return robust_model(robust, robust_k, gtsam.noiseModel.Gaussian.Covariance(cov))


def pseudorange_factor_xc(k: int, pr_m: float, sat_pos: np.ndarray, model: gtsam.noiseModel.Base
                          ) -> gtsam.PseudorangeFactor:
    """Pseudorange of one satellite at epoch ``k``: range(x(k), sat_pos) + c * c(k).

    sat_pos (3,) ECEF at transmit time (GTSAM adds the Sagnac term); model: 1-D noise model [m]."""
    return gtsam.PseudorangeFactor(pos_key(k), clock_key(k), float(pr_m), sat_pos, 0.0, model)


def pseudorange_factor_xci(k: int, comp: int, group: int, pr_m: float, sat_pos: np.ndarray,
                           model: gtsam.noiseModel.Base) -> gtsam.DifferentialPseudorangeFactor:
    """Pseudorange of a non-reference signal: range + c * c(k) + ISB of ``group`` in ``comp``.

    GTSAM's ``DifferentialPseudorangeFactor`` models ``pr = range + c*clock - corr``, so the bias
    variable :func:`isb_key` holds ``-ISB``."""
    return gtsam.DifferentialPseudorangeFactor(pos_key(k), clock_key(k), isb_key(comp, group), float(pr_m),
                                               sat_pos, 0.0, model)


def clock_factor_cc(j: int, k: int, change_m: float, sigma_m: float) -> gtsam.BetweenFactorDouble:
    """Receiver clock random walk from epoch ``j`` to ``k``: c(k) - c(j) ~ N(change, sigma^2), given
    in metres and converted to the clock variables' seconds."""
    return gtsam.BetweenFactorDouble(clock_key(j), clock_key(k), float(change_m / C_LIGHT),
                                     gtsam.noiseModel.Isotropic.Sigma(1, float(sigma_m / C_LIGHT)))


def position_prior_factor_x(k: int, mean: np.ndarray, model: gtsam.noiseModel.Base) -> gtsam.PriorFactorPoint3:
    """A position prior (e.g. the learned correction) on x(k): mean (3,) ECEF [m]."""
    return gtsam.PriorFactorPoint3(pos_key(k), mean, model)


def isb_prior_factor_i(comp: int, group: int, sigma_m: float) -> gtsam.PriorFactorDouble:
    """Zero-mean prior on an inter-system bias: keeps a group seen by one satellite determinable."""
    return gtsam.PriorFactorDouble(isb_key(comp, group), 0.0, gtsam.noiseModel.Isotropic.Sigma(1, float(sigma_m)))


def velocity_prior_factor_v(k: int, vel: np.ndarray, sigma_mps: float) -> gtsam.PriorFactorPoint3:
    """A loose prior on v(k) (3,) ECEF [m/s]: a component's first velocity is otherwise free when the
    component has a single epoch."""
    return gtsam.PriorFactorPoint3(vel_key(k), vel, gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_mps)))
