"""Satellite dropout in training: a sample keeps whole satellites, never fewer than four; a rate changes the
run and is recorded, the recipe's checkpoints read as before."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fusion.errors import CheckpointError
from learned.augment import THIN_MIN_SATS, satellite_groups, thin_satellites
from learned.checkpoint import read_checkpoint
from learned.data import build_samples, split_random
from learned.toy import toy_dataset
from learned.train import TrainConfig, train


def _two_signal_epochs(n_epochs=400, n_sats=9, seed=0):
    """(N,S,3) satellite positions with every satellite's second signal in slot i + n_sats, and the mask."""
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(n_epochs, n_sats, 3)) * 2.0e7
    pos = np.concatenate([pos, pos + rng.normal(size=pos.shape) * 1e-3], axis=1)   # L5: millimetres away
    mask = np.ones((n_epochs, 2 * n_sats), bool)
    mask[:, n_sats:] = rng.random((n_epochs, n_sats)) < 0.5          # not every satellite has a second signal
    mask[:50, 5:n_sats] = False                                       # five satellites: room for one to go
    mask[:50, n_sats + 5:] = False
    return torch.as_tensor(pos), torch.as_tensor(mask)


def test_slots_of_one_satellite_are_grouped():
    pos, mask = _two_signal_epochs()
    g = satellite_groups(pos, mask, chunk=64)
    n = mask.shape[1] // 2
    second = mask[:, n:]
    assert torch.equal(g[:, n:][second], torch.arange(n).expand_as(second)[second])
    assert torch.equal(g[:, :n], torch.arange(n).expand(mask.shape[0], n))


def test_thinning_keeps_whole_satellites_and_at_least_four():
    pos, mask = _two_signal_epochs()
    g = satellite_groups(pos, mask)
    out = thin_satellites(mask, g, 1.0, torch.Generator().manual_seed(1))
    n = mask.shape[1] // 2
    assert not (out & ~mask).any()
    both = mask[:, n:]
    assert torch.equal(out[:, n:][both], out[:, :n][both])            # a satellite goes with all its signals
    kept = out[:, :n].sum(1)
    assert kept.min() >= THIN_MIN_SATS
    assert (kept < n).float().mean() > 0.5                            # most samples lost satellites
    counts = torch.bincount(kept, minlength=n + 1)[THIN_MIN_SATS:]
    assert (counts > 0).all()                                         # every count from four to all of them


def test_rate_is_the_share_of_samples_thinned():
    pos, mask = _two_signal_epochs(n_epochs=4000)
    out = thin_satellites(mask, satellite_groups(pos, mask), 0.3, torch.Generator().manual_seed(2))
    n = mask.shape[1] // 2
    lost = (out[:, :n].sum(1) < mask[:, :n].sum(1)).float().mean().item()
    # k = n is drawn by one sample in n - 3 of those thinned: 0.3 * (1 - 1/6) = 0.25
    assert 0.21 < lost < 0.29


@pytest.fixture(scope="module")
def tiny():
    torch.set_num_threads(1)
    return split_random(build_samples(toy_dataset(3, 60, seed=7)), 0.2, np.random.default_rng(0))


def test_a_rate_changes_the_run_and_is_recorded(tiny, tmp_path):
    tr, va = tiny
    train(tr, va, TrainConfig(epochs=1, seed=3), tmp_path / "a.pt", progress=False)
    train(tr, va, TrainConfig(epochs=1, seed=3, sat_dropout=0.5), tmp_path / "c.pt", progress=False)
    a, c = (read_checkpoint(tmp_path / f"{x}.pt") for x in "ac")
    assert any(not torch.equal(a["model_state"][k], c["model_state"][k]) for k in a["model_state"])
    assert c["config"]["sat_dropout"] == 0.5
    assert "sat_dropout" not in a["config"]                            # checkpoints of the recipe read as before


def test_a_resumed_run_keeps_its_rate(tiny, tmp_path):
    tr, va = tiny
    train(tr, va, TrainConfig(epochs=1, seed=3, sat_dropout=0.5), tmp_path / "r.pt", progress=False)
    with pytest.raises(CheckpointError, match="sat_dropout"):
        train(tr, va, TrainConfig(epochs=2, seed=3), tmp_path / "r.pt", resume=True, progress=False)
