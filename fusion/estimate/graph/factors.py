"""One small builder per factor kind of the fused graph, named like gtsam_gnss's factors: what is
measured, then the keys it ties (``x`` position, ``c`` clock, ``v`` velocity, ``i`` inter-system
bias, ``d`` clock drift; see :mod:`fusion.estimate.graph.keys`).

Measurement factors (pseudorange, Doppler, time-differenced carrier) take a noise model from the
caller, which wraps it in :func:`robust_model`; process models (clock and drift random walks) are
linear and exact as whitened ``JacobianFactor``s in C++.

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
from fusion.estimate.graph.keys import DRIFT_HORIZON_S, clock_key, drift_key, isb_key, pos_key, vel_key
from fusion.geometry import C_LIGHT, OMEGA_E


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


def doppler_factor_vcd(k: int, prr_mps: float, sat_pos: np.ndarray, sat_vel: np.ndarray, rx_guess: np.ndarray,
                       model: gtsam.noiseModel.Base) -> gtsam.DopplerFactor:
    """Doppler (pseudorange rate) of one satellite at epoch ``k``:
    ``prr = los . (sat_vel - v(k)) + OMEGA_E/c rate term + c * drift(k)``, in GTSAM's C++ factor.

    The drift enters as ``(d(k) - c(k)) / DRIFT_HORIZON_S`` (the drift key's convention, see
    :mod:`fusion.estimate.graph.keys`). prr_mps already has the satellite clock drift removed, so
    GTSAM's satellite-drift argument is 0; it wants ``-wavelength * doppler``, hence ``-prr`` with a
    unit wavelength. sat_pos, sat_vel (3,) ECEF at transmit time; rx_guess (3,) the receiver position
    fixing the line of sight (metres of position error turn it by ~1e-7 rad); model 1-D [m/s]."""
    return gtsam.DopplerFactor(vel_key(k), clock_key(k), drift_key(k), -float(prr_mps), 1.0,
                               np.asarray(sat_pos, float), np.asarray(sat_vel, float),
                               np.asarray(rx_guess, float), DRIFT_HORIZON_S, 0.0, model)


def sagnac_rows(sat: np.ndarray) -> np.ndarray:
    """(n,3) rows m with m . x = OMEGA_E / c (x_sat y - y_sat x), the first-order Earth-rotation range
    term of GTSAM's pseudorange factors for receiver x (3,); also its gradient in x. sat (n,3) ECEF."""
    w = OMEGA_E / C_LIGHT
    return w * np.stack([-sat[:, 1], sat[:, 0], np.zeros(len(sat))], axis=1)


def _ranges_and_gradients(sat: np.ndarray, sagnac: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's pseudorange geometry |sat - x| + sagnac . x, (n,), and its gradient in x, (n,3).
    sat (n,3) transmit-time ECEF, sagnac (n,3) from :func:`sagnac_rows`, x (3,) receiver ECEF."""
    d = sat - x
    r = np.sqrt((d * d).sum(axis=1))
    return r + sagnac @ x, sagnac - d / r[:, None]


def robust_rows(e: np.ndarray, kind: str, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-row robust loss on whitened errors e (n,), as GTSAM's ``Robust`` noise model does it for a
    whole factor: the cost rows r (n,) with r^2 / 2 = rho(e), and the reweighting sqrt(w(e)) (n,),
    w = psi(e) / e, that linearisation applies to the row and its Jacobian (iteratively reweighted
    least squares). Used where one factor holds several measurements, each of which must be
    down-weighted alone (GTSAM's Robust would down-weight the whole factor)."""
    a = np.abs(e)
    if kind == "none":
        return e, np.ones_like(e)
    if kind == "huber":
        rho, w = np.where(a <= k, 0.5 * e**2, k * a - 0.5 * k * k), np.where(a <= k, 1.0, k / np.maximum(a, k))
    elif kind == "cauchy":
        rho, w = 0.5 * k * k * np.log1p((e / k) ** 2), 1.0 / (1.0 + (e / k) ** 2)
    else:
        raise GeometryError(f"unknown robust loss {kind!r}; choose huber, cauchy or none")
    return np.sign(e) * np.sqrt(2.0 * rho), np.sqrt(w)


def tdcp_factor_xxcc(j: int, k: int, delta_adr_m: np.ndarray, sat_j: np.ndarray, sat_k: np.ndarray,
                     sigma_m: np.ndarray, robust: str, robust_k: float) -> gtsam.CustomFactor:
    """Time-differenced carrier phase of n satellites between epochs ``j`` and ``k`` (no slip between):
    ``adr(k) - adr(j) = range(x(k), sat_k) - range(x(j), sat_j) + c * (c(k) - c(j))``; the ambiguity
    cancels. GTSAM 4.3 has no C++ factor of this form, so it is a Python ``CustomFactor`` with
    analytic Jacobians; one factor per epoch pair (its rows vectorised, each row with its own robust
    loss, :func:`robust_rows`; the factor's own noise model is the unit one), because per-satellite
    Python factors cost ~6x more (benchmarks/bench_doppler_carrier.py).
    delta_adr_m (n,) [m]; sat_j, sat_k (n,3) ECEF at transmit time; sigma_m (n,) [m]."""
    robust_rows(np.zeros(1), robust, robust_k)                 # an unknown loss fails here, not in GTSAM
    keys = [pos_key(j), pos_key(k), clock_key(j), clock_key(k)]
    sj, sk = np.array(sat_j, float), np.array(sat_k, float)
    mj, mk = sagnac_rows(sj), sagnac_rows(sk)
    z, inv = np.array(delta_adr_m, float), 1.0 / np.asarray(sigma_m, float)
    d_clock = C_LIGHT * inv[:, None]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        rj, gj = _ranges_and_gradients(sj, mj, values.atPoint3(keys[0]))
        rk, gk = _ranges_and_gradients(sk, mk, values.atPoint3(keys[1]))
        e = (rk - rj + C_LIGHT * (values.atDouble(keys[3]) - values.atDouble(keys[2])) - z) * inv
        cost_rows, sqrt_w = robust_rows(e, robust, robust_k)
        if H is None:                      # error(): the robust cost itself
            return cost_rows
        # linearize(): the reweighted rows and Jacobians, like GTSAM's Robust::WhitenSystem
        s = sqrt_w[:, None]
        H[0], H[1], H[2], H[3] = -(s * inv[:, None]) * gj, (s * inv[:, None]) * gk, -s * d_clock, s * d_clock
        return sqrt_w * e

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(len(z)), gtsam.KeyVector(keys), error)


