"""Bridged epochs with Doppler: their sigmas checked against the graph without Doppler, carrier or anything
learned.

Where fewer than 4 satellites' pseudoranges place an epoch, Doppler carries the track through (a carrier
factor needs 5 satellites, so none is there): a graph with it is usually far better there than one without
(``experiments/results/doppler_carrier.md``), but nothing checks it. Two or three satellites leave a horizontal
direction, and the velocity's trade with the clock drift, to the motion model and the clock's walk; where those
models are wrong for the phone the track runs off by hundreds of metres with a sigma of tens
(``experiments/results/canyon_on_phone.md``, deep layout 1), and no residual shows it. The graph without Doppler
and carrier (``fused-nodnn`` on pseudoranges alone, for ``fused`` too) is a second opinion that does not share
that weakness. Where the two disagree on an axis by more than ``GraphConfig.bridged_check_sigmas`` times their
combined calibrated sigma there, neither sigma covers the truth for sure, so the graph's variance on that axis
takes the squared disagreement on top (``experiments/results/bridged_check.md``).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.geometry import ecef2ned_cov, ecef2ned_vec, ned2ecef_cov
from fusion.run_types import ModeResult, RunOptions


def bridged_with_doppler(result: ModeResult) -> np.ndarray:
    """(E,) bool solved epochs the graph bridged where Doppler measured the motion."""
    bridged, without = (result.info.get(k) for k in ("bridged", "bridged_without_doppler"))
    if not isinstance(bridged, np.ndarray) or not isinstance(without, np.ndarray):
        return np.zeros(len(result.valid), bool)
    return bridged & ~without & result.valid


def disagreement(result: ModeResult, reference: ModeResult, rows: np.ndarray, n_sigma: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where both results have a covariance among ``rows`` (E,) bool: those rows (E,) bool, the NED difference
    ``result - reference`` (n,3) [m] there, and (n,3) bool where it exceeds ``n_sigma`` times the two results'
    combined sigma on the axis."""
    rows = rows & result.valid & reference.valid & np.isfinite(reference.cov).all(axis=(1, 2)) \
        & np.isfinite(result.cov).all(axis=(1, 2))
    pos = result.pos[rows]
    d = ecef2ned_vec(pos - reference.pos[rows], pos)
    both = (np.diagonal(ecef2ned_cov(result.cov[rows], pos), axis1=1, axis2=2)
            + np.diagonal(ecef2ned_cov(reference.cov[rows], pos), axis1=1, axis2=2))
    return rows, d, np.abs(d) > n_sigma * np.sqrt(both)


def widen_by_disagreement(result: ModeResult, reference: ModeResult, rows: np.ndarray, n_sigma: float
                          ) -> int:
    """Add, in place, the squared NED disagreement with ``reference`` to ``result``'s variance on each axis of
    ``rows`` (E,) bool where it exceeds ``n_sigma`` times the two results' combined sigma (:func:`disagreement`).
    Returns the count of epochs widened."""
    if reference.cov is None:
        return 0
    rows, d, beyond = disagreement(result, reference, rows, n_sigma)
    if not rows.any():
        return 0
    pos = result.pos[rows]
    add = np.where(beyond, d ** 2, 0.0)
    result.cov = result.cov.copy()
    result.cov[rows] = ned2ecef_cov(ecef2ned_cov(result.cov[rows], pos) + add[:, :, None] * np.eye(3), pos)
    return int((add > 0).any(axis=1).sum())


def check_bridged(result: ModeResult, trace, wls, opts: RunOptions) -> ModeResult:
    """``result`` (a calibrated graph mode's) with its bridged epochs with Doppler checked against the calibrated
    ``fused-nodnn`` graph without Doppler and carrier (module docstring); ``info["bridged_widened"]`` counts the
    epochs widened. Nothing is solved where the check is off (``GraphConfig.bridged_check_sigmas`` 0, or no
    sigma calibration), there is no covariance, or no such epoch."""
    from fusion.estimate.graph.fuse import estimate_fused_nodnn

    n_sigma = opts.graph.bridged_check_sigmas
    rows = bridged_with_doppler(result)
    if n_sigma <= 0 or not opts.sigma_calibration or result.cov is None or not rows.any():
        return result
    plain = replace(opts, graph=replace(opts.graph, use_doppler=False, use_carrier=False))
    result.info["bridged_widened"] = widen_by_disagreement(result, estimate_fused_nodnn(trace, wls, plain), rows,
                                                           n_sigma)
    return result
