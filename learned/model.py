"""Networks mapping a padded set of per-satellite features (B,S,F) + mask (B,S) to a 3-vector.

All models return ``(mean (B,3), log_var (B,3), sat (B,S,2))``: the correction (in units of the feature
config's ``out_scale``), the per-axis log-variance of its error (same units squared), and per satellite
slot the log of its pseudorange error sigma relative to a physical sigma model and its bias (in units of
``res_scale``; see :func:`sat_sigma_bias`). The per-satellite head reads each slot's own embedding after the encoder, which has
already attended to the whole set.

- :class:`SetTransformer` (paper Sec. 5.0): Linear(4->64)+ReLU, 2 Transformer encoder layers, attention
  pooling with one learned seed (PMA), 2 Transformer decoder layers attending to the encoded set,
  Linear(64->3). With ``d_model=64, dim_feedforward=64`` the mean path has 151,619 parameters, 0.34 %
  above the paper's 151,107 (which we could not match exactly with standard PyTorch layers); the
  log-variance head adds 195.
- :class:`DeepSets`: per-element MLP, masked mean + masked max pooling, MLP decoder.

The per-satellite head (``Linear(d_model -> 2)``) adds 130 parameters to the set transformer.

Padding slots (mask False) are excluded by key padding masks in every attention and by the pooling
masks, so the output does not depend on what the padded slots contain or on slot order.
"""
from __future__ import annotations

import torch
from torch import nn

# one definition of each constant, shared with the torch-free inference (learned/heads.py, learned/npnet.py)
from learned.heads import LOGSIG_RANGE, ZENITH_SIGMA_M  # noqa: E402,F401
from learned.npnet import LOGVAR_RANGE  # noqa: E402,F401


def base_sigma(pr_sigma: torch.Tensor, sin_el: torch.Tensor) -> torch.Tensor:
    """The physical pseudorange sigma model [m], ``sqrt(pr_sigma^2 + (ZENITH_SIGMA_M / sin el)^2)``: the
    phone's reported uncertainty and an elevation term; both (B,S), sin_el clipped to [0.1, 1]."""
    return torch.sqrt(pr_sigma.double() ** 2 + (ZENITH_SIGMA_M / sin_el.double().clamp(0.1, 1.0)) ** 2)


def sat_sigma_bias(sat: torch.Tensor, res_scale: float, base: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-slot pseudorange error sigma and bias [m] from the head's (B,S,2) output: the head scales the
    physical model ``base`` (B,S) [m] (it learns what the phone's report and the elevation miss, and starts
    from them) and predicts the bias in units of ``res_scale``."""
    return base * torch.exp(sat[..., 0].double().clamp(*LOGSIG_RANGE)), sat[..., 1].double() * res_scale


class PMA(nn.Module):
    """Pooling by multi-head attention: ``k`` learned seed queries attend to the set."""

    def __init__(self, d_model: int, n_heads: int, k: int = 1):
        super().__init__()
        self.seed = nn.Parameter(torch.randn(1, k, d_model) * d_model ** -0.5)
        self.attn = nn.MultiheadAttention(d_model, n_heads, batch_first=True)

    def forward(self, h: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
        """h (B,S,D), pad (B,S) True where padded -> (B,k,D)."""
        q = self.seed.expand(h.shape[0], -1, -1)
        out, _ = self.attn(q, h, h, key_padding_mask=pad, need_weights=False)
        return out


class SetTransformer(nn.Module):
    def __init__(self, d_in: int = 4, d_model: int = 64, n_heads: int = 4, dim_feedforward: int = 64,
                 n_encoder: int = 2, n_decoder: int = 2, d_out: int = 3, dropout: float = 0.0):
        """``dropout``: the transformer layers' dropout in training (inference, in eval mode, has none)."""
        super().__init__()
        self.embed = nn.Sequential(nn.Linear(d_in, d_model), nn.ReLU())
        self.encoder = nn.ModuleList(nn.TransformerEncoderLayer(
            d_model, n_heads, dim_feedforward, dropout=dropout, batch_first=True) for _ in range(n_encoder))
        self.pool = PMA(d_model, n_heads)
        self.decoder = nn.ModuleList(nn.TransformerDecoderLayer(
            d_model, n_heads, dim_feedforward, dropout=dropout, batch_first=True) for _ in range(n_decoder))
        self.head = nn.Linear(d_model, d_out)
        self.logvar_head = nn.Linear(d_model, d_out)
        self.sat_head = nn.Linear(d_model, 2)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (B,S,F) float32, mask (B,S) bool True for real slots -> mean (B,3), log_var (B,3), sat (B,S,2)."""
        pad = ~mask
        h = self.embed(x)
        for layer in self.encoder:
            h = layer(h, src_key_padding_mask=pad)
        z = self.pool(h, pad)
        for layer in self.decoder:
            z = layer(z, h, memory_key_padding_mask=pad)
        z = z[:, 0]
        return self.head(z), self.logvar_head(z).clamp(*LOGVAR_RANGE), self.sat_head(h)


class DeepSets(nn.Module):
    def __init__(self, d_in: int = 4, d_model: int = 128, d_out: int = 3):
        super().__init__()
        self.phi = nn.Sequential(nn.Linear(d_in, d_model), nn.ReLU(), nn.Linear(d_model, d_model), nn.ReLU(),
                                 nn.Linear(d_model, d_model), nn.ReLU())
        self.rho = nn.Sequential(nn.Linear(2 * d_model, d_model), nn.ReLU(), nn.Linear(d_model, d_model), nn.ReLU())
        self.head = nn.Linear(d_model, d_out)
        self.logvar_head = nn.Linear(d_model, d_out)
        self.sat_head = nn.Linear(d_model + 2 * d_model, 2)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (B,S,F), mask (B,S) -> mean (B,3), log_var (B,3), sat (B,S,2). Masked mean and max pooling;
        the per-satellite head reads each element's embedding beside the pooled set."""
        h = self.phi(x)
        m = mask[..., None].to(h.dtype)
        mean = (h * m).sum(1) / m.sum(1).clamp_min(1.0)
        mx = h.masked_fill(~mask[..., None], float("-inf")).amax(1)
        mx = torch.where(torch.isfinite(mx), mx, torch.zeros_like(mx))
        pooled = torch.cat([mean, mx], -1)
        z = self.rho(pooled)
        sat = self.sat_head(torch.cat([h, pooled[:, None, :].expand(-1, h.shape[1], -1)], -1))
        return self.head(z), self.logvar_head(z).clamp(*LOGVAR_RANGE), sat


#: ``--model`` name -> class.
MODELS = {"set": SetTransformer, "deepsets": DeepSets}


def build_model(kind: str, **hparams) -> nn.Module:
    if kind not in MODELS:
        raise ValueError(f"unknown model kind {kind!r}; choose one of {sorted(MODELS)}")
    return MODELS[kind](**hparams)


def count_parameters(model: nn.Module, include_heads: bool = True) -> int:
    """Parameters, or without the variance and per-satellite heads (the paper's mean path) when
    ``include_heads`` is False."""
    extra = ("logvar_head", "sat_head")
    if hasattr(model, "weights"):          # a learned.npnet.NpNet (inference without torch)
        return sum(int(v.size) for n, v in model.weights.items() if include_heads or not n.startswith(extra))
    return sum(p.numel() for n, p in model.named_parameters() if include_heads or not n.startswith(extra))
