"""One small builder per factor kind of the fused graph, named like gtsam_gnss's factors: what is
measured, then the keys it ties (``x`` position, ``c`` clock, ``v`` velocity, ``i`` inter-system
bias, ``d`` clock drift; see :mod:`fusion.estimate.graph.keys`).

Measurement factors (pseudorange, Doppler, time-differenced carrier) take a noise model from the
caller, which wraps it in :func:`robust_model`; process models (clock and drift random walks) are
linear and exact as whitened ``JacobianFactor``s in C++.

Sagnac: GTSAM 4.3's ``PseudorangeFactor`` already adds the Earth-rotation range term
``OMEGA_E / c * (x_sat * y_rx - y_sat * x_rx)`` to the geometric range (checked against
:func:`fusion.geometry.line_of_sight` in ``tests/estimate/test_graph.py``), which is the first-order form of
:func:`fusion.geometry.sagnac_rotate`. Satellite positions are therefore passed at transmit time,
unrotated: rotating them as well would apply the correction twice.
"""
from __future__ import annotations

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.keys import (DRIFT_HORIZON_S, carrier_clock_key, clock_key, disp_key, doppler_drift_key,
                                        drift_key, isb_key, pos_key, vel_key)
from fusion.geometry import C_LIGHT, OMEGA_E


#: GraphConfig's robust-loss names -> GTSAM's M-estimators ("gm": Geman-McClure, which redescends).
M_ESTIMATORS = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
                "gm": gtsam.noiseModel.mEstimator.GemanMcClure}


def m_estimator(kind: str, k: float):
    """GTSAM's M-estimator ``kind`` at ``k`` (in sigmas of the whitened error)."""
    if kind not in M_ESTIMATORS:
        raise GeometryError(f"unknown robust loss {kind!r}; choose {', '.join(M_ESTIMATORS)} or none")
    return M_ESTIMATORS[kind].Create(k)


