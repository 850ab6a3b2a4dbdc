"""Training loop: reproducibility, resume, augmentation modes, CLI and data guards (tiny toy data)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from fusion.errors import CheckpointError, DataError, GnssfuseError
from learned.checkpoint import load_model, read_checkpoint, save_checkpoint
from learned.data import build_samples, check_not_forbidden, split_random
from learned.features import CHANNELS, FEATURE_VERSION, RECIPE_INPUTS, FeatureConfig
from learned.infer import Corrector
from learned.toy import toy_dataset
from learned.train import TrainConfig, setup, train
from fusion.cli.train import main
from learned.train_command import parse_loss


@pytest.fixture(scope="module")
def tiny():
    torch.set_num_threads(1)
    s = build_samples(toy_dataset(3, 60, seed=7))
    return split_random(s, 0.2, np.random.default_rng(0))


def _weights(path):
    return read_checkpoint(path)["model_state"]


def _same(a, b):
    return all(torch.equal(a[k], b[k]) for k in a)


def test_two_runs_identical_weights(tiny, tmp_path):
    tr, va = tiny
    for name in ("a", "b"):
        train(tr, va, TrainConfig(epochs=1, seed=3), tmp_path / f"{name}.pt", progress=False)
    assert _same(_weights(tmp_path / "a.pt"), _weights(tmp_path / "b.pt"))
    train(tr, va, TrainConfig(epochs=1, seed=4), tmp_path / "c.pt", progress=False)
    assert not _same(_weights(tmp_path / "a.pt"), _weights(tmp_path / "c.pt"))


def test_a_run_that_diverges_says_so_and_writes_no_checkpoint(tiny, tmp_path):
    """A learning rate that blows the weights up to NaN was saved as the best epoch, and every run with it wrote
    empty estimates: now the training stops with a one-line error and leaves no checkpoint."""
    tr, va = tiny
    with pytest.raises(GnssfuseError, match="training diverged in epoch 1: its loss is not finite"):
        train(tr, va, TrainConfig(epochs=2, seed=3, lr=1e9), tmp_path / "nan.pt", progress=False)
    assert not (tmp_path / "nan.pt").exists()


def test_resume_reproduces_uninterrupted_run(tiny, tmp_path):
    tr, va = tiny
    cfg = dict(seed=1, warmup_epochs=1)
    train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "full.pt", progress=False)
    train(tr, va, TrainConfig(epochs=1, **cfg), tmp_path / "part.pt", progress=False)
    hist = train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "part.pt", resume=True, progress=False)
    assert [h["epoch"] for h in hist] == [1, 2]
    assert set(hist[1]) == {"epoch", "train_loss", "val_score_m", "val_mae_ned_m", "val_wls_mae_ned_m", "time_s",
                            "samples", "world_size", "nll", "feature_s", "model_s"}
    assert hist[1]["world_size"] == 1 and hist[1]["samples"] == len(tr)
    assert len(hist[1]["val_mae_ned_m"]) == 3 and len(hist[1]["val_wls_mae_ned_m"]) == 3
    full, part = (read_checkpoint(tmp_path / f"{n}.pt.last") for n in ("full", "part"))
    assert _same(full["model_state"], part["model_state"])
    with pytest.raises(CheckpointError, match="'eta' differs"):
        train(tr, va, TrainConfig(epochs=3, eta=30.0, **cfg), tmp_path / "part.pt", resume=True, progress=False)
    for changed in ({"lr": 1e-4}, {"batch": 7}):
        with pytest.raises(CheckpointError, match=f"'{next(iter(changed))}' differs"):
            train(tr, va, TrainConfig(epochs=3, **cfg, **changed), tmp_path / "part.pt", resume=True, progress=False)
    with pytest.raises(CheckpointError, match="no checkpoint to resume"):
        train(tr, va, TrainConfig(epochs=1), tmp_path / "none.pt", resume=True, progress=False)


def test_a_network_with_dropout_resumes_as_an_uninterrupted_run(tiny, tmp_path):
    """The layers' dropout draws from the global generator: its state travels in ``<out>.last``."""
    tr, va = tiny
    cfg = dict(seed=3, warmup_epochs=1, hparams={"dropout": 0.2})
    train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "full.pt", progress=False)
    train(tr, va, TrainConfig(epochs=1, **cfg), tmp_path / "part.pt", progress=False)
    torch.manual_seed(99)                                    # what ran in between must not matter
    train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "part.pt", resume=True, progress=False)
    full, part = (read_checkpoint(tmp_path / f"{n}.pt.last") for n in ("full", "part"))
    assert _same(full["model_state"], part["model_state"])
    assert read_checkpoint(tmp_path / "full.pt")["config"]["model"]["hparams"]["dropout"] == 0.2


