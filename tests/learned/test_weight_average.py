"""The weight average (``TrainConfig.ema_decay``, ``gnssfuse train --ema``): what is saved, and resume."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fusion.errors import CheckpointError, DataError
from learned.checkpoint import read_checkpoint
from learned.data import build_samples, split_random
from learned.toy import toy_dataset
from learned.train import TrainConfig, train
from fusion.cli.train import main


@pytest.fixture(scope="module")
def tiny():
    torch.set_num_threads(1)
    s = build_samples(toy_dataset(3, 60, seed=7))
    return split_random(s, 0.2, np.random.default_rng(0))


def _same(a, b):
    return all(torch.equal(a[k], b[k]) for k in a)


def test_the_saved_network_is_the_average_and_the_last_state_keeps_the_trained_weights(tiny, tmp_path):
    tr, va = tiny
    train(tr, va, TrainConfig(epochs=1, seed=2, ema_decay=0.9), tmp_path / "avg.pt", progress=False)
    saved, last = read_checkpoint(tmp_path / "avg.pt"), read_checkpoint(tmp_path / "avg.pt.last")
    assert saved["config"]["ema_decay"] == 0.9 and saved["epoch"] == 1
    assert not _same(saved["model_state"], last["model_state"])
    module = {k[len("module."):]: v for k, v in last["average_state"].items() if k.startswith("module.")}
    assert _same(saved["model_state"], module)
    # a decay of ~0 averages nothing: the saved network is the trained one, as without the option
    train(tr, va, TrainConfig(epochs=1, seed=2, ema_decay=1e-12), tmp_path / "none.pt", progress=False)
    train(tr, va, TrainConfig(epochs=1, seed=2), tmp_path / "off.pt", progress=False)
    off = read_checkpoint(tmp_path / "off.pt")
    assert "ema_decay" not in off["config"] and "average_state" not in read_checkpoint(tmp_path / "off.pt.last")
    assert all(torch.allclose(v, off["model_state"][k], atol=1e-6)
               for k, v in read_checkpoint(tmp_path / "none.pt")["model_state"].items())


def test_a_resumed_run_averages_as_an_uninterrupted_one(tiny, tmp_path):
    tr, va = tiny
    cfg = dict(seed=1, warmup_epochs=1, ema_decay=0.95)
    train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "full.pt", progress=False)
    train(tr, va, TrainConfig(epochs=1, **cfg), tmp_path / "part.pt", progress=False)
    train(tr, va, TrainConfig(epochs=2, **cfg), tmp_path / "part.pt", resume=True, progress=False)
    full, part = (read_checkpoint(tmp_path / f"{n}.pt.last") for n in ("full", "part"))
    assert _same(full["average_state"], part["average_state"])
    with pytest.raises(CheckpointError, match="'ema_decay' differs"):
        train(tr, va, TrainConfig(epochs=3, seed=1, warmup_epochs=1, ema_decay=0.9), tmp_path / "part.pt",
              resume=True, progress=False)


def test_cli_writes_the_decay_and_refuses_one_outside_zero_to_one(tmp_path):
    out = tmp_path / "ema.pt"
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--out", str(out),
                 "--quiet", "--threads", "1", "--ema", "0.99"]) == 0
    assert read_checkpoint(out)["config"]["ema_decay"] == 0.99
    with pytest.raises(DataError, match="--ema"):
        main(["--data", "toy", "--epochs", "1", "--ema", "1.5", "--out", str(tmp_path / "x.pt")])

