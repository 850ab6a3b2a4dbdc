"""experiments/shift_lowpass.py: the moving mean skips incomplete rows, and a shift moves north and east only."""
from __future__ import annotations

import numpy as np

from tests.experiment_module import experiment_module


def test_moving_mean_is_centred_and_skips_rows_with_a_nan():
    mod = experiment_module("shift_lowpass")
    x = np.array([[1.0], [np.nan], [3.0], [5.0], [7.0]])
    m = mod.moving_mean(x, 3)
    assert np.allclose(m[:, 0], [1.0, 2.0, 4.0, 5.0, 6.0])          # row 1's window holds rows 0 and 2 only
    assert np.allclose(mod.moving_mean(x, 0)[:, 0], 4.0)             # the whole drive
    assert np.isnan(mod.moving_mean(np.full((3, 1), np.nan), 3)).all()


def test_a_shift_moves_the_horizontal_by_alpha_times_the_slow_difference():
    mod = experiment_module("shift_lowpass")
    fused = np.zeros((50, 3))
    toward = np.tile([2.0, -1.0, 5.0], (50, 1))
    out = mod.shifted(fused, toward, fused, 0.5, 0)
    assert np.allclose(out, [1.0, -0.5, 0.0])                       # down untouched
    gap = toward.copy()
    gap[10] = np.nan                                                   # an epoch one mode did not solve
    assert np.allclose(mod.shifted(fused, gap, fused, 0.5, 0), [1.0, -0.5, 0.0])
