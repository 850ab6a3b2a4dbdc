"""experiments/precise_holes.py: the interpolation error a hole cut into an orbit file leaves."""
from __future__ import annotations

import numpy as np

from fusion.io.sp3 import Sp3Orbits
from tests.experiment_module import experiment_module


def test_a_wider_hole_leaves_a_larger_error_and_a_narrow_one_next_to_none(monkeypatch):
    """A circular orbit sampled every 5 minutes: a 10-min step interpolates back to well under a millimetre, a
    150-min one a thousand times worse (the real file's perturbed orbits, hundreds of metres: what MAX_STEP_S
    keeps out); the experiment lifts the run's limit to measure it."""
    mod = experiment_module("precise_holes")
    monkeypatch.setattr(mod.precise, "MAX_STEP_S", np.inf)
    t = np.arange(200) * 300_000
    phase = 2 * np.pi * t[:, None] / 43_082_000.0 + np.array([0.0, 1.0])         # GPS-like period, two satellites
    pos = 26_560e3 * np.stack([np.cos(phase), np.sin(phase), 0.3 * np.sin(phase)], axis=-1)
    orb = Sp3Orbits(t_ms=t, sats=np.array(["G01", "G02"]), pos=pos, source="circle.sp3")
    narrow, wide = mod.hole_errors(orb, 2).max(), mod.hole_errors(orb, 30).max()
    assert narrow < 1e-3 and wide > 1000 * narrow
