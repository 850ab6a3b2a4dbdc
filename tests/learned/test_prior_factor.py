"""The fused mode's learned prior widened where the pseudorange residuals exceed their model
(``GraphConfig.prior_factor_*``, learned.modes.prior_by_factor)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.errors import ConfigError
from fusion.estimate.graph.config import GraphConfig, load_graph_config
from fusion.estimate.graph.priors import LearnedGraphInputs
from fusion.eval.summary import learned_words
from fusion.options import RunOptions
from learned.infer import graph_sigma
from learned.modes import prior_by_factor, residual_factor, sigma_power_by_factor
from learned.toy import toy_trace

E = 40


@pytest.fixture(scope="module")
def noisy():
    """A toy trace whose pseudoranges fit their 6 m model in the first half and carry 60 m of extra noise in
    the second (a reflection-ridden stretch), with a prior of identity covariance at every epoch."""
    tr = toy_trace(E, seed=3, n_sats=(8, 9))
    rng = np.random.default_rng(0)
    pr = tr.pr + np.where(np.arange(E)[:, None] >= E // 2, rng.normal(0.0, 60.0, tr.pr.shape), 0.0)
    tr = replace(tr, pr=pr)
    learned = LearnedGraphInputs(prior_mean=tr.truth.copy(), prior_cov=np.tile(np.eye(3), (E, 1, 1)),
                                 prior_ok=np.ones(E, bool), info={"learned_epochs_asked": E})
    return tr, learned


def _opts(**graph) -> RunOptions:
    return RunOptions(graph=replace(GraphConfig(), prior_factor_window_s=5.0, **graph))


def _widen(tr, learned, at, opts):
    return prior_by_factor(learned, residual_factor(tr, at, opts), opts)


def test_the_prior_widens_where_the_residuals_exceed_their_model_and_only_there(noisy):
    tr, learned = noisy
    out = _widen(tr, learned, tr.truth, _opts())
    scale = out.prior_cov[:, 0, 0]
    # isotropic: the covariance is the network's times one number per epoch
    np.testing.assert_allclose(out.prior_cov, scale[:, None, None] * np.eye(3))
    clean, bad = slice(0, E // 2 - 3), slice(E // 2 + 3, E)     # away from the window's overlap
    assert np.all(scale[clean] < 2.0)
    assert np.all(scale[bad] > 1e3)           # ~ (60 / 6)^2 = 100 times the variance, cubed
    assert out.info["learned_prior_widened"] == int(np.sum(scale > 1))
    assert out.info["learned_prior_factor_p50"] > 1.0
    # the prior's mean and the network's other outputs are untouched, and so is the input
    assert out.prior_mean is learned.prior_mean and out.prior_ok is learned.prior_ok
    np.testing.assert_array_equal(learned.prior_cov, np.tile(np.eye(3), (E, 1, 1)))


def test_a_higher_power_widens_more_and_power_zero_or_the_incremental_smoother_leaves_it(noisy):
    tr, learned = noisy
    s1 = _widen(tr, learned, tr.truth, _opts(prior_factor_power=1.0)).prior_cov[:, 0, 0]
    s3 = _widen(tr, learned, tr.truth, _opts(prior_factor_power=3.0)).prior_cov[:, 0, 0]
    np.testing.assert_allclose(s3, s1 ** 3)
    assert _widen(tr, learned, tr.truth, _opts(prior_factor_power=0.0)) is learned
    assert _widen(tr, learned, tr.truth, _opts(incremental=True)) is learned
    assert _widen(tr, replace(learned, prior_cov=None, prior_mean=None, prior_ok=None), tr.truth,
                           _opts()).prior_cov is None


def test_a_higher_reference_factor_widens_fewer_epochs(noisy):
    tr, learned = noisy
    low = _widen(tr, learned, tr.truth, _opts(prior_factor_ref=1.0)).info["learned_prior_widened"]
    high = _widen(tr, learned, tr.truth, _opts(prior_factor_ref=1e6)).info["learned_prior_widened"]
    assert low >= E // 2 and high == 0


def test_the_summary_says_how_many_epochs_were_widened():
    words = learned_words({"learned_epochs_asked": 10, "learned_prior_widened": 7, "learned_prior_factor_p50": 6.1})
    assert "prior widened in 7 epochs" in words and "6.10" in words
    assert "prior widened" not in learned_words({"learned_epochs_asked": 10})


def test_the_settings_are_checked_with_a_one_line_error(tmp_path):
    g = GraphConfig()
    assert (g.prior_factor_power, g.prior_factor_ref, g.prior_factor_window_s) == (3.0, 1.0, 300.0)
    for line in ("prior_factor_power = -1.0", "prior_factor_ref = 0.0", "prior_factor_window_s = 0.0"):
        f = tmp_path / "g.toml"
        f.write_text(line + "\n")
        with pytest.raises(ConfigError, match=line.split()[0]):
            load_graph_config(f)
    f = tmp_path / "off.toml"
    f.write_text("prior_factor_power = 0.0\n")
    assert load_graph_config(f).prior_factor_power == 0.0


def test_the_sigma_power_rises_with_the_factor_from_one_to_its_high_point(noisy):
    tr, _ = noisy
    opts = _opts(learned_sigma_power=3.0, learned_sigma_power_high=5.0, learned_sigma_power_f_high=4.0)
    F = np.array([0.3, 1.0, 2.0, 4.0, 50.0])
    np.testing.assert_allclose(sigma_power_by_factor(F, opts)[:, 0], [3.0, 3.0, 4.0, 5.0, 5.0])
    # on the toy trace: the clean half keeps the low power, the noisy half takes the high one
    power = sigma_power_by_factor(residual_factor(tr, tr.truth, opts), opts)
    assert power.shape == (E, 1)
    assert np.all(power[: E // 2 - 3] < 3.5) and np.all(power[E // 2 + 3:] == 5.0)
    # equal powers, or no factor (the incremental smoother), give the one number
    assert sigma_power_by_factor(F, _opts(learned_sigma_power=4.0, learned_sigma_power_high=4.0)) == 4.0
    assert residual_factor(tr, tr.truth, _opts(incremental=True)) is None
    # nothing reads the factor with the widening and the ramp both off: it is not computed
    assert residual_factor(tr, tr.truth, _opts(prior_factor_power=0.0)) is None
    assert sigma_power_by_factor(None, opts) == 3.0


def test_a_per_epoch_power_raises_each_epochs_multiplier_by_its_own_power():
    base = np.full((2, 3), 6.0)
    sigma = base * np.array([[2.0, 0.5, np.nan], [2.0, 0.5, 1.0]])
    out = graph_sigma(sigma, base, np.array([[1.0], [3.0]]))
    np.testing.assert_allclose(out[0, :2], sigma[0, :2])
    np.testing.assert_allclose(out[1], base[1] * np.array([8.0, 0.125, 1.0]))
    assert np.isnan(out[0, 2])
    np.testing.assert_allclose(graph_sigma(sigma, base, np.ones((2, 1))), sigma)


def test_the_ramps_high_point_must_lie_above_one(tmp_path):
    f = tmp_path / "g.toml"
    f.write_text("learned_sigma_power_high = 5.0\nlearned_sigma_power_f_high = 2.0\n")
    g = load_graph_config(f)
    assert (g.learned_sigma_power, g.learned_sigma_power_high, g.learned_sigma_power_f_high) == (4.0, 5.0, 2.0)
    f.write_text("learned_sigma_power_f_high = 1.0\n")
    with pytest.raises(ConfigError, match="learned_sigma_power_f_high.*> 1"):
        load_graph_config(f)
