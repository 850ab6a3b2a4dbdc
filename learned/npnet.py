"""The networks of :mod:`learned.model` evaluated in numpy from their weights: inference without torch.

``forward(kind, weights, x, mask)`` returns what the torch module returns in eval mode, ``(mean (B,3),
log_var (B,3), sat (B,S,H))``, from ``weights`` (the state dict as float32 numpy arrays, keys as torch names
them) for inputs ``x`` (B,S,F) and ``mask`` (B,S) bool (True on real slots). Arithmetic in float32, as torch's
CPU forward pass; ``tests/learned/test_npnet.py`` holds the two within 1e-5 on random inputs with padding.

Semantics reproduced (PyTorch 2.x, ``batch_first=True``, ``dropout=0``): ``nn.TransformerEncoderLayer`` and
``nn.TransformerDecoderLayer`` in post-norm form (``norm_first=False``) with ReLU feed-forward and LayerNorm
eps 1e-5; ``nn.MultiheadAttention`` with packed input projections and a key padding mask (padded keys get no
weight); the PMA pooling and the DeepSets masked mean/max pooling of :mod:`learned.model`. Outputs at padded
slots of ``sat`` are whatever the arithmetic gives there: callers ignore them, as with torch.
"""
from __future__ import annotations

import numpy as np

#: Log-variance output is clamped to this range (variance between ~5e-5 and ~2e4 out_scale^2).
LOGVAR_RANGE = (-10.0, 10.0)
_LN_EPS = 1e-5


def linear(w: dict, name: str, x: np.ndarray) -> np.ndarray:
    """``x @ W^T + b`` with ``name.weight`` (out,in) and ``name.bias`` (out,); x (..., in) -> (..., out)."""
    return project(x, w[f"{name}.weight"], w[f"{name}.bias"])


def project(x: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """``x @ weight^T + bias``, x (..., in), weight (out,in): as one matrix product over all leading axes (numpy
    multiplies a stack of (S,in) matrices one by one, twice as slow at the sizes asked; bench_infer.py)."""
    flat = x.reshape(-1, x.shape[-1]) @ weight.T + bias
    return flat.reshape(x.shape[:-1] + (weight.shape[0],))


def layer_norm(w: dict, name: str, x: np.ndarray) -> np.ndarray:
    """LayerNorm over the last axis (biased variance, eps 1e-5, as torch)."""
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + _LN_EPS) * w[f"{name}.weight"] + w[f"{name}.bias"]


def relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def attention(w: dict, name: str, q: np.ndarray, kv: np.ndarray, n_heads: int,
              key_pad: np.ndarray | None = None) -> np.ndarray:
    """``nn.MultiheadAttention(q, kv, kv, key_padding_mask=key_pad)``: q (B,L,D), kv (B,S,D), key_pad (B,S)
    True where padded (None: no padding) -> (B,L,D)."""
    D = q.shape[-1]
    W, b = w[f"{name}.in_proj_weight"], w[f"{name}.in_proj_bias"]
    dh = D // n_heads

    def heads(a: np.ndarray) -> np.ndarray:        # (B,L,D) -> (B,H,L,dh)
        return a.reshape(a.shape[0], a.shape[1], n_heads, dh).transpose(0, 2, 1, 3)
    if q is kv:                                     # self-attention: the three projections in one product
        Q, K, V = (heads(a) for a in np.split(project(q, W, b), 3, axis=-1))
    else:
        Q = heads(project(q, W[:D], b[:D]))
        K, V = (heads(a) for a in np.split(project(kv, W[D:], b[D:]), 2, axis=-1))
    logits = (Q / np.float32(np.sqrt(dh))) @ K.transpose(0, 1, 3, 2)      # (B,H,L,S)
    if key_pad is not None:
        logits = np.where(key_pad[:, None, None, :], -np.inf, logits)
    logits -= logits.max(-1, keepdims=True)
    p = np.exp(logits, out=logits)
    p /= p.sum(-1, keepdims=True)
    out = (p @ V).transpose(0, 2, 1, 3).reshape(q.shape[0], q.shape[1], D)
    return linear(w, f"{name}.out_proj", out)


def encoder_layer(w: dict, name: str, h: np.ndarray, pad: np.ndarray, n_heads: int) -> np.ndarray:
    """Post-norm ``nn.TransformerEncoderLayer``: h (B,S,D), pad (B,S) True where padded."""
    h = layer_norm(w, f"{name}.norm1", h + attention(w, f"{name}.self_attn", h, h, n_heads, pad))
    ff = linear(w, f"{name}.linear2", relu(linear(w, f"{name}.linear1", h)))
    return layer_norm(w, f"{name}.norm2", h + ff)


def decoder_layer(w: dict, name: str, z: np.ndarray, mem: np.ndarray, pad: np.ndarray, n_heads: int) -> np.ndarray:
    """Post-norm ``nn.TransformerDecoderLayer``: z (B,L,D) queries, mem (B,S,D), pad (B,S) on the memory."""
    z = layer_norm(w, f"{name}.norm1", z + attention(w, f"{name}.self_attn", z, z, n_heads))
    z = layer_norm(w, f"{name}.norm2", z + attention(w, f"{name}.multihead_attn", z, mem, n_heads, pad))
    ff = linear(w, f"{name}.linear2", relu(linear(w, f"{name}.linear1", z)))
    return layer_norm(w, f"{name}.norm3", z + ff)


