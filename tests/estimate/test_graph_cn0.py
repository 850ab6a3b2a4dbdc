"""Doppler sigmas follow C/N0 where the trace has it (GraphConfig.prr_cn0_ref_dbhz)."""
from __future__ import annotations

import dataclasses

import numpy as np

from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.raw_inputs import cn0_scale, doppler_slots
from fusion.sim.simulate import SimConfig, simulate


def _trace(cn0):
    tr = simulate(n_epochs=20, seed=2, config=SimConfig(doppler=True, carrier=False)).trace
    return dataclasses.replace(tr, cn0=np.where(tr.mask, cn0, 0.0))


def test_weak_signals_get_larger_doppler_sigmas_and_unknown_cn0_keeps_the_reported_one():
    tr = _trace(25.0)
    np.testing.assert_allclose(cn0_scale(tr, 35.0)[tr.mask], 10 ** 0.5)
    np.testing.assert_allclose(cn0_scale(dataclasses.replace(tr, cn0=None), 35.0), 1.0)
    np.testing.assert_allclose(cn0_scale(_trace(45.0), 35.0)[tr.mask], 1.0)     # strong: as reported
    above = np.ones(tr.mask.shape, bool)
    has_clock = np.ones(tr.n_epochs, bool)
    weak, _ = doppler_slots(tr, above, has_clock, GraphConfig(), {})
    s_weak = doppler_slots(tr, above, has_clock, GraphConfig(), {})[1]
    s_off = doppler_slots(tr, above, has_clock, GraphConfig(prr_cn0_ref_dbhz=0.0), {})[1]
    assert weak.any()
    assert np.all(s_weak[weak] > 2.0 * s_off[weak])
