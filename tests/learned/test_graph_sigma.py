"""The learned pseudorange sigmas as the graph takes them: the head's multiplier raised to
``GraphConfig.learned_sigma_power`` (learned.infer.graph_sigma), from the one network pass."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.wls import solve_wls
from fusion.options import RunOptions
from learned.features import CHANNELS, FeatureConfig
from learned.infer import Corrector, graph_sigma
from learned.toy import toy_trace


def test_graph_sigma_raises_the_multiplier_and_keeps_no_opinion():
    base = np.array([[2.0, 4.0, np.nan]])
    sigma = np.array([[4.0, 2.0, np.nan]])           # multipliers 2 and 0.5
    assert graph_sigma(sigma, base, 1.0) is sigma
    np.testing.assert_allclose(graph_sigma(sigma, base, 2.0)[0, :2], [8.0, 1.0])
    np.testing.assert_allclose(graph_sigma(sigma, base, 0.0)[0, :2], [2.0, 4.0])   # the physical model
    assert np.isnan(graph_sigma(sigma, base, 2.0)[0, 2])
    # the raised multiplier keeps the head's clamp: e^(3 * 3) would be 8103 x
    np.testing.assert_allclose(graph_sigma(np.array([np.exp(3.0)]), np.array([1.0]), 3.0), [np.exp(4.0)])


class _SlotNet:
    """Log-multiplier +0.5 on even slots and -0.5 on odd ones, no bias, no correction (numpy interface)."""

    def __call__(self, x, mask):
        sat = np.zeros(x.shape[:2] + (2,), np.float32)
        sat[:, 0::2, 0], sat[:, 1::2, 0] = 0.5, -0.5
        return np.zeros((x.shape[0], 3), np.float32), np.zeros((x.shape[0], 3), np.float32), sat


def _corrector():
    from learned.train import TrainConfig
    cfg = TrainConfig(features=FeatureConfig(inputs=tuple(CHANNELS))).to_checkpoint_config()
    return Corrector(_SlotNet(), dict(cfg, input_ranges=None))


def test_the_fused_mode_takes_the_configured_power_from_one_pass():
    from learned.modes import graph_inputs
    tr = toy_trace(20, seed=3, n_sats=(8, 8))
    wls = solve_wls(tr)
    corr = _corrector()
    c = corr.predict(tr, wls.pos, wls.valid)
    ok = np.isfinite(c.sigma)
    assert ok.sum() > 100
    mult = c.sigma[ok] / c.base[ok]
    assert np.allclose(np.sort(np.unique(np.round(mult, 6))), np.round(np.exp([-0.5, 0.5]), 6))
    for power in (1.0, 2.5):
        opts = RunOptions(graph=replace(GraphConfig(), learned_sigma_power=power))
        g = graph_inputs(corr, tr, wls, opts, at=wls.pos)
        np.testing.assert_allclose(g.pr_sigma[ok], c.base[ok] * mult ** power)
        np.testing.assert_array_equal(g.pr_bias[ok], c.bias[ok])


def test_pseudorange_factors_take_the_power_when_asked():
    import gtsam
    from learned.factor import learned_pseudorange_factors
    tr = toy_trace(5, seed=4, n_sats=(7, 7))
    wls = solve_wls(tr)
    corr = _corrector()
    keys = [gtsam.symbol("x", k) for k in range(5)], [gtsam.symbol("c", k) for k in range(5)]
    _, one = learned_pseudorange_factors(corr, tr, wls.pos, wls.valid, *keys)      # the head as trained
    _, three = learned_pseudorange_factors(corr, tr, wls.pos, wls.valid, *keys, sigma_power=3.0)
    base = corr.predict(tr, wls.pos, wls.valid).base
    ok = np.isfinite(base) & tr.mask
    np.testing.assert_allclose(three[ok], base[ok] * (one[ok] / base[ok]) ** 3)


def test_the_graph_defaults_are_the_ones_chosen():
    """The settings experiments/results/sigma_power.md chose (a change needs that file rerun)."""
    cfg = GraphConfig()
    assert (cfg.learned_sigma_power, cfg.robust_k, cfg.rate_robust_k) == (4.0, 1.5, 2.0)
