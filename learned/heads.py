"""What the per-satellite head's numbers mean in metres, and the least-squares step its weights feed:
numpy twins of :func:`learned.model.base_sigma`, :func:`learned.model.sat_sigma_bias` and
:func:`learned.losses.weighted_ls_step` for inference without torch (tested equal to them)."""
from __future__ import annotations

import numpy as np

from fusion.geometry import line_of_sight

#: Outputs a checkpoint can serve: the learned-weight least squares, or the paper's correction.
OUTPUTS = ("wls", "correction")
#: The per-satellite log-multiplier is clamped to this range (sigma between 1/50 and 50 x the model's).
LOGSIG_RANGE = (-4.0, 4.0)
#: Zenith term of the physical sigma model [m] (the graph's default: GraphConfig.pr_sigma_zenith_m).
ZENITH_SIGMA_M = 1.0
#: Diagonal load on the normal matrix, relative to its mean diagonal: keeps a near-singular epoch solvable.
RIDGE = 1e-9


def base_sigma(pr_sigma: np.ndarray, sin_el: np.ndarray) -> np.ndarray:
    """The physical pseudorange sigma model [m], ``sqrt(pr_sigma^2 + (ZENITH_SIGMA_M / sin el)^2)``, (B,S)."""
    return np.sqrt(np.asarray(pr_sigma, float) ** 2 + (ZENITH_SIGMA_M / np.clip(sin_el, 0.1, 1.0)) ** 2)


def sat_sigma_bias(sat: np.ndarray, res_scale: float, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-slot sigma and bias [m] from the head's (B,S,2) output and the physical model ``base`` (B,S)."""
    sat = np.asarray(sat, float)
    return base * np.exp(np.clip(sat[..., 0], *LOGSIG_RANGE)), sat[..., 1] * res_scale


def weighted_ls_step(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, guess: np.ndarray,
                     sigma: np.ndarray, bias: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton step of weighted least squares from ``guess`` (B,3): sat_pos (B,S,3), pr, sigma,
    bias (B,S) [m], mask (B,S) bool. Returns position (B,3) ECEF and its covariance (B,3,3) [m^2]."""
    m = np.asarray(mask, bool)
    sat_pos = np.where(m[..., None], sat_pos, 0.0)
    sigma = np.where(m, sigma, 1.0)
    rng, los = line_of_sight(sat_pos, guess)
    H = np.concatenate([-los, np.ones(rng.shape + (1,))], -1)
    r = np.where(m, pr - rng - (0.0 if bias is None else np.where(m, bias, 0.0)), 0.0)
    r = np.where(m, r - r.sum(1, keepdims=True) / np.maximum(m.sum(1, keepdims=True), 1), 0.0)
    w = m / sigma ** 2
    Hw = H * w[..., None]
    N = Hw.transpose(0, 2, 1) @ H
    N = N + RIDGE * np.trace(N, axis1=1, axis2=2)[:, None, None] / 4 * np.eye(4)
    step = np.linalg.solve(N, Hw.transpose(0, 2, 1) @ r[..., None])[..., 0]
    return guess + step[:, :3], np.linalg.inv(N)[:, :3, :3]


#: Pseudorange sigma [m] when a measurement has neither a reported sigma nor a C/N0 (the raw reader's
#: model at 10 dB-Hz below its reference C/N0).
DEFAULT_SIGMA_M = 3.0 * 10 ** 0.5


def cn0_sigma(cn0: np.ndarray) -> np.ndarray:
    """Pseudorange sigma [m] from C/N0 [dB-Hz], the raw reader's model (fusion/prepare/raw_trace.py):
    ``3 m * 10^((35 - C/N0) / 20)`` within [3, 100] m."""
    from fusion.prepare.raw_trace import pr_sigma_model
    return pr_sigma_model(np.asarray(cn0, float))


def report_sigma(pr_sigma: np.ndarray, reported: np.ndarray, cn0: np.ndarray) -> np.ndarray:
    """(N,S) the pseudorange sigma [m] the physical model starts from: the receiver's report where it
    gave one, else the C/N0 model where the file has C/N0, else :data:`DEFAULT_SIGMA_M`."""
    cn0 = np.asarray(cn0, float)
    model = np.where(cn0 > 0, cn0_sigma(np.where(cn0 > 0, cn0, 35.0)), DEFAULT_SIGMA_M)
    return np.where(np.asarray(reported, bool), pr_sigma, model)