def test_a_run_starts_from_a_pretrained_network_and_says_so(tiny, tmp_path):
    tr, va = tiny
    pre = tmp_path / "pre.pt"
    train(tr, va, TrainConfig(epochs=1, seed=3), pre, progress=False)
    started, *_ = setup(TrainConfig(epochs=1, seed=5, init=str(pre)), tmp_path / "x.pt.last", False, "cpu")
    fresh, *_ = setup(TrainConfig(epochs=1, seed=5), tmp_path / "x.pt.last", False, "cpu")
    assert _same(started.state_dict(), _weights(pre)) and not _same(fresh.state_dict(), _weights(pre))
    # pre-trained on inputs wider than the fine-tuning data's: the guard keeps the pre-training's ranges
    model, blob = load_model(pre)
    cfg = blob["config"]
    wide = {"lo": [v - 50.0 for v in cfg["input_ranges"]["lo"]], "hi": [v + 50.0 for v in cfg["input_ranges"]["hi"]]}
    save_checkpoint(pre, model, {**cfg, "input_ranges": wide})
    train(tr, va, TrainConfig(epochs=1, seed=5, init=str(pre)), tmp_path / "tuned.pt", progress=False)
    tuned = read_checkpoint(tmp_path / "tuned.pt")
    assert tuned["config"]["init"] == str(pre) and not _same(tuned["model_state"], _weights(pre))
    assert tuned["config"]["input_ranges"] == wide
    train(tr, va, TrainConfig(epochs=1, seed=5), tmp_path / "fresh.pt", progress=False)
    assert read_checkpoint(tmp_path / "fresh.pt")["config"]["input_ranges"] != wide
    other = FeatureConfig(inputs=RECIPE_INPUTS)                # another network's inputs: refused, naming the file
    with pytest.raises(CheckpointError, match=r"pre\.pt: cannot start from it, its '(model|features)' differs"):
        setup(TrainConfig(epochs=1, init=str(pre), features=other), tmp_path / "x.pt.last", False, "cpu")
    with pytest.raises(CheckpointError, match="no checkpoint to start from"):
        setup(TrainConfig(epochs=1, init=str(tmp_path / "none.pt")), tmp_path / "x.pt.last", False, "cpu")


def test_resume_with_more_epochs_keeps_the_default_warmup(tiny, tmp_path):
    """The default warm-up (a tenth of the epochs) is the run's own: more epochs do not change it."""
    tr, va = tiny
    train(tr, va, TrainConfig(epochs=1, seed=1), tmp_path / "w.pt", progress=False)
    more = TrainConfig(epochs=40, seed=1)                   # its own default warm-up would be 4
    _, _, _, start, history = setup(more, tmp_path / "w.pt.last", True, torch.device("cpu"))
    assert start == 1 and len(history) == 1 and more.warmup() == 1
    with pytest.raises(CheckpointError, match="'warmup_epochs' differs"):
        setup(TrainConfig(epochs=40, seed=1, warmup_epochs=4), tmp_path / "w.pt.last", True, torch.device("cpu"))


def test_resume_needs_only_the_dropout_rates_of_the_groups_read(tiny, tmp_path):
    """A checkpoint written before an input group existed has no dropout rate for it and still resumes; a
    changed rate of a group the run reads still refuses."""
    tr, va = tiny
    cfg = dict(seed=1, features=FeatureConfig(inputs=("res", "los", "cn0")))
    train(tr, va, TrainConfig(epochs=1, **cfg), tmp_path / "d.pt", progress=False)
    blob = torch.load(tmp_path / "d.pt.last", weights_only=True)
    del blob["config"]["dropout"]["heading"]                       # as written before "heading" existed
    torch.save(blob, tmp_path / "d.pt.last")
    _, _, _, start, _ = setup(TrainConfig(epochs=2, **cfg), tmp_path / "d.pt.last", True, torch.device("cpu"))
    assert start == 1
    with pytest.raises(CheckpointError, match="'dropout' differs"):
        setup(TrainConfig(epochs=2, dropout={"cn0": 0.9}, **cfg), tmp_path / "d.pt.last", True, torch.device("cpu"))


