"""Training loop: reproducibility, resume, augmentation modes, CLI and data guards (tiny toy data)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fusion.errors import CheckpointError, DataError
from learned.checkpoint import read_checkpoint
from learned.data import build_samples, check_not_forbidden, split_random
from learned.features import FEATURE_VERSION
from learned.toy import toy_dataset
from learned.train import TrainConfig, main, train


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


def test_resume_reproduces_uninterrupted_run(tiny, tmp_path):
    tr, va = tiny
    cfg = dict(seed=1, warmup_epochs=1)
    train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "full.pt", progress=False)
    train(tr, va, TrainConfig(epochs=1, **cfg), tmp_path / "part.pt", progress=False)
    hist = train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "part.pt", resume=True, progress=False)
    assert [h["epoch"] for h in hist] == [1, 2] and hist[1]["nll"]
    full, part = (read_checkpoint(tmp_path / f"{n}.pt.last") for n in ("full", "part"))
    assert _same(full["model_state"], part["model_state"])
    with pytest.raises(CheckpointError, match="'eta' differs"):
        train(tr, va, TrainConfig(epochs=3, eta=30.0, **cfg), tmp_path / "part.pt", resume=True, progress=False)
    with pytest.raises(CheckpointError, match="no checkpoint to resume"):
        train(tr, va, TrainConfig(epochs=1), tmp_path / "none.pt", resume=True, progress=False)


def test_training_learns_and_no_augment_differs(tmp_path):
    torch.set_num_threads(1)
    s = build_samples(toy_dataset(4, 150, seed=11, sigma=1.0))
    tr, va = split_random(s, 0.2, np.random.default_rng(0))
    hist = train(tr, va, TrainConfig(epochs=4, eta=15.0, batch=32, lr=1e-3), tmp_path / "aug.pt", progress=False)
    # Guess error is U(-15, 15) per axis: MAE 7.5 m before correction; the net must beat it clearly.
    assert hist[-1]["val_mae_m"] < 5.0, hist[-1]
    assert hist[-1]["val_mse"] < hist[0]["val_mse"]
    hist2 = train(tr, va, TrainConfig(epochs=1, eta=15.0, batch=32, augment=False), tmp_path / "noaug.pt",
                  progress=False)
    assert hist2[0]["train_mse"] != hist[0]["train_mse"]


def test_augmentation_redraws_guesses_each_epoch_and_no_augment_keeps_them(tmp_path, monkeypatch):
    import learned.train as lt

    s = build_samples(toy_dataset(2, 60, seed=3, sigma=1.0))
    tr, va = split_random(s, 0.2, np.random.default_rng(0))
    seen = []
    real = lt.make_inputs

    def spy(t, guess, fcfg):
        if guess.shape[0] == len(tr):  # the training set's guesses (validation is smaller)
            seen.append(guess.clone())
        return real(t, guess, fcfg)

    monkeypatch.setattr(lt, "make_inputs", spy)
    for augment, expect_sets in ((True, 3), (False, 1)):
        seen.clear()
        train(tr, va, TrainConfig(epochs=3, eta=15.0, batch=32, augment=augment), tmp_path / f"{augment}.pt",
              progress=False)
        assert len(seen) == expect_sets
        # Each epoch's draw differs from every other one.
        assert all(not torch.equal(a, b) for i, a in enumerate(seen) for b in seen[i + 1:])


def test_cli_writes_checkpoint_with_config(tmp_path, capsys):
    out = tmp_path / "ck.pt"
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--eta", "20",
                 "--out", str(out), "--quiet", "--seed", "5", "--threads", "1"], prog="gnssfuse train") == 0
    cfg = read_checkpoint(out)["config"]
    assert cfg["eta"] == 20.0 and cfg["features"]["version"] == FEATURE_VERSION and cfg["seed"] == 5
    assert cfg["model"]["kind"] == "set" and cfg["data"]["n_train"] + cfg["data"]["n_val"] == 80
    assert "best epoch 1" in capsys.readouterr().out


def test_direct_model_trains_with_reference(tiny, tmp_path):
    tr, va = tiny
    train(tr, va, TrainConfig(epochs=1, model="direct"), tmp_path / "d.pt", progress=False)
    cfg = read_checkpoint(tmp_path / "d.pt")["config"]
    assert cfg["reference_ecef"] is not None and cfg["features"]["out_scale"] == 1000.0


def test_forbidden_traces_and_bad_args_rejected(tmp_path):
    with pytest.raises(DataError, match="held-out test trace"):
        check_not_forbidden(tmp_path / "train" / "2021-04-28-US-MTV-1" / "Pixel4")
    with pytest.raises(DataError, match="held-out"):
        check_not_forbidden(tmp_path / "2021-04-28-US-SJC-1" / "Pixel4")
    check_not_forbidden(tmp_path / "2021-04-28-US-MTV-1" / "Pixel5")  # other phone of that drive: allowed
    with pytest.raises(DataError, match="--epochs"):
        main(["--data", "toy", "--epochs", "0", "--out", str(tmp_path / "x.pt")])
    with pytest.raises(DataError, match="does not exist"):
        main(["--data", str(tmp_path / "nope"), "--out", str(tmp_path / "x.pt"), "--quiet"])


def test_direct_model_keeps_the_given_clock_mode(tmp_path):
    """The direct model rescales its features; it used to rebuild FeatureConfig and silently drop
    ``clock="given"``, so a paper-leak experiment would have trained on the median clock instead."""
    from dataclasses import replace

    from learned.data import samples_from_trace
    from learned.features import FeatureConfig
    from learned.toy import toy_trace

    torch.set_num_threads(1)
    tr = toy_trace(40, seed=5)
    s = samples_from_trace(tr, clock=np.zeros(tr.n_epochs), with_wls=False)
    s = replace(s, clock=np.full(len(s), 123.0))
    train(s, s.subset(np.arange(0)), TrainConfig(epochs=1, model="direct", features=FeatureConfig(clock="given")),
          tmp_path / "leak.pt", progress=False)
    f = read_checkpoint(tmp_path / "leak.pt")["config"]["features"]
    assert f["clock"] == "given" and f["res_scale"] == 1000.0 and f["out_scale"] == 1000.0
