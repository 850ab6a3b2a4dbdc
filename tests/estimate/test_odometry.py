"""Vehicle odometry in the graph (fusion/estimate/graph/odometry.py): the heading fit, the step
factor's geometry and heading state, and the whole graph on a simulated drive."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fusion.errors import GeometryError
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.keys import pos_key
from fusion.estimate.graph.odometry import (BIAS_GRID_RADPS, fit_heading, heading_key, integrated_turn,
                                            odometry_factors, steps_en)
from fusion.geometry import ecef2ned_vec, geodetic2ecef, ned2ecef_vec
from fusion.trace import ODOMETRY_COLUMNS, Trace, empty_trace

ORIGIN = geodetic2ecef(np.array([52.5046, 13.3737, 76.0]))


def _drive(n: int = 400, dt: float = 0.2, psi0: float = 1.1, bias: float = 0.0015, seed: int = 0):
    """A winding drive: times (E,), speed (E,), measured turn rate (E,) and the true path (E,) complex
    east + i north, whose heading is ``theta + psi0 + bias * tau`` (tau from the middle)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    speed = 6.0 + 2.0 * np.sin(t / 9.0)
    rate = 0.15 * np.sin(t / 7.0) + 0.01 * rng.standard_normal(n)
    theta = integrated_turn(t, rate)
    tau = t - 0.5 * (t[0] + t[-1])
    path = np.cumsum(steps_en(speed, theta + psi0 + bias * tau, np.r_[0.0, np.diff(t)]))
    return t, speed, rate, path


def _odometry(speed: np.ndarray, rate: np.ndarray) -> np.ndarray:
    odo = np.zeros((speed.size, len(ODOMETRY_COLUMNS)))
    odo[:, ODOMETRY_COLUMNS.index("vx")] = speed
    odo[:, ODOMETRY_COLUMNS.index("wz")] = rate
    odo[:, 6:9] = [0.0025, 0.0009, 0.0009]
    odo[:, 9:] = 4e-6
    return odo


def _ecef(path: np.ndarray) -> np.ndarray:
    ned = np.stack([path.imag, path.real, np.zeros(path.size)], -1)
    return ORIGIN + ned2ecef_vec(ned, ORIGIN)


def _trace(t: np.ndarray, odo: np.ndarray) -> Trace:
    kw = empty_trace(t.size, 1)
    kw.update(t_ms=np.round(t * 1000).astype(np.int64), odometry=odo)
    return Trace(**kw)


def test_heading_fit_recovers_offset_and_gyro_bias_despite_outliers():
    t, speed, rate, path = _drive(psi0=1.1, bias=BIAS_GRID_RADPS[50])
    rng = np.random.default_rng(1)
    track = path + 8.0 * (rng.standard_normal(path.size) + 1j * rng.standard_normal(path.size))
    out = rng.random(path.size) < 0.1
    track[out] += 150.0                                               # 10 % far outliers on one side
    psi0, bias = fit_heading(t, speed, integrated_turn(t, rate), track, np.ones(t.size, bool),
                             np.zeros(t.size, np.int64))
    step = BIAS_GRID_RADPS[1] - BIAS_GRID_RADPS[0]
    assert abs(psi0 - 1.1) < 0.02 and abs(bias - BIAS_GRID_RADPS[50]) <= step + 1e-12


