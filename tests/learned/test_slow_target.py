"""The lasting-error target (``TrainConfig.slow_target_s``): each pseudorange's fast error part is its error at
the truth minus the centred window mean along its satellite and signal; training scores the per-satellite losses
on what is left, reproducibly, and refuses samples built for another target."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from fusion.cli.train import main
from fusion.errors import DataError
from fusion.geometry import line_of_sight
from learned.checkpoint import read_checkpoint
from learned.data import build_samples, fast_error, split_random
from learned.features import line_of_sight_torch
from learned.losses import weighted_ls_step
from learned.toy import toy_dataset
from learned.train import LossWeights, TrainConfig, batch_loss, train


def _brute_fast(tr, window_s):
    """The same quantity by loops: error after the epoch median, minus its mean over the arc's window."""
    rng, _ = line_of_sight(tr.sat_pos, tr.truth)
    ok = tr.mask & np.isfinite(tr.truth).all(1)[:, None]
    r = np.where(ok, tr.pr - rng, np.nan)
    e = r - np.nanmedian(r, axis=1, keepdims=True)
    t = tr.t_ms / 1000.0
    out = np.full(e.shape, np.nan)
    for i, s in zip(*np.nonzero(ok)):
        same = ok & (tr.sat_id == tr.sat_id[i, s]) & (tr.signal == tr.signal[i, s])
        near = same & (np.abs(t - t[i])[:, None] <= window_s / 2)
        out[i, s] = e[i, s] - e[near].mean()
    return out


@pytest.fixture(scope="module")
def toy():
    tr = toy_dataset(1, 40, seed=5)[0]
    mask = tr.mask.copy()
    mask[10:14, 2] = False                                   # an arc with a gap
    # a second signal of satellite 3 in slot 9, and times with a 20 s jump
    sat_id, signal = tr.sat_id.copy(), tr.signal.copy()
    sat_id[:, 9], signal[:, 9] = sat_id[:, 3], 1
    t_ms = tr.t_ms + np.where(np.arange(len(tr.t_ms)) >= 25, 20_000, 0)
    return replace(tr, mask=mask, sat_id=sat_id, signal=signal, t_ms=t_ms)


def test_fast_error_matches_the_loops(toy):
    got, want = fast_error(toy, 7.0), _brute_fast(toy, 7.0)
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.isfinite(got).sum() > 300
    assert np.allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-6)


def test_an_error_that_lasts_the_whole_arc_is_no_fast_error(toy):
    biased = replace(toy, pr=toy.pr + np.where(np.arange(toy.pr.shape[1]) == 4, 50.0, 0.0))
    a, b = fast_error(toy, 7.0), fast_error(biased, 7.0)
    # the epoch median moves by at most one slot's share; slot 4's own fast part does not see the 50 m
    col = np.isfinite(a[:, 4])
    assert np.abs(b[col, 4] - a[col, 4]).max() < 5.0 and np.abs(b[col, 4]).max() < 20.0


def test_training_on_the_lasting_part_differs_reproducibly_and_is_recorded(tmp_path):
    torch.set_num_threads(1)
    traces = toy_dataset(3, 60, seed=7)
    slow = split_random(build_samples(traces, slow_window_s=15.0), 0.2, np.random.default_rng(0))
    plain = split_random(build_samples(traces), 0.2, np.random.default_rng(0))
    assert slow[0].pr_fast is not None and plain[0].pr_fast is None
    cfg = TrainConfig(epochs=1, seed=3, slow_target_s=15.0)
    for name in ("a", "b"):
        train(*slow, cfg, tmp_path / f"{name}.pt", progress=False)
    train(*plain, TrainConfig(epochs=1, seed=3), tmp_path / "plain.pt", progress=False)
    w = {n: read_checkpoint(tmp_path / f"{n}.pt") for n in ("a", "b", "plain")}
    assert all(torch.equal(w["a"]["model_state"][k], w["b"]["model_state"][k]) for k in w["a"]["model_state"])
    assert not all(torch.equal(w["a"]["model_state"][k], w["plain"]["model_state"][k]) for k in w["a"]["model_state"])
    assert w["a"]["config"]["slow_target_s"] == 15.0 and "slow_target_s" not in w["plain"]["config"]
    with pytest.raises(DataError, match="slow_target_s"):
        train(*plain, cfg, tmp_path / "x.pt", progress=False)
    with pytest.raises(DataError, match="slow_target_s"):
        train(*slow, TrainConfig(epochs=1), tmp_path / "y.pt", progress=False)


def test_the_losses_read_the_target_not_the_measurement():
    g = torch.Generator().manual_seed(0)
    B, S = 6, 7
    b = {"sat_pos": torch.randn(B, S, 3, generator=g, dtype=torch.float64) * 2e7,
         "truth": torch.randn(B, 3, generator=g, dtype=torch.float64) * 10 + torch.tensor([6.37e6, 0, 0]),
         "mask": torch.ones(B, S, dtype=torch.bool), "y": torch.zeros(B, 3),
         "R": torch.eye(3, dtype=torch.float64).expand(B, 3, 3)}
    rng, _ = line_of_sight_torch(b["sat_pos"], b["truth"])
    b["pr"] = rng + torch.randn(B, S, generator=g, dtype=torch.float64) * 5
    b["guess"] = b["truth"] + 3.0
    out = {"mean": torch.zeros(B, 3), "logvar": torch.zeros(B, 3),
           "sigma": torch.full((B, S), 3.0, dtype=torch.float64), "bias": torch.zeros(B, S, dtype=torch.float64)}
    out["pos"] = weighted_ls_step(b["sat_pos"], b["pr"], b["mask"], b["guess"], out["sigma"], out["bias"])[0]
    w = LossWeights(shrink=0.0)
    plain = batch_loss(out, b, w, False)
    assert torch.isclose(batch_loss(out, dict(b, pr_target=b["pr"].clone()), w, False), plain)
    assert batch_loss(out, dict(b, pr_target=rng.clone()), w, False) < plain       # no error left to score


def test_the_train_command_takes_the_window_and_refuses_a_negative_one(tmp_path):
    out = tmp_path / "slow.pt"
    args = ["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--quiet", "--threads", "1"]
    assert main(args + ["--out", str(out), "--slow-target", "10"]) == 0
    assert read_checkpoint(out)["config"]["slow_target_s"] == 10.0
    with pytest.raises(DataError, match="--slow-target"):
        main(args + ["--out", str(tmp_path / "neg.pt"), "--slow-target", "-1"])
    assert not (tmp_path / "neg.pt").exists()
