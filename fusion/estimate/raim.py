"""Robust stages of the snapshot WLS: RAIM-style fault detection and exclusion, and Huber IRLS.

Fault detection and exclusion (:func:`exclude_faults`), every epoch at once:

1. *Detect*: the weighted sum of squared residuals ``T = v^T W v`` (a-priori weights) against the
   chi-square threshold for ``n - 4`` degrees of freedom at false-alarm probability 1e-3. An epoch
   that passes keeps every satellite.
2. *Identify*: for k = 1, 2, ... ``max_exclusions``, every set of k satellites (for k >= 2, of the
   :data:`MAX_SUSPECTS` whose single removal helps most) is removed in turn (one linear step from
   the current solution) while ``n - k >= 5`` satellites remain; the first k
   for which the best set (least ``T``) passes the test wins, and that set is excluded - provided
   the runner-up set's ``T`` is at least ``SEPARATION`` times larger, else the fault is ambiguous
   (typical of multipath spread over several satellites) and nothing is excluded. Searching
   sets rather than dropping the largest residual one at a time finds two faults that drag the fit
   toward each other, where the largest standardised residual often points at a good satellite.
3. Re-solve the epochs that lost satellites. With an exclusion guard (``exclude_above_m``, set by
   :data:`fusion.estimate.wls.TRACE_DEFAULTS`), an exclusion whose removed residuals at the re-solved
   position are all below ``exclude_above_m`` metres and that raises the weighted position DOP by
   more than ``max_dop_growth`` is undone (:func:`costly_exclusions`): the epoch is flagged instead.

An epoch whose test fails and that no allowed exclusion repairs (5 satellites, more faults than
``max_exclusions``, or an ambiguous best set) is *flagged*: the test cannot decide which measurement
is wrong. Its solution is kept (the caller, :func:`fusion.estimate.wls.solve_wls_arrays`, re-solves it with Huber
weights) and the flag is counted in the report.
"""
from __future__ import annotations

from itertools import combinations
from math import comb

import numpy as np

from fusion.estimate.lsq import (gauss_newton, ill_conditioned, normal_equations, position_dop,
                                 standardised_residuals)
from fusion.estimate.wls_state import FitState, WlsSettings
from fusion.trace import count_skip

#: Normal quantile of the default false-alarm probability 1e-3 (one-sided).
Z_PFA_1E3 = 3.0902
#: A set is identified as the fault only when the runner-up set's SSE is at least this many times
#: its own; otherwise the epoch is flagged, not guessed at.
SEPARATION = 2.0
#: Sets of two or more satellites are searched among this many suspects per epoch (those whose
#: single removal lowers the SSE most), which bounds the search on multi-constellation epochs.
MAX_SUSPECTS = 12


def chi2_threshold(dof: np.ndarray, z: float = Z_PFA_1E3) -> np.ndarray:
    """Chi-square quantile for ``dof`` (any shape, >= 1) at the normal quantile ``z``.

    Wilson-Hilferty: within 3% of the exact quantile for dof >= 1 at z = 3.09 (10.83 -> 11.15
    for dof = 1), which is far finer than the gap between clean epochs and a gross fault.
    """
    k = np.maximum(np.asarray(dof, float), 1.0)
    return k * (1.0 - 2.0 / (9.0 * k) + z * np.sqrt(2.0 / (9.0 * k))) ** 3


def chi2_test(sat_pos, pr, w, x, used, scale: float = 1.0):
    """(E,) weighted SSE ``T`` and (E,) bool ``fails`` of the chi-square test at state x (E, 4).

    sat_pos: (E, S, 3), pr / w / used: (E, S). Epochs with no redundancy (n <= 4) never fail.
    ``scale``: variance factor of the weights (the threshold is multiplied by it).
    """
    _, _, r, _ = normal_equations(sat_pos, pr, w, x)
    T = np.sum(np.where(used, w * r**2, 0.0), axis=1)
    dof = used.sum(1) - 4
    return T, (dof > 0) & (T > scale * chi2_threshold(dof))