def _graph(trace, pos, init_pos, anchors=(), cfg=None):
    n = trace.n_epochs
    inp = odometry_factors(trace, init_pos, np.ones(n, bool), np.r_[False, np.ones(n - 1, bool)],
                           np.zeros(n, np.int64), np.ones(n, bool), cfg or GraphConfig())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(n):
        values.insert(pos_key(k), pos[k])
    values.insert(inp.values)
    for f in inp.factors:
        graph.add(f)
    for k in anchors:
        graph.add(gtsam.PriorFactorPoint3(pos_key(k), pos[k], gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
    return inp, graph, values


def test_factors_vanish_on_the_true_path_and_see_a_sideways_metre():
    t, speed, rate, path = _drive(bias=BIAS_GRID_RADPS[44])
    pos = _ecef(path)
    tr = _trace(t, _odometry(speed, rate))
    inp, graph, values = _graph(tr, pos, pos)
    assert len(inp.factors) == tr.n_epochs and inp.counts["odometry_steps"] == tr.n_epochs - 1
    # the trapezoid of a curving path is not exact: millimetres per step against ~1.2 m steps
    assert graph.error(values) < 1e-2 * tr.n_epochs
    moved = gtsam.Values(values)
    k = tr.n_epochs // 2
    ned = ecef2ned_vec(pos[k + 1] - pos[k], pos[k])
    side = ned2ecef_vec(np.array([-ned[1], ned[0], 0.0]) / np.hypot(ned[0], ned[1]), pos[k])
    moved.update(pos_key(k), pos[k] + side)
    assert graph.error(moved) > 100 * graph.error(values) + 50


def test_heading_state_corrects_a_fit_made_on_a_rotated_track():
    """The initial track rotated by 3 deg makes the fit 3 deg wrong; anchors on the true path let the
    heading state take it back (the sign of its Jacobian)."""
    t, speed, rate, path = _drive(bias=BIAS_GRID_RADPS[40])
    pos = _ecef(path)
    tr = _trace(t, _odometry(speed, rate))
    turned = _ecef(path * np.exp(1j * np.radians(3.0)))
    _, graph, values = _graph(tr, pos, turned, anchors=range(0, tr.n_epochs, 50))
    start = gtsam.Values(values)
    result = gtsam.LevenbergMarquardtOptimizer(graph, start).optimize()
    assert abs(np.degrees(result.atVector(heading_key())[0]) + 3.0) < 0.3
    err = np.array([np.linalg.norm(result.atPoint3(pos_key(k)) - pos[k]) for k in range(tr.n_epochs)])
    assert err.max() < 0.5


def test_asking_for_odometry_without_any_is_an_error():
    kw = empty_trace(3, 1)
    kw["t_ms"] = np.arange(3, dtype=np.int64) * 1000
    with pytest.raises(GeometryError, match="carries none"):
        odometry_factors(Trace(**kw), np.zeros((3, 3)), np.ones(3, bool), np.ones(3, bool),
                         np.zeros(3, np.int64), np.ones(3, bool), GraphConfig())


def test_flag_reaches_the_run_options():
    from tests.run_options import parse_run_options

    assert parse_run_options([]).use_odometry is False
    assert parse_run_options(["--odometry"]).use_odometry is True


def test_odometry_improves_the_graph_on_a_simulated_drive():
    """Speed and turn rate taken from the simulated truth (with a gyro bias and noise) must bring the
    pseudorange-only graph closer to the truth."""
    from dataclasses import replace

    from fusion.eval.metrics import mode_metrics
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    from fusion.sim.simulate import simulate

    tr = simulate(n_epochs=240, seed=3).trace
    t = (tr.t_ms - tr.t_ms[0]) / 1000.0
    ned = ecef2ned_vec(tr.truth - tr.truth[0], tr.truth[0])
    z = ned[:, 1] + 1j * ned[:, 0]
    vel = np.gradient(z, t)
    heading = np.unwrap(np.angle(vel))
    rng = np.random.default_rng(4)
    rate = np.gradient(heading, t) - 0.002 + 0.002 * rng.standard_normal(t.size)
    tr = replace(tr, odometry=_odometry(np.abs(vel) + 0.05 * rng.standard_normal(t.size), rate))
    off, on = (run_modes(tr, ["fused-nodnn"], RunOptions(graph=GraphConfig(use_odometry=u)))["fused-nodnn"]
               for u in (False, True))
    m_off, m_on = mode_metrics(tr, off), mode_metrics(tr, on)
    assert m_on["h_p50"] < 0.8 * m_off["h_p50"] and m_on["h_p95"] < m_off["h_p95"]


def test_odometry_on_a_trace_without_it_is_a_one_line_error(shipped_trace_dir, tmp_path, capsys):
    from fusion.cli import main
    assert main(["run", str(shipped_trace_dir), "--mode", "fused-nodnn", "--odometry", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "odometry was asked for" in err and err.strip().count("\n") == 0


def test_a_standing_car_whose_log_reports_no_variance_still_solves():
    """Odometry that reports zero speed and zero variances (smartLoc variants at a stop): the steps across and up
    keep a floor (odometry.MIN_VAR_MPS2) instead of becoming exact, and the graph solves every epoch."""
    from dataclasses import replace

    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    from fusion.sim.simulate import simulate

    tr = simulate(n_epochs=60, seed=3).trace
    odo = _odometry(np.zeros(tr.n_epochs), np.zeros(tr.n_epochs))
    odo[:, 6:] = 0.0
    res = run_modes(replace(tr, odometry=odo), ["fused-nodnn"],
                    RunOptions(graph=GraphConfig(use_odometry=True)))["fused-nodnn"]
    assert res.valid.all() and np.isfinite(res.pos).all() and np.isfinite(res.info["final_error"])