def _count(w: dict, prefix: str) -> int:
    """Number of stacked layers ``prefix.<i>.`` in the weights."""
    return len({k.split(".")[1] for k in w if k.startswith(prefix + ".")})


def set_transformer(w: dict, x: np.ndarray, mask: np.ndarray, n_heads: int) -> tuple:
    """:class:`learned.model.SetTransformer` in numpy."""
    pad = ~mask
    h = relu(linear(w, "embed.0", x))
    for i in range(_count(w, "encoder")):
        h = encoder_layer(w, f"encoder.{i}", h, pad, n_heads)
    seed = w["pool.seed"]
    z = attention(w, "pool.attn", np.broadcast_to(seed, (x.shape[0],) + seed.shape[1:]), h, n_heads, pad)
    for i in range(_count(w, "decoder")):
        z = decoder_layer(w, f"decoder.{i}", z, h, pad, n_heads)
    z = z[:, 0]
    return linear(w, "head", z), np.clip(linear(w, "logvar_head", z), *LOGVAR_RANGE), linear(w, "sat_head", h)


def deep_sets(w: dict, x: np.ndarray, mask: np.ndarray) -> tuple:
    """:class:`learned.model.DeepSets` in numpy."""
    h = x
    for i in (0, 2, 4):
        h = relu(linear(w, f"phi.{i}", h))
    m = mask[..., None].astype(h.dtype)
    mean = (h * m).sum(1) / np.maximum(m.sum(1), 1.0)
    mx = np.where(mask[..., None], h, -np.inf).max(1)
    mx = np.where(np.isfinite(mx), mx, 0.0).astype(h.dtype)
    pooled = np.concatenate([mean, mx], -1)
    z = relu(linear(w, "rho.2", relu(linear(w, "rho.0", pooled))))
    sat_in = np.concatenate([h, np.broadcast_to(pooled[:, None, :], h.shape[:2] + pooled.shape[-1:])], -1)
    return linear(w, "head", z), np.clip(linear(w, "logvar_head", z), *LOGVAR_RANGE), linear(w, "sat_head", sat_in)


def forward(kind: str, hparams: dict, weights: dict, x: np.ndarray, mask: np.ndarray) -> tuple:
    """The network ``kind`` ("set" or "deepsets", with its ``hparams``) on x (B,S,F), mask (B,S) bool ->
    mean (B,3), log_var (B,3), sat (B,S,H), all float32."""
    x, mask = np.asarray(x, np.float32), np.asarray(mask, bool)
    with np.errstate(over="ignore", invalid="ignore"):
        if kind == "set":
            return set_transformer(weights, x, mask, int(hparams.get("n_heads", 4)))
        if kind == "deepsets":
            return deep_sets(weights, x, mask)
    raise ValueError(f"unknown model kind {kind!r}")


#: Model kinds this module evaluates (those of :data:`learned.model.MODELS`).
KINDS = ("set", "deepsets")


class NpNet:
    """A network as weights + kind: ``net(x (B,S,F), mask (B,S)) -> (mean, log_var, sat)`` in numpy."""

    def __init__(self, kind: str, hparams: dict, weights: dict[str, np.ndarray]):
        if kind not in KINDS:
            raise ValueError(f"unknown model kind {kind!r} (known: {', '.join(KINDS)})")
        self.kind, self.hparams = kind, dict(hparams)
        self.weights = {k: np.asarray(v, np.float32) for k, v in weights.items()}
        self.d_in = int(self.hparams.get("d_in", 4))
        d_model, heads = int(self.hparams.get("d_model", 64)), int(self.hparams.get("n_heads", 4))
        if kind == "set" and (heads < 1 or d_model % heads):
            raise ValueError(f"d_model {d_model} is not divisible by n_heads {heads}")

    def __call__(self, x: np.ndarray, mask: np.ndarray) -> tuple:
        return forward(self.kind, self.hparams, self.weights, x, mask)

    def check(self) -> None:
        """One forward pass on a dummy epoch: KeyError / ValueError when the weights do not fit the kind."""
        mean, logvar, sat = self(np.zeros((1, 4, self.d_in), np.float32), np.ones((1, 4), bool))
        if mean.shape != (1, 3) or logvar.shape != (1, 3) or sat.shape[:2] != (1, 4):
            raise ValueError(f"outputs of shapes {mean.shape}, {logvar.shape}, {sat.shape}")


class TorchNet:
    """A torch module behind the numpy interface (tests and experiments hand the corrector modules)."""

    def __init__(self, module):
        self.module = module.eval()

    def __call__(self, x: np.ndarray, mask: np.ndarray) -> tuple:
        import torch
        with torch.no_grad():
            out = self.module(torch.as_tensor(np.asarray(x, np.float32)), torch.as_tensor(np.asarray(mask, bool)))
        return tuple(o.detach().cpu().numpy() for o in out)


def as_net(model):
    """A torch module wrapped in :class:`TorchNet`; an :class:`NpNet` (or any numpy callable) as is."""
    return TorchNet(model) if hasattr(model, "state_dict") and hasattr(model, "eval") else model
