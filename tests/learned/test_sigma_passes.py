"""The fused mode's further network passes for the pseudorange sigmas (``GraphConfig.learned_sigma_passes``,
learned.modes.sigmas_again): where each pass is asked, what it replaces and what it keeps."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.errors import ConfigError
from fusion.estimate.graph.config import GraphConfig, load_graph_config
from fusion.estimate.graph.fuse import learned_guess_and_start, solve_graph
from fusion.estimate.wls import solve_wls
from fusion.options import RunOptions
from learned.features import CHANNELS, FeatureConfig
from learned.infer import Corrector
from learned.modes import graph_inputs, sigmas_again
from learned.toy import toy_trace


class _ResidualNet:
    """Log-multiplier tanh(first input / 10) per slot (it reads the residual channel, so a pass at
    another guess answers differently), a constant bias and no correction (numpy interface)."""

    def __call__(self, x, mask):
        sat = np.zeros(x.shape[:2] + (2,), np.float32)
        sat[..., 0] = np.tanh(x[..., 0] / 10.0)
        sat[..., 1] = 0.3
        return np.zeros((x.shape[0], 3), np.float32), np.zeros((x.shape[0], 3), np.float32), sat


class _Recording:
    """A corrector that remembers where it was asked."""

    def __init__(self, corrector):
        self.corrector, self.asked = corrector, []

    def graph_inputs(self, trace, init_pos, valid, **kw):
        self.asked.append(np.array(init_pos, copy=True))
        return self.corrector.graph_inputs(trace, init_pos, valid, **kw)


@pytest.fixture(scope="module")
def case():
    from learned.train import TrainConfig
    cfg = TrainConfig(features=FeatureConfig(inputs=tuple(CHANNELS))).to_checkpoint_config()
    corrector = Corrector(_ResidualNet(), dict(cfg, input_ranges=None))
    tr = toy_trace(25, seed=5, n_sats=(8, 9), bias=True)
    return corrector, tr, solve_wls(tr)


def _passes(n: int) -> RunOptions:
    return RunOptions(graph=replace(GraphConfig(), learned_sigma_passes=n))


def _ask(case, opts: RunOptions):
    """The fused mode's passes through a recording corrector: (recorder, first pass, its guess, the no-net
    start, sigmas_again's inputs, sigmas_again's start)."""
    corrector, tr, wls = case
    at, start = learned_guess_and_start(tr, wls, opts)
    rec = _Recording(corrector)
    first = graph_inputs(rec, tr, wls, opts, at)
    out, out_start = sigmas_again(rec, tr, wls, opts, first, at, start)
    return rec, first, at, start, out, out_start


def test_one_pass_leaves_the_inputs_and_the_start_as_they_are(case):
    rec, first, _, start, out, out_start = _ask(case, _passes(1))
    assert out is first and out_start is start and len(rec.asked) == 1


def test_the_second_pass_is_asked_at_the_solve_with_the_first_sigmas(case):
    corrector, tr, wls = case
    opts = _passes(2)
    rec, first, at, start, out, out_start = _ask(case, opts)
    assert len(rec.asked) == 2
    solved = solve_graph(tr, wls, opts, opts.graph, first, want_cov=False, start=start)
    ok = solved.valid
    assert ok.sum() > 20
    np.testing.assert_allclose(rec.asked[1][ok], solved.pos[ok], atol=1e-6)
    assert np.abs(rec.asked[1][ok] - at[ok]).max() > 0.1          # not the first guess again
    # the sigmas are the second pass's; the prior and the biases stay the first's
    again = corrector.graph_inputs(tr, rec.asked[1], tr.n_sats >= 1, elev_mask_deg=opts.elev_mask_deg,
                                   sigma_power=opts.graph.learned_sigma_power)
    np.testing.assert_array_equal(out.pr_sigma, again.pr_sigma)
    assert not np.allclose(np.nan_to_num(out.pr_sigma), np.nan_to_num(first.pr_sigma))
    assert out.pr_bias is first.pr_bias and out.prior_mean is first.prior_mean and out.prior_ok is first.prior_ok
    assert out.info["learned_sigma_passes"] == 2 and out_start is not start


def test_each_further_pass_asks_once_more_and_the_incremental_smoother_asks_once(case):
    for n in (2, 3):
        assert len(_ask(case, _passes(n))[0].asked) == n
    rec, first, _, _, out, _ = _ask(case, RunOptions(graph=replace(GraphConfig(), learned_sigma_passes=3,
                                                                     incremental=True)))
    assert out is first and len(rec.asked) == 1


def test_without_learned_sigmas_there_is_nothing_to_ask_again(case):
    rec, first, _, _, out, _ = _ask(case, replace(_passes(2), learned_sigmas=False))
    assert out is first and len(rec.asked) == 1


def test_the_setting_is_a_whole_number_of_at_least_one(tmp_path):
    assert GraphConfig().learned_sigma_passes == 2
    for value in ("0", "1.5"):
        f = tmp_path / "g.toml"
        f.write_text(f"learned_sigma_passes = {value}\n")
        with pytest.raises(ConfigError, match="learned_sigma_passes") as err:
            load_graph_config(f)
        assert str(f) in str(err.value) or f.name in str(err.value)
    f = tmp_path / "ok.toml"
    f.write_text("learned_sigma_passes = 3\n")
    assert load_graph_config(f).learned_sigma_passes == 3
