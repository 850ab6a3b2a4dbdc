"""The adaptation's second self-check, in the graph's own terms: satellites held out of the graph.

The first check (:mod:`learned.selfcheck`) scores one epoch at a time: how well each satellite is
predicted by the others' weighted snapshot solution. The graph weighs the same pseudoranges against
Doppler, carrier phase and the motion model over many epochs, and sigmas that make snapshots more
consistent can place the graph worse (the Pixel5 RINEX test trace: the snapshot criterion 1.6 % better,
the graph's score 2-5 % worse, ``experiments/results/adapt.md``).

Here the ``fused`` graph is solved ``folds`` times, each time without one fold of the satellites (every
signal of them: their pseudoranges, Doppler and carrier), and the held-out satellites' pseudoranges are
predicted at the graph's positions, each epoch's clock per signal taken as the median residual of the
satellites the graph kept. The held-out satellites' own errors (multipath, NLOS) are the same whichever
weights solved the graph; what differs is where each graph puts the phone. The score is the mean of
min(|residual|, ``CAP``) over the held-out pseudoranges, pooled over the logs. Nothing here reads truth.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.geometry import line_of_sight
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from fusion.trace import Trace

#: Satellite folds, and the cap [m] on a held-out residual (a NLOS satellite's tens of metres would
#: otherwise decide the comparison alone).
FOLDS, CAP = 4, 10.0


def satellite_folds(trace: Trace, folds: int = FOLDS, seed: int = 0) -> np.ndarray:
    """(E,S) int: the fold of each slot's satellite (all its signals in one fold), -1 on padding.
    Satellites are dealt to folds in a seeded random order, so each fold holds every constellation."""
    ids = np.unique(trace.sat_id[trace.mask])
    order = np.random.default_rng(seed).permutation(len(ids)) % folds
    pos = np.searchsorted(ids, trace.sat_id)
    known = trace.mask & (pos < len(ids)) & (ids[np.minimum(pos, len(ids) - 1)] == trace.sat_id)
    return np.where(known, order[np.minimum(pos, len(ids) - 1)], -1)


def heldout_residuals(trace: Trace, pos: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(N,) |pseudorange residual| [m] of the ``held`` (E,S) slots at ``pos`` (E,3) ECEF (NaN rows:
    unsolved), each epoch's clock per signal the median residual of that signal's slots not held out
    (an epoch or signal without such a slot scores nothing)."""
    ok = np.isfinite(pos).all(axis=1)
    rng, _ = line_of_sight(trace.sat_pos, np.where(ok[:, None], pos, 0.0))
    resid = trace.pr - rng
    kept = trace.mask & ~held & ok[:, None]
    clock = np.full(resid.shape, np.nan)
    for sig in np.unique(trace.signal[trace.mask]):
        of_sig = trace.signal == sig
        use = kept & of_sig
        has = use.any(axis=1)
        med = np.full(trace.n_epochs, np.nan)
        if has.any():
            med[has] = np.nanmedian(np.where(use[has], resid[has], np.nan), axis=1)
        clock = np.where(of_sig, med[:, None], clock)
    score = held & trace.mask & ok[:, None] & np.isfinite(clock)
    return np.abs(resid - clock)[score]


def graph_error(traces: list[Trace], opts: RunOptions, folds: int = FOLDS, seed: int = 0) -> dict:
    """The held-out score of ``fused`` with ``opts.weights`` over ``traces``: ``error_m`` (mean capped
    |residual|, NaN when nothing could be scored) and ``measurements`` (how many)."""
    opts = replace(opts, sigma_calibration=False)      # positions only: the covariance is not used
    parts = []
    for trace in traces:
        fold = satellite_folds(trace, folds, seed)
        for k in range(folds):
            held = fold == k
            if not held.any():
                continue
            res = run_modes(trace.select_slots(~held), ["fused"], opts)["fused"]
            parts.append(heldout_residuals(trace, np.where(res.valid[:, None], res.pos, np.nan), held))
    e = np.concatenate(parts) if parts else np.zeros(0)
    return {"error_m": float(np.minimum(e, CAP).mean()) if e.size else float("nan"), "measurements": int(e.size)}


def graph_decision(base: dict, adapted: dict, margin: float) -> tuple[bool, str]:
    """Keep the adaptation? True when the adapted weights' held-out graph error is at least ``margin``
    (relative) below the base's; and the reason, in words."""
    b, a = base["error_m"], adapted["error_m"]
    what = (f"graph check: held-out satellites' pseudorange error at the fused graph {b:.3f} m (base) -> "
            f"{a:.3f} m (adapted), {adapted['measurements']} pseudoranges")
    if not (np.isfinite(b) and np.isfinite(a)):
        return False, f"{what}: nothing to compare"
    gain = 1.0 - a / b if b > 0 else 0.0
    if not gain > margin:
        return False, f"{what}: gain {gain:.2%} not above {margin:.2%}"
    return True, f"{what}: gain {gain:.2%}"
