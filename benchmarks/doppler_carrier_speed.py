"""Speed of the Doppler and carrier-phase factors, each against the alternative it replaced, in the
same run on the same simulated trace (Doppler + carrier, 1 Hz, ~10 satellites per epoch).

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/doppler_carrier_speed.py [--epochs 600]

1. Time-differenced carrier: ours (GTSAM's C++ ``DopplerFactor`` on the displacement u(k),
   :func:`fusion.estimate.graph.factors.tdcp_factor_uqq`, linearised at the WLS track or at the
   carrier-free graph's solution, the default) vs the exact model as a vectorised Python
   ``CustomFactor`` per epoch pair on (x, x, c, c) with a robust loss per row (below):
   Levenberg-Marquardt time and the position error p50 of each against the truth.
2. Doppler: GTSAM's C++ ``DopplerFactor`` (ours) vs the same model, less GTSAM's Earth-rotation
   rate term (a few mm/s), as a per-satellite Python ``CustomFactor`` on (v, c, d), both on the
   pseudorange + Doppler graph.
Best of ``--repeat`` runs; the machine is shared, so ratios matter more than seconds.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import time

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph import build
from fusion.estimate.graph.build import build_graph
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.factors import robust_model
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.keys import DRIFT_HORIZON_S, clock_key, drift_key, pos_key, vel_key
from fusion.estimate.wls import solve_wls
from fusion.geometry import C_LIGHT, OMEGA_E
from fusion.sim.simulate import SimConfig, simulate


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
    cancels. Exact (no linearisation at a guess), as a Python ``CustomFactor`` with analytic
    Jacobians; one factor per epoch pair (its rows vectorised, each row with its own robust loss,
    :func:`robust_rows`; the factor's own noise model is the unit one): per-satellite Python factors
    cost ~6x more again.
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


def tdcp_custom(k, trace, inp, cfg, values) -> list:
    """The alternative carrier builder: one exact Python factor per epoch pair."""
    raw = inp.raw
    cur = np.flatnonzero(raw.tdcp_prev[k] >= 0)
    if cur.size == 0:
        return []
    prev = raw.tdcp_prev[k, cur]
    return [tdcp_factor_xxcc(k - 1, k, trace.adr[k, cur] - trace.adr[k - 1, prev], trace.sat_pos[k - 1, prev],
                             trace.sat_pos[k, cur], raw.tdcp_sigma[k, cur], cfg.robust, cfg.rate_robust_k)]


def tdcp_custom_all(p, trace, inp, cfg, epochs, lin) -> None:
    """:func:`tdcp_custom` for every kept epoch, in place of ``build.add_carriers``."""
    for k in epochs:
        if k > 0:
            p.add(int(k), tdcp_custom(int(k), trace, inp, cfg, None))


def doppler_custom_all(p, trace, inp, cfg, epochs) -> None:
    """:func:`doppler_custom` for every kept epoch, in place of ``build.add_dopplers``."""
    for k in epochs:
        p.add(int(k), doppler_custom(int(k), trace, inp, cfg))


def doppler_custom(k, trace, inp, cfg) -> list:
    """The alternative Doppler builder: the model as a per-satellite Python factor on (v, c, d)."""
    raw, out = inp.raw, []
    for s in np.flatnonzero(raw.doppler[k]):
        keys = [vel_key(k), clock_key(k), drift_key(k)]
        d = trace.sat_pos[k, s] - inp.init_pos[k]
        los, sv, z = d / np.linalg.norm(d), trace.sat_vel[k, s], float(trace.prr[k, s])
        w = C_LIGHT / DRIFT_HORIZON_S

        def error(this, v, H, keys=keys, los=los, sv=sv, z=z, w=w):
            if H is not None:
                H[0], H[1], H[2] = -los[None], np.array([[-w]]), np.array([[w]])
            drift = w * (v.atDouble(keys[2]) - v.atDouble(keys[1]))
            return np.array([los @ (sv - v.atPoint3(keys[0])) + drift - z])

        model = robust_model(cfg.robust, cfg.rate_robust_k, gtsam.noiseModel.Isotropic.Sigma(1, float(raw.prr_sigma[k, s])))
        out.append(gtsam.CustomFactor(model, gtsam.KeyVector(keys), error))
    return out


def solve_with(trace, inp, cfg, swap: tuple[str, object] | None, repeat: int) -> tuple[float, np.ndarray]:
    """Best LM time [s] and positions (E,3), with build.<name> swapped for another builder."""
    saved = None
    if swap is not None:
        saved = getattr(build, swap[0])
        setattr(build, swap[0], swap[1])
    try:
        graph, values, epochs = build_graph(trace, inp, cfg)
    finally:
        if saved is not None:
            setattr(build, swap[0], saved)
    best = np.inf
    for _ in range(repeat):
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.lm_max_iter)
        params.setRelativeErrorTol(cfg.lm_rel_tol)
        t0 = time.perf_counter()
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        best = min(best, time.perf_counter() - t0)
    pos = np.full((trace.n_epochs, 3), np.nan)
    for k in epochs:
        pos[k] = result.atPoint3(pos_key(int(k)))
    return best, pos


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--epochs", type=int, default=600)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    tr = simulate(n_epochs=args.epochs, seed=3, config=SimConfig(doppler=True, carrier=True, slip_prob=0.01)).trace
    wls, cfg = solve_wls(tr, elev_mask_deg=10.0), GraphConfig()
    print(f"trace: {tr.n_epochs} epochs, {tr.n_sats.mean():.1f} satellites/epoch")

    def p50(pos):
        return np.nanmedian(np.linalg.norm(pos - tr.truth, axis=1))

    inp = prepare_inputs(tr, wls, replace(cfg, use_doppler=False, use_carrier=True))
    alt, p_alt = solve_with(tr, inp, cfg, ("add_carriers", tdcp_custom_all), args.repeat)
    ours_init, p_init = solve_with(tr, inp, cfg, None, args.repeat)
    print(f"TDCP exact Python CustomFactor per epoch pair: {alt:6.2f} s LM, p50 {p50(p_alt):.3f} m")
    print(f"TDCP C++ DopplerFactor on u(k), linearised at WLS (ours): {ours_init:6.2f} s LM, p50 {p50(p_init):.3f} m "
          f"| ratio {alt / ours_init:.1f}x")
    inp = prepare_inputs(tr, wls, replace(cfg, use_doppler=True, use_carrier=False))
    ours, p_ours = solve_with(tr, inp, cfg, None, args.repeat)
    alt, p_alt = solve_with(tr, inp, cfg, ("add_dopplers", doppler_custom_all), args.repeat)
    print(f"Doppler C++ DopplerFactor (ours): {ours:6.2f} s LM, p50 {p50(p_ours):.3f} m | Python CustomFactor: "
          f"{alt:6.2f} s LM, p50 {p50(p_alt):.3f} m | ratio {alt / ours:.1f}x")


if __name__ == "__main__":
    main()