def variance_factor(sat_pos, pr, w, x, used, epochs) -> float:
    """How much larger than the a-priori model the trace's own residuals are (never below 1).

    sat_pos: (E, S, 3); pr, w, used: (E, S); x: (E, 4); epochs: (E,) bool, the epochs to use
    (best: those a first exclusion pass settled, so that faults do not inflate the estimate).
    A robust (median) estimate over every used measurement of those epochs, corrected for the
    redundancy a least-squares residual loses: ``(median |v| sqrt(w) / 0.6745)^2 / mean((n-4)/n)``,
    rounded to a power of sqrt(2).
    The median ignores the few faults left; the floor at 1 keeps the a-priori
    model wherever it is pessimistic (most open-sky drives), so it only relaxes the test on traces
    whose noise the model underrates (urban multipath), where it would otherwise fire on clean epochs.
    """
    _, _, r, _ = normal_equations(sat_pos, pr, w, x)
    sel = used & epochs[:, None]
    n = used.sum(1)[epochs]
    if not sel.any() or not np.any(n > 4):
        return 1.0
    z = np.abs(r[sel]) * np.sqrt(w[sel])
    redundancy = np.mean(np.maximum(n - 4, 0) / np.maximum(n, 1))
    f = max(1.0, (np.median(z) / 0.6745) ** 2 / max(redundancy, 1e-3))
    # in half-octave steps: a coarse calibration, and a few changed rows elsewhere in the file must
    # not move every epoch's test
    return float(2.0 ** (np.round(2.0 * np.log2(f)) / 2.0))


def subset_sse(H: np.ndarray, r: np.ndarray, w: np.ndarray, used: np.ndarray, k: int,
               among: int | None = None):
    """Weighted SSE after removing each set of ``k`` used satellites (one linear step).

    H: (E, S, 4) design matrix, r: (E, S) residuals, w: (E, S) weights, used: (E, S) bool.
    ``among``: remove only slots from the first ``among`` (every slot still enters the fit).
    Returns (sse (E, C) with inf where a removed slot is unused or the rest is singular,
    removal sets (C, k) slot indices).
    """
    E, S = r.shape
    pool = S if among is None else min(S, among)
    sets = np.array(list(combinations(range(pool), k)), dtype=np.int64).reshape(-1, k)
    keep = np.ones((sets.shape[0], S))
    np.put_along_axis(keep, sets, 0.0, axis=1)
    wc = w[:, None, :] * keep[None]                                   # (E, C, S)
    N = np.einsum("ecs,esi,esj->ecij", wc, H, H)
    b = np.einsum("ecs,esi,es->eci", wc, H, r)
    C = sets.shape[0]
    sing = ill_conditioned(N.reshape(E * C, 4, 4), 1e10).reshape(E, C)
    N = np.where(sing[..., None, None], np.eye(4), N)
    dx = np.linalg.solve(N, b[..., None])[..., 0]                      # (E, C, 4)
    v = r[:, None, :] - np.einsum("esk,eck->ecs", H, dx)
    sse = np.sum(wc * v**2, axis=2)
    removable = used[:, sets].all(-1)                                 # (E, C)
    return np.where(removable & ~sing, sse, np.inf), sets


