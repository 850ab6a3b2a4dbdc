"""experiments/sigma_calibration.py's ``tune --keep``: the setting in variance_factor.DEFAULTS kept, its levels
refitted on the collected runs."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from tests.experiment_module import experiment_module


def _runs(mod, sigma_err: float, sigma_reported: float, n: int = 400) -> dict:
    """Collected wls runs of every GSDC drive: errors of sigma_err [m] where sigma_reported is reported, residuals
    that fit their model (F = 1)."""
    rng = np.random.default_rng(0)
    return {name: {"t": np.arange(n, dtype=float), "wls/err": rng.normal(0.0, sigma_err, (n, 3)),
                   "wls/var": np.full((n, 3), sigma_reported ** 2), "wls/snap": np.zeros((n, 3)),
                   "wls/chi2": np.full(n, 10.0), "wls/dof": np.full(n, 10.0)}
            for drives in mod.FOLDS.values() for name in drives}


def test_keep_refits_only_the_levels_and_scores_the_setting_as_the_grid_would():
    mod = experiment_module("sigma_calibration")
    data = _runs(mod, 3.0, 2.0)
    cal, cov, pen = mod.kept_mode(data, "wls")
    shipped = mod.DEFAULTS["wls"]
    assert replace(cal, a=shipped.a) == shipped                          # window, exponent, floors... as they were
    assert np.allclose(cal.a, (3.0 / 2.0) ** 2, rtol=0.1)                 # errors 1.5 x the reported sigma
    want_pen, want_cov = mod.held_out(data, "wls", shipped)
    assert pen == want_pen and cov.keys() == want_cov.keys()
    assert all(np.allclose(cov[k], want_cov[k]) for k in cov)
    assert mod.tuned_mode(data, "wls", ("wls",))[0] == cal
