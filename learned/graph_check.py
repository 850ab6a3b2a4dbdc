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
min(|residual|, ``CAP``) over the held-out pseudoranges, pooled over the logs, on the same measurements for
both graphs. Those own errors make the score noisy: a gain counts only above ``Z`` standard errors of the
paired difference, clustered by blocks of ``BLOCK`` epochs. Nothing here reads truth.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fusion.errors import GnssfuseError
from fusion.geometry import line_of_sight
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from fusion.trace import Trace

#: Satellite folds, and the cap [m] on a held-out residual (a NLOS satellite's tens of metres would
#: otherwise decide the comparison alone).
FOLDS, CAP = 4, 10.0
#: Residuals within a block of this many epochs share their satellites' multipath: the unit of the standard
#: error; and how many standard errors a gain must clear (one-sided, about 98 %), fixed before any log was run.
BLOCK, Z = 60, 2.0


def satellite_folds(trace: Trace, folds: int = FOLDS, seed: int = 0) -> np.ndarray:
    """(E,S) int: the fold of each slot's satellite (all its signals in one fold), -1 on padding.
    Satellites are dealt to folds in a seeded random order (not by number, which would put neighbouring
    orbit slots together)."""
    ids = np.unique(trace.sat_id[trace.mask])
    order = np.random.default_rng(seed).permutation(len(ids)) % folds
    pos = np.searchsorted(ids, trace.sat_id)
    known = trace.mask & (pos < len(ids)) & (ids[np.minimum(pos, len(ids) - 1)] == trace.sat_id)
    return np.where(known, order[np.minimum(pos, len(ids) - 1)], -1)


def heldout_grid(trace: Trace, pos: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(E,S) |pseudorange residual| [m] of the ``held`` (E,S) slots at ``pos`` (E,3) ECEF (NaN rows:
    unsolved), each epoch's clock per signal the median residual of that signal's slots not held out; NaN
    where nothing is scored (not held out, unsolved, or no kept slot of that signal at that epoch)."""
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
    return np.where(score, np.abs(resid - clock), np.nan)


def heldout_residuals(trace: Trace, pos: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(N,) the scored entries of :func:`heldout_grid`, epoch by epoch."""
    grid = heldout_grid(trace, pos, held)
    return grid[np.isfinite(grid)]


@dataclass
class GraphScores:
    """Held-out residuals of several graphs on the same measurements: ``capped`` (K,N) min(|residual|,
    CAP) [m] per graph, ``blocks`` (N,) the block of ``BLOCK`` epochs (of one trace) each came from,
    ``folds_unsolved`` how many folds no comparison could use."""

    capped: np.ndarray
    blocks: np.ndarray
    folds_unsolved: int

    def summary(self, k: int) -> dict:
        """Graph ``k``'s ``error_m`` (mean capped residual, NaN when nothing was scored) and ``measurements``."""
        n = self.capped.shape[1]
        return {"error_m": float(self.capped[k].mean()) if n else float("nan"), "measurements": int(n),
                "folds_unsolved": self.folds_unsolved}

    def gain(self, base: int, other: int) -> tuple[float, float]:
        """Relative gain of graph ``other`` over ``base`` (1 - mean_other / mean_base) and its standard error,
        clustered by block (residuals of neighbouring epochs share multipath and are not independent)."""
        d = self.capped[other] - self.capped[base]
        n, mb = d.size, self.capped[base].mean() if d.size else float("nan")
        if not n or not mb > 0:
            return float("nan"), float("nan")
        _, inv = np.unique(self.blocks, return_inverse=True)
        sums = np.bincount(inv, weights=d - d.mean())
        return float(-d.mean() / mb), float(np.sqrt((sums ** 2).sum()) / n / mb)


def graph_errors(traces: list[Trace], options: list[RunOptions], folds: int = FOLDS, seed: int = 0) -> GraphScores:
    """The held-out residuals of ``fused`` under each of ``options`` (e.g. base and adapted weights), paired:
    the same traces, folds and measurements for every one (a measurement only where every graph scores it,
    a fold left out for all when any graph cannot be solved without it)."""
    options = [replace(o, sigma_calibration=False) for o in options]     # positions only
    parts, blocks, unsolved = [[] for _ in options], [], 0
    for t, trace in enumerate(traces):
        fold = satellite_folds(trace, folds, seed)
        for k in range(folds):
            held = fold == k
            if not held.any():
                continue
            try:
                grids = [heldout_grid(trace, _positions(trace.select_slots(~held), o), held) for o in options]
            except GnssfuseError:           # too few satellites left for any graph: no comparison there
                unsolved += 1
                continue
            common = np.logical_and.reduce([np.isfinite(g) for g in grids])
            for part, g in zip(parts, grids):
                part.append(np.minimum(g[common], CAP))
            blocks.append(t * 1_000_000 + np.nonzero(common)[0] // BLOCK)
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)   # noqa: E731
    return GraphScores(np.array([cat(p) for p in parts]).reshape(len(options), -1), cat(blocks).astype(np.int64),
                       unsolved)


def _positions(trace: Trace, opts: RunOptions) -> np.ndarray:
    """(E,3) ECEF positions of ``fused`` on ``trace``, NaN where unsolved."""
    res = run_modes(trace, ["fused"], opts)["fused"]
    return np.where(res.valid[:, None], res.pos, np.nan)


def graph_decision(scores: GraphScores, margin: float, z: float = Z) -> tuple[bool, str]:
    """Keep the adaptation (graph 1 of ``scores``) over the base (graph 0)? True when its relative gain in
    held-out error is above ``margin`` and above ``z`` of its standard errors (a gain the held-out
    satellites' own noise could give is none); and the reason, in words."""
    b, a = scores.summary(0), scores.summary(1)
    what = (f"graph check: held-out satellites' pseudorange error at the fused graph {b['error_m']:.3f} m (base) "
            f"-> {a['error_m']:.3f} m (adapted), {a['measurements']} pseudoranges")
    gain, se = scores.gain(0, 1)
    if not (np.isfinite(gain) and np.isfinite(se)):
        return False, f"{what}: nothing to compare"
    words = f"gain {gain:.2%} (standard error {se:.2%})"
    if not (gain > margin and gain > z * se):
        return False, f"{what}: {words} not above {margin:.2%} and {z:g} standard errors"
    return True, f"{what}: {words}"
