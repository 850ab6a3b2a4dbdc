"""Features and augmentation: numpy/torch agreement, clock handling, frames, targets."""
from __future__ import annotations

import numpy as np
import torch

from fusion.geometry import ecef2ned_vec, ned_rotation
from learned.augment import draw_guesses, epoch_generator
from learned.features import (FeatureConfig, elevation_mask, features_numpy, features_torch,
                              masked_median_numpy, ned_rotation_torch, target_numpy, target_torch)
from learned.toy import toy_trace


def _t(a):
    return torch.as_tensor(a, dtype=torch.float64) if a.dtype != bool else torch.as_tensor(a)


def test_numpy_and_torch_features_agree():
    tr = toy_trace(50, seed=1)
    guess = tr.truth + np.random.default_rng(0).uniform(-15, 15, (50, 3))
    xn, clock = features_numpy(tr.sat_pos, tr.pr, tr.mask, guess)
    xt, R = features_torch(_t(tr.sat_pos), _t(tr.pr), _t(tr.mask), _t(guess))
    np.testing.assert_allclose(xt.numpy(), xn, atol=1e-5)
    np.testing.assert_allclose(R.numpy(), ned_rotation(guess), atol=1e-12)
    yt = target_torch(_t(tr.truth), _t(guess), R).numpy()
    np.testing.assert_allclose(yt, target_numpy(tr.truth, guess), atol=1e-5)
    assert np.all(xn[~tr.mask] == 0)


def test_ned_rotation_torch_matches_pymap3d_frame_everywhere():
    rng = np.random.default_rng(3)
    llh = np.c_[rng.uniform(-89, 89, 200), rng.uniform(-180, 180, 200), rng.uniform(-100, 5000, 200)]
    from fusion.geometry import geodetic2ecef
    x = geodetic2ecef(llh)
    np.testing.assert_allclose(ned_rotation_torch(_t(x)).numpy(), ned_rotation(x), atol=1e-11)


def test_residuals_are_linear_model_of_offset_and_clock_is_removed():
    # Noise-free: residual ~ -los . dx (up to the common clock offset removed by the median).
    tr = toy_trace(20, seed=2, sigma=0.0, clock_m=3e5)
    dx_ned = np.array([4.0, -3.0, 2.0])
    R = ned_rotation(tr.truth)
    guess = tr.truth - np.einsum("eji,j->ei", R, dx_ned)          # truth = guess + dx (NED)
    x, clock = features_numpy(tr.sat_pos, tr.pr, tr.mask, guess, FeatureConfig(res_scale=1.0))
    res, los = x[..., 0], x[..., 1:]
    pred = -(los @ dx_ned.astype(np.float32))
    diff = np.where(tr.mask, res - pred, np.nan)
    # What remains after the median is the same constant for every slot of an epoch.
    spread = np.nanmax(diff, 1) - np.nanmin(diff, 1)
    assert spread.max() < 1e-3
    # The estimated clock is near the true one (~3e5 m scale), never the truth's.
    assert np.all(np.abs(clock) > 1.0)
    np.testing.assert_allclose(target_numpy(tr.truth, guess, FeatureConfig(out_scale=1.0)),
                               np.broadcast_to(dx_ned, (20, 3)), atol=1e-4)


def test_median_ignores_one_biased_satellite():
    vals = np.array([[1.0, 2.0, 3.0, 500.0, 0.0], [5.0, 5.0, 5.0, 5.0, 5.0]])
    mask = np.array([[True, True, True, True, False], [True] * 5])
    np.testing.assert_allclose(masked_median_numpy(vals, mask), [2.0, 5.0])
    t = torch.tensor(vals).masked_fill(~torch.tensor(mask), float("nan")).nanmedian(1).values
    np.testing.assert_allclose(t.numpy(), [2.0, 5.0])


def test_elevation_mask_drops_low_satellites():
    tr = toy_trace(30, seed=4, min_elev_deg=5.0)
    m10 = elevation_mask(tr.sat_pos, tr.mask, tr.truth, 10.0)
    m5 = elevation_mask(tr.sat_pos, tr.mask, tr.truth, 4.0)
    assert (m5 == tr.mask).all() and m10.sum() < tr.mask.sum() and not (m10 & ~tr.mask).any()


def test_augmentation_box_in_ned_of_truth_and_seeded():
    tr = toy_trace(4000, seed=5)
    truth = _t(tr.truth)
    g1 = draw_guesses(truth, 15.0, epoch_generator(0, 3))
    g2 = draw_guesses(truth, 15.0, epoch_generator(0, 3))
    g3 = draw_guesses(truth, 15.0, epoch_generator(0, 4))
    assert torch.equal(g1, g2) and not torch.equal(g1, g3)
    off = ecef2ned_vec(g1.numpy() - tr.truth, tr.truth)
    assert np.abs(off).max() <= 15.0 + 1e-6
    assert np.abs(off).max() > 14.5                       # fills the box
    np.testing.assert_allclose(off.mean(0), 0, atol=0.6)  # uniform, zero-mean (sd of mean ~0.14)
    np.testing.assert_allclose(off.std(0), 15 / np.sqrt(3), rtol=0.05)
