"""Realistic initial guesses (box / WLS mix), block validation split, variance calibration, checkpoint fields."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import nn

from fusion.errors import CheckpointError, DataError
from fusion.geometry import ecef2ned_vec
from fusion.estimate.wls import solve_wls
from learned.augment import draw_mixed_guesses, epoch_generator, parse_guess_mix
from learned.checkpoint import read_checkpoint, save_checkpoint
from learned.data import build_samples, samples_from_trace, split_blocks
from learned.features import FeatureConfig
from learned.infer import Corrector
from learned.model import SetTransformer
from learned.toy import toy_dataset, toy_trace
from learned.calibrate import sigma_scale
from learned.context import context_wls
from learned.train import TrainConfig, train
from fusion.cli.train import main


def test_parse_guess_mix_normalises_and_rejects_bad_text():
    assert parse_guess_mix("box=1,wls=3") == {"box": 0.25, "wls": 0.75}
    assert parse_guess_mix("wls=2") == {"box": 0.0, "wls": 1.0}
    assert parse_guess_mix({"box": 0.5, "wls": 0.5}) == {"box": 0.5, "wls": 0.5}
    for bad, msg in [("box=0.5,truth=0.5", "unknown source 'truth'"), ("box", "not SOURCE=FRACTION"),
                     ("box=x", "not a number"), ("box=-1,wls=2", ">= 0"), ("box=0", "sum to zero")]:
        with pytest.raises(ValueError, match=msg):
            parse_guess_mix(bad)


def _mix_inputs(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    truth = torch.as_tensor(toy_trace(1, seed=seed).truth.repeat(n, 0) + rng.normal(0, 50, (n, 3)))
    wls = truth + torch.as_tensor(rng.normal(0, 10, (n, 3)))
    usable = torch.as_tensor(rng.random(n) > 0.1)
    return truth, wls, usable


def test_mixed_guesses_respect_fraction_jitter_and_seed():
    truth, wls, usable = _mix_inputs()
    g, is_box = draw_mixed_guesses(truth, wls, usable, 15.0, 0.3, 2.0, epoch_generator(1, 0))
    # Box with probability 0.3 among usable samples; every unusable sample falls back to the box.
    frac = is_box[usable].double().mean().item()
    assert abs(frac - 0.3) < 0.015, frac
    assert is_box[~usable].all()
    d_wls = ecef2ned_vec((g - wls).numpy(), wls.numpy())
    assert np.abs(d_wls[~is_box.numpy()]).max() <= 2.0 + 1e-6          # jitter box around the WLS position
    assert np.abs(d_wls[~is_box.numpy()]).max() > 1.8                   # ... and it is actually used
    d_truth = ecef2ned_vec((g - truth).numpy(), truth.numpy())
    assert np.abs(d_truth[is_box.numpy()]).max() <= 15.0 + 1e-6
    g2, b2 = draw_mixed_guesses(truth, wls, usable, 15.0, 0.3, 2.0, epoch_generator(1, 0))
    assert torch.equal(g, g2) and torch.equal(is_box, b2)
    g3, _ = draw_mixed_guesses(truth, wls, usable, 15.0, 0.3, 2.0, epoch_generator(1, 1))
    assert not torch.equal(g, g3)
    _, all_box = draw_mixed_guesses(truth, wls, usable, 15.0, 1.0, 2.0, epoch_generator(1, 0))
    assert all_box.all()


def test_wls_branch_needs_no_truth():
    """Guesses of WLS-branch samples do not change when the truth does (same generator state)."""
    truth, wls, usable = _mix_inputs(2000, seed=3)
    g, is_box = draw_mixed_guesses(truth, wls, usable, 15.0, 0.5, 2.0, epoch_generator(0, 5))
    g_other, is_box2 = draw_mixed_guesses(truth + 1234.0, wls, usable, 15.0, 0.5, 2.0, epoch_generator(0, 5))
    assert torch.equal(is_box, is_box2)
    assert torch.equal(g[~is_box], g_other[~is_box]) and not torch.equal(g[is_box], g_other[is_box])


def test_sample_wls_is_the_truth_free_inference_solution():
    tr = toy_trace(50, seed=4, bias=True)
    s = samples_from_trace(tr, real=True)
    blind = context_wls(dataclasses.replace(tr, truth=None), 10.0)   # what the corrector computes at inference
    ok = np.isfinite(tr.truth).all(1)
    np.testing.assert_allclose(s.wls, blind.pos[ok], atol=1e-6)
    assert s.real.all() and s.skipped["wls_invalid"] == 0
    both = build_samples([tr, toy_trace(20, seed=5)], real=[True, False])
    assert both.wls.shape == (70, 3) and both.real.sum() == 50
    assert both.subset(np.array([0, 60])).real.tolist() == [True, False]
    with pytest.raises(ValueError):                      # one tag per trace, never silently fewer traces
        build_samples([tr, toy_trace(20, seed=5)], real=[True])


def test_split_blocks_is_contiguous_and_disjoint():
    s = build_samples(toy_dataset(3, 200, seed=2), with_wls=False)
    tr, va = split_blocks(s, 0.2, np.random.default_rng(0), block=50)
    assert len(tr) + len(va) == 600 and abs(len(va) - 120) <= 25
    assert not set(map(tuple, tr.truth.round(3))) & set(map(tuple, va.truth.round(3)))
    # Every validation block is whole: 50 consecutive samples of one trace (trace length 200 = 4 blocks).
    assert len(va) % 50 == 0
    tr2, va2 = split_blocks(s, 0.2, np.random.default_rng(0), block=50)
    np.testing.assert_array_equal(va.truth, va2.truth)


def test_sigma_scale_recovers_the_scale():
    g = np.random.default_rng(0)
    z = g.standard_normal((20000, 3)) * np.array([2.0, 1.0, 0.5])   # true sigma / predicted sigma
    cal = sigma_scale(z)
    np.testing.assert_allclose(cal["scale_ned"], [2.0, 1.0, 0.5], rtol=0.03)
    np.testing.assert_allclose(cal["within_1sigma_after"], 0.683, atol=0.01)
    assert cal["within_1sigma_before"][0] < 0.45 and cal["within_1sigma_before"][2] > 0.9


class UnitNet(nn.Module):
    def forward(self, x, mask):
        B, S = x.shape[:2]
        return torch.ones(B, 3), torch.zeros(B, 3), torch.zeros(B, S, 2)


def test_calibration_scale_applied_by_predict_and_old_configs_load():
    tr = toy_trace(20, seed=1)
    init, valid = tr.truth + 3.0, np.ones(20, bool)
    cfg = TrainConfig().to_checkpoint_config()
    calib = {"correction": {"scale_ned": [2.0, 1.0, 0.5]}, "wls": {"scale_ned": [1.0, 3.0, 1.0]}}
    for output, var in (("correction", [4.0, 1.0, 0.25]), ("wls", [1.0, 9.0, 1.0])):
        raw = Corrector(UnitNet(), cfg).predict(tr, init, valid, output=output)
        cal = Corrector(UnitNet(), dict(cfg, calibration=calib))
        np.testing.assert_allclose(cal.var_scale[output], var)
        c = cal.predict(tr, init, valid, output=output)
        np.testing.assert_allclose(c.mean_ecef, raw.mean_ecef)                  # means untouched
        # per NED axis: the covariance scales by s_i * s_j
        s = np.sqrt(var)
        np.testing.assert_allclose(c.cov_ned, raw.cov_ned * np.outer(s, s), rtol=1e-9, atol=1e-12)
        off = Corrector(UnitNet(), dict(cfg, calibration=calib), calibrated=False)
        np.testing.assert_allclose(off.predict(tr, init, valid, output=output).cov_ned, raw.cov_ned)
    with pytest.raises(CheckpointError, match="scale_ned"):
        Corrector(UnitNet(), dict(cfg, calibration={"wls": {"scale_ned": [1.0, -1.0, 1.0]}}))


def test_unseen_drive_scale_applies_only_to_the_output_it_was_fitted_on():
    tr = toy_trace(10, seed=2)
    init, valid = tr.truth + 3.0, np.ones(10, bool)
    cfg = dict(TrainConfig(output="wls").to_checkpoint_config(), output="wls")
    plain = Corrector(UnitNet(), cfg)
    unseen = Corrector(UnitNet(), dict(cfg, calibration={"unseen_dnn": {"scale_ned": [2.0, 2.0, 2.0]}}))
    for output, factor in (("wls", 4.0), ("correction", 1.0)):
        np.testing.assert_allclose(unseen.predict(tr, init, valid, output=output).cov_ned,
                                   factor * plain.predict(tr, init, valid, output=output).cov_ned, rtol=1e-9)


def test_old_checkpoint_without_new_fields_loads_with_defaults(tmp_path):
    old_cfg = TrainConfig().to_checkpoint_config()
    for k in ("guess_mix", "wls_jitter", "wls_max_err", "output", "loss"):
        old_cfg.pop(k)
    path = save_checkpoint(tmp_path / "old.pt", SetTransformer(), old_cfg)
    c = Corrector.load(path)
    assert c.output == "correction" and c.ranges is None
    for v in c.var_scale.values():
        np.testing.assert_array_equal(v, np.ones(3))
    tr = toy_trace(10, seed=6)
    assert c.predict(tr, tr.truth + 2.0, np.ones(10, bool)).valid.all()


@pytest.fixture(scope="module")
def tiny():
    torch.set_num_threads(1)
    s = build_samples(toy_dataset(2, 80, seed=9, bias=True), real=[True, False])
    return split_blocks(s, 0.25, np.random.default_rng(0), block=20)


def test_checkpoint_round_trip_with_mix_and_calibration(tiny, tmp_path):
    tr, va = tiny
    cfg = TrainConfig(epochs=1, guess_mix={"box": 0.5, "wls": 0.5}, wls_jitter=1.5, wls_max_err=80.0)
    hist = train(tr, va, cfg, tmp_path / "m.pt", progress=False)
    assert len(hist[0]["val_wls_mae_ned_m"]) == 3 and len(hist[0]["val_mae_ned_m"]) == 3
    conf = read_checkpoint(tmp_path / "m.pt")["config"]
    assert conf["guess_mix"] == {"box": 0.5, "wls": 0.5} and conf["wls_jitter"] == 1.5
    assert conf["wls_max_err"] == 80.0
    cal = conf["calibration"]
    assert set(cal) == {"wls", "correction"}
    for c in cal.values():
        # fewer than CALIB_MIN_REAL real samples: calibrated on all of them (every sample has a WLS fix)
        assert len(c["scale_ned"]) == 3 and c["n"] == len(va) and c["subset"] == "all validation samples"
        assert all(s > 0 for s in c["scale_ned"])
    c = Corrector.load(tmp_path / "m.pt")
    for name in ("wls", "correction"):
        np.testing.assert_allclose(c.var_scale[name], np.square(cal[name]["scale_ned"]))
    assert "calibration" not in read_checkpoint(tmp_path / "m.pt.last")["config"]
    # A box-only run and a mixed run see different guesses -> different first-epoch losses.
    hist_box = train(tr, va, TrainConfig(epochs=1), tmp_path / "b.pt", progress=False)
    assert hist_box[0]["train_loss"] != hist[0]["train_loss"]
    with pytest.raises(CheckpointError, match="'guess_mix' differs"):
        train(tr, va, dataclasses.replace(cfg, epochs=2, guess_mix={"box": 1.0}), tmp_path / "m.pt",
              resume=True, progress=False)
    train(tr, va, dataclasses.replace(cfg, calibrate=False), tmp_path / "nc.pt", progress=False)
    assert "calibration" not in read_checkpoint(tmp_path / "nc.pt")["config"]


def test_calibrated_scale_makes_the_validation_coverage_nominal(tiny, tmp_path):
    """After calibration the stored 1-sigma coverage on the validation split is the nominal ~68 %."""
    tr, va = tiny
    train(tr, va, TrainConfig(epochs=1), tmp_path / "m.pt", progress=False)
    for name, c in read_checkpoint(tmp_path / "m.pt")["config"]["calibration"].items():
        np.testing.assert_allclose(c["within_1sigma_after"], 0.683, atol=0.1, err_msg=name)


def test_cli_guess_mix_and_bias_source(tmp_path, capsys):
    out = tmp_path / "ck.pt"
    assert main(["--data", "toy", "toy-bias", "--sim-traces", "1", "--sim-epochs", "60",
                 "--epochs", "1", "--guess-mix", "box=0.25,wls=0.75", "--val-split", "blocks", "--out", str(out),
                 "--quiet", "--threads", "1"]) == 0
    conf = read_checkpoint(out)["config"]
    assert conf["guess_mix"] == {"box": 0.25, "wls": 0.75} and conf["data"]["toy-bias"]["bias"]
    assert conf["data"]["toy-bias"]["traces"] == 1 and not conf["data"]["toy"]["bias"]
    assert conf["data"]["toy-bias"]["seed"] == conf["data"]["toy"]["seed"] + 1          # other drives
    assert conf["data"]["val_split"] == "blocks" and set(conf["calibration"]) == {"wls", "correction"}
    printed = capsys.readouterr().out
    assert "wls covariance scale N/E/D" in printed and "correction covariance scale N/E/D" in printed
    with pytest.raises(DataError, match="--guess-mix"):
        main(["--data", "toy", "--guess-mix", "truth=1", "--out", str(tmp_path / "x.pt")])
    with pytest.raises(SystemExit):                              # the old flag is gone: use the 'sim-bias' source
        main(["--data", "toy", "--sim-bias-traces", "1", "--out", str(tmp_path / "x.pt")])


def test_load_training_data_sources():
    from learned.train_command import load_training_data

    s, desc = load_training_data(["toy", "toy-bias"], sim_traces=2, sim_epochs=20, seed=3, elev_mask_deg=10.0)
    assert len(s.names) == 4 and desc["toy"]["seed"] == 3 and desc["toy-bias"]["seed"] == 4
    assert desc["n_samples"] == len(s) and s.graph is None and s.ctx is not None
    assert not s.real_or_false().any()
    g, _ = load_training_data(["toy"], sim_traces=1, sim_epochs=20, seed=3, elev_mask_deg=10.0, with_graph=True)
    assert g.graph is not None and np.isfinite(g.graph).all()


# ------------------------------------------------------------------ graph guesses (no-prior graph solution)
def test_parse_guess_mix_graph_source_is_additive():
    assert parse_guess_mix("box=1,wls=1,graph=2") == {"box": 0.25, "wls": 0.25, "graph": 0.5}
    assert parse_guess_mix("box=1,graph=0") == {"box": 1.0, "wls": 0.0}       # old mixes parse as before
    with pytest.raises(ValueError, match="fraction of 'graph'"):
        parse_guess_mix("box=1,graph=-1")


def test_graph_branch_fraction_fallback_and_bit_identity():
    truth, wls, usable = _mix_inputs(20000, seed=1)
    graph = truth + 300.0                                                       # far from box and WLS
    g_use = torch.as_tensor(np.random.default_rng(2).random(len(truth)) > 0.2)
    gen = lambda: epoch_generator(4, 0)                                         # noqa: E731
    g, is_box = draw_mixed_guesses(truth, wls, usable, 15.0, 0.25, 2.0, gen(), graph, g_use, 0.5)
    old, old_box = draw_mixed_guesses(truth, wls, usable, 15.0, 0.25, 2.0, gen())
    # graph_frac = 0 (or no graph) reproduces the two-source draw bit for bit
    g0, b0 = draw_mixed_guesses(truth, wls, usable, 15.0, 0.25, 2.0, gen(), graph, g_use, 0.0)
    assert torch.equal(g0, old) and torch.equal(b0, old_box)
    near_graph = np.abs(ecef2ned_vec((g - graph).numpy(), graph.numpy())).max(1) <= 2.0 + 1e-6
    near_wls = np.abs(ecef2ned_vec((g - wls).numpy(), wls.numpy())).max(1) <= 2.0 + 1e-6
    both = usable.numpy() & g_use.numpy()
    assert abs(near_graph[both].mean() - 0.5) < 0.015, near_graph[both].mean()
    assert abs(is_box[both].double().mean().item() - 0.25) < 0.015
    assert not near_graph[~g_use.numpy()].any()                                # unusable graph: never used
    # Samples that would have taken the graph but have none fall back to WLS (or the box without WLS).
    rest = (~g_use).numpy() & usable.numpy() & ~is_box.numpy()
    assert near_wls[rest].all() and rest.sum() > 0.75 * 0.2 * 0.9 * 20000 * 0.8


def test_sample_graph_is_the_truth_free_nodnn_solution():
    from fusion.estimate.graph.fuse import estimate_fused_nodnn
    from fusion.run_types import RunOptions

    tr = toy_trace(60, seed=4, bias=True)
    s = samples_from_trace(tr, real=True, with_graph=True)
    blind_tr = dataclasses.replace(tr, truth=None)
    nodnn = estimate_fused_nodnn(blind_tr, solve_wls(blind_tr), RunOptions())   # the pipeline's mode
    ok = np.isfinite(tr.truth).all(1)
    np.testing.assert_allclose(s.graph, nodnn.pos[ok], atol=1e-6)
    assert s.skipped["graph_invalid"] == 0
    assert np.linalg.norm(s.graph - s.wls, axis=1).max() > 0.1                 # not just the WLS again
    assert samples_from_trace(tr).graph is None                                 # off by default
    both = build_samples([tr, toy_trace(20, seed=5)], with_graph=True)
    assert both.graph.shape == (80, 3) and both.subset(np.array([1, 70])).graph.shape == (2, 3)


def test_train_with_graph_mix_needs_graph_positions(tmp_path):
    torch.set_num_threads(1)
    s = build_samples(toy_dataset(2, 80, seed=9, bias=True), real=[True, False], with_graph=True)
    tr, va = split_blocks(s, 0.25, np.random.default_rng(0), block=20)
    cfg = TrainConfig(epochs=1, guess_mix="box=0.25,wls=0.25,graph=0.5")
    hist = train(tr, va, cfg, tmp_path / "g.pt", progress=False)
    assert np.isfinite(hist[0]["val_score_m"]) and np.isfinite(hist[0]["train_loss"])
    conf = read_checkpoint(tmp_path / "g.pt")["config"]
    assert conf["guess_mix"] == {"box": 0.25, "wls": 0.25, "graph": 0.5}
    # a graph mix and a two-source mix draw different guesses -> different training losses
    h2 = train(tr, va, TrainConfig(epochs=1, guess_mix="box=0.25,wls=0.75"), tmp_path / "w.pt", progress=False)
    assert h2[0]["train_loss"] != hist[0]["train_loss"]
    assert set(h2[0]) == set(hist[0])
    tr_nog, va_nog = split_blocks(build_samples(toy_dataset(2, 80, seed=9)), 0.25, np.random.default_rng(0), block=20)
    with pytest.raises(DataError, match="no graph positions"):
        train(tr_nog, va_nog, cfg, tmp_path / "x.pt", progress=False)


def test_cli_graph_mix(tmp_path, capsys):
    out = tmp_path / "cg.pt"
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "60", "--epochs", "1",
                 "--guess-mix", "box=0.25,wls=0.25,graph=0.5", "--val-split", "blocks", "--out", str(out),
                 "--quiet", "--threads", "1"]) == 0
    conf = read_checkpoint(out)["config"]
    assert conf["guess_mix"]["graph"] == 0.5 and conf["data"]["skipped"]["graph_invalid"] == 0
    assert "best epoch 1" in capsys.readouterr().out


def test_epoch_generator_streams_per_seed_epoch_and_rank():
    draw = lambda **kw: torch.rand(8, generator=epoch_generator(**kw))          # noqa: E731
    a = draw(seed=1, epoch=3)
    assert torch.equal(a, draw(seed=1, epoch=3, rank=0))                        # rank 0 = the one-process run
    assert torch.equal(a, draw(seed=1, epoch=3, device="cpu"))
    others = [draw(seed=1, epoch=3, rank=1), draw(seed=1, epoch=4), draw(seed=2, epoch=3), draw(seed=1, epoch=3, rank=2)]
    assert all(not torch.equal(a, o) for o in others)
    assert not torch.equal(others[0], others[3])
