"""Three-satellite epochs between good ones: the receiver clock from its neighbours, then position alone.

Four unknowns need four satellites; with three, the clock can come from the epochs around: a phone's
clock drifts smoothly (metres per second, nearly constant over seconds), so a straight line between
the last good epoch before and the first good epoch after predicts it to about a metre. The
prediction is used only when both neighbours are within ``max_gap_ms``, no clock reset lies between
them, and the line between them agrees (within ``JUMP_TOL_M``) with the clock extrapolated from the
good epoch before the earlier neighbour or after the later one - a jump the file does not flag
(GSDC 2021 derived files carry no discontinuity column) would otherwise be spread over the gap.
Otherwise the epoch stays unsolved with the reason ``three_sats_no_clock``.
"""
from __future__ import annotations

import numpy as np

from fusion.geometry import line_of_sight

#: Furthest a neighbouring good epoch may be for its clock to be used [ms].
MAX_GAP_MS = 3000
#: Largest disagreement between interpolated and extrapolated clock that is not a jump [m]
#: (WLS clocks are good to a few metres; phone clock jumps are hundreds of metres and more).
JUMP_TOL_M = 50.0


def interpolate_clock(t_ms: np.ndarray, clock_m: np.ndarray, valid: np.ndarray, clock_reset: np.ndarray,
                      targets: np.ndarray, max_gap_ms: float = MAX_GAP_MS) -> tuple[np.ndarray, np.ndarray]:
    """Receiver clock at ``targets`` from the valid epochs on both sides.

    t_ms: (E,) epoch times; clock_m: (E,) solved clocks [m]; valid: (E,) bool; clock_reset: (E,)
    bool (a jump between epoch e-1 and e); targets: (K,) epoch indices.
    Returns (clock (K,) [m], ok (K,) bool).
    """
    good = np.flatnonzero(valid)
    K = targets.shape[0]
    if good.size < 2 or K == 0:
        return np.full(K, np.nan), np.zeros(K, bool)
    seg = np.cumsum(clock_reset)
    j = np.searchsorted(good, targets)
    prev = good[np.clip(j - 1, 0, good.size - 1)]
    nxt = good[np.clip(j, 0, good.size - 1)]
    t = t_ms.astype(float)
    ok = ((j > 0) & (j < good.size) & (seg[prev] == seg[targets]) & (seg[nxt] == seg[targets])
          & (t[targets] - t[prev] <= max_gap_ms) & (t[nxt] - t[targets] <= max_gap_ms))
    span = np.where(ok, t[nxt] - t[prev], 1.0)
    a = (t[targets] - t[prev]) / span
    clock = clock_m[prev] + a * (clock_m[nxt] - clock_m[prev])
    # the line prev -> nxt checked against each side's own drift (one more good epoch outward)
    before = good[np.clip(j - 2, 0, good.size - 1)]
    after = good[np.clip(j + 1, 0, good.size - 1)]
    agree = np.zeros(K, bool)
    for far, near, other in ((before, prev, nxt), (after, nxt, prev)):
        has = (far != near) & (seg[far] == seg[near]) & (np.abs(t[near] - t[far]) <= max_gap_ms)
        drift = (clock_m[near] - clock_m[far]) / np.where(has, t[near] - t[far], 1.0)
        predicted = clock_m[near] + drift * (t[other] - t[near])
        agree |= has & (np.abs(predicted - clock_m[other]) <= JUMP_TOL_M)
    ok &= agree
    return np.where(ok, clock, np.nan), ok


def solve_fixed_clock(sat_pos: np.ndarray, pr: np.ndarray, w: np.ndarray, pos0: np.ndarray,
                      clock_m: np.ndarray, max_iter: int = 10, tol: float = 1e-4):
    """Position-only Gauss-Newton with a known clock.

    sat_pos: (K, S, 3); pr, w: (K, S) (weight 0 on unused slots); pos0: (K, 3) start; clock_m: (K,).
    Returns (pos (K, 3), converged (K,) bool, cov (K, 3, 3) = (H^T W H)^-1, NaN where singular).
    """
    pos = pos0.copy()
    conv = np.zeros(pos.shape[0], bool)
    N = np.zeros((pos.shape[0], 3, 3))
    for _ in range(max_iter):
        rng, los = line_of_sight(sat_pos, pos)
        r = pr - rng - clock_m[:, None]
        H = -los
        N = np.einsum("ks,ksi,ksj->kij", w, H, H)
        b = np.einsum("ks,ksi,ks->ki", w, H, r)
        det = np.linalg.det(N)
        ok = np.isfinite(det) & (np.abs(det) > 1e-12 * np.einsum("kii->k", N) ** 3)
        dx = np.zeros_like(pos)
        dx[ok] = np.linalg.solve(N[ok], b[ok][..., None])[..., 0]
        pos += np.where(conv[:, None], 0.0, dx)
        conv |= ok & (np.linalg.norm(dx, axis=1) < tol)
    cov = np.full(N.shape, np.nan)
    det = np.linalg.det(N)
    inv = np.isfinite(det) & (det > 0)
    cov[inv] = np.linalg.inv(N[inv])
    return pos, conv & inv, cov
