"""experiments/trace_biases.py: trace-level biases solved with every epoch's position and clock eliminated."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.prepare.load import load_trace
from tests.experiment_module import experiment_module


def test_a_delay_scale_added_to_the_pseudoranges_is_found_and_taken_out(shipped_trace_dir):
    mod = experiment_module("trace_biases")
    trace = load_trace(shipped_trace_dir)
    atm = np.nan_to_num(mod.atmosphere(shipped_trace_dir, trace))
    assert (atm[trace.mask][:, 0] > 0).mean() > 0.9            # the file's ionosphere found for its slots
    iono = lambda e, s: (atm[e, s][:, :1], np.array([0]))     # noqa: E731
    before = mod.EpochSystem(trace)
    k0, _, pos0 = before.solve(iono, 1, 1e3)
    # half the modelled ionosphere more on every pseudorange: the scale grows by 0.5, and what it moved the WLS
    # positions by (metres) is taken out again (the step is linear, the WLS weights and exclusions are not)
    after = mod.EpochSystem(replace(trace, pr=trace.pr + 0.5 * atm[..., 0]))
    k1, sd, pos1 = after.solve(iono, 1, 1e3)
    assert abs((k1[0] - k0[0]) - 0.5) < 0.05 and np.isfinite(sd[0])
    both = np.isfinite(pos0).all(axis=1) & np.isfinite(pos1).all(axis=1)
    assert both.sum() > 10
    moved = lambda a, b: np.median(np.linalg.norm(a[both] - b[both], axis=1))     # noqa: E731
    assert moved(after.pos, before.pos) > 1.0
    assert moved(pos1, pos0) < 0.1 * moved(after.pos, before.pos)
    # a tight prior keeps the scale near zero
    assert abs(after.solve(iono, 1, 1e-3)[0][0]) < 0.01


def test_arcs_break_at_gaps_and_follow_the_satellite_not_the_slot():
    mod = experiment_module("trace_biases")

    class Fake:
        t_ms = np.array([0, 1000, 2000, 30_000])
        sat_id = np.array([[1005, 1007], [1007, 1005], [1005, 0], [1005, 1007]])
        signal = np.zeros((4, 2), int)
    used = np.array([[True, True], [True, True], [True, False], [True, True]])
    arc, n = mod.arcs(Fake, used)
    assert arc[0, 0] == arc[1, 1] == arc[2, 0]                   # G05 across slots
    assert arc[0, 1] == arc[1, 0]                                # G07
    assert arc[3, 0] != arc[2, 0] and arc[3, 1] != arc[1, 0]     # both back after 28 s: new arcs
    assert arc[2, 1] == -1 and n == 4
