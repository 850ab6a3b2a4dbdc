"""The learned package's new parts: per-slot context features, the feature-version guard on checkpoints,
the per-satellite head's least-squares layer and NLL, the out-of-distribution guard, and the graph's
slot-noise provider. Toy data only (no ../shared)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from fusion.errors import CheckpointError
from fusion.estimate.wls import solve_wls, solve_wls_arrays
from fusion.geometry import ecef2ned_vec, line_of_sight
from learned.checkpoint import load_model, save_checkpoint
from learned.context import slot_context
from learned.features import CHANNELS, FeatureConfig, context_channels
from learned.guard import MARGIN, input_ranges, slot_out_of_range, trust
from learned.infer import Corrector
from learned.losses import sat_nll, weighted_ls_step
from learned.model import SetTransformer
from learned.toy import toy_trace
from learned.train import TrainConfig

f64 = dict(dtype=torch.float64)


def _t(a):
    return torch.as_tensor(a) if np.asarray(a).dtype == bool else torch.as_tensor(a, **f64)


# --------------------------------------------------------------------------------------- (1) context
@pytest.fixture(scope="module")
def ctx_trace():
    """12 epochs at 1 Hz, 6 satellites (ids 1001..1006); satellite 1003 missing at epoch 3, slots 0 and 1
    swapped at epoch 6 (same satellites, other slots), a clock reset at epoch 8, a 10 s gap before epoch 10."""
    tr = toy_trace(12, seed=3, n_sats=(6, 6))
    tr.mask[3, 2] = False
    for name in ("sat_pos", "pr", "pr_sigma", "sat_id"):
        a = getattr(tr, name)
        a[6, [0, 1]] = a[6, [1, 0]]
    tr.clock_reset[8] = True
    tr.t_ms[10:] += 10_000
    return tr, solve_wls(tr)


def test_context_dres_is_the_wls_residual_change_of_the_same_satellite(ctx_trace):
    tr, wls = ctx_trace
    assert wls.valid.all()
    ctx = slot_context(tr, wls)
    ids = tr.sat_id
    linked = 0
    for k in range(1, tr.n_epochs):
        for s in np.flatnonzero(tr.mask[k]):
            prev = np.flatnonzero(tr.mask[k - 1] & (ids[k - 1] == ids[k, s]))
            if ctx.prev_ok[k, s]:
                assert prev.size == 1
                assert ctx.dres[k, s] == pytest.approx(wls.resid[k, s] - wls.resid[k - 1, prev[0]], abs=1e-9)
                linked += 1
            else:
                assert ctx.dres[k, s] == 0.0
    assert linked > 40
    # the swap at epoch 6 is followed by satellite id, not slot: slot 0 at epoch 6 holds epoch 5's slot 1
    assert ctx.prev_ok[6, 0] and ctx.dres[6, 0] == pytest.approx(wls.resid[6, 0] - wls.resid[5, 1], abs=1e-9)
    assert abs(ctx.dres[6, 0] - (wls.resid[6, 0] - wls.resid[5, 0])) > 1e-6    # (not the slot's previous)


def test_context_prev_ok_breaks_at_first_epoch_reset_gap_and_reappearance(ctx_trace):
    tr, wls = ctx_trace
    ctx = slot_context(tr, wls)
    assert not ctx.prev_ok[0].any()
    assert not ctx.prev_ok[8].any()                  # clock reset
    assert not ctx.prev_ok[10].any()                 # 10 s gap
    assert not ctx.prev_ok[4, 2] and ctx.prev_ok[4, [0, 1, 3, 4, 5]].all()   # 1003 came back at epoch 4
    assert ctx.prev_ok[[1, 2, 5, 7, 9, 11]].all()
    assert not ctx.prev_ok[~tr.mask].any()


def test_context_arc_age_grows_one_second_per_epoch_and_restarts(ctx_trace):
    tr, wls = ctx_trace
    arc = slot_context(tr, wls).arc_s
    np.testing.assert_allclose(arc[:8, 0], np.arange(8.0))          # satellite in slot 0 (swaps keep the id)
    np.testing.assert_allclose(arc[6, [0, 1]], [6.0, 6.0])
    np.testing.assert_allclose(arc[8:10, 0], [0.0, 1.0])             # reset restarts every arc
    np.testing.assert_allclose(arc[10:, 0], [0.0, 1.0])              # and the gap
    np.testing.assert_allclose(arc[:8, 2], [0.0, 1.0, 2.0, 0.0, 0.0, 1.0, 2.0, 3.0])   # gone at 3, back at 4
    assert (arc[~tr.mask] == 0).all()


def test_context_channels_are_scaled_and_zero_on_padding(ctx_trace):
    tr, wls = ctx_trace
    ctx = slot_context(tr, wls).as_dict()
    cfg = FeatureConfig(inputs=tuple(CHANNELS))
    extra = context_channels(ctx, tr.mask, cfg)
    assert extra.shape == tr.mask.shape + (cfg.n_inputs - 4,) and extra.dtype == np.float32
    assert (extra[~tr.mask] == 0).all()
    # channel order follows cfg.inputs: pr_sigma (value, reported), cn0 (value, have), dres (value, prev_ok),
    # arc, cmd (value, have), carrier (has, ok, slip), system one-hot (+ unknown), signal one-hot (+ unknown)
    np.testing.assert_allclose(extra[..., 0][tr.mask], np.log(tr.pr_sigma[tr.mask] / 3.0), rtol=1e-5)
    np.testing.assert_array_equal(extra[..., 1][tr.mask], 1.0)
    np.testing.assert_allclose(extra[..., 4][tr.mask], (ctx["dres"][tr.mask] / cfg.res_scale).clip(-10, 10),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(extra[..., 5][tr.mask], ctx["prev_ok"][tr.mask])
    assert extra[..., 6].max() <= 1.0 and (np.diff(extra[:8, 0, 6]) > 0).all()
    sl = cfg.slices()
    one_hot = extra[..., sl["signal"].start - 4:sl["signal"].stop - 4][tr.mask]
    np.testing.assert_array_equal(one_hot.sum(-1), 1.0)
    np.testing.assert_array_equal(one_hot.argmax(-1), tr.signal[tr.mask])
    # missing: the report's value and flag zero; a signal read as unknown: its last entry
    gone = context_channels(ctx, tr.mask, cfg, {"pr_sigma": np.ones(tr.mask.shape, bool),
                                                  "signal": np.ones(tr.mask.shape, bool)})
    assert (gone[..., :2] == 0).all()
    np.testing.assert_array_equal(gone[..., sl["signal"].stop - 5][tr.mask], 1.0)
    only_arc = context_channels(ctx, tr.mask, FeatureConfig(inputs=("res", "los", "arc")))
    np.testing.assert_array_equal(only_arc[..., 0], extra[..., 6])
    assert context_channels(ctx, tr.mask, FeatureConfig()).shape == tr.mask.shape + (0,)
    assert FeatureConfig().n_inputs == 4 and cfg.n_inputs == 4 + sum(CHANNELS[c] for c in cfg.inputs[2:])
    with pytest.raises(ValueError, match="must start with"):
        FeatureConfig(inputs=("los", "res"))
    with pytest.raises(ValueError, match="must start with"):
        FeatureConfig(inputs=("res", "los", "doppler"))


# --------------------------------------------------------------------------------- (2) old checkpoints
def test_feature_version_1_checkpoint_is_refused_naming_the_version(tmp_path):
    cfg = TrainConfig().to_checkpoint_config()
    old = save_checkpoint(tmp_path / "v1.pt", SetTransformer(), dict(cfg, features={**cfg["features"], "version": 1}))
    with pytest.raises(CheckpointError, match=r"v1\.pt: feature version 1; this code reads versions \(2, 3\)"):
        Corrector.load(old)
    with pytest.raises(CheckpointError, match="feature version 1"):
        load_model(old)
    ok = save_checkpoint(tmp_path / "v3.pt", SetTransformer(), cfg)
    assert Corrector.load(ok).features.version == 3
    # version 2 (the previous release's weights) still loads and reads its own channels
    v2 = FeatureConfig(version=2, inputs=("res", "los", "pr_sigma")).to_dict()
    old2 = save_checkpoint(tmp_path / "v2.pt", SetTransformer(d_in=5),
                           dict(cfg, features=v2, model={"kind": "set", "hparams": {"d_in": 5}}))
    assert Corrector.load(old2).features.n_inputs == 5


# -------------------------------------------------------------------------- (3) per-satellite head maths
def _epochs(B=40, S=8, sigma=3.0, seed=0):
    """sat_pos, pr (range + clock + N(0, sigma)), mask, truth of ``B`` toy epochs with ``S`` satellites."""
    tr = toy_trace(B, seed=seed, n_sats=(S, S))
    rng, _ = line_of_sight(tr.sat_pos, tr.truth)
    noise = np.random.default_rng(seed + 1).normal(0.0, sigma, rng.shape)
    clock = np.random.default_rng(seed + 2).uniform(-1e5, 1e5, (B, 1))
    return tr.sat_pos, rng + clock + noise, tr.mask, tr.truth


def test_weighted_ls_step_with_equal_sigmas_is_plain_least_squares():
    sat_pos, pr, mask, truth = _epochs()
    guess = truth + np.random.default_rng(5).uniform(-20, 20, truth.shape)
    pos, cov = weighted_ls_step(_t(sat_pos), _t(pr), _t(mask), _t(guess), torch.full(pr.shape, 3.0, **f64))
    ref = solve_wls_arrays(sat_pos, pr, mask, weighting="none", elev_mask_deg=-90.0)
    assert ref.valid.all()
    # one Gauss-Newton step from within 20 m lands within millimetres of the converged solution
    np.testing.assert_allclose(pos.numpy(), ref.pos, atol=5e-3)
    # its covariance is sigma^2 (H^T H)^-1: the same for any common sigma scale up to sigma^2
    _, cov6 = weighted_ls_step(_t(sat_pos), _t(pr), _t(mask), _t(guess), torch.full(pr.shape, 6.0, **f64))
    np.testing.assert_allclose(cov6.numpy(), 4.0 * cov.numpy(), rtol=1e-6)
    # and the step is not the guess: it did move by the guess error
    assert np.linalg.norm(pos.numpy() - guess, axis=1).min() > 1.0


def test_a_huge_sigma_removes_one_slots_influence_and_a_bias_is_subtracted():
    sat_pos, pr, mask, truth = _epochs(seed=3)
    pr = pr.copy()
    pr[:, 2] += 100.0                                      # an NLOS-like bias on one satellite
    guess = truth + 5.0
    sigma = torch.full(pr.shape, 3.0, **f64)
    plain, _ = weighted_ls_step(_t(sat_pos), _t(pr), _t(mask), _t(guess), sigma)
    big = sigma.clone()
    big[:, 2] = 1e6
    down, _ = weighted_ls_step(_t(sat_pos), _t(pr), _t(mask), _t(guess), big)
    without = mask.copy()
    without[:, 2] = False
    dropped, _ = weighted_ls_step(_t(sat_pos), _t(pr), _t(without), _t(guess), sigma)
    np.testing.assert_allclose(down.numpy(), dropped.numpy(), atol=1e-3)
    err = lambda p: np.linalg.norm(p.numpy() - truth, axis=1)          # noqa: E731
    assert np.median(err(plain)) > 3 * np.median(err(down))          # the bias hurt; the weight removed it
    bias = torch.zeros(pr.shape, **f64)
    bias[:, 2] = 100.0
    unbiased, _ = weighted_ls_step(_t(sat_pos), _t(pr - np.where(np.arange(pr.shape[1]) == 2, 100.0, 0.0)),
                                   _t(mask), _t(guess), sigma)
    with_bias, _ = weighted_ls_step(_t(sat_pos), _t(pr), _t(mask), _t(guess), sigma, bias)
    np.testing.assert_allclose(with_bias.numpy(), unbiased.numpy(), atol=1e-6)


def test_sat_nll_is_smallest_at_the_true_sigma_and_bias():
    S, true_sigma = 12, 4.0
    sat_pos, pr, mask, truth = _epochs(B=3000, S=S, sigma=true_sigma, seed=7)
    args = (_t(sat_pos), _t(pr), _t(mask), _t(truth))
    zero = torch.zeros(pr.shape, **f64)
    scan = np.linspace(2.0, 8.0, 121)
    nll = [float(sat_nll(*args, torch.full(pr.shape, s, **f64), zero)) for s in scan]
    best = scan[int(np.argmin(nll))]
    # the clock is profiled out, so the minimum sits at sigma * sqrt((S-1)/S) (one dof per epoch spent)
    assert best == pytest.approx(true_sigma * np.sqrt((S - 1) / S), rel=0.03), best
    assert nll[0] > min(nll) + 0.1 and nll[-1] > min(nll) + 0.1
    # a biased slot: the NLL is lower when the bias head names the bias
    pr_b = pr.copy()
    pr_b[:, 0] += 60.0
    args_b = (_t(sat_pos), _t(pr_b), _t(mask), _t(truth))
    sig = torch.full(pr.shape, true_sigma, **f64)
    named = zero.clone()
    named[:, 0] = 60.0
    assert float(sat_nll(*args_b, sig, named)) < float(sat_nll(*args_b, sig, zero)) - 1.0
    assert float(sat_nll(*args_b, sig, named)) == pytest.approx(float(sat_nll(*args, sig, zero)), abs=1e-9)


# ---------------------------------------------------------------------------------------- (4) the guard
def test_guard_ranges_out_of_range_slots_and_trust():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(500, 8, 6, generator=g)
    mask = torch.ones(500, 8, dtype=torch.bool)
    mask[:, 6:] = False
    x[~mask] = 1e6                                               # padding never enters the ranges
    r = input_ranges(x, mask)
    assert len(r["lo"]) == len(r["hi"]) == 6 and all(-5 < lo < -2 for lo in r["lo"])
    xn, m = x.numpy(), mask.numpy()
    inside = slot_out_of_range(np.clip(xn, -1, 1), m, r)
    assert not inside.any()
    np.testing.assert_array_equal(trust(inside, m), 1.0)
    far = np.clip(xn, -1, 1)
    far[:, :5, 0] = 50.0                                         # 5 of 6 real slots: residual far outside
    far[:, :, 1:4] = 50.0                                        # line-of-sight channels are never checked
    oor = slot_out_of_range(far, m, r)
    assert oor[:, :5].all() and not oor[:, 5:].any()
    np.testing.assert_array_equal(trust(oor, m), 0.0)
    # just inside the widened range is in; share 2 of 6 (0.33) is between full and none trust
    edge = np.clip(xn, -1, 1)
    width = r["hi"][0] - r["lo"][0]
    edge[:, :2, 0] = r["hi"][0] + 0.5 * MARGIN * width
    assert not slot_out_of_range(edge, m, r).any()
    edge[:, :2, 0] = r["hi"][0] + 2.0 * MARGIN * width
    t = trust(slot_out_of_range(edge, m, r), m)
    np.testing.assert_allclose(t, (0.5 - 2 / 6) / 0.4)
    assert not slot_out_of_range(far, m, None).any()             # no ranges (old checkpoints): no guard
    # satellites of signals the network cannot read count as out of range: 6 read + 6 unseen -> none,
    # 6 read + 1 unseen -> share 1/7
    np.testing.assert_array_equal(trust(inside, m, np.full(500, 6)), 0.0)
    np.testing.assert_allclose(trust(inside, m, np.full(500, 1)), (0.5 - 1 / 7) / 0.4)


class _HeadNet(nn.Module):
    """Correction (1, 1, 1) * out_scale, unit variance, per-satellite head log-scale 0 and bias 0."""

    def forward(self, x, mask):
        B, S = x.shape[:2]
        return torch.ones(B, 3), torch.zeros(B, 3), torch.zeros(B, S, 2)


@pytest.mark.parametrize("output", ["wls", "correction"])
def test_corrector_shrinks_to_the_guess_where_inputs_leave_the_training_range(output):
    tr = toy_trace(15, seed=2)
    init = tr.truth + np.array([7.0, -3.0, 4.0])
    valid = np.ones(15, bool)
    cfg = TrainConfig(output=output).to_checkpoint_config()
    free = Corrector(_HeadNet(), dict(cfg, input_ranges=None)).predict(tr, init, valid)
    assert free.valid.all() and (free.trust == 1).all()
    assert np.linalg.norm(free.mean_ecef - init, axis=1).min() > 1.0      # without the guard it corrects
    assert np.isfinite(free.sigma[tr.mask]).all()
    n = FeatureConfig.from_dict(cfg["features"]).n_inputs
    tiny = {"lo": [5.0] * n, "hi": [5.0 + 1e-6] * n}                      # nothing real fits in it
    c = Corrector(_HeadNet(), dict(cfg, input_ranges=tiny)).predict(tr, init, valid)
    assert c.valid.all()
    np.testing.assert_array_equal(c.trust, 0.0)
    np.testing.assert_allclose(c.mean_ecef, init, atol=1e-9)
    np.testing.assert_allclose(c.corr_ned, 0.0, atol=1e-12)
    # version 3: every slot handed to the physical model (sigma from the report and elevation, no bias)
    m = tr.mask
    assert np.isfinite(c.sigma[m]).all() and (c.bias[m] == 0).all() and np.isnan(c.sigma[~m]).all()
    assert (c.sigma[m] >= np.sqrt(tr.pr_sigma[m] ** 2 + 1.0) - 1e-9).all()
    assert c.info["meas_out_of_range"] == int(m.sum()) == c.info["meas_asked"]
    assert c.info["epochs_guard_off"] == 15
    # what the shrink left out is carried by the covariance
    assert (np.diagonal(c.cov_ned, axis1=1, axis2=2) >= np.diagonal(free.cov_ned, axis1=1, axis2=2) - 1e-9).all()
    # a wide range: full trust, the same answer as without a guard
    wide = {"lo": [-1e6] * n, "hi": [1e6] * n}
    w = Corrector(_HeadNet(), dict(cfg, input_ranges=wide)).predict(tr, init, valid)
    np.testing.assert_allclose(w.mean_ecef, free.mean_ecef)


# ---------------------------------------------------------------------- (5) slot noise in the fused graph
@pytest.fixture(scope="module")
def biased_trace():
    """A toy drive whose satellite in slot 2 carries +100 m on every epoch."""
    tr = toy_trace(60, seed=11, n_sats=(8, 8), sigma=2.0)
    tr.pr[:, 2] += 100.0
    return tr, solve_wls(tr, robust=False)        # plain: the fault must reach the graph


def _h_err(tr, res):
    e = ecef2ned_vec(res.pos - tr.truth, tr.truth)
    return np.linalg.norm(e[:, :2], axis=1)[res.valid]


def test_fuse_with_slot_noise_downweights_a_biased_satellite(biased_trace):
    """Without a robust loss (isolating the slot noise) the +100 m satellite pulls the plain graph off;
    a huge sigma on it, or its bias named, brings the solution back. With the default (Cauchy) graph the
    provider does no harm."""
    from fusion.estimate.graph.config import GraphConfig
    from fusion.estimate.graph.fuse import fuse
    from fusion.run_types import RunOptions

    tr, wls = biased_trace
    cfg = GraphConfig(robust="none", unlearned_robust="none")     # the sigmas alone
    seen = {}

    def provider(trace, init_pos, valid):
        seen["shape"], seen["valid"] = init_pos.shape, valid.copy()
        sigma = np.where(trace.mask, 2.0, np.nan)
        sigma[:, 2] = 1e4
        return sigma, np.zeros(trace.mask.shape)

    base = fuse(tr, wls, RunOptions(), cfg=cfg, want_cov=False)
    noisy = fuse(tr, wls, RunOptions(), cfg=cfg, want_cov=False, slot_noise=provider)
    assert seen["shape"] == (60, 3) and seen["valid"].all()
    assert base.valid.all() and noisy.valid.all()
    assert noisy.info["learned_sigmas"] == int(tr.mask.sum())
    e0, e1 = np.median(_h_err(tr, base)), np.median(_h_err(tr, noisy))
    assert e1 < 0.6 * e0, (e0, e1)

    # the provider's bias is subtracted: naming the +100 m is about as good as dropping the satellite
    def bias_provider(trace, init_pos, valid):
        bias = np.zeros(trace.mask.shape)
        bias[:, 2] = 100.0
        return np.where(trace.mask, 2.0, np.nan), bias

    named = fuse(tr, wls, RunOptions(), cfg=cfg, want_cov=False, slot_noise=bias_provider)
    assert np.median(_h_err(tr, named)) < 0.6 * e0
    robust = fuse(tr, wls, RunOptions(), want_cov=False)
    robust_noisy = fuse(tr, wls, RunOptions(), want_cov=False, slot_noise=provider)
    assert np.median(_h_err(tr, robust_noisy)) <= np.median(_h_err(tr, robust)) + 0.5


def test_fuse_with_a_provider_without_opinion_is_the_plain_graph(biased_trace):
    from fusion.estimate.graph.fuse import fuse
    from fusion.run_types import RunOptions

    tr, wls = biased_trace

    def nothing(trace, init_pos, valid):
        return np.full(trace.mask.shape, np.nan), np.full(trace.mask.shape, np.nan)

    base = fuse(tr, wls, RunOptions(), want_cov=False)
    same = fuse(tr, wls, RunOptions(), want_cov=False, slot_noise=nothing)
    np.testing.assert_array_equal(same.valid, base.valid)
    np.testing.assert_allclose(same.pos, base.pos, atol=1e-9)


def test_fused_mode_switches_each_learned_part(tmp_path):
    """RunOptions.learned_prior / learned_sigmas / learned_bias switch the network's prior, its slot noise and
    that noise's bias in the fused mode; with the prior and the slot noise off it is the no-prior graph, and
    dnn_output picks the dnn mode's output."""
    from fusion.estimate.graph.fuse import estimate_fused_nodnn
    from fusion.run_types import RunOptions
    from learned.modes import estimate_dnn, estimate_fused

    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "u.pt", SetTransformer(), TrainConfig().to_checkpoint_config())
    tr = toy_trace(30, seed=4, n_sats=(7, 7))
    wls = solve_wls(tr)
    nodnn = estimate_fused_nodnn(tr, wls, RunOptions())
    off = estimate_fused(tr, wls, RunOptions(weights=ckpt, learned_prior=False, learned_sigmas=False))
    np.testing.assert_allclose(off.pos, nodnn.pos, atol=1e-9)
    sig = estimate_fused(tr, wls, RunOptions(weights=ckpt, learned_prior=False))
    assert sig.info["learned_sigmas"] > 0 and sig.info.get("priors_used", 0) == 0
    assert np.abs(sig.pos - nodnn.pos).max() > 1e-3
    pri = estimate_fused(tr, wls, RunOptions(weights=ckpt, learned_sigmas=False))
    assert pri.info["priors_used"] > 0 and pri.info.get("learned_sigmas", 0) == 0
    # the sigmas without the biases: as many learned sigmas, another solution
    unbiased = estimate_fused(tr, wls, RunOptions(weights=ckpt, learned_prior=False, learned_bias=False))
    assert unbiased.info["learned_sigmas"] == sig.info["learned_sigmas"]
    assert np.abs(unbiased.pos - sig.pos).max() > 1e-3 and np.abs(unbiased.pos - nodnn.pos).max() > 1e-3
    d_w = estimate_dnn(tr, wls, RunOptions(weights=ckpt))
    d_c = estimate_dnn(tr, wls, RunOptions(weights=ckpt, dnn_output="correction"))
    assert d_w.info["output"] == "wls" and d_c.info["output"] == "correction"
    assert np.abs(d_w.pos - d_c.pos)[d_w.valid & d_c.valid].max() > 1e-3


def test_build_samples_numbers_traces_and_split_traces_holds_out_whole_ones():
    import numpy as np
    from learned.data import build_samples, split_traces
    from learned.toy import toy_dataset
    s = build_samples(toy_dataset(5, 30, seed=0))
    assert sorted(set(s.trace.tolist())) == [0, 1, 2, 3, 4]
    tr, va = split_traces(s, 0.2, np.random.default_rng(0))
    assert len(va) > 0 and len(tr) > 0
    assert not set(tr.trace.tolist()) & set(va.trace.tolist())
    # traces with no sample left (every epoch dropped) are never the validation ones
    three = s.subset(np.flatnonzero(s.trace < 3))
    three.names = s.names
    for seed in range(20):
        tr, va = split_traces(three, 0.2, np.random.default_rng(seed))
        assert len(va) > 0 and len(tr) > 0 and set(va.trace.tolist()) <= {0, 1, 2}
