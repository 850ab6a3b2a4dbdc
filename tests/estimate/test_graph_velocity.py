"""The graph's velocity in estimates.csv: where Doppler measures it, close to the true velocity, with sigmas that
cover its errors; absent on a trace without Doppler."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fusion.estimate.graph.fuse import estimate_fused_nodnn
from fusion.geometry import ecef2ned_vec
from fusion.io.estimates import VELOCITY_COLUMNS, VELOCITY_SIGMA_COLUMNS, estimates_frame
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate


def test_velocity_columns_follow_the_doppler():
    sim = simulate(n_epochs=60, nav=read_rinex_nav(default_nav_path()), seed=12,
                   config=SimConfig(doppler=True, carrier=False))
    trace, opts = sim.trace, RunOptions()
    res = estimate_fused_nodnn(trace, solve_initial(trace, opts), opts)
    assert res.info["doppler_epochs"].all()
    frame = estimates_frame(trace, res)
    ok = res.valid
    truth = ecef2ned_vec(sim.rx_vel_mps[ok], res.pos[ok])
    err = frame[VELOCITY_COLUMNS].to_numpy() - truth
    speed = np.hypot(truth[:, 0], truth[:, 1])
    assert np.median(speed) > 3.0                                  # a moving receiver, so the check means something
    assert np.median(np.hypot(err[:, 0], err[:, 1])) < 0.3         # Doppler noise 0.2 m/s per satellite
    # the graph's velocity marginals: the simulator's noise is the noise the graph assumes, so they hold
    sig = frame[VELOCITY_SIGMA_COLUMNS].to_numpy()
    assert np.isfinite(sig).all() and (sig > 0).all()
    assert ((np.abs(err) <= 2 * sig).mean(axis=0) > 0.85).all()
    assert (np.median(np.abs(err) / sig, axis=0) > 0.3).all()      # and are not a blanket
    # ISAM2 (--incremental) on the same graph: its velocity with the same graph's marginals at its estimate
    inc = estimate_fused_nodnn(trace, solve_initial(trace, opts), replace(opts, graph=replace(opts.graph,
                                                                                          incremental=True)))
    inc_sig = estimates_frame(trace, inc)[VELOCITY_SIGMA_COLUMNS].to_numpy()
    np.testing.assert_allclose(inc_sig, sig, rtol=0.05)
    # the same trace without its Doppler: the graph keeps velocity states, but nothing measures them
    no_doppler = replace(trace, prr=None, prr_sigma=None, prr_ok=None)
    res = estimate_fused_nodnn(no_doppler, solve_initial(no_doppler, opts), opts)
    assert not res.info["doppler_epochs"].any()
    assert not set(VELOCITY_COLUMNS) & set(estimates_frame(no_doppler, res).columns)