def _linear_factor(keys: list[int], coeffs: list[float], sigma: float) -> gtsam.LinearContainerFactor:
    """The scalar constraint ``sum(coeffs * keys) ~ N(0, sigma^2)`` over 1 to 4 Double keys, exact as a
    whitened linear factor linearised at zero (so its error is exactly A x)."""
    a = np.asarray(coeffs, float) / sigma
    lin = gtsam.Values()
    for key in keys:
        lin.insert(key, 0.0)
    if len(keys) <= 3:
        args = [x for key, ai in zip(keys, a) for x in (key, np.array([[ai]]))]
        return gtsam.LinearContainerFactor(gtsam.JacobianFactor(*args, np.zeros(1), gtsam.noiseModel.Unit.Create(1)), lin)
    return gtsam.LinearContainerFactor(_four_key_hessian(keys, np.outer(a, a)), lin)


def _four_key_hessian(keys: list[int], H: np.ndarray) -> gtsam.HessianFactor:
    """A zero-mean HessianFactor with information H (4,4) over four keys. The Python wrapper builds
    JacobianFactors and HessianFactors of at most three keys, so H is split into three disjoint
    pieces of <= 3 keys (each holding some of its entries) that ``HessianFactor(graph)`` sums back."""
    m, z, g = (lambda i, j: np.array([[H[i, j]]])), np.zeros((1, 1)), np.zeros(1)
    k0, k1, k2, k3 = keys
    parts = gtsam.GaussianFactorGraph()
    parts.push_back(gtsam.HessianFactor(k0, k1, k2, m(0, 0), m(0, 1), m(0, 2), g, m(1, 1), m(1, 2), g,
                                        m(2, 2), g, 0.0))
    parts.push_back(gtsam.HessianFactor(k3, k0, k1, m(3, 3), m(3, 0), m(3, 1), g, z, z, g, z, g, 0.0))
    parts.push_back(gtsam.HessianFactor(k3, k2, z, m(3, 2), g, z, g, 0.0))
    return gtsam.HessianFactor(parts)


def clock_drift_factor_ccd(j: int, k: int, span_s: float, sigma_m: float) -> gtsam.LinearContainerFactor:
    """Clock with drift from epoch ``j`` to ``k``: c(k) - c(j) - drift(j) span ~ N(0, sigma^2), with
    drift(j) = (d(j) - c(j)) / DRIFT_HORIZON_S; sigma given in metres, variables in seconds."""
    a = span_s / DRIFT_HORIZON_S
    return _linear_factor([clock_key(k), clock_key(j), drift_key(j)], [1.0, a - 1.0, -a], sigma_m / C_LIGHT)


def drift_walk_factor_cdcd(j: int, k: int, sigma_mps: float) -> gtsam.LinearContainerFactor:
    """Drift random walk: drift(k) - drift(j) ~ N(0, sigma^2), sigma in m/s."""
    keys = [drift_key(k), clock_key(k), drift_key(j), clock_key(j)]
    return _linear_factor(keys, [1.0, -1.0, -1.0, 1.0], sigma_mps * DRIFT_HORIZON_S / C_LIGHT)


def drift_prior_factor_cd(k: int, drift_mps: float, sigma_mps: float) -> gtsam.LinearContainerFactor:
    """A loose prior drift(k) ~ N(drift_mps, sigma^2) at the start of a clock chain, so that an epoch
    without Doppler keeps a determinable drift."""
    w = C_LIGHT / (sigma_mps * DRIFT_HORIZON_S)
    jf = gtsam.JacobianFactor(drift_key(k), np.array([[w]]), clock_key(k), np.array([[-w]]),
                              np.array([drift_mps / sigma_mps]), gtsam.noiseModel.Unit.Create(1))
    lin = gtsam.Values()
    lin.insert(drift_key(k), 0.0)
    lin.insert(clock_key(k), 0.0)
    return gtsam.LinearContainerFactor(jf, lin)
