"""Snapshot positions with a receiver clock per signal: the receiver guess of a raw log none of whose signals
solves an epoch alone.

A raw log's signals each carry a bias of their own (metres to hundreds on phones) until the loader measures
it against a reference signal's clock, which needs epochs the reference solves alone
(:mod:`fusion.prepare.raw_trace`). Where no signal has four satellites in any epoch (a street canyon with a
GPS-only navigation file and a phone logging L1 and L5), the textbook answer is to give each signal present
in an epoch its own clock, as RTKLIB's single point solution gives each constellation one: 3 + G unknowns
for G signals. Gauss-Newton from the Earth's centre, all epochs at once, no robust stage (with so few
satellites there is nothing to spare); an epoch is kept when it has a satellite to spare beyond its unknowns
and its fit is plausible.
"""
from __future__ import annotations

import numpy as np

from fusion.geometry import ecef2geodetic, line_of_sight

#: Gauss-Newton iterations from the Earth's centre (pseudorange positioning converges in fewer)
ITERATIONS = 10
#: an epoch's fit is kept when its residuals' RMS is below this [m] and its height is plausible
MAX_RMS_M = 100.0
HEIGHT_RANGE_M = (-2000.0, 100_000.0)


def multi_clock_positions(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, group: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Positions (E,3) ECEF [m] (NaN where not solved) and each signal's clock (E,G) [m] (NaN where the epoch
    has none of it or is not solved).

    sat_pos (E,S,3), pr (E,S) [m], mask (E,S) bool, group (E,S) int in [0, G): each slot's signal."""
    E = mask.shape[0]
    G = int(group[mask].max()) + 1 if mask.any() else 1
    onehot = (group[..., None] == np.arange(G)) & mask[..., None]              # (E,S,G)
    present = onehot.any(axis=1)                                                # (E,G)
    unknowns = 3 + present.sum(axis=1)
    solvable = mask.sum(axis=1) > unknowns
    x = np.zeros((E, 3 + G))
    for _ in range(ITERATIONS):
        rng, los = line_of_sight(sat_pos, x[:, :3])
        H = np.concatenate([-los, onehot.astype(float)], axis=2) * mask[..., None]
        r = np.where(mask, pr - rng - np.einsum("esg,eg->es", onehot, x[:, 3:]), 0.0)
        N = np.einsum("esi,esj->eij", H, H)
        N[:, 3:, 3:] += np.einsum("eg,gh->egh", (~present).astype(float), np.eye(G))   # absent signals: no clock
        ok = solvable & (np.linalg.cond(N) < 1e10)
        if not ok.any():
            break
        x[ok] += np.linalg.solve(N[ok], np.einsum("esi,es->ei", H, r)[ok][..., None])[..., 0]
    rng, _ = line_of_sight(sat_pos, x[:, :3])
    r = np.where(mask, pr - rng - np.einsum("esg,eg->es", onehot, x[:, 3:]), 0.0)
    rms = np.sqrt((r ** 2).sum(axis=1) / np.maximum(mask.sum(axis=1), 1))
    h = ecef2geodetic(x[:, :3])[:, 2]
    good = ok & (rms < MAX_RMS_M) & (h > HEIGHT_RANGE_M[0]) & (h < HEIGHT_RANGE_M[1])
    pos = np.where(good[:, None], x[:, :3], np.nan)
    return pos, np.where(good[:, None] & present, x[:, 3:], np.nan)