def _chunked_subset_sse(H, r, w, used, k, among, max_elements: int = 20_000_000):
    """:func:`subset_sse` over blocks of epochs, so that (epochs x sets x slots) stays bounded in
    memory."""
    E, S = r.shape
    n_sets = comb(min(S, among), k)
    step = max(1, max_elements // max(1, n_sets * S * 4))
    parts = [subset_sse(H[a:a + step], r[a:a + step], w[a:a + step], used[a:a + step], k, among)
             for a in range(0, E, step)]
    return np.concatenate([p[0] for p in parts], axis=0), parts[0][1]


def _suspects_first(H, r, w, used):
    """Per-epoch slot order (E, S): the slots whose single removal lowers the SSE most come first
    (sets of two or three are searched among the first :data:`MAX_SUSPECTS` only)."""
    sse1, _ = subset_sse(H, r, w, used, 1)
    return np.argsort(sse1, axis=1, kind="stable")


def _best_exclusion(sat_pos, pr, w, x, used, fails, max_exclusions, separation, scale):
    """For failing epochs: the smallest set of satellites (up to ``max_exclusions``) whose removal
    passes the test, the set with the least SSE among those of that size, if it stands out from the
    runner-up by ``separation``.

    sat_pos: (E, S, 3); pr, w, used: (E, S); x: (E, 4); fails: (E,) bool.
    Returns (E, S) bool of slots to remove (empty rows where none is identified) and (E,) bool
    decided (passed, or repaired by a clearly identified set).
    """
    E, S = used.shape
    remove = np.zeros((E, S), bool)
    ambiguous = np.zeros(E, bool)
    decided = ~fails
    n = used.sum(1)
    # only the failing epochs are searched (each epoch's residuals are its own): f holds them, and
    # H, r, w, used_o, order below are rows of f
    f = np.flatnonzero(fails)
    _, _, r, H = normal_equations(sat_pos[f], pr[f], w[f], x[f])
    # slots reordered per epoch, suspects first: the k-sets come from the first MAX_SUSPECTS
    order = np.tile(np.arange(S), (f.size, 1))
    cand = np.flatnonzero(n[f] >= 6)
    if cand.size:
        order[cand] = _suspects_first(H[cand], r[cand], w[f][cand], used[f][cand])
    H, r, w, used_o = (np.take_along_axis(a, order[..., None] if a.ndim == 3 else order, axis=1)
                       for a in (H, r, w[f], used[f]))
    for k in range(1, max_exclusions + 1):
        loc = np.flatnonzero(~decided[f] & (n[f] - k >= 5))
        if loc.size == 0:
            break
        idx = f[loc]
        sse, sets = _chunked_subset_sse(H[loc], r[loc], w[loc], used_o[loc], k, MAX_SUSPECTS if k > 1 else S)
        best = np.argmin(sse, axis=1)
        best_sse = sse[np.arange(idx.size), best]
        runner_up = np.partition(sse, 1, axis=1)[:, 1] if sse.shape[1] > 1 else np.full(idx.size, np.inf)
        passes = np.isfinite(best_sse) & (best_sse <= scale * chi2_threshold(n[idx] - k - 4))
        # identified only when no other set explains the data nearly as well
        clear = runner_up >= separation * np.maximum(best_sse, 1e-9)
        ok = passes & clear
        rows = loc[ok]
        remove[f[rows][:, None], order[rows[:, None], sets[best[ok]]]] = True
        decided[idx[passes]] = True
        ambiguous[idx[passes & ~clear]] = True
    return remove, decided & ~ambiguous


def costly_exclusions(before: FitState, after: FitState, settings: WlsSettings) -> np.ndarray:
    """(E,) bool: epochs whose exclusions (slots used in ``before``, not in ``after``) removed only
    moderate residuals (each below ``settings.exclude_above_m`` at ``after``'s solution) and raised the
    position DOP (weighted with the a-priori weights) by more than the factor ``settings.max_dop_growth``.

    Such an exclusion is not worth its cost in a street canyon: multipath spreads errors of tens of
    metres over many satellites, the chi-square test cannot single out the one to drop, and the
    satellite's geometry is worth more down-weighted (Huber) than lost. A gross fault (hundreds of
    metres: a wrong ephemeris, a clock or code error) is still excluded unless its exclusion raises the
    DOP by more than ``settings.gross_dop_growth``: Huber bounds its pull, a lost satellite in a weak
    geometry can cost more.
    """
    removed = before.used & ~after.used
    out = np.zeros(removed.shape[0], bool)
    rows = np.flatnonzero(removed.any(1))
    if rows.size == 0 or not (np.isfinite(settings.exclude_above_m) or np.isfinite(settings.gross_dop_growth)):
        return out
    sp, w = before.sat_pos[rows], before.w_prior[rows]
    _, _, r, _ = normal_equations(sp, before.pr[rows], np.where(after.used[rows], w, 0.0), after.x[rows])
    moderate = np.where(removed[rows], np.abs(r), 0.0).max(1) < settings.exclude_above_m
    dop_before = position_dop(sp, before.x[rows], np.where(before.used[rows], w, 0.0))
    dop_after = position_dop(sp, before.x[rows], np.where(after.used[rows], w, 0.0))
    out[rows] = ((moderate & ~(dop_after <= settings.max_dop_growth * dop_before))
                 | ~(dop_after <= settings.gross_dop_growth * dop_before))
    return out


def identify_faults(fit: FitState, eligible: np.ndarray, settings: WlsSettings, *, scale: float = 1.0,
                    separation: float = SEPARATION) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1-2 of :func:`exclude_faults` (module docstring): the test at the fit and the sets it
    identifies. Returns (E,) bool failing epochs, (E, S) bool slots to remove and (E,) bool decided epochs
    (see :func:`_best_exclusion`). It depends on the fit, ``eligible``, ``scale``, ``separation`` and
    ``settings.max_exclusions`` alone, so passes that share them may share it."""
    w = fit.weights
    _, fails = chi2_test(fit.sat_pos, fit.pr, w, fit.x, fit.used, scale)
    fails &= eligible
    remove, decided = _best_exclusion(fit.sat_pos, fit.pr, w, fit.x, fit.used, fails, settings.max_exclusions,
                                      separation, scale)
    return fails, remove, decided


#: A residual above this [m] is beyond the subset test's one linear step, whose linearisation point such a fault
#: pulls as far off (a millisecond-ambiguous pseudorange is 300 km wrong): :func:`exclude_gross` first.
GROSS_RESIDUAL_M = 1000.0


def exclude_gross(fit: FitState, eligible: np.ndarray, settings: WlsSettings) -> tuple[FitState, np.ndarray]:
    """The epochs in ``eligible`` (E,) whose fit leaves a residual above :data:`GROSS_RESIDUAL_M`: the slot of
    the largest standardised residual removed and the epoch re-solved, up to ``settings.max_exclusions`` times
    while more than 5 slots stay. Kept where the re-solve converges with every residual below the bound (the
    usual test then judges the rest), undone elsewhere. Returns the fit and (E,) the slots it removed (counted
    as outliers)."""
    after, removed = fit, np.zeros(fit.used.shape, bool)
    for _ in range(settings.max_exclusions):
        r, largest = _largest_residual(after)
        gross = eligible & (largest > GROSS_RESIDUAL_M) & (after.used.sum(1) > 5)
        if not gross.any():
            break
        worst = np.argmax(np.where(after.used, np.abs(r) * np.sqrt(after.w_prior), -1.0), axis=1)
        rows = np.flatnonzero(gross)
        removed[rows, worst[rows]] = True
        after = after.replace(used=fit.used & ~removed)
        after = after.solve(gross, after.weights, settings.max_iter, settings.tol_m, settings.max_cond)
    tried = removed.any(1)
    if not tried.any():
        return fit, removed
    settled = after.conv & ~after.bad & ~after.runaway & (_largest_residual(after)[1] <= GROSS_RESIDUAL_M)
    undo = tried & ~settled
    after, removed[undo] = _undo(fit, after, undo), False
    count_skip(fit.dropped, "outlier", removed)
    return after.replace(w_fit=after.weights), removed


def _largest_residual(fit: FitState) -> tuple[np.ndarray, np.ndarray]:
    """(E,S) the fit's residuals [m] and (E,) the largest of each epoch's used ones in magnitude."""
    _, _, r, _ = normal_equations(fit.sat_pos, fit.pr, fit.weights, fit.x)
    return r, np.where(fit.used, np.abs(r), 0.0).max(1)


def exclude_faults(fit: FitState, eligible: np.ndarray, settings: WlsSettings, *, scale: float = 1.0,
                   separation: float = SEPARATION,
                   identified: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> FitState:
    """Fault detection and exclusion (module docstring) on the epochs in ``eligible`` (E,) bool.

    fit: the converged fit (its ``used`` slots are the candidates); settings: ``max_exclusions`` and the
    Gauss-Newton limits of the re-solve. ``scale``: variance factor of ``fit.w_prior`` for the test
    (:func:`variance_factor`). ``identified``: :func:`identify_faults` of the same fit, eligible epochs,
    scale, separation and ``max_exclusions``, when a caller has it already (not modified here).
    Returns the fit with the exclusions removed from ``used`` and re-solved,
    ``w_fit`` the a-priori weights of the used slots, ``flagged`` the undecided epochs and
    ``n_excluded`` this pass's exclusions; excluded slots are counted in ``fit.dropped["outlier"]``.
    """
    if identified is None:
        identified = identify_faults(fit, eligible, settings, scale=scale, separation=separation)
    fails, remove, decided = identified[0], identified[1].copy(), identified[2].copy()
    after = fit.replace(used=fit.used & ~remove)
    redo = remove.any(1)
    if redo.any():
        after = after.solve(redo, after.weights, settings.max_iter, settings.tol_m, settings.max_cond)
        # an exclusion of a moderate residual that leaves much weaker geometry is undone: the epoch
        # stays undecided (flagged), and Huber IRLS down-weights the satellite instead of losing it
        held = costly_exclusions(fit, after, settings)
        if held.any():
            after = _undo(fit, after, held)
            remove[held] = False
            decided &= ~held
    count_skip(fit.dropped, "outlier", remove)
    return after.replace(w_fit=after.weights, flagged=fails & ~decided, n_excluded=remove.sum(1))


def _undo(before: FitState, after: FitState, rows: np.ndarray) -> FitState:
    """``after`` with the epochs in ``rows`` (E,) bool back at ``before``'s fit."""
    r = rows[:, None]
    return after.replace(used=np.where(r, before.used, after.used), x=np.where(r, before.x, after.x),
                         conv=np.where(rows, before.conv, after.conv), bad=np.where(rows, before.bad, after.bad),
                         runaway=np.where(rows, before.runaway, after.runaway))


def m_weights(z: np.ndarray, k: float, kind: str) -> np.ndarray:
    """IRLS weight factors in (0, 1] of standardised residuals ``z`` (any shape): Huber ``min(1, k/|z|)``
    or Cauchy ``1 / (1 + (z/k)^2)`` (redescending: a gross residual loses almost all its weight, a
    moderate one keeps most of it)."""
    z = np.abs(z)
    if kind == "cauchy":
        return 1.0 / (1.0 + (z / k) ** 2)
    return np.minimum(1.0, k / np.maximum(z, 1e-12))


def huber_irls(fit: FitState, eligible: np.ndarray, settings: WlsSettings, rounds: int = 8,
               scale: float = 1.0, sigma_factor: np.ndarray | None = None) -> FitState:
    """Iteratively reweighted LS with M-estimator weights (``settings.m_estimator``: Huber or Cauchy, threshold
    ``settings.huber_k``) on standardised residuals, on the ``eligible`` (E,) epochs, starting from the
    a-priori weights of the used slots. ``scale``: variance factor of the a-priori weights the residuals
    are standardised with (used when ``settings.irls_scale == "trace"``). ``sigma_factor``: (E, S) factor
    >= 1 on the a-priori sigmas of the eligible epochs (:func:`fusion.estimate.wls.reported_sigma_factor`).

    Returns the re-solved fit with ``w_fit`` the final (down-weighted) weights.
    """
    used, w_prior = fit.used, fit.w_prior
    if sigma_factor is not None:
        w_prior = np.where(eligible[:, None], w_prior / sigma_factor ** 2, w_prior)
    # in a street canyon every residual is larger than the a-priori model says; standardised with the
    # trace's own noise level the estimator down-weights what stands out of it, not every measurement
    k = settings.huber_k * (np.sqrt(scale) if settings.irls_scale == "trace" else 1.0)
    x, conv, bad, runaway = fit.x.copy(), fit.conv, fit.bad, fit.runaway
    # the weights ``x`` was solved with: a reported-sigma factor alone already changes them (re-solved)
    w = np.where(used, fit.w_prior, 0.0)
    for _ in range(rounds):
        # Standardise with the a-priori weights: with the current (reduced) ones a down-weighted
        # residual would look small next round and the weights would oscillate.
        # Only the eligible epochs' weights change and each epoch's residuals are its own: compute
        # them for those alone (a trace's few undecided epochs, not all of it, every round).
        e = np.flatnonzero(eligible)
        z = standardised_residuals(fit.sat_pos[e], fit.pr[e], np.where(used[e], w_prior[e], 0.0), x[e], used[e])
        w_new = w.copy()
        w_new[e] = np.where(used[e], w_prior[e] * m_weights(z, k, settings.m_estimator), 0.0)
        changed = eligible & (np.abs(w_new - w).max(1) > 1e-3 * w_prior.max(1, initial=0))
        w = w_new
        if not changed.any():
            break
        x, c2, b2, r2 = gauss_newton(fit.sat_pos, fit.pr, w, x, changed, settings.max_iter, settings.tol_m,
                                     settings.max_cond, fit.n_iter)
        conv = np.where(changed, c2, conv)
        bad = bad | (changed & b2)
        runaway = runaway | (changed & r2)
        eligible = eligible & ~(changed & (~c2 | b2 | r2))
    return fit.replace(x=x, conv=conv, bad=bad, runaway=runaway, w_fit=w)