def test_training_learns_and_no_augment_differs(tmp_path):
    """On toy data with NLOS-like biases (+50..200 m on about one satellite per epoch) the learned-weight
    WLS must clearly beat plain WLS at the validation samples' WLS solutions after a few epochs."""
    from fusion.geometry import ecef2ned_vec

    torch.set_num_threads(1)
    s = build_samples(toy_dataset(4, 150, seed=11, sigma=1.0, bias=True))
    tr, va = split_random(s, 0.2, np.random.default_rng(0))
    e = ecef2ned_vec(va.wls - va.truth, va.truth)
    plain = np.linalg.norm(e[:, :2], axis=1).mean()            # the same score for plain WLS (~50 m here)
    cfg = TrainConfig(epochs=3, batch=32, lr=3e-3, guess_mix={"box": 0.5, "wls": 0.5})
    hist = train(tr, va, cfg, tmp_path / "aug.pt", progress=False)
    assert min(h["val_score_m"] for h in hist) < 0.7 * plain, (plain, hist)
    assert hist[-1]["train_loss"] < hist[0]["train_loss"]
    # the score is the learned-WLS horizontal error (output "wls"), consistent with its per-axis MAE
    assert hist[-1]["val_score_m"] <= np.hypot(*hist[-1]["val_wls_mae_ned_m"][:2]) * 1.5
    best = read_checkpoint(tmp_path / "aug.pt")
    assert best["history"][best["epoch"] - 1]["val_score_m"] == min(h["val_score_m"] for h in hist)
    hist2 = train(tr, va, dataclasses.replace(cfg, epochs=1, augment=False), tmp_path / "noaug.pt",
                  progress=False)
    assert hist2[0]["train_loss"] != hist[0]["train_loss"]


def test_augmentation_redraws_guesses_each_epoch_and_no_augment_keeps_them(tmp_path, monkeypatch):
    import learned.train as lt

    s = build_samples(toy_dataset(2, 60, seed=3, sigma=1.0))
    tr, va = split_random(s, 0.2, np.random.default_rng(0))
    seen = []
    real = lt.make_inputs

    at_wls = torch.as_tensor(tr.wls)

    def spy(t, guess, fcfg):
        # the training set's drawn guesses (validation is smaller; the guard's input ranges are taken at
        # the training samples' own WLS solutions, once per run)
        if guess.shape[0] == len(tr) and not torch.equal(guess, at_wls):
            seen.append(guess.clone())
        return real(t, guess, fcfg)

    monkeypatch.setattr(lt, "make_inputs", spy)
    for augment in (True, False):
        seen.clear()
        train(tr, va, TrainConfig(epochs=3, eta=15.0, batch=32, augment=augment), tmp_path / f"{augment}.pt",
              progress=False)
        assert len(seen) == 3                                   # inputs are rebuilt every epoch
        if augment:                                             # each epoch's draw differs from every other one
            assert all(not torch.equal(a, b) for i, a in enumerate(seen) for b in seen[i + 1:])
        else:                                                   # --no-augment: the same guesses every epoch
            assert all(torch.equal(seen[0], b) for b in seen[1:])


