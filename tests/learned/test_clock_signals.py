"""Experiment-only true-clock features (paper-leak reproduction) and the checkpoint's signal set."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fusion.errors import CheckpointError, DataError
from fusion.geometry import line_of_sight
from fusion.trace import SIGNALS
from learned.checkpoint import save_checkpoint
from learned.features import FeatureConfig, features_numpy, features_torch
from learned.infer import Corrector
from learned.modes import estimate_dnn
from learned.model import build_model
from learned.toy import toy_trace
from learned.train import TrainConfig, train


def _consistent_epochs(seed=0, B=6, S=7, clock=123_456.0):
    """pr = Sagnac range from the true position + clock (no noise): sat_pos, pr, mask, truth, clock."""
    tr = toy_trace(B, seed=seed, n_sats=(S, S))
    rng, _ = line_of_sight(tr.sat_pos, tr.truth)
    clk = clock + np.arange(B) * 10.0
    return tr.sat_pos, rng + clk[:, None], tr.mask, tr.truth, clk


def test_given_clock_features_remove_exactly_that_clock():
    sat_pos, pr, mask, truth, clk = _consistent_epochs()
    cfg = FeatureConfig(clock="given")
    x, used = features_numpy(sat_pos, pr, mask, truth, cfg, clk)
    np.testing.assert_allclose(used, clk)
    np.testing.assert_allclose(x[..., 0][mask], 0.0, atol=1e-6)    # true clock at the truth: zero residuals
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)
    xt, _ = features_torch(t(sat_pos), t(pr), torch.as_tensor(mask), t(truth), cfg, t(clk))
    np.testing.assert_allclose(xt.numpy(), x, atol=1e-5)
    # A guess offset straight down: with the true clock removed the residuals all move with the
    # vertical (common mode); the median clock absorbs most of that, which is why the leak helps D.
    guess = truth + 20.0 * truth / np.linalg.norm(truth, axis=1, keepdims=True) * -1.0
    xg, _ = features_numpy(sat_pos, pr, mask, guess, cfg, clk)
    xm, _ = features_numpy(sat_pos, pr, mask, guess, FeatureConfig())
    assert np.abs(xg[..., 0][mask]).mean() > 3 * np.abs(xm[..., 0][mask]).mean()


def test_clock_mode_errors_and_config_round_trip():
    sat_pos, pr, mask, truth, clk = _consistent_epochs()
    with pytest.raises(ValueError, match="needs a per-sample clock"):
        features_numpy(sat_pos, pr, mask, truth, FeatureConfig(clock="given"))
    with pytest.raises(ValueError, match="clock array was passed"):
        features_numpy(sat_pos, pr, mask, truth, FeatureConfig(), clk)
    with pytest.raises(ValueError, match="FeatureConfig.clock must be"):
        FeatureConfig(clock="truth")
    assert FeatureConfig.from_dict(FeatureConfig(clock="given").to_dict()).clock == "given"
    old = {k: v for k, v in FeatureConfig().to_dict().items() if k != "clock"}
    assert FeatureConfig.from_dict(old).clock == "median"          # checkpoints from before the option


def test_product_refuses_leaky_checkpoints(tmp_path):
    from fusion.run_types import RunOptions
    from fusion.estimate.wls import solve_wls
    cfg = TrainConfig(features=FeatureConfig(clock="given")).to_checkpoint_config()
    with pytest.raises(CheckpointError, match="true-clock leak"):
        Corrector(build_model("set"), cfg)
    path = save_checkpoint(tmp_path / "leak.pt", build_model("set"), cfg)
    tr = toy_trace(10, seed=1)
    with pytest.raises(CheckpointError, match="leak.pt.*experiment only"):
        estimate_dnn(tr, solve_wls(tr), RunOptions(weights=path))


def test_simulated_samples_carry_true_clock_and_training_needs_it(tmp_path):
    from learned.data import build_samples, simulated_samples_with_clock, split_random
    from fusion.sim.simulate import SimConfig, simulate_dataset
    s = simulated_samples_with_clock(2, 8, seed=5)
    res = simulate_dataset(2, 8, seed=5, config=SimConfig(), results=True)
    assert s.clock is not None and s.clock.shape == (len(s),)
    np.testing.assert_allclose(s.truth, np.concatenate([r.trace.truth for r in res])[:len(s)])
    # The true clock explains the raw residuals at the truth up to the 6 m noise (median over satellites).
    rng, _ = line_of_sight(s.sat_pos, s.truth)
    raw = np.where(s.mask, s.pr - rng - s.clock[:, None], np.nan)
    assert np.nanmedian(np.abs(raw)) < 15.0
    assert np.ptp(s.clock) > 0 and s.subset(np.array([0, 2])).clock.shape == (2,)
    # "given" training refuses samples without a clock (phone data, plain simulated traces).
    torch.set_num_threads(1)
    plain = build_samples([r.trace for r in res])
    tr, va = split_random(plain, 0.25, np.random.default_rng(0))
    with pytest.raises(DataError, match="needs samples with a true clock"):
        train(tr, va, TrainConfig(epochs=1, features=FeatureConfig(clock="given")), tmp_path / "x.pt",
              progress=False)
    tr, va = split_random(s, 0.25, np.random.default_rng(0))
    train(tr, va, TrainConfig(epochs=1, features=FeatureConfig(clock="given")), tmp_path / "g.pt", progress=False)
    with pytest.raises(CheckpointError, match="true-clock leak"):
        Corrector.load(tmp_path / "g.pt")


def _net():
    torch.manual_seed(0)
    return build_model("set")


def test_predict_uses_only_the_trained_signals():
    tr = toy_trace(20, seed=4, n_sats=(10, 10))
    glo = SIGNALS.index("GLO_G1")
    tr.signal[:, 6:] = glo                        # 4 of 10 slots are GLONASS (with a big inter-system offset)
    tr.pr[:, 6:] += 300.0
    init = tr.truth + 4.0
    valid = np.ones(20, bool)
    # feature version 2 (the previous release's weights) reads only its trained signals; version 3 reads
    # every signal on the reference clock (tests/test_learned_v3.py)
    base = TrainConfig(features=FeatureConfig(version=2)).to_checkpoint_config()
    assert base["signals"] == ["GPS_L1"]
    gps_only = tr.select_slots(tr.signal != glo)
    c = Corrector(_net(), base).predict(tr, init, valid)
    ref = Corrector(_net(), base).predict(gps_only, init, valid)
    # the network reads the six GPS slots alone; the four GLONASS satellites count against its trust
    # (share 0.4 of the epoch: trust (0.5 - 0.4) / 0.4), which shrinks the GPS-only correction
    np.testing.assert_allclose(ref.trust, 1.0)
    np.testing.assert_allclose(c.trust, 0.25)
    np.testing.assert_allclose(c.mean_ecef - init, 0.25 * (ref.mean_ecef - init), atol=1e-6)
    np.testing.assert_allclose(c.sigma[:, :6], ref.sigma, atol=1e-9)
    assert np.isnan(c.sigma[:, 6:]).all()
    # Checkpoints without the key are GPS L1; a checkpoint trained on both uses both.
    legacy = {k: v for k, v in base.items() if k != "signals"}
    np.testing.assert_allclose(Corrector(_net(), legacy).predict(tr, init, valid).mean_ecef, c.mean_ecef,
                               atol=1e-9)
    both = Corrector(_net(), dict(base, signals=["GPS_L1", "GLO_G1"])).predict(tr, init, valid)
    assert np.abs(both.mean_ecef - ref.mean_ecef).max() > 1e-3
    # Epochs with < 4 satellites of the trained signals are not solved (and counted).
    tr.signal[3, 3:6] = glo
    c = Corrector(_net(), base).predict(tr, init, valid)
    assert not c.valid[3] and c.n_too_few == 1
    with pytest.raises(CheckpointError, match="unknown training signal"):
        Corrector(_net(), dict(base, signals=["GPS_L9"]))


def test_compacting_slots_does_not_change_predictions():
    """Inference drops padding (fewer slots -> faster); the output must not depend on it."""
    from learned.features import compact_slots
    tr = toy_trace(15, seed=6, n_sats=(5, 9))
    init = tr.truth + 3.0
    valid = np.ones(15, bool)
    pad = lambda a, v: np.concatenate([np.full(a.shape[:1] + (4,) + a.shape[2:], v, a.dtype), a], 1)
    wide = tr.select(np.ones(15, bool))
    wide.sat_pos, wide.pr, wide.mask = pad(tr.sat_pos, 1e7), pad(tr.pr, 2e7), pad(tr.mask, False)
    wide.signal, wide.sat_id, wide.pr_sigma = pad(tr.signal, 0), pad(tr.sat_id, 0), pad(tr.pr_sigma, 1.0)
    from learned.features import CHANNELS
    for inputs in (("res", "los"), tuple(CHANNELS)):           # the paper's inputs, and every context channel
        cfg = TrainConfig(features=FeatureConfig(inputs=inputs)).to_checkpoint_config()
        net = lambda: (torch.manual_seed(0), build_model("set", d_in=cfg["model"]["hparams"]["d_in"]))[1]  # noqa: E731
        a = Corrector(net(), cfg).predict(tr, init, valid)
        b = Corrector(net(), cfg).predict(wide, init, valid)
        assert a.valid.all()
        np.testing.assert_allclose(b.mean_ecef, a.mean_ecef, atol=1e-6)
        np.testing.assert_allclose(b.cov_ecef, a.cov_ecef, rtol=1e-5)
        np.testing.assert_allclose(b.sigma[:, 4:], a.sigma, rtol=1e-5)          # per-slot outputs stay in place
        assert np.isnan(b.sigma[:, :4]).all()
    sp, pr, m = compact_slots(wide.sat_pos, wide.pr, wide.mask)
    assert m.shape[1] == tr.mask.sum(1).max() and (m.sum(1) == tr.mask.sum(1)).all()
    assert m[:, 0].all() and (pr[m] == tr.pr[tr.mask]).all()
