"""experiments/carrier_calibration.py's score of the shipped carrier setting on the collected runs."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from tests.experiment_module import experiment_module


def _runs(sigma_err: float, n_traces: int = 8, n: int = 300) -> dict:
    """Collected ``fused`` runs: carrier-tied epochs with errors of sigma_err [m] and raw variances of 1 m^2,
    residuals that fit their model (F = 1), no floor share needed beyond the setting's own."""
    rng = np.random.default_rng(1)
    return {f"sim/t{k}": {"t": np.arange(n, dtype=float), "fused/err": rng.normal(0.0, sigma_err, (n, 3)),
                          "fused/var": np.ones((n, 3)), "fused/snap": np.zeros((n, 3)),
                          "fused/carrier": np.ones(n, bool), "wls/chi2": np.full(n, 10.0),
                          "wls/dof": np.full(n, 10.0)}
            for k in range(n_traces)}


def test_the_shipped_setting_is_scored_as_it_is_and_with_its_levels_refitted(monkeypatch):
    mod = experiment_module("carrier_calibration")
    shipped = replace(mod.CARRIER_DEFAULTS["fused"], a=(1.0, 1.0, 1.0), floor_m=(0.0, 0.0, 0.0), snapshot=0.0)
    monkeypatch.setitem(mod.CARRIER_DEFAULTS, "fused", shipped)
    data = _runs(3.0)
    names = sorted(data)
    line = mod.shipped_scores(data, names, "fused")
    # the levels as they are: sigma 1 m against errors of 3 m, a quarter within: every axis of every trace out
    assert f"{3 * len(names)} trace-axes out" in line
    pen, held = mod.held_out(mod.carrier_items(data, names, "fused", shipped), shipped.b, np.zeros(3))
    assert f"its levels refitted leave-fold-out, penalty {pen:.3f}, {mod.n_outside(held)} out" in line
    assert mod.n_outside(held) < 3 * len(names)                           # refitted, the levels follow the errors
    assert mod.shipped_scores(data, names, "fused-nodnn") is None         # no carrier setting shipped for it
