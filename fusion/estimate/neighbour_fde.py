"""Fault identification for epochs snapshot FDE cannot decide, from the positions around them.

A snapshot test with few satellites often cannot tell which measurement is wrong: with six or seven
satellites two faults drag the fit toward each other and several exclusion sets pass alike; with five,
one fault cannot be isolated at all (:mod:`fusion.estimate.raim` flags such epochs). The epochs around
it usually can: a vehicle moves smoothly over a second or two, so the straight line between the settled
epochs on both sides (each within :data:`MAX_GAP_MS`) predicts the position to a few metres. Seen from
that prediction, with the receiver clock taken as the median residual (robust to the faults), a fault
of tens of metres stands out of the other residuals. Slots whose deviation exceeds
``GATE * sqrt(sigma^2 * scale + PRED_SIGMA_M^2)`` are excluded (at most ``max_exclusions``, never fewer
than five satellites left), the epoch is re-solved, and the exclusion is kept only if the re-solved
epoch then passes the chi-square test (and the exclusion guard, :func:`fusion.estimate.raim.costly_exclusions`,
does not keep the satellites down-weighted instead); otherwise nothing changes and the epoch stays flagged.
"""
from __future__ import annotations

import numpy as np

from fusion.estimate.lsq import gauss_newton
from fusion.estimate.raim import chi2_test, costly_exclusions
from fusion.estimate.wls_state import FitState, WlsSettings
from fusion.geometry import line_of_sight
from fusion.trace import count_skip

#: Furthest a settled neighbour may be for the prediction [ms] (two epochs at 1 Hz, and a spare).
MAX_GAP_MS = 3000
#: 1-sigma error of the predicted position projected on a line of sight [m]: the neighbours' own
#: WLS errors (metres, more in streets) and the bend of the path between them.
PRED_SIGMA_M = 10.0
#: Deviation, in combined sigmas, beyond which a slot is excluded.
GATE = 4.0


def predict_positions(t_ms: np.ndarray, pos: np.ndarray, settled: np.ndarray, targets: np.ndarray,
                      max_gap_ms: float = MAX_GAP_MS) -> tuple[np.ndarray, np.ndarray]:
    """Positions at epochs ``targets`` (K,) on the line between the settled epochs around each.

    t_ms: (E,) epoch times; pos: (E, 3) solutions; settled: (E,) bool, epochs to predict from.
    Returns (pred (K, 3), ok (K,) bool: a settled epoch on each side within ``max_gap_ms``).
    """
    good = np.flatnonzero(settled)
    K = targets.shape[0]
    if good.size < 2 or K == 0:
        return np.full((K, 3), np.nan), np.zeros(K, bool)
    j = np.searchsorted(good, targets)
    prev = good[np.clip(j - 1, 0, good.size - 1)]
    nxt = good[np.clip(j, 0, good.size - 1)]
    t = t_ms.astype(float)
    ok = ((j > 0) & (j < good.size) & (t[targets] - t[prev] <= max_gap_ms)
          & (t[nxt] - t[targets] <= max_gap_ms))
    a = (t[targets] - t[prev]) / np.where(ok, t[nxt] - t[prev], 1.0)
    pred = pos[prev] + a[:, None] * (pos[nxt] - pos[prev])
    return np.where(ok[:, None], pred, np.nan), ok


def outlying_slots(sat_pos: np.ndarray, pr: np.ndarray, used: np.ndarray, w_prior: np.ndarray,
                   pred: np.ndarray, scale: float) -> np.ndarray:
    """(K, S) bool: used slots whose residual at the predicted position ``pred`` (K, 3), less the
    median residual of the epoch (the clock), is beyond the gate. sat_pos (K, S, 3); pr, used,
    w_prior (K, S) with ``w_prior = 1 / sigma^2``."""
    rng, _ = line_of_sight(sat_pos, pred)
    r = np.where(used, pr - rng, np.nan)
    dev = np.abs(r - np.nanmedian(r, axis=1, keepdims=True))
    var = scale / np.where(used, w_prior, 1.0) + PRED_SIGMA_M ** 2
    return used & (dev > GATE * np.sqrt(var))


