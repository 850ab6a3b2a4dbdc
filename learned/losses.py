"""Training losses, and the weighted least-squares layer the per-satellite head feeds.

Three signals train the network (:class:`learned.train.LossWeights` mixes them):

- ``global``: the paper's loss, MSE of the NED correction (plus a Gaussian NLL on the detached mean for
  the variance head after warm-up);
- ``sat``: each pseudorange's error under the per-satellite head's sigma (and bias), a Gaussian NLL at the
  true position with the receiver clock profiled out (the clock is what the weighted residuals say it is);
- ``wls``: the position the per-satellite weights give, one weighted Gauss-Newton step from the guess
  (:func:`weighted_ls_step`), against the truth: trains the weights for what they are used for.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from learned.features import line_of_sight_torch

#: Diagonal load on the normal matrix [1/m^2 scale-free]: keeps a near-singular batch item solvable.
_RIDGE = 1e-9


def gaussian_nll(mean: torch.Tensor, logvar: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean Gaussian negative log-likelihood (constants dropped); all (B,3)."""
    return 0.5 * (logvar + (y - mean) ** 2 * torch.exp(-logvar)).mean()


def _finite_padding(mask: torch.Tensor, sat_pos: torch.Tensor, pr: torch.Tensor, sigma: torch.Tensor,
                    bias: torch.Tensor | None) -> tuple:
    """Padded slots (mask (B,S) False) of sat_pos (B,S,3), pr, sigma, bias (B,S) set to finite filler:
    the masked sums below multiply by the mask, and NaN times 0 is NaN."""
    real = mask.bool()
    return (sat_pos.masked_fill(~real[..., None], 0.0), pr.masked_fill(~real, 0.0),
            sigma.masked_fill(~real, 1.0), None if bias is None else bias.masked_fill(~real, 0.0))


def _weighted_clock(resid: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(B,) weighted mean of (B,S) residuals with weights (B,S) (0 on padding)."""
    return (w * resid).sum(1) / w.sum(1).clamp_min(1e-12)


def sat_nll(sat_pos: torch.Tensor, pr: torch.Tensor, mask: torch.Tensor, truth: torch.Tensor,
            sigma: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Per-satellite Gaussian NLL of the pseudorange errors at the truth, clock profiled out.

    sat_pos (B,S,3), pr (B,S), truth (B,3) float64; mask (B,S) bool; sigma, bias (B,S) [m]. The error of
    slot s is ``pr - range(truth) - bias - clock`` with ``clock`` the sigma-weighted mean over the epoch:
    the receiver clock is unknown, and the weighted mean is its maximum-likelihood value.
    """
    sat_pos, pr, sigma, bias = _finite_padding(mask, sat_pos, pr, sigma, bias)
    rng, _ = line_of_sight_torch(sat_pos, truth)
    sigma, bias = sigma.double(), bias.double()
    w = mask / sigma ** 2
    r = pr - rng - bias
    e = (r - _weighted_clock(r, w)[:, None]) / sigma
    per_slot = torch.log(sigma) + 0.5 * e ** 2
    return (per_slot * mask).sum() / mask.sum().clamp_min(1)


def weighted_ls_step(sat_pos: torch.Tensor, pr: torch.Tensor, mask: torch.Tensor, guess: torch.Tensor,
                     sigma: torch.Tensor, bias: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """One Gauss-Newton step of weighted least squares from ``guess``, differentiable in the weights.

    sat_pos (B,S,3), pr (B,S), guess (B,3) float64; mask (B,S) bool; sigma (B,S) [m]; bias (B,S) [m] or None.
    The pseudorange model is the WLS one (Sagnac included); it is so nearly linear over tens of metres that
    one step from a guess within ~100 m lands within millimetres of the converged solution.
    Returns position (B,3) ECEF and its covariance (B,3,3) [m^2] (``(H^T W H)^-1``, position block).
    """
    sat_pos, pr, sigma, bias = _finite_padding(mask, sat_pos, pr, sigma, bias)
    rng, los = line_of_sight_torch(sat_pos, guess)
    H = torch.cat([-los, torch.ones_like(rng)[..., None]], -1)               # (B,S,4)
    r = pr - rng - (0.0 if bias is None else bias.double())
    r = r - (r * mask).sum(1, keepdim=True) / mask.sum(1, keepdim=True).clamp_min(1)   # clock: centred
    w = mask / sigma.double() ** 2
    Hw = H * w[..., None]
    N = Hw.transpose(1, 2) @ H
    N = N + _RIDGE * N.diagonal(dim1=1, dim2=2).mean(-1)[:, None, None] * torch.eye(4, dtype=N.dtype, device=N.device)
    step = torch.linalg.solve(N, (Hw.transpose(1, 2) @ r[..., None]))[..., 0]
    cov = torch.linalg.inv(N)[:, :3, :3]
    return guess + step[:, :3], cov


def position_loss(pos: torch.Tensor, truth: torch.Tensor, R: torch.Tensor, scale: float) -> torch.Tensor:
    """Huber loss of (pos - truth) in the NED frame R (B,3,3) over ``scale`` [m]: a few guesses far off
    must not dominate the batch."""
    err = torch.einsum("bij,bj->bi", R, pos - truth) / scale
    return F.huber_loss(err.float(), torch.zeros_like(err, dtype=torch.float32), delta=1.0)
