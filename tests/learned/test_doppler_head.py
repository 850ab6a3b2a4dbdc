"""The learned Doppler head: truth-free features, a head that learns which Doppler measurements are bad, its
guard, its place in a checkpoint and in the fused graph, and one-line refusals."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.errors import CheckpointError, DataError
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import run_modes, solve_initial
from fusion.run_types import RunOptions
from fusion.sim.config import scenario_config
from fusion.sim.simulate import simulate
from learned.doppler_head import (FEATURES, GUARDED, DopplerNoise, check_head, doppler_features, guard,
                                  head_outputs, relative, sigma_multiplier)
from learned.doppler_train import HeadConfig, fit, head_dict, trace_rows, truth_errors

BAD_SYSTEM = 3000       # GLONASS (1000 * constellationType): the test traces' bad Doppler
BAD_SIGMA = 2.0         # m/s


def bad_doppler(seed: int):
    """A simulated suburban trace whose GLONASS Doppler carries N(0, BAD_SIGMA) errors its stated sigma does
    not show (a receiver's poor GLONASS tracking), and the (E,S) bool of those measurements."""
    trace = simulate(n_epochs=240, nav=read_rinex_nav(default_nav_path()), seed=seed,
                     config=scenario_config("suburban")).trace
    bad = trace.prr_ok & (trace.sat_id // 1000 == BAD_SYSTEM // 1000)
    rng = np.random.default_rng(seed)
    prr = trace.prr + np.where(bad, rng.normal(0.0, BAD_SIGMA, bad.shape), 0.0)
    return dataclasses.replace(trace, prr=prr), bad


def graph_inputs(trace):
    cfg = GraphConfig(use_carrier=False, doppler_check_window_s=0.0)
    return prepare_inputs(trace, solve_initial(trace, RunOptions()), cfg)


@pytest.fixture(scope="module")
def trained():
    opts = RunOptions(signals="all")
    parts = [trace_rows(bad_doppler(seed)[0], opts) for seed in (1, 2)]
    rows = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    cfg = HeadConfig(epochs=20, batch=1024, seed=0)
    net, hist = fit(rows, cfg)
    return head_dict(net, rows, cfg, ["sim-1", "sim-2"]), hist


def test_features_read_no_truth():
    trace, _ = bad_doppler(3)
    x, ks, ss = doppler_features(trace, graph_inputs(trace))
    moved = dataclasses.replace(trace, truth=trace.truth + 50.0)
    x2, ks2, ss2 = doppler_features(moved, graph_inputs(moved))
    np.testing.assert_array_equal(ks, ks2)
    np.testing.assert_array_equal(x, x2)
    assert x.shape == (len(ks), len(FEATURES)) and np.isfinite(x).all()


def test_truth_errors_find_the_injected_doppler_errors():
    trace, bad = bad_doppler(4)
    inp = graph_inputs(trace)
    _, ks, ss = doppler_features(trace, inp)
    err = truth_errors(trace, inp, ks, ss)
    hit = bad[ks, ss]
    assert 1.5 < np.nanstd(err[hit]) < 2.5
    assert np.nanmedian(np.abs(err[~hit])) < 0.3


def test_the_head_learns_which_doppler_to_trust(trained):
    head, hist = trained
    assert hist[-1] < hist[0]
    trace, bad = bad_doppler(5)          # a trace the head never saw
    inp = graph_inputs(trace)
    x, ks, ss = doppler_features(trace, inp)
    m, p = head_outputs(head, x)
    mult = sigma_multiplier(m, p)
    hit = bad[ks, ss]
    # the bad Doppler's errors are ~13 times its stated sigma, the rest's about one
    assert np.median(mult[hit]) > 6 * np.median(mult[~hit])
    assert 0.7 < np.median(mult[~hit]) < 1.4


def test_the_head_scales_the_graphs_doppler_sigmas_within_each_epoch(trained):
    head, _ = trained
    trace, bad = bad_doppler(5)
    inp = graph_inputs(trace)
    before = inp.raw.prr_sigma.copy()
    counts = DopplerNoise(head)(trace, inp)
    use = inp.raw.doppler & inp.keep[:, None]
    ratio = np.where(use, inp.raw.prr_sigma / before, np.nan)
    assert counts["doppler_sigmas"] + counts["doppler_out_of_range"] + counts["doppler_unseen_system"] == use.sum()
    # relative: each epoch's median factor is one (the absolute level is the physical model's)
    np.testing.assert_allclose(np.nanmedian(np.log(ratio[use.any(axis=1)]), axis=1), 0.0, atol=1e-9)
    assert np.median(ratio[use & bad]) > 3 * np.median(ratio[use & ~bad])


def test_the_numpy_head_is_the_torch_head(trained):
    import torch

    from learned.doppler_train import HeadNet

    head, _ = trained
    net = HeadNet(len(head["layers"][0][1]))
    lin = [m for m in net.net if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for m, (w, b) in zip(lin, head["layers"]):
            m.weight.copy_(torch.tensor(w))
            m.bias.copy_(torch.tensor(b))
        x = np.random.default_rng(0).normal(size=(50, len(FEATURES))).astype(np.float32)
        m_t, logit = net(torch.from_numpy(x))
    m, p = head_outputs(head, x)
    np.testing.assert_allclose(m, m_t.numpy(), atol=1e-5)
    np.testing.assert_allclose(p, torch.sigmoid(logit).numpy(), atol=1e-6)


def test_relative_divides_by_each_epochs_median():
    ks, ss = np.array([0, 0, 0, 2, 2]), np.array([0, 1, 2, 0, 3])
    out = relative(np.array([1.0, 2.0, 4.0, 3.0, 12.0]), ks, ss, (3, 4))
    np.testing.assert_allclose(out, [0.5, 1.0, 2.0, 0.5, 2.0])


def test_the_guard_keeps_the_physical_model_for_unseen_systems_and_inputs(trained):
    head, _ = trained
    trace, _ = bad_doppler(5)
    x, _, _ = doppler_features(trace, graph_inputs(trace))
    gps_only = dict(head, systems=["GPS"])
    unseen, out = guard(gps_only, x)
    np.testing.assert_array_equal(unseen, x[:, FEATURES.index("sys_GPS")] < 0.5)
    narrow = dict(head, range=[[0.0, 0.0] if g == "speed" else r for g, r in zip(GUARDED, head["range"])])
    _, out = guard(narrow, x)
    assert out.sum() == (x[:, FEATURES.index("speed")] != 0).sum()
    # a log without C/N0 reads as missing, not out of range
    no_cn0 = x.copy()
    no_cn0[:, [FEATURES.index("cn0_present"), FEATURES.index("cn0")]] = 0.0
    assert not guard(head, no_cn0)[1].any()


def test_a_bad_head_is_refused_naming_the_file(trained):
    head, _ = trained
    check_head(head, "w.pt")
    for bad in ({**head, "version": 99}, {**head, "features": ["cn0"]}, {**head, "layers": []}, "head", None):
        with pytest.raises(CheckpointError, match="w.pt: its doppler_head"):
            check_head(bad, "w.pt")


def test_a_trace_without_truth_or_doppler_cannot_train_the_head():
    trace, _ = bad_doppler(6)
    with pytest.raises(DataError, match="lacks ground truth"):
        trace_rows(dataclasses.replace(trace, truth=None), RunOptions())
    plain = dataclasses.replace(trace, prr=None, prr_sigma=None, prr_ok=None)
    with pytest.raises(DataError, match="lacks Doppler"):
        trace_rows(plain, RunOptions())


def test_a_checkpoint_carries_the_head_into_the_fused_mode(trained, tmp_path):
    from learned.checkpoint import load_model, save_checkpoint
    from learned.ensemble import read_manifest
    from learned.infer import SHIPPED_WEIGHTS, Corrector

    head, _ = trained
    model, blob = load_model(read_manifest(SHIPPED_WEIGHTS)[0][0])
    path = save_checkpoint(tmp_path / "w.pt", model, dict(blob["config"], doppler_head=head))
    assert Corrector.load(path).doppler is not None
    assert Corrector.load(SHIPPED_WEIGHTS).doppler is None or "doppler_head" in blob["config"]
    trace, _ = bad_doppler(5)
    opts = RunOptions(signals="all", weights=path, graph=GraphConfig(use_carrier=False))
    on = run_modes(trace, ["fused"], opts)["fused"]
    off = run_modes(trace, ["fused"], dataclasses.replace(opts, learned_doppler=False))["fused"]
    assert on.info["learned_doppler_sigmas"] > 0 and "learned_doppler_sigmas" not in off.info
    ok = on.valid & off.valid
    assert np.abs(on.pos[ok] - off.pos[ok]).max() > 1e-3


def test_train_doppler_writes_the_head_into_a_copy_of_the_weights(tmp_path, capsys):
    from fusion.cli import main as cli
    from learned.checkpoint import read_checkpoint
    from learned.ensemble import read_manifest
    from learned.infer import SHIPPED_WEIGHTS, Corrector
    from learned.npz_weights import read_npz

    assert cli(["simulate", "--out", str(tmp_path / "sim"), "--scenario", "suburban", "--epochs", "120",
                "--seed", "3", "--collection", "drive"]) == 0
    bases, cal = read_manifest(SHIPPED_WEIGHTS)
    out = tmp_path / "w.pt"
    assert cli(["train-doppler", str(tmp_path / "sim"), "--weights", str(bases[1]), "--out", str(out),
                "--epochs", "2", "--threads", "1", "--quiet"]) == 0
    assert "written into" in capsys.readouterr().out
    base, new = read_checkpoint(bases[1]), read_checkpoint(out)
    assert all((new["model_state"][k] == v).all() for k, v in base["model_state"].items())
    head = check_head(new["config"]["doppler_head"], out)
    assert head["trained_on"] == ["drive/SimPhone"] and head["recipe"]["epochs"] == 2
    assert read_npz(out.with_suffix(".npz"))[1]["doppler_head"] == head
    # the shipped ensemble (the default): the same head into every member, the manifest's calibration kept
    assert cli(["train-doppler", str(tmp_path / "sim"), "--out", str(tmp_path / "e.pt"), "--quiet"]) == 2
    assert "give --out a .json" in capsys.readouterr().err
    ens = tmp_path / "e.json"
    assert cli(["train-doppler", str(tmp_path / "sim"), "--out", str(ens), "--epochs", "2", "--threads", "1",
                "--quiet"]) == 0
    members, new_cal = read_manifest(ens)
    assert [m.name for m in members] == [f"e_m{i}.pt" for i in range(len(bases))] and new_cal == cal
    for b, m in zip(bases, members):
        blob = read_checkpoint(m)
        assert blob["config"]["doppler_head"] == head
        assert all((blob["model_state"][k] == v).all() for k, v in read_checkpoint(b)["model_state"].items())
    assert Corrector.load(ens).doppler is not None


def test_train_doppler_refuses_test_traces_and_logs_without_doppler_in_one_line(shipped_trace_dir, tmp_path, capsys):
    from fusion.cli import main as cli

    assert cli(["train-doppler", str(shipped_trace_dir), "--out", str(tmp_path / "w.json"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "held-out test trace" in err
    # the simulator's default output is the GSDC 2021 derived format: pseudoranges, no Doppler
    assert cli(["simulate", "--out", str(tmp_path / "sim"), "--epochs", "30", "--seed", "1"]) == 0
    capsys.readouterr()
    assert cli(["train-doppler", str(tmp_path / "sim"), "--out", str(tmp_path / "w.json"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "lacks Doppler" in err