def robust_model(kind: str, k: float, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """``base`` wrapped in a robust loss. GTSAM applies the M-estimator to the norm of the
    *whitened* error, i.e. to the Mahalanobis distance for a full-covariance ``base`` (checked in
    ``tests/estimate/test_graph.py``), so ``k`` is in sigmas whatever the covariance."""
    if kind == "none":
        return base
    return gtsam.noiseModel.Robust.Create(m_estimator(kind, k), base)


def scalar_robust_models(kind: str, k: float, sigmas: np.ndarray) -> list:
    """One 1-D :func:`robust_model` per sigma (N,) [measurement units], as a builder adding a whole
    trace's factors of one kind needs them: one M-estimator shared by all (GTSAM holds it by shared
    pointer and never changes it) and one model per distinct sigma (a phone reports few distinct
    sigmas), so a trace costs a few hundred GTSAM calls instead of three per factor."""
    est = None if kind == "none" else m_estimator(kind, k)
    made: dict[float, gtsam.noiseModel.Base] = {}
    out = []
    for sg in np.asarray(sigmas, float).tolist():
        model = made.get(sg)
        if model is None:
            base = gtsam.noiseModel.Isotropic.Sigma(1, sg)
            model = made[sg] = base if est is None else gtsam.noiseModel.Robust.Create(est, base)
        out.append(model)
    return out


def prior_noise_model(cov: np.ndarray, robust: str = "none", robust_k: float = 1.0) -> gtsam.noiseModel.Base:
    """Noise model of one position prior: Gaussian with ``cov`` (3,3) (already cleaned by
    :func:`fusion.estimate.graph.priors.clean_priors`), wrapped in ``robust`` (a key of :data:`M_ESTIMATORS` or
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
                       model: gtsam.noiseModel.Base, drift: int | None = None) -> gtsam.DopplerFactor:
    """Doppler (pseudorange rate) of one satellite at epoch ``k``:
    ``prr = los . (sat_vel - v(k)) + OMEGA_E/c rate term + c * drift(k)``, in GTSAM's C++ factor.

    The drift enters as ``(d(k) - c(k)) / DRIFT_HORIZON_S`` (the drift key's convention, see
    :mod:`fusion.estimate.graph.keys`). prr_mps already has the satellite clock drift removed, so
    GTSAM's satellite-drift argument is 0; it wants ``-wavelength * doppler``, hence ``-prr`` with a
    unit wavelength. sat_pos, sat_vel (3,) ECEF at transmit time; rx_guess (3,) the receiver position
    fixing the line of sight (metres of position error turn it by ~1e-7 rad); model 1-D [m/s]; drift: the key
    of the drift the Doppler sees (None: ``drift_key(k)``; :func:`doppler_drift_factor_jd`)."""
    return gtsam.DopplerFactor(vel_key(k), clock_key(k), drift_key(k) if drift is None else drift, -float(prr_mps), 1.0,
                               np.asarray(sat_pos, float), np.asarray(sat_vel, float),
                               np.asarray(rx_guess, float), DRIFT_HORIZON_S, 0.0, model)


def tdcp_factor_uqq(k: int, delta_adr_m: float, sat_j: np.ndarray, sat_k: np.ndarray, guess_j: np.ndarray,
                    guess_k: np.ndarray, model: gtsam.noiseModel.Base) -> gtsam.DopplerFactor:
    """Time-differenced carrier phase of one satellite from epoch ``k - 1`` to ``k`` (no slip between),
    on the displacement u(k) = x(k) - x(k-1) and the carrier clocks q(k-1), q(k) [m]:
    ``adr(k) - adr(k-1) = R_k(x(k)) - R_{k-1}(x(k-1)) + q(k) - q(k-1)``, R the pseudorange geometry
    (range + first-order Sagnac term); the ambiguity cancels. (Why q and not c: :mod:`keys`.)

    Linearised at the initial positions guess_j, guess_k (3,): ``R_k(x(k)) - R_{k-1}(x(k-1)) ~=
    R_k(guess_k) - R_{k-1}(guess_j) + g_k . (u(k) - (guess_k - guess_j))`` with g_k the gradient of
    R_k. What this drops, (g_k - g_{k-1}) . (x(k-1) - guess_j), is ~1e-4 of the initial position error
    per second of epoch gap (1 mm for a 10 m WLS error at 1 Hz). ``g . u + q(k) - q(k-1)`` is exactly
    GTSAM's C++ ``DopplerFactor`` model with the displacement as its velocity, a zero satellite velocity
    (carrier phase is integrated Doppler) and dt = c (its clock term is c * (clock_b - clock_a) / dt,
    so clocks in metres enter as they are), so the factor runs in C++ with its
    own robust loss (a Python ``CustomFactor`` costs ~6-70x more, benchmarks/doppler_carrier_speed.py).
    sat_j, sat_k (3,) ECEF at transmit time; model 1-D [m]."""
    measured = tdcp_measured(np.array([delta_adr_m], float), np.asarray(sat_j, float)[None],
                             np.asarray(sat_k, float)[None], np.asarray(guess_j, float)[None],
                             np.asarray(guess_k, float)[None])[0][0]
    return tdcp_factor_linearised(k, float(measured), sat_k, guess_k, model)


def tdcp_measured(delta_adr_m: np.ndarray, sat_j: np.ndarray, sat_k: np.ndarray, guess_j: np.ndarray,
                  guess_k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the linearised carrier measurement of :func:`tdcp_factor_uqq` for N factors at once:
    ``delta_adr - R_k(guess_k) + R_{k-1}(guess_j) + g_k . (guess_k - guess_j)``, and (N,3) g_k, the range's
    gradient at guess_k. delta_adr_m (N,); sat_j, sat_k, guess_j, guess_k (N,3)."""
    geom_j, _ = range_and_gradient(sat_j, guess_j)
    geom_k, grad_k = range_and_gradient(sat_k, guess_k)
    return delta_adr_m - geom_k + geom_j + np.einsum("ij,ij->i", grad_k, guess_k - guess_j), grad_k


def doppler_rows(prr_mps: np.ndarray, sat: np.ndarray, sat_vel: np.ndarray, rx: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The linear model of :func:`doppler_factor_vcd` for N measurements at once: ``rhs = grad . v + drift``.
    prr_mps (N,) [m/s]; sat, sat_vel, rx (N,3) ECEF. Returns grad (N,3) (the line of sight's d(range rate)/dv
    with its Sagnac term) and rhs (N,) [m/s] (the rate less the satellite's own motion)."""
    _, grad = range_and_gradient(sat, rx)
    los = (sat - rx) / np.linalg.norm(sat - rx, axis=1)[:, None]
    sagnac = OMEGA_E / C_LIGHT * (sat_vel[:, 1] * rx[:, 0] - sat_vel[:, 0] * rx[:, 1])
    return grad, prr_mps - np.einsum("ij,ij->i", los, sat_vel) + sagnac


def tdcp_factor_linearised(k: int, measured: float, sat_k: np.ndarray, guess_k: np.ndarray,
                           model: gtsam.noiseModel.Base) -> gtsam.DopplerFactor:
    """:func:`tdcp_factor_uqq` from its linearised measurement (:func:`tdcp_measured`) [m]: ``sat_k`` (3,)
    the satellite's ECEF position at epoch ``k`` and ``guess_k`` (3,) the receiver's guess there [m]."""
    return gtsam.DopplerFactor(disp_key(k), carrier_clock_key(k - 1), carrier_clock_key(k), -measured, 1.0,
                               sat_k, _ZERO3, guess_k, C_LIGHT, 0.0, model)


_ZERO3 = np.zeros(3)


def range_and_gradient(sat: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's pseudorange geometry |sat - x| + OMEGA_E / c (x_sat y - y_sat x) (N,) and its (N,3)
    gradient in x; sat (N,3) transmit-time ECEF, x (N,3) receiver ECEF."""
    d = sat - x
    r = np.sqrt(np.einsum("ij,ij->i", d, d))
    m = OMEGA_E / C_LIGHT * np.stack([-sat[:, 1], sat[:, 0], np.zeros(len(sat))], axis=1)
    return r + np.einsum("ij,ij->i", m, x), m - d / r[:, None]


def zero_point(keys, kind: str = "point3") -> gtsam.Values:
    """Values holding zero at every key (``kind`` "point3" or "double"): the linearisation point of the
    exact linear factors below. One shared Values serves every factor of a graph (each factor copies
    only its own keys, in C++), instead of a Values built per factor (~20x the cost)."""
    lin = gtsam.Values()
    for key in keys:
        if kind == "double":
            lin.insert(int(key), c=0.0)      # the keyword picks the scalar overload at once (3x faster)
        else:
            lin.insert(int(key), np.zeros(3))
    return lin


def displacement_factor_xxu(k: int, sigma_m: float, lin: gtsam.Values | None = None) -> gtsam.LinearContainerFactor:
    """Ties the displacement to the positions: u(k) - (x(k) - x(k-1)) ~ N(0, sigma^2 I) [m], linear and
    exact as a whitened JacobianFactor (sigma small: it is a definition, not a measurement). ``lin``: a
    Values with zeros at these keys (None: made here)."""
    w, I3 = 1.0 / sigma_m, np.eye(3)
    keys = (disp_key(k), pos_key(k), pos_key(k - 1))
    jf = gtsam.JacobianFactor(keys[0], w * I3, keys[1], -w * I3, keys[2], w * I3, np.zeros(3),
                              gtsam.noiseModel.Unit.Create(3))
    return gtsam.LinearContainerFactor(jf, zero_point(keys) if lin is None else lin)


def _linear_factor(keys: list[int], coeffs: list[float], sigma: float, lin: gtsam.Values | None = None
                   ) -> gtsam.LinearContainerFactor:
    """The scalar constraint ``sum(coeffs * keys) ~ N(0, sigma^2)`` over 1 to 4 Double keys, exact as a
    whitened linear factor linearised at zero (so its error is exactly A x); ``lin`` a Values with zeros
    at these keys (None: made here)."""
    a = np.asarray(coeffs, float) / sigma
    lin = zero_point(keys, "double") if lin is None else lin
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


def clock_drift_factor_ccd(j: int, k: int, span_s: float, sigma_m: float, lin: gtsam.Values | None = None
                           ) -> gtsam.LinearContainerFactor:
    """Clock with drift from epoch ``j`` to ``k``: c(k) - c(j) - drift(j) span ~ N(0, sigma^2), with
    drift(j) = (d(j) - c(j)) / DRIFT_HORIZON_S; sigma given in metres, variables in seconds."""
    a = span_s / DRIFT_HORIZON_S
    return _linear_factor([clock_key(k), clock_key(j), drift_key(j)], [1.0, a - 1.0, -a], sigma_m / C_LIGHT, lin)


def drift_walk_factor_cdcd(j: int, k: int, sigma_mps: float, lin: gtsam.Values | None = None
                           ) -> gtsam.LinearContainerFactor:
    """Drift random walk: drift(k) - drift(j) ~ N(0, sigma^2), sigma in m/s."""
    keys = [drift_key(k), clock_key(k), drift_key(j), clock_key(j)]
    return _linear_factor(keys, [1.0, -1.0, -1.0, 1.0], sigma_mps * DRIFT_HORIZON_S / C_LIGHT, lin)


def doppler_drift_factor_jd(k: int, sigma_mps: float, lin: gtsam.Values | None = None
                            ) -> gtsam.LinearContainerFactor:
    """The drift the Doppler of epoch ``k`` sees is the clock's drift plus a white jump:
    doppler_drift(k) - drift(k) ~ N(0, sigma^2), sigma in m/s (both held as :func:`drift_key` is)."""
    return _linear_factor([doppler_drift_key(k), drift_key(k)], [1.0, -1.0], sigma_mps * DRIFT_HORIZON_S / C_LIGHT, lin)


def drift_prior_factor_cd(k: int, drift_mps: float, sigma_mps: float, lin: gtsam.Values | None = None
                          ) -> gtsam.LinearContainerFactor:
    """A loose prior drift(k) ~ N(drift_mps, sigma^2) at the start of a clock chain, so that an epoch
    without Doppler keeps a determinable drift."""
    w = C_LIGHT / (sigma_mps * DRIFT_HORIZON_S)
    jf = gtsam.JacobianFactor(drift_key(k), np.array([[w]]), clock_key(k), np.array([[-w]]),
                              np.array([drift_mps / sigma_mps]), gtsam.noiseModel.Unit.Create(1))
    return gtsam.LinearContainerFactor(jf, zero_point([drift_key(k), clock_key(k)], "double") if lin is None else lin)
