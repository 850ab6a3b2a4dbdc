"""Model architecture: parameter count, set semantics (permutation / padding invariance), any S >= 4."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from learned.model import (LOGSIG_RANGE, ZENITH_SIGMA_M, DeepSets, SetTransformer, base_sigma, build_model,
                           count_parameters, sat_sigma_bias)

PAPER_PARAMS = 151_107


def test_set_transformer_parameter_count_matches_paper():
    m = SetTransformer()
    n = count_parameters(m, include_heads=False)
    assert abs(n - PAPER_PARAMS) / PAPER_PARAMS < 0.01, n
    # the log-variance head (64 -> 3) and the per-satellite head (64 -> 2)
    assert count_parameters(m) == n + (64 * 3 + 3) + (64 * 2 + 2)
    # the per-satellite head reads the input width: context channels widen only the embedding
    wide = SetTransformer(d_in=10)
    assert count_parameters(wide) == count_parameters(m) + 6 * 64


def _inputs(B=6, S=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, S, 4, generator=g)
    n = torch.randint(4, S + 1, (B,), generator=g)
    mask = torch.arange(S)[None, :] < n[:, None]
    return x * mask[..., None], mask


@pytest.mark.parametrize("kind", ["set", "deepsets"])
def test_permutation_invariance(kind):
    torch.manual_seed(0)
    m = build_model(kind).eval()
    x, mask = _inputs()
    perm = torch.randperm(x.shape[1])
    with torch.no_grad():
        a, la, sa = m(x, mask)
        b, lb, sb = m(x[:, perm], mask[:, perm])
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(la, lb, atol=1e-5, rtol=1e-5)
    # the per-satellite head is permutation-equivariant: each slot keeps its own output
    assert sa.shape == (x.shape[0], x.shape[1], 2)
    m2 = mask[:, perm]
    torch.testing.assert_close(sa[:, perm][m2], sb[m2], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("kind", ["set", "deepsets"])
def test_padding_invariance(kind):
    """Extra padded slots holding garbage change nothing; neither does training-mode vs eval-mode."""
    torch.manual_seed(0)
    m = build_model(kind).eval()
    x, mask = _inputs(S=8)
    junk = torch.randn(x.shape[0], 5, 4) * 100
    x2 = torch.cat([x, junk], 1)
    mask2 = torch.cat([mask, torch.zeros(x.shape[0], 5, dtype=torch.bool)], 1)
    x2[:, :8][~mask] = 55.0                                   # garbage in the original padding too
    with torch.no_grad():
        a, _, sa = m(x, mask)
        b, _, sb = m(x2, mask2)
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(sa[mask], sb[:, :8][mask], atol=1e-5, rtol=1e-5)   # real slots' sat head too
    m.train()                                                 # no dropout: the same function in train mode
    with torch.no_grad():
        c, _, _ = m(x2, mask2)
    torch.testing.assert_close(a, c, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("S", [4, 5, 12, 30])
def test_any_set_size_and_gradients_flow(S):
    torch.manual_seed(1)
    m = SetTransformer()
    x = torch.randn(3, S, 4)
    mask = torch.ones(3, S, dtype=torch.bool)
    mean, logvar, sat = m(x, mask)
    assert mean.shape == (3, 3) and logvar.shape == (3, 3) and sat.shape == (3, S, 2)
    assert torch.isfinite(mean).all() and torch.isfinite(sat).all()
    mean.sum().backward(retain_graph=True)
    heads = ("logvar_head", "sat_head")
    assert all(p.grad is not None for n, p in m.named_parameters() if not n.startswith(heads))
    assert all(p.grad is None for n, p in m.named_parameters() if n.startswith(heads))
    m.zero_grad(set_to_none=True)
    sat.sum().backward()
    assert m.sat_head.weight.grad is not None and m.embed[0].weight.grad is not None


def test_output_depends_on_inputs():
    # Guards against a degenerate net (e.g. masks inverted so every slot is ignored).
    torch.manual_seed(2)
    m = SetTransformer().eval()
    x, mask = _inputs()
    with torch.no_grad():
        a, _, sa = m(x, mask)
        x2 = x.clone()
        x2[0, 0] += 1.0
        b, _, sb = m(x2, mask)
    assert (a[0] - b[0]).abs().max() > 1e-4 and torch.equal(a[1:], b[1:])
    assert (sa[0, 0] - sb[0, 0]).abs().max() > 1e-4 and torch.equal(sa[1:], sb[1:])


def test_deepsets_smaller_and_unknown_kind_rejected():
    assert count_parameters(DeepSets()) < count_parameters(SetTransformer())
    with pytest.raises(ValueError, match="unknown model kind"):
        build_model("mlp")
    with pytest.raises(ValueError, match="unknown model kind"):    # the direct-position ablation is gone
        build_model("direct")


def test_sat_sigma_bias_scales_and_clamps():
    """The head scales the physical sigma model (phone's reported sigma and an elevation term) and gives the
    bias in units of res_scale; its log-scale is clamped so sigmas stay finite and positive."""
    sat = torch.tensor([[[0.0, 0.5], [float(np.log(2.0)), -1.0], [50.0, 0.0], [-50.0, 0.0]]])
    base = torch.tensor([[3.0, 3.0, 3.0, 3.0]], dtype=torch.float64)
    sigma, bias = sat_sigma_bias(sat, 10.0, base)
    torch.testing.assert_close(sigma[0, :2], torch.tensor([3.0, 6.0], dtype=sigma.dtype))
    torch.testing.assert_close(bias[0, :2], torch.tensor([5.0, -10.0], dtype=bias.dtype))
    lo, hi = LOGSIG_RANGE
    torch.testing.assert_close(sigma[0, 2:], 3.0 * torch.exp(torch.tensor([hi, lo], dtype=sigma.dtype)))
    # the physical model: reported sigma and 1/sin(elevation) in quadrature, low elevations clipped
    b = base_sigma(torch.tensor([[3.0, 3.0, 0.0]]), torch.tensor([[1.0, 0.5, 0.01]]))
    z = ZENITH_SIGMA_M
    torch.testing.assert_close(b[0], torch.tensor([np.hypot(3.0, z), np.hypot(3.0, 2 * z), 10 * z], dtype=b.dtype))
