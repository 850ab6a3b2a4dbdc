"""Model architecture: parameter count, set semantics (permutation / padding invariance), any S >= 4."""
from __future__ import annotations

import pytest
import torch

from learned.model import DeepSets, SetTransformer, build_model, count_parameters

PAPER_PARAMS = 151_107


def test_set_transformer_parameter_count_matches_paper():
    m = SetTransformer()
    n = count_parameters(m, include_logvar=False)
    assert abs(n - PAPER_PARAMS) / PAPER_PARAMS < 0.01, n
    assert count_parameters(m) == n + 64 * 3 + 3            # the log-variance head


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
        a, la = m(x, mask)
        b, lb = m(x[:, perm], mask[:, perm])
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(la, lb, atol=1e-5, rtol=1e-5)


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
        a, _ = m(x, mask)
        b, _ = m(x2, mask2)
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    m.train()                                                 # no dropout: the same function in train mode
    with torch.no_grad():
        c, _ = m(x2, mask2)
    torch.testing.assert_close(a, c, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("S", [4, 5, 12, 30])
def test_any_set_size_and_gradients_flow(S):
    torch.manual_seed(1)
    m = SetTransformer()
    x = torch.randn(3, S, 4)
    mask = torch.ones(3, S, dtype=torch.bool)
    mean, logvar = m(x, mask)
    assert mean.shape == (3, 3) and logvar.shape == (3, 3) and torch.isfinite(mean).all()
    mean.sum().backward()
    assert all(p.grad is not None for n, p in m.named_parameters() if not n.startswith("logvar_head"))


def test_output_depends_on_inputs():
    # Guards against a degenerate net (e.g. masks inverted so every slot is ignored).
    torch.manual_seed(2)
    m = SetTransformer().eval()
    x, mask = _inputs()
    with torch.no_grad():
        a, _ = m(x, mask)
        x2 = x.clone()
        x2[0, 0] += 1.0
        b, _ = m(x2, mask)
    assert (a[0] - b[0]).abs().max() > 1e-4 and torch.equal(a[1:], b[1:])


def test_deepsets_smaller_and_unknown_kind_rejected():
    assert count_parameters(DeepSets()) < count_parameters(SetTransformer())
    with pytest.raises(ValueError, match="unknown model kind"):
        build_model("mlp")
