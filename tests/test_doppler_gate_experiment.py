"""experiments/doppler_gate.py's helpers: the gate reaches exactly the epochs within its window, and
down-weights (or drops) Doppler and carrier of those epochs only."""
from __future__ import annotations

import numpy as np

from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.sim.simulate import SimConfig, simulate_dataset
from tests.experiment_module import experiment_module


def test_within_matches_the_brute_force_distance_to_the_nearest_flagged_epoch():
    mod = experiment_module("doppler_gate")
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.choice([1.0, 1.0, 1.0, 7.0], 300))          # 1 s epochs with gaps
    for p in (0.0, 0.01, 0.2):
        rows = rng.random(300) < p
        got = mod.within(t, rows, 5.0)
        want = (np.abs(t[:, None] - t[rows][None, :]) <= 5.0).any(1) if rows.any() else np.zeros(300, bool)
        assert np.array_equal(got, want)


def test_down_weighted_touches_only_the_gated_epochs():
    mod = experiment_module("doppler_gate")
    nav = read_rinex_nav(default_nav_path())
    tr = simulate_dataset(1, 20, seed=1, nav=nav, config=SimConfig(doppler=True, carrier=True))[0]
    rows = np.zeros(tr.n_epochs, bool)
    rows[5:9] = True
    x3 = mod.down_weighted(tr, rows, 3.0)
    assert np.allclose(x3.prr_sigma[rows], 3 * tr.prr_sigma[rows]) and np.allclose(x3.adr_sigma[rows],
                                                                                   3 * tr.adr_sigma[rows])
    assert np.array_equal(x3.prr_sigma[~rows], tr.prr_sigma[~rows]) and np.array_equal(x3.prr_ok, tr.prr_ok)
    off = mod.down_weighted(tr, rows, 0.0)
    assert not off.prr_ok[rows].any() and not off.adr_ok[rows].any()
    assert np.array_equal(off.prr_ok[~rows], tr.prr_ok[~rows]) and tr.prr_ok[rows].any()