def test_cli_writes_checkpoint_with_config(tmp_path, capsys):
    out = tmp_path / "ck.pt"
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--eta", "20",
                 "--out", str(out), "--quiet", "--seed", "5", "--threads", "1"], prog="gnssfuse train") == 0
    cfg = read_checkpoint(out)["config"]
    assert cfg["eta"] == 20.0 and cfg["features"]["version"] == FEATURE_VERSION and cfg["seed"] == 5
    assert cfg["model"]["kind"] == "set" and cfg["data"]["n_train"] + cfg["data"]["n_val"] == 80
    # the defaults: every context channel but the opt-in heading, learned-weight WLS output, three-loss mix,
    # box/wls/graph guesses
    width = sum(CHANNELS[c] for c in RECIPE_INPUTS)
    assert "heading" not in RECIPE_INPUTS and set(RECIPE_INPUTS) | {"heading"} == set(CHANNELS)
    assert cfg["features"]["inputs"] == list(RECIPE_INPUTS) and cfg["model"]["hparams"]["d_in"] == width
    assert cfg["dropout"]["pr_sigma"] > 0 and (tmp_path / "ck.npz").is_file()
    assert cfg["output"] == "wls" and cfg["loss"]["sat"] == 0.1 and cfg["loss"]["wls"] == 1.0
    assert cfg["guess_mix"] == {"box": 0.2, "wls": 0.5, "graph": 0.3} and cfg["data"]["val_split"] == "traces"
    assert set(cfg["calibration"]) == {"wls", "correction"}
    assert all(len(c["scale_ned"]) == 3 for c in cfg["calibration"].values())
    assert len(cfg["input_ranges"]["lo"]) == len(cfg["input_ranges"]["hi"]) == width
    assert "best epoch 1" in capsys.readouterr().out


def test_cli_inputs_output_and_loss_options(tmp_path, capsys):
    out = tmp_path / "paper.pt"
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--out", str(out),
                 "--quiet", "--threads", "1", "--inputs", "res,los,cn0", "--output", "correction",
                 "--loss", "sat=0,wls=0.5", "--guess-mix", "box=0.5,wls=0.5", "--val-split", "random"]) == 0
    cfg = read_checkpoint(out)["config"]
    assert cfg["features"]["inputs"] == ["res", "los", "cn0"] and cfg["model"]["hparams"]["d_in"] == 6
    assert cfg["output"] == "correction" and cfg["loss"] == {"correction": 1.0, "sat": 0.0, "wls": 0.5,
                                                             "wls_scale": 5.0, "shrink": 1.0}
    assert Corrector.load(out).output == "correction"
    tuned = tmp_path / "tuned.pt"                             # --init: fine-tune it, the same network and inputs
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--out", str(tuned),
                 "--quiet", "--threads", "1", "--inputs", "res,los,cn0", "--output", "correction",
                 "--val-split", "random", "--init", str(out)]) == 0
    assert read_checkpoint(tuned)["config"]["init"] == str(out)
    # a checkpoint that cannot start the run is refused before any data is read (this data does not exist)
    with pytest.raises(CheckpointError, match="paper.pt: cannot start from it, its 'model' differs"):
        main(["--data", str(tmp_path / "nope"), "--epochs", "1", "--out", str(tmp_path / "x.pt"), "--init", str(out)])
    capsys.readouterr()
    with pytest.raises(DataError, match="--loss: unknown term 'nll'"):
        parse_loss("nll=1")
    with pytest.raises(DataError, match="name=number"):
        parse_loss("sat=lots")
    with pytest.raises(DataError, match="--inputs"):
        main(["--data", "toy", "--sim-traces", "1", "--sim-epochs", "20", "--inputs", "los,res",
              "--out", str(tmp_path / "x.pt"), "--quiet"])
    with pytest.raises(SystemExit):                                   # argparse rejects an unknown output
        main(["--data", "toy", "--output", "direct", "--out", str(tmp_path / "x.pt")])


def test_train_config_checkpoint_config_follows_the_inputs():
    cfg = TrainConfig(features=FeatureConfig(inputs=("res", "los", "pr_sigma", "arc")), hparams={"d_model": 32})
    c = cfg.to_checkpoint_config()
    assert c["model"]["hparams"] == {"d_model": 32, "d_in": 7} and c["features"]["inputs"] == ["res", "los",
                                                                                             "pr_sigma", "arc"]
    assert c["output"] == "wls" and set(c["loss"]) == {"correction", "sat", "wls", "wls_scale", "shrink"}
    assert TrainConfig().to_checkpoint_config()["model"]["hparams"]["d_in"] == 4      # the paper's inputs
    with pytest.raises(DataError, match="output must be one of"):
        train(build_samples(toy_dataset(1, 10, seed=1)), build_samples(toy_dataset(1, 10, seed=2)),
              TrainConfig(epochs=1, output="direct"), "/nonexistent/never.pt", progress=False)


