"""learned.factor: the learned correction as a GTSAM factor, and example 04 that composes it."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

from fusion.errors import GeometryError
from learned.factor import (learned_pose_translation_factor, learned_prior_factor, learned_pseudorange_factors,
                            one_epoch_trace)
from learned.toy import toy_trace

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory) -> Path:
    """An untrained, tiny set-transformer checkpoint: enough to exercise the factor plumbing."""
    torch = pytest.importorskip("torch")
    from learned.checkpoint import save_checkpoint
    from learned.features import FeatureConfig
    from learned.model import build_model

    torch.manual_seed(0)
    hp = dict(d_model=16, n_heads=2, dim_feedforward=16, n_encoder=1, n_decoder=1)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, build_model("set", **hp), {"model": {"kind": "set", "hparams": hp},
                                                      "features": FeatureConfig().to_dict()})
    return path


@pytest.fixture(scope="module")
def epoch():
    tr = toy_trace(3, seed=4, n_sats=(8, 8))
    return tr.sat_pos[0], tr.pr[0], tr.mask[0], tr.truth[0] + np.array([8.0, -5.0, 3.0])


def test_factor_matches_corrector_prediction(tiny_ckpt, epoch):
    from learned.infer import Corrector

    corr = Corrector.load(tiny_ckpt)
    sat_pos, pr, mask, guess = epoch
    key = gtsam.symbol("x", 7)
    factor, mean, cov = learned_prior_factor(corr, sat_pos, pr, mask, guess, key)
    c = corr.predict(one_epoch_trace(sat_pos, pr, mask), guess[None], np.ones(1, bool))
    np.testing.assert_allclose(mean, c.mean_ecef[0], atol=1e-9)
    np.testing.assert_allclose(cov, c.cov_ecef[0], atol=1e-9)
    assert isinstance(factor, gtsam.PriorFactorPoint3) and list(factor.keys()) == [key]
    v = gtsam.Values()
    v.insert(key, mean)
    assert factor.error(v) == pytest.approx(0.0, abs=1e-12)
    # the noise model is the network's covariance: error of a 1-sigma step along an eigenvector = 0.5
    w, U = np.linalg.eigh(cov)
    v2 = gtsam.Values()
    v2.insert(key, mean + np.sqrt(w[0]) * U[:, 0])
    assert factor.error(v2) == pytest.approx(0.5, rel=1e-6)


@pytest.fixture(scope="module")
def context_ckpt(tmp_path_factory) -> Path:
    """An untrained tiny checkpoint reading every context channel (reported sigma, C/N0, history)."""
    torch = pytest.importorskip("torch")
    from learned.checkpoint import save_checkpoint
    from learned.features import CHANNELS, FeatureConfig
    from learned.model import build_model

    torch.manual_seed(1)
    features = FeatureConfig(inputs=tuple(CHANNELS))
    hp = dict(d_model=16, n_heads=2, dim_feedforward=16, n_encoder=1, n_decoder=1, d_in=features.n_inputs)
    path = tmp_path_factory.mktemp("ckpt") / "context.pt"
    save_checkpoint(path, build_model("set", **hp), {"model": {"kind": "set", "hparams": hp},
                                                      "features": features.to_dict(), "output": "wls"})
    return path


def test_one_epoch_factor_with_the_phone_inputs_matches_the_trace_prediction(context_ckpt):
    """At a trace's first epoch (no history there either), the one-epoch API given the reported sigma,
    C/N0 and signals gives what predict(trace) gives; leaving the sigma out is refused, not defaulted."""
    from dataclasses import replace

    from learned.infer import Corrector

    tr = toy_trace(4, seed=5, n_sats=(9, 9))
    rng = np.random.default_rng(0)
    tr = replace(tr, pr_sigma=np.where(tr.mask, rng.uniform(2.0, 30.0, tr.mask.shape), 1.0),
                 cn0=np.where(tr.mask, rng.uniform(20.0, 45.0, tr.mask.shape), 0.0))
    guess = tr.truth + np.array([6.0, -4.0, 2.0])
    corr = Corrector.load(context_ckpt)
    whole = corr.predict(tr, guess, np.ones(tr.n_epochs, bool))
    _, mean, cov = learned_prior_factor(corr, tr.sat_pos[0], tr.pr[0], tr.mask[0], guess[0], gtsam.symbol("x", 0),
                                        pr_sigma=tr.pr_sigma[0], cn0=tr.cn0[0],
                                        signal=np.array(["GPS_L1"] * tr.mask.shape[1]))
    np.testing.assert_allclose(mean, whole.mean_ecef[0], atol=1e-6)
    # the network runs in float32: one epoch against a batch of four differs in the last digits (BLAS sums in
    # another order), by 2e-6 of an off-diagonal term on one machine; a wrong input moves it by percent
    np.testing.assert_allclose(cov, whole.cov_ecef[0], rtol=1e-5, atol=1e-6 * np.abs(whole.cov_ecef[0]).max())
    # the sigma is read: a different one moves the answer
    _, other, _ = learned_prior_factor(corr, tr.sat_pos[0], tr.pr[0], tr.mask[0], guess[0], 1,
                                       pr_sigma=np.ones(tr.mask.shape[1]), cn0=tr.cn0[0])
    assert np.abs(other - mean).max() > 1e-3
    with pytest.raises(GeometryError, match=r"context\.pt: reads each satellite's reported pseudorange sigma"):
        learned_prior_factor(corr, tr.sat_pos[0], tr.pr[0], tr.mask[0], guess[0], 1)
    with pytest.raises(GeometryError, match=r"pr_sigma must be finite and > 0 on real slots; slot 2"):
        learned_prior_factor(corr, tr.sat_pos[0], tr.pr[0], tr.mask[0], guess[0], 1,
                             pr_sigma=np.where(np.arange(tr.mask.shape[1]) == 2, 0.0, 3.0))
    with pytest.raises(GeometryError, match=r"unknown signal\(s\) \['GPS_L9'\]"):
        one_epoch_trace(tr.sat_pos[0], tr.pr[0], tr.mask[0], signal=np.array(["GPS_L9"] * tr.mask.shape[1]))


def test_factor_with_any_provider_and_padding():
    tr = toy_trace(1, seed=1, n_sats=(6, 6))
    sat_pos = np.vstack([tr.sat_pos[0], np.full((2, 3), np.nan)])    # padded slots may hold NaN
    pr = np.r_[tr.pr[0], np.nan, np.nan]
    mask = np.r_[tr.mask[0], False, False]
    seen = {}

    def provider(trace, init_pos, valid):
        seen["S"], seen["mask"] = trace.n_slots, trace.mask.copy()
        return init_pos + 1.0, np.tile(np.diag([4.0, 9.0, 16.0]), (1, 1, 1)), valid.copy()

    f, mean, cov = learned_prior_factor(provider, sat_pos, pr, mask, tr.truth[0], gtsam.symbol("x", 0))
    assert seen["S"] == 8 and seen["mask"][0].sum() == 6
    np.testing.assert_allclose(mean, tr.truth[0] + 1.0)
    np.testing.assert_allclose(cov, np.diag([4.0, 9.0, 16.0]))


def test_declined_epoch_and_bad_inputs_raise_geometry_error(tiny_ckpt, epoch):
    from learned.infer import Corrector

    corr = Corrector.load(tiny_ckpt)
    sat_pos, pr, mask, guess = epoch
    few = mask.copy()
    few[3:] = False
    with pytest.raises(GeometryError, match="no estimate"):
        learned_prior_factor(corr, sat_pos, pr, few, guess, 1)
    with pytest.raises(GeometryError, match=r"sat_pos \(S,3\)"):
        learned_prior_factor(corr, sat_pos[:, :2], pr, mask, guess, 1)
    with pytest.raises(GeometryError, match="init_pos"):
        learned_prior_factor(corr, sat_pos, pr, mask, np.array([np.nan, 0, 0]), 1)
    with pytest.raises(GeometryError, match=r"pr_sigma must have shape"):
        one_epoch_trace(sat_pos, pr, mask, pr_sigma=np.ones(len(pr) + 1))
    with pytest.raises(GeometryError, match=r"signal must have shape"):
        one_epoch_trace(sat_pos, pr, mask, signal=np.zeros((1, len(pr))))

    def singular(trace, init_pos, valid):
        return init_pos, np.zeros((1, 3, 3)), valid
    with pytest.raises(GeometryError, match="not positive definite"):
        learned_prior_factor(singular, sat_pos, pr, mask, guess, 1)


def test_pose_translation_prior_is_in_world_frame():
    def provider(trace, init_pos, valid):
        return init_pos, np.tile(np.diag([1.0, 100.0, 1.0]), (1, 1, 1)), valid
    tr = toy_trace(1, seed=2, n_sats=(6, 6))
    key = gtsam.symbol("p", 0)
    f, mean, _ = learned_pose_translation_factor(provider, tr.sat_pos[0], tr.pr[0], tr.mask[0], tr.truth[0], key)
    v = gtsam.Values()
    # a pose rotated by 90 deg yaw, displaced 10 m along world y: the loose (100 m^2) world-y axis
    v.insert(key, gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), mean + np.array([0.0, 10.0, 0.0])))
    assert f.error(v) == pytest.approx(0.5 * 100.0 / 100.0, rel=1e-9)


def _run_example(script: str, ckpt, epochs: int, trace_dir) -> subprocess.CompletedProcess:
    """Run ``examples/<script>`` with ``ckpt`` on its first ``epochs`` epochs; skip without the shipped trace."""
    if not trace_dir.is_dir():
        pytest.skip("shipped trace not present")
    out = subprocess.run([sys.executable, str(REPO / "examples" / script), "--weights", str(ckpt),
                          "--epochs", str(epochs)], capture_output=True, text=True, timeout=120,
                         env={"OMP_NUM_THREADS": "2", "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def test_example_04_runs(tiny_ckpt, shipped_trace_dir):
    out = _run_example("04_learned_factor_in_your_graph.py", tiny_ckpt, 40, shipped_trace_dir)
    assert "pose graph  horizontal error p50" in out.stdout
    assert "40 epochs" in out.stdout


def test_example_05_runs(tiny_ckpt, shipped_trace_dir):
    out = _run_example("05_learned_pseudorange_factors.py", tiny_ckpt, 30, shipped_trace_dir)
    rows = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(fixed 5 m sigma|learned sigmas)\s+horizontal "
                                                               r"error p50 ([\d.]+) m", out.stdout, re.M)}
    assert set(rows) == {"fixed 5 m sigma", "learned sigmas"} and all(0 < v < 100 for v in rows.values()), out.stdout
    n = int(re.search(r"over (\d+) measurements", out.stdout).group(1))
    assert n > 30 * 4                                        # every measurement got a sigma


def test_pseudorange_factors_take_the_heads_sigma_and_bias():
    """Slots with an opinion get its sigma and bias; NaN slots get the default sigma and no bias."""
    tr = toy_trace(3, seed=6, n_sats=(7, 7))
    sig = np.full(tr.mask.shape, np.nan)
    bias = np.full(tr.mask.shape, np.nan)
    sig[:, 0], bias[:, 0] = 2.0, 50.0

    class Head:
        def slot_noise(self, elev_mask_deg=None):
            return lambda trace, init_pos, valid: (sig, bias)

    pk, ck = [gtsam.symbol("x", k) for k in range(3)], [gtsam.symbol("c", k) for k in range(3)]
    factors, used = learned_pseudorange_factors(Head(), tr, tr.truth, np.ones(3, bool), pk, ck, default_sigma_m=5.0,
                                                robust="none")
    assert [len(f) for f in factors] == [7, 7, 7]
    np.testing.assert_array_equal(used[:, 0], 2.0)
    np.testing.assert_array_equal(used[:, 1:], 5.0)
    # the factor on slot 0 measures pr - 50 m with sigma 2 m: against the same slot without the bias its
    # unwhitened error moves by exactly 50 m, and the noise model is the head's sigma
    bias[:, 0] = 0.0
    plain, _ = learned_pseudorange_factors(Head(), tr, tr.truth, np.ones(3, bool), pk, ck, robust="none")
    v = gtsam.Values()
    v.insert(pk[0], tr.truth[0])
    v.insert(ck[0], 1e-4)
    d = factors[0][0].unwhitenedError(v) - plain[0][0].unwhitenedError(v)
    assert abs(float(d[0])) == pytest.approx(50.0, abs=1e-6)
    np.testing.assert_allclose(factors[0][0].noiseModel().sigmas(), [2.0])
    np.testing.assert_allclose(factors[0][1].noiseModel().sigmas(), [5.0])


def test_factor_safety_options_inflate_floor_and_robustify():
    tr = toy_trace(1, seed=2, n_sats=(6, 6))

    def provider(trace, init_pos, valid):
        return init_pos + 1.0, np.tile(np.eye(3), (1, 1, 1)), valid.copy()

    key = gtsam.symbol("x", 0)
    f, mean, cov = learned_prior_factor(provider, tr.sat_pos[0], tr.pr[0], tr.mask[0], tr.truth[0], key,
                                        cov_scale=4.0, sigma_floor_m=2.0, robust="huber", robust_k=1.0)
    np.testing.assert_allclose(cov, 8.0 * np.eye(3))
    v = gtsam.Values()
    v.insert(key, mean + np.array([0.0, 0.0, 10 * np.sqrt(8.0)]))     # 10 sigma away
    assert f.error(v) == pytest.approx(10.0 - 0.5, rel=1e-6)           # Huber: linear, not 50
    with pytest.raises(GeometryError):
        learned_prior_factor(provider, tr.sat_pos[0], tr.pr[0], tr.mask[0], tr.truth[0], key, cov_scale=-1.0)
    with pytest.raises(TypeError, match="cov_scal"):                    # a misspelt option is not ignored
        learned_prior_factor(provider, tr.sat_pos[0], tr.pr[0], tr.mask[0], tr.truth[0], key, cov_scal=4.0)


def test_one_prior_rule_for_factor_and_graph():
    """The factor helpers and the graph clean a provider's output with the same rule (it had drifted:
    the factors accepted any eigenvalue > 0, the graph needs > 1e-6 m^2)."""
    from fusion.estimate.graph.config import GraphConfig
    from fusion.estimate.graph.inputs import prepare_inputs
    from fusion.estimate.graph.priors import learned_from_providers
    from fusion.estimate.wls import solve_wls
    from learned.factor import learned_prior_factors

    tr = toy_trace(3, seed=5, n_sats=(8, 8))
    near_singular = np.diag([1e-7, 1.0, 1.0])

    def provider(trace, init_pos, valid):
        cov = np.tile(np.diag([4.0, 9.0, 16.0]), (trace.n_epochs, 1, 1))
        if trace.n_epochs == 3:
            cov[1] = near_singular
        return init_pos + 1.0, cov, valid.copy()

    with pytest.raises(GeometryError, match="not positive definite"):
        learned_prior_factor(lambda t, p, v: (p, near_singular[None], v), tr.sat_pos[0], tr.pr[0], tr.mask[0],
                             tr.truth[0], 1)
    keys = [gtsam.symbol("x", k) for k in range(3)]
    factors, mean, cov, ok = learned_prior_factors(provider, tr, tr.truth, np.ones(3, bool), keys,
                                                   cov_scale=4.0, sigma_floor_m=2.0, robust="huber")
    assert ok.tolist() == [True, False, True] and factors[1] is None
    np.testing.assert_allclose(cov[0], 4.0 * np.diag([4.0, 9.0, 16.0]) + 4.0 * np.eye(3))
    # the batched factor equals the one-epoch factor with the same options (huber: linear far out)
    f1, m1, c1 = learned_prior_factor(provider, tr.sat_pos[0], tr.pr[0], tr.mask[0], tr.truth[0], keys[0],
                                      cov_scale=4.0, sigma_floor_m=2.0, robust="huber")
    np.testing.assert_allclose(m1, mean[0])
    np.testing.assert_allclose(c1, cov[0])
    v = gtsam.Values()
    v.insert(keys[0], mean[0] + np.array([0.0, 0.0, 300.0]))
    assert factors[0].error(v) == pytest.approx(f1.error(v), rel=1e-12)
    assert factors[0].error(v) < 0.5 * 300.0 ** 2 / cov[0][2, 2]         # robust, not quadratic
    # the graph rejects the same epoch
    w = solve_wls(tr)
    inp = prepare_inputs(tr, w, GraphConfig(), learned=learned_from_providers(tr, provider, None, w.pos))
    assert inp.prior_ok.tolist() == ok.tolist() and inp.dropped["prior_rejected"] == 1
    np.testing.assert_allclose(inp.prior_cov[0], GraphConfig().prior_cov_scale * np.diag([4.0, 9.0, 16.0])
                               + GraphConfig().prior_sigma_floor_m ** 2 * np.eye(3))
