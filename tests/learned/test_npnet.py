"""The numpy forward pass (learned/npnet.py) against torch's, on random inputs with padding."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from learned.model import build_model  # noqa: E402
from learned.npnet import forward  # noqa: E402


def _inputs(B=7, S=9, F=6, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(B, S, F)).astype(np.float32)
    n = rng.integers(1, S + 1, size=B)
    n[0] = S                                 # one row without padding
    mask = np.arange(S)[None, :] < n[:, None]
    perm = rng.permuted(np.tile(np.arange(S), (B, 1)), axis=1)   # padding not only at the end
    mask = np.take_along_axis(mask, perm, axis=1)
    x[~mask] = rng.normal(size=(int((~mask).sum()), F)) * 100   # garbage in padded slots
    return x, mask


@pytest.mark.parametrize("kind,hp", [("set", {"d_in": 6}), ("set", {"d_in": 6, "d_model": 32, "n_heads": 2,
                                                                     "n_encoder": 1, "n_decoder": 3}),
                                     ("deepsets", {"d_in": 6, "d_model": 16})])
def test_numpy_forward_equals_torch(kind, hp):
    torch.manual_seed(1)
    model = build_model(kind, **hp).eval()
    w = {k: v.detach().numpy() for k, v in model.state_dict().items()}
    x, mask = _inputs()
    with torch.no_grad():
        ref = [t.numpy() for t in model(torch.from_numpy(x), torch.from_numpy(mask))]
    got = forward(kind, hp, w, x, mask)
    for r, g, name in zip(ref, got, ("mean", "logvar", "sat")):
        if name == "sat":
            r, g = r[mask], g[mask]          # padded slots' outputs are ignored by every caller
        np.testing.assert_allclose(g, r, atol=1e-5, rtol=1e-5, err_msg=name)


def test_padding_does_not_change_numpy_output():
    torch.manual_seed(2)
    hp = {"d_in": 6}
    w = {k: v.detach().numpy() for k, v in build_model("set", **hp).state_dict().items()}
    x, mask = _inputs()
    y = x.copy()
    y[~mask] = 7.0
    a, b = forward("set", hp, w, x, mask), forward("set", hp, w, y, mask)
    np.testing.assert_allclose(a[0], b[0], atol=1e-6)
    np.testing.assert_allclose(a[2][mask], b[2][mask], atol=1e-6)


def test_numpy_heads_equal_torch_heads():
    """learned/heads.py (inference) against the torch functions training uses."""
    from learned.heads import base_sigma as np_base, sat_sigma_bias as np_sb, weighted_ls_step as np_step
    from learned.losses import weighted_ls_step
    from learned.model import base_sigma, sat_sigma_bias
    rng = np.random.default_rng(3)
    B, S = 5, 8
    rx = np.array([-2700000.0, -4290000.0, 3860000.0])
    guess = rx + rng.normal(size=(B, 3)) * 20
    sat_pos = rx + rng.normal(size=(B, S, 3)) * 1.5e7
    sat_pos *= (2.6e7 / np.linalg.norm(sat_pos, axis=-1))[..., None]
    pr = np.linalg.norm(sat_pos - rx, axis=-1) + rng.normal(size=(B, S)) * 5 + 3e4
    mask = rng.random((B, S)) > 0.2
    mask[:, :5] = True
    prs, sin_el = rng.uniform(1, 20, (B, S)), rng.uniform(0.05, 1, (B, S))
    sat = rng.normal(size=(B, S, 2))
    t = lambda a: torch.as_tensor(a)  # noqa: E731
    base = np_base(prs, sin_el)
    np.testing.assert_allclose(base, base_sigma(t(prs), t(sin_el)).numpy(), rtol=1e-12)
    sig, bias = np_sb(sat, 10.0, base)
    ts, tb = sat_sigma_bias(t(sat), 10.0, t(base))
    np.testing.assert_allclose(sig, ts.numpy(), rtol=1e-12)
    np.testing.assert_allclose(bias, tb.numpy(), rtol=1e-12)
    pos, cov = np_step(sat_pos, pr, mask, guess, sig, bias)
    tp, tc = weighted_ls_step(t(sat_pos), t(pr), t(mask), t(guess), t(sig), t(bias))
    np.testing.assert_allclose(pos, tp.numpy(), atol=1e-6)
    np.testing.assert_allclose(cov, tc.numpy(), rtol=1e-6, atol=1e-9)
