"""Batched Gauss-Newton for snapshot positioning: the linear algebra WLS and its robust stages share.

State per epoch: ``x = [x, y, z, clock]`` (ECEF [m], receiver clock c*dt [m]). Every function works
on all epochs at once; padding and excluded slots carry weight 0.
"""
from __future__ import annotations

import numpy as np

from fusion.geometry import line_of_sight

#: Positions farther than this from the Earth's centre mean Gauss-Newton has run away [m].
R_RUNAWAY = 1.0e8


def normal_equations(sat_pos, pr, w, x):
    """Linearise at state x (E, 4), with sat_pos (E,S,3), pr (E,S), weights w (E,S): returns
    N (E,4,4), b (E,4), residuals r (E,S), H (E,S,4)."""
    rng, los = line_of_sight(sat_pos, x[:, :3])
    H = np.empty(los.shape[:-1] + (4,), np.result_type(los.dtype, np.float64))     # [-los, 1]
    np.negative(los, out=H[..., :3])
    H[..., 3] = 1.0
    r = pr - rng - x[:, 3:4]
    Hw = H * w[..., None]
    N = np.matmul(Hw.transpose(0, 2, 1), H)
    b = np.matmul(Hw.transpose(0, 2, 1), r[..., None])[..., 0]
    return N, b, r, H


def ill_conditioned(N: np.ndarray, max_cond: float) -> np.ndarray:
    """(E,) True where the normal matrix is singular or badly conditioned.

    The test is on the Jacobi-scaled matrix C = D^-1/2 N D^-1/2 (unit diagonal), so it does not
    depend on how the weights are scaled. A cheap determinant screens every epoch: with trace(C) = 4,
    cond(C) <= 4^4 / det(C), so det(C) >= 256 / max_cond proves the epoch fine; only the few
    epochs that fail the screen pay for an eigen-decomposition.
    """
    out = np.ones(N.shape[0], bool)
    d = np.diagonal(N, axis1=1, axis2=2)
    ok = np.isfinite(N).all(axis=(1, 2)) & (d > 0).all(1)
    if not ok.any():
        return out
    s = 1.0 / np.sqrt(d[ok])
    C = N[ok] * s[:, :, None] * s[:, None, :]
    fine = np.linalg.det(C) >= 256.0 / max_cond
    if not fine.all():
        ev = np.linalg.eigvalsh(C[~fine])
        fine[~fine] = ev[:, 0] * max_cond >= ev[:, -1]
    out[ok] = ~fine
    return out


def gauss_newton(sat_pos, pr, w, x, active, max_iter, tol, max_cond, n_iter):
    """Iterate the epochs in ``active`` until the state step is below ``tol`` [m].

    x: (E, 4) updated in place for active epochs. n_iter: (E,) incremented in place.
    Returns (x, converged, ill_conditioned, runaway), each flag (E,) bool.
    """
    E = x.shape[0]
    active = active.copy()
    conv = np.zeros(E, bool)
    bad = np.zeros(E, bool)
    runaway = np.zeros(E, bool)
    eye = np.eye(4)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        # every epoch active (the first steps of a stage): the arrays themselves, not copies of them
        rows = (sat_pos, pr, w, x) if idx.size == E else (sat_pos[idx], pr[idx], w[idx], x[idx])
        N, b, _, _ = normal_equations(*rows)
        sing = ill_conditioned(N, max_cond)
        N[sing] = eye
        b[sing] = 0.0
        dx = np.linalg.solve(N, b[..., None])[..., 0]
        x[idx] += dx
        n_iter[idx] += 1
        step = np.linalg.norm(dx, axis=1)
        lost = ~np.isfinite(x[idx]).all(1) | (np.linalg.norm(x[idx, :3], axis=1) > R_RUNAWAY)
        done = (step < tol) & ~sing & ~lost
        conv[idx[done]] = True
        bad[idx[sing]] = True
        runaway[idx[lost]] = True
        active[idx[done | sing | lost]] = False
    # A runaway state must not poison later stages with inf / NaN.
    x[runaway] = 0.0
    return x, conv, bad, runaway


def standardised_residuals(sat_pos, pr, w, x, used):
    """|v| / sqrt(Qv_ii) with Qv = W^-1 - H N^-1 H^T (the residuals' own covariance).

    Unlike |v| * sqrt(w), this accounts for the fit pulling the residual of a faulty satellite
    toward zero. Returns (E, S) with 0 on unused slots.
    """
    N, _, r, H = normal_equations(sat_pos, pr, w, x)
    safe = np.where(ill_conditioned(N, 1e12)[:, None, None], np.eye(4), N)
    Ninv = np.linalg.inv(safe)
    hnh = np.einsum("esi,eij,esj->es", H, Ninv, H)
    qv = np.where(used, 1.0 / np.where(used, w, 1.0) - hnh, 1.0)
    z = np.abs(r) / np.sqrt(np.maximum(qv, 1e-12))
    return np.where(used, z, 0.0)


def position_dop(sat_pos, x, w):
    """(E,) weighted position dilution of precision ``sqrt(trace((H^T W H)^-1)[:3, :3])`` [m per m of
    unit-weight range error] at state x (E, 4), with sat_pos (E, S, 3) and weights w (E, S) (0 on
    unused slots); inf where the normal matrix is singular."""
    N, _, _, _ = normal_equations(sat_pos, np.zeros(w.shape), w, x)
    sing = ill_conditioned(N, 1e12)
    Q = np.linalg.inv(np.where(sing[:, None, None], np.eye(4), N))
    return np.where(sing, np.inf, np.sqrt(np.trace(Q[:, :3, :3], axis1=1, axis2=2)))
