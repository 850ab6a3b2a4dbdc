"""The receiver clock's drift states (GraphConfig.clock_drift_states): pseudorange-only graphs get them by
default, with their own clock walk; "doppler" keeps the chain that follows the WLS clock's drift."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

from fusion.errors import GeometryError
from fusion.estimate.graph.build import graph_pieces
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.fuse import estimate_fused_nodnn
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.wls import solve_wls
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.prepare.load import load_trace
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate
from tests.estimate.test_graph import synth_trace

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))


def _options(**change) -> RunOptions:
    return RunOptions(graph=dataclasses.replace(GraphConfig(), **change))


def _drift_keys(trace, cfg: GraphConfig) -> int:
    inp = prepare_inputs(trace, solve_wls(trace), cfg)
    values = graph_pieces(trace, inp, cfg).values()
    return sum(chr(gtsam.Symbol(k).chr()) == "d" for k in values.keys())


@pytest.fixture(scope="module")
def doppler_trace():
    return simulate(n_epochs=60, nav=read_rinex_nav(default_nav_path()), seed=12,
                    config=SimConfig(doppler=True, carrier=False)).trace


def test_pseudorange_only_graphs_get_drift_states_unless_told_doppler(doppler_trace):
    tr = synth_trace(E=40)
    assert _drift_keys(tr, GraphConfig()) == 40
    assert _drift_keys(tr, GraphConfig(clock_drift_states="doppler")) == 0
    assert _drift_keys(doppler_trace, GraphConfig(clock_drift_states="doppler")) == doppler_trace.n_epochs
    with pytest.raises(GeometryError, match="clock_drift_states"):
        prepare_inputs(tr, solve_wls(tr), GraphConfig(clock_drift_states="sometimes"))


def test_each_graph_takes_its_own_clock_walk(doppler_trace):
    """drift_clock_rw_no_doppler_m moves a pseudorange-only graph and not one with Doppler; drift_clock_rw_m
    the other way round."""
    tr = synth_trace(E=60, clock_drift_mps=40.0)
    for trace, own, other in ((tr, "drift_clock_rw_no_doppler_m", "drift_clock_rw_m"),
                              (doppler_trace, "drift_clock_rw_m", "drift_clock_rw_no_doppler_m")):
        wls = solve_wls(trace)
        base = estimate_fused_nodnn(trace, wls, _options()).pos
        assert np.abs(estimate_fused_nodnn(trace, wls, _options(**{own: 0.05})).pos - base).max() > 1e-3
        np.testing.assert_array_equal(estimate_fused_nodnn(trace, wls, _options(**{other: 0.05})).pos, base)


def test_drift_states_hold_a_real_track_through_a_stretch_of_three_satellites(shipped_trace_dir):
    """The shipped real trace with 3 satellites in 120 s of every 180 s (WLS solves none of those epochs):
    the drift estimated from the pseudoranges left keeps the track closer than the WLS drift interpolated
    across the stretch (on the twelve GSDC training drives: experiments/few_satellites_models.py)."""
    from few_satellites import thinned

    thin, poor = thinned(load_trace(shipped_trace_dir, min_sats=1), 3, 0)
    err = {}
    for mode in ("doppler", "always"):
        opts = _options(clock_drift_states=mode)
        res = estimate_fused_nodnn(thin, solve_initial(thin, opts), opts)
        err[mode] = np.nanmean(np.linalg.norm(res.pos[poor] - thin.truth[poor], axis=1))
    assert err["always"] < 0.8 * err["doppler"]
