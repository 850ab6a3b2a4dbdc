"""Leave-one-satellite-out consistency: a truth-free loss on the per-satellite head.

Each satellite's pseudorange is predicted from the *other* satellites of its epoch: the position and
clock solved (one weighted Gauss-Newton step from an anchor, the teacher) without it, with the head's
sigmas as weights. The satellite's residual at that solution has variance ``sigma_i^2 + h_i' P_-i h_i``
(its own noise plus the leave-one-out solution's, ``P_-i`` that solution's covariance); the loss is its
Gaussian NLL. A satellite the others disagree with must get a large sigma (or a bias), one they agree
with a small one: what ground truth would teach, up to the geometry, from the measurements alone.
"""
from __future__ import annotations

import torch

from learned.features import line_of_sight_torch

#: Diagonal load on the leave-one-out normal matrices (scale-free units of 1/m^2).
_RIDGE = 1e-6


def loo_nll(sat_pos: torch.Tensor, pr: torch.Tensor, mask: torch.Tensor, anchor: torch.Tensor,
            sigma: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Mean leave-one-out NLL over slots of epochs with >= 5 satellites (others: no term).

    sat_pos (B,S,3), pr (B,S), anchor (B,3) float64; mask (B,S) bool; sigma, bias (B,S) [m].
    """
    e, var, use = loo_residuals(sat_pos, pr, mask, anchor, sigma, bias)
    per_slot = 0.5 * torch.log(var) + 0.5 * e ** 2 / var
    return (per_slot * use).sum() / use.sum().clamp_min(1)


def loo_residuals(sat_pos: torch.Tensor, pr: torch.Tensor, mask: torch.Tensor, anchor: torch.Tensor,
                  sigma: torch.Tensor, bias: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each slot's residual at the solution of the others ``e`` (B,S) [m], its predicted variance ``var``
    (B,S) [m^2] and ``use`` (B,S) bool: real slots of epochs with >= 5 satellites. Inputs as :func:`loo_nll`."""
    real = mask.bool()
    sat_pos = sat_pos.masked_fill(~real[..., None], 0.0)
    sigma = sigma.double().masked_fill(~real, 1.0)
    bias = bias.double().masked_fill(~real, 0.0)
    rng, los = line_of_sight_torch(sat_pos, anchor)
    H = torch.cat([-los, torch.ones_like(rng)[..., None]], dim=-1)              # (B,S,4)
    dz = (pr - bias - rng).masked_fill(~real, 0.0)
    dz = dz - (dz * real).sum(1, keepdim=True) / real.sum(1, keepdim=True).clamp_min(1)   # clock near zero
    w = real / sigma ** 2
    outer = H[..., :, None] * H[..., None, :]                                    # (B,S,4,4)
    N = (w[..., None, None] * outer).sum(1)                                      # (B,4,4)
    b = (w[..., None] * H * dz[..., None]).sum(1)                                # (B,4)
    N_loo = N[:, None] - w[..., None, None] * outer + _RIDGE * torch.eye(4, dtype=N.dtype)
    b_loo = b[:, None] - w[..., None] * H * dz[..., None]
    P = torch.linalg.inv(N_loo)                                                  # (B,S,4,4)
    delta = (P @ b_loo[..., None])[..., 0]
    e = dz - (H * delta).sum(-1)
    var = sigma ** 2 + (H[..., None, :] @ P @ H[..., :, None])[..., 0, 0]
    use = real & (real.sum(1, keepdim=True) >= 5)
    return e, var, use
