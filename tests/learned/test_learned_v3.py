"""Feature version 3: inputs every log format carries, a guard per measurement and feature, feature
dropout in training, and the one network pass the graph takes (Corrector.graph_inputs)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.estimate.wls import solve_wls
from fusion.trace import SIGNALS
from learned.context import slot_context
from learned.features import CHANNELS, FeatureConfig, context_channels
from learned.guard import feature_guard
from learned.toy import toy_trace

CFG = FeatureConfig(inputs=tuple(CHANNELS))


def _two_signal_trace(isb_m=37.0, n=30, seed=4):
    """A toy drive whose slots 0-2 are Galileo E1 with a +isb_m clock offset, the rest GPS L1."""
    tr = toy_trace(n, seed=seed, n_sats=(9, 9), sigma=1.0)
    tr.signal[:, :3] = SIGNALS.index("GAL_E1")
    tr.pr[:, :3] += isb_m
    return tr


def test_inter_system_bias_is_recovered_and_removed():
    tr = _two_signal_trace()
    ctx = slot_context(tr, solve_wls(tr, robust=False)).as_dict()
    np.testing.assert_allclose(ctx["isb"][:, :3], 37.0, atol=1.5)
    np.testing.assert_array_equal(ctx["isb"][:, 3:][tr.mask[:, 3:]], 0.0)
    one = toy_trace(30, seed=4, n_sats=(9, 9))
    assert (slot_context(one, solve_wls(one)).as_dict()["isb"] == 0).all()     # one signal: no bias


def test_code_minus_doppler_is_small_when_consistent_and_shows_a_jump():
    tr = toy_trace(20, seed=5, n_sats=(7, 7), sigma=0.0)
    t = (tr.t_ms - tr.t_ms[0]) / 1000.0
    # pseudoranges changing at a constant rate per slot, and the Doppler saying so
    rate = np.linspace(-300.0, 300.0, 7)
    tr.pr[:] = tr.pr[:1] + rate * t[:, None]
    prr = np.broadcast_to(rate, tr.pr.shape).copy()
    tr = replace(tr, prr=prr, prr_sigma=np.full(prr.shape, 0.1), prr_ok=tr.mask.copy())
    wls = solve_wls(toy_trace(20, seed=5, n_sats=(7, 7)))
    ctx = slot_context(tr, wls).as_dict()
    assert not ctx["cmd_ok"][0].any() and ctx["cmd_ok"][1:].all()
    assert np.abs(ctx["cmd"]).max() < 1e-6
    tr.pr[10, 4] += 30.0                                                   # a reflection appears
    ctx = slot_context(tr, wls).as_dict()
    assert abs(ctx["cmd"][10, 4] - 30.0) < 1e-6 and abs(ctx["cmd"][11, 4] + 30.0) < 1e-6
    bare = toy_trace(5, seed=1)
    assert (slot_context(bare, solve_wls(bare)).as_dict()["cmd_ok"] == 0).all()     # no Doppler: missing


def _ranges(x, mask):
    """Training ranges of inputs x (N,S,F) the way input_ranges makes them (min / max here)."""
    v = x[mask]
    return {"lo": v.min(0).tolist(), "hi": v.max(0).tolist()}


def test_guard_reads_unseen_features_as_missing_and_unseen_signals_as_unknown():
    train = toy_trace(40, seed=6, n_sats=(8, 8))              # GPS L1, reported sigma, no C/N0
    ctx = slot_context(train, solve_wls(train)).as_dict()
    xt = np.concatenate([np.zeros(train.mask.shape + (4,), np.float32), context_channels(ctx, train.mask, CFG)], -1)
    ranges = _ranges(xt, train.mask)
    # a raw log: C/N0 present, a Galileo signal, no report
    raw = _two_signal_trace(0.0, 40, seed=6)
    raw = replace(raw, cn0=np.where(raw.mask, 38.0, 0.0), pr_sigma_ok=np.zeros(raw.mask.shape, bool))
    rctx = slot_context(raw, solve_wls(raw)).as_dict()
    x = np.concatenate([np.zeros(raw.mask.shape + (4,), np.float32), context_channels(rctx, raw.mask, CFG)], -1)
    missing, core, counts = feature_guard(x, raw.mask, ranges, CFG)
    m = raw.mask
    assert missing["cn0"][m].all() and counts["meas_cn0_unseen_in_training"] == m.sum()
    assert missing["signal"][:, :3][m[:, :3]].all() and not missing["signal"][:, 3:].any()
    assert missing["system"][:, :3][m[:, :3]].all()
    assert counts["meas_signal_unseen_in_training"] == counts["meas_signal_read_as_unknown"] == m[:, :3].sum()
    assert not core.any()                                   # their own residuals are in range: not handed off
    y = context_channels(rctx, m, CFG, missing)
    sl = CFG.slices()
    assert (y[..., sl["cn0"].start - 4:sl["cn0"].stop - 4] == 0).all()
    assert (y[..., sl["signal"].stop - 5][:, :3][m[:, :3]] == 1).all()       # Galileo reads as unknown
    x[5, 1, 0] = 1e3                                                        # a far residual: physical model
    _, core, counts = feature_guard(x, m, ranges, CFG)
    assert core[5, 1] and core.sum() == 1 and counts["meas_out_of_range"] == 1


class _ZeroNet:
    """Head log-multiplier 0, no bias, no correction (numpy interface of learned.npnet)."""

    def __call__(self, x, mask):
        return np.zeros((x.shape[0], 3), np.float32), np.zeros((x.shape[0], 3), np.float32), \
            np.zeros(x.shape[:2] + (2,), np.float32)


def _config(ranges=None):
    from learned.train import TrainConfig
    cfg = TrainConfig(features=CFG).to_checkpoint_config()
    return dict(cfg, input_ranges=ranges)


def test_raw_log_is_not_switched_off_and_graph_inputs_come_from_one_pass():
    from learned.infer import Corrector
    train = toy_trace(40, seed=6, n_sats=(8, 8))
    ctx = slot_context(train, solve_wls(train)).as_dict()
    feats = context_channels(ctx, train.mask, CFG)
    xt = np.concatenate([np.random.default_rng(0).normal(size=train.mask.shape + (4,)) * 3, feats], -1)
    raw = _two_signal_trace(25.0, 40, seed=6)
    raw = replace(raw, cn0=np.where(raw.mask, 38.0, 0.0), pr_sigma_ok=np.zeros(raw.mask.shape, bool))
    corr = Corrector(_ZeroNet(), _config(_ranges(xt, train.mask)))
    wls = solve_wls(raw)
    calls = []
    orig = corr.predict

    def count(*a, **k):
        calls.append(1)
        return orig(*a, **k)
    corr.predict = count
    g = corr.graph_inputs(raw, wls.pos, wls.valid)
    assert len(calls) == 1
    E, S = raw.mask.shape
    assert g.prior_mean.shape == (E, 3) and g.prior_cov.shape == (E, 3, 3) and g.pr_sigma.shape == (E, S)
    assert g.doppler_noise is None                      # this checkpoint has no Doppler head
    # every epoch asked, none switched off; every slot (Galileo too) has a sigma: the physical model from C/N0
    assert g.prior_ok[wls.valid].all() and g.info["epochs_guard_off"] == 0
    assert np.isfinite(g.pr_sigma[raw.mask & wls.valid[:, None]]).all()
    assert g.info["meas_cn0_unseen_in_training"] > 0 and g.info["meas_signal_unseen_in_training"] > 0
    # the inter-system bias was removed: the learned position is near the truth, not pulled by 25 m
    err = np.linalg.norm(g.prior_mean[g.prior_ok] - raw.truth[g.prior_ok], axis=1)
    assert np.median(err) < 5.0


def test_feature_dropout_drops_the_report_per_sample_and_signals_per_slot():
    torch = pytest.importorskip("torch")
    from learned.data import build_samples
    from learned.train import TrainConfig, feature_dropout, sample_tensors
    tr = toy_trace(200, seed=7, n_sats=(8, 8))
    s = build_samples([tr])
    cfg = TrainConfig(features=CFG, dropout={"pr_sigma": 0.5, "signal": 0.2})
    t = sample_tensors(s, CFG, "cpu")
    g = torch.Generator().manual_seed(0)
    d = feature_dropout(t, cfg, g)
    sl = CFG.slices()
    flag = d["extra"][..., sl["pr_sigma"].start - 4 + 1]
    m = t["mask"]
    dropped = (flag == 0) & m
    per_sample = dropped.any(1)
    assert 0.35 < per_sample.float().mean() < 0.65
    assert torch.equal(dropped.any(1), (dropped | ~m).all(1) & m.any(1))        # whole samples
    assert torch.allclose(d["pr_sigma"][dropped], t["pr_sigma_alt"][dropped])
    assert torch.allclose(d["pr_sigma"][~dropped & m], t["pr_sigma"][~dropped & m])
    unknown = d["extra"][..., sl["signal"].stop - 5][m]
    assert 0.1 < unknown.float().mean() < 0.3
    assert torch.equal(feature_dropout(t, TrainConfig(features=CFG, dropout={}), g)["extra"], t["extra"])


def test_signals_newer_than_the_network_read_as_unknown():
    """BeiDou B1C / B2a (appended to SIGNALS after the network's one-hots were fixed) read as an unknown
    signal of an unknown system, like a signal unseen in training."""
    tr = toy_trace(10, seed=3, n_sats=(8, 8))
    tr.signal[:, :2] = SIGNALS.index("BDS_B1C")
    tr.signal[:, 2] = SIGNALS.index("BDS_B2A")
    ctx = slot_context(tr, solve_wls(tr)).as_dict()
    y = context_channels(ctx, tr.mask, CFG)
    sl = CFG.slices()
    for group in ("signal", "system"):
        onehot = y[..., sl[group].start - 4:sl[group].stop - 4]
        assert (onehot[:, :3, -1] == 1).all() and (onehot[:, :3, :-1] == 0).all()
        assert (onehot[:, 3:, -1] == 0).all()
    x = np.concatenate([np.zeros(tr.mask.shape + (4,), np.float32), y], -1)
    ranges = {"lo": x[tr.mask].min(0).tolist(), "hi": x[tr.mask].max(0).tolist()}
    ranges["hi"][sl["signal"].stop - 1] = 1.0               # feature dropout showed the network "unknown"
    _, core, counts = feature_guard(x, tr.mask, ranges, CFG)
    assert counts["meas_signal_read_as_unknown"] == tr.mask[:, :3].sum() and not core.any()