def exclude_by_neighbours(fit: FitState, candidates: np.ndarray, targets: np.ndarray, settled: np.ndarray,
                          t_ms: np.ndarray, settings: WlsSettings, scale: float) -> tuple[FitState, np.ndarray]:
    """The module docstring's exclusion on the ``targets`` (E,) epochs, predicted from ``settled`` (E,).

    fit: the snapshot exclusion's fit (``used`` its choice, ``n_excluded`` its exclusions);
    candidates: (E, S) bool, the satellites above the mask (snapshot exclusions are reconsidered: with
    few satellites the snapshot test may have removed a good one and kept the fault); t_ms: (E,);
    settings: ``max_exclusions`` and the Gauss-Newton limits; scale: the test's variance factor.
    Returns (the fit with the repaired epochs re-solved, their ``used``, ``conv`` and ``n_excluded``
    changed, repaired (E,) bool); ``fit.dropped["outlier"]`` follows the changed exclusions.
    """
    idx = np.flatnonzero(targets)
    pred, ok = predict_positions(t_ms, fit.x[:, :3], settled, idx)
    idx, pred = idx[ok], pred[ok]
    out = outlying_slots(fit.sat_pos[idx], fit.pr[idx], candidates[idx], fit.w_prior[idx], pred, scale)
    new = candidates[idx] & ~out
    take = ((new != fit.used[idx]).any(1) & (out.sum(1) <= settings.max_exclusions) & (new.sum(1) >= 5))
    repaired = np.zeros(fit.used.shape[0], bool)
    if not take.any():
        return fit, repaired
    idx, new = idx[take], new[take]
    trial_used = fit.used.copy()
    trial_used[idx] = new
    trial = np.zeros_like(repaired)
    trial[idx] = True
    w = np.where(trial_used, fit.w_prior, 0.0)
    x2, c2, b2, r2 = gauss_newton(fit.sat_pos, fit.pr, w, fit.x.copy(), trial, settings.max_iter, settings.tol_m,
                                  settings.max_cond, fit.n_iter)
    _, fails = chi2_test(fit.sat_pos, fit.pr, w, x2, trial_used, scale)
    repaired = trial & c2 & ~b2 & ~r2 & ~fails
    repaired &= ~costly_exclusions(fit.replace(used=np.where(trial[:, None], candidates, fit.used)),
                                   fit.replace(used=trial_used, x=x2), settings)
    used = np.where(repaired[:, None], trial_used, fit.used)
    n_new = np.where(repaired, (candidates & ~used).sum(1), fit.n_excluded)
    count_skip(fit.dropped, "outlier", int((n_new - fit.n_excluded).sum()))
    return fit.replace(x=np.where(repaired[:, None], x2, fit.x), used=used, conv=fit.conv | repaired,
                       n_excluded=n_new), repaired


def gross_outliers(t_ms: np.ndarray, sat_pos: np.ndarray, pr: np.ndarray, pos: np.ndarray, targets: np.ndarray,
                   settled: np.ndarray, candidates: np.ndarray, gross_m: float, off_m: float = 0.0,
                   max_gap_ms: float = MAX_GAP_MS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measurements of the ``targets`` epochs that deviate by more than ``gross_m`` metres from the position
    the ``settled`` epochs around them predict (clock: the median residual there), on the epochs whose own
    position is more than ``off_m`` metres off the prediction.

    A gross fault in a five- or six-satellite epoch is absorbed by the fit (small residuals, a position
    off by the fault), and the snapshot test may even exclude a good satellite instead; only the
    neighbours show it. The WLS keeps such a measurement (in a street canyon its geometry is worth more
    than the doubt); a consumer that must not be pulled by it (the learned snapshot, :mod:`learned.modes`)
    drops it. Where more than three deviate or fewer than four would remain, nothing is decided.
    t_ms: (E,); sat_pos: (E, S, 3); pr, candidates: (E, S) (the slots to judge, e.g. those above the mask);
    pos: (E, 3) solutions; targets, settled: (E,) bool. Returns (far (E, S) bool, decided (E,) bool: the
    epochs judged (elsewhere ``far`` is False), predicted (E, 3) positions of the decided epochs, NaN elsewhere).
    """
    far, decided = np.zeros(candidates.shape, bool), np.zeros(targets.shape, bool)
    predicted = np.full(pos.shape, np.nan)
    idx = np.flatnonzero(targets)
    pred, ok = predict_positions(np.asarray(t_ms), np.nan_to_num(pos), settled, idx, max_gap_ms)
    idx, pred = idx[ok], pred[ok]
    if idx.size == 0:
        return far, decided, predicted
    rng, _ = line_of_sight(sat_pos[idx], pred)
    cand = candidates[idx]
    r = np.where(cand, pr[idx] - rng, np.nan)
    out = cand & (np.abs(r - np.nanmedian(r, axis=1, keepdims=True)) > gross_m)
    # only an epoch whose own position is off the prediction: a fault the fit absorbed moved it
    off = np.linalg.norm(pos[idx] - pred, axis=1) > off_m
    take = off & (out.sum(1) <= 3) & ((cand & ~out).sum(1) >= 4)
    far[idx[take]], decided[idx[take]], predicted[idx[take]] = out[take], True, pred[take]
    return far, decided, predicted