def test_forbidden_traces_and_bad_args_rejected(tmp_path):
    with pytest.raises(DataError, match="held-out test trace"):
        check_not_forbidden(tmp_path / "train" / "2021-04-28-US-MTV-1" / "Pixel4")
    with pytest.raises(DataError, match="held-out"):
        check_not_forbidden(tmp_path / "2021-04-28-US-SJC-1" / "Pixel4")
    with pytest.raises(DataError, match="held-out"):       # the raw-measurement test trace too
        check_not_forbidden(tmp_path / "2021-04-28-US-MTV-1" / "Pixel5")
    check_not_forbidden(tmp_path / "2021-04-28-US-MTV-1" / "Pixel4XL")  # other phones of that drive: allowed
    with pytest.raises(DataError, match="--epochs"):
        main(["--data", "toy", "--epochs", "0", "--out", str(tmp_path / "x.pt")])
    for bad in (["--eta", "nan"], ["--lr", "nan"], ["--lr", "-1"]):
        with pytest.raises(DataError, match=bad[0]):
            main(["--data", "toy", *bad, "--out", str(tmp_path / "x.pt")])
    with pytest.raises(DataError, match="does not exist"):
        main(["--data", str(tmp_path / "nope"), "--out", str(tmp_path / "x.pt"), "--quiet"])


def test_train_signals_all_teaches_every_constellation_of_the_data(tmp_path, capsys):
    """``--signals all`` trains on every signal of a multi-constellation trace (here a simulated city one):
    its checkpoint records them and its guard then reads none of the trace's signals as unseen; by default
    training reads GPS L1 only and the other signals stay unknown to the network."""
    from fusion.cli import main as cli
    from fusion.prepare.load import load_trace
    from fusion.estimate.wls import solve_wls

    assert cli(["simulate", "--out", str(tmp_path / "sim"), "--scenario", "urban", "--epochs", "40",
                "--collection", "c", "--phone", "p", "--seed", "3"]) == 0
    trace_dir = tmp_path / "sim" / "c" / "p"
    common = ["--data", str(trace_dir), "--epochs", "1", "--guess-mix", "box=1", "--val-split", "random",
              "--quiet", "--threads", "1"]
    assert main([*common, "--signals", "all", "--out", str(tmp_path / "all.pt")]) == 0
    assert main([*common, "--out", str(tmp_path / "l1.pt")]) == 0
    tr = load_trace(trace_dir, signals=("GPS_L1", "GLO_G1", "GAL_E1", "BDS_B1I"))
    w = solve_wls(tr)
    unseen = {}
    for name in ("all", "l1"):
        ckpt = tmp_path / f"{name}.pt"
        info = Corrector.load(ckpt).predict(tr, w.pos, w.valid).info
        unseen[name] = info.get("meas_signal_unseen_in_training", 0)
    assert "GAL_E1" in read_checkpoint(tmp_path / "all.pt")["config"]["signals"]
    assert read_checkpoint(tmp_path / "l1.pt")["config"]["signals"] == ["GPS_L1"]
    assert unseen["all"] == 0 < unseen["l1"]
    assert cli(["train", *common, "--signals", "GPS_X9", "--out", str(tmp_path / "bad.pt")]) == 2
    assert "unknown signal name" in capsys.readouterr().err


def test_a_root_leaves_its_test_traces_out_and_a_named_test_trace_is_refused(shipped_trace_dir, tmp_path):
    """A Kaggle ``train/`` folder holds the 2021-04-28 test drives: found under a root they are left out
    with a warning naming them; named themselves, or all a root holds, they are refused."""
    import shutil

    from learned.data import load_real_traces

    root = tmp_path / "train"
    test_dir, other = root / "2021-04-28-US-MTV-1" / "Pixel4", root / "2020-01-02-US-ABC-1" / "Pixel4"
    for d in (test_dir, other):
        shutil.copytree(shipped_trace_dir, d)
    with pytest.warns(UserWarning, match=r"left out 1 held-out test trace.*2021-04-28-US-MTV-1"):
        traces = load_real_traces([root])
    assert len(traces) == 1
    with pytest.raises(DataError, match="held-out test trace"):
        load_real_traces([test_dir])
    shutil.rmtree(other.parent)
    with pytest.warns(UserWarning), pytest.raises(DataError, match="every trace under it is a held-out"):
        load_real_traces([root])
