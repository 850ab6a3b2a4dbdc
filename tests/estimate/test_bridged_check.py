"""fusion.estimate.graph.bridged_check: bridged epochs with Doppler widened where the graph without Doppler and
carrier disagrees beyond their combined sigma."""
import dataclasses

import numpy as np
import pytest

from fusion.estimate.graph.bridged_check import bridged_with_doppler, widen_by_disagreement
from fusion.geometry import ecef2ned_cov, ned2ecef_cov, ned2ecef_vec
from fusion.run_types import ModeResult, RunOptions

POS = np.array([-2694685.0, -4293642.0, 3857878.0])      # near Mountain View


def _result(offset_ned: np.ndarray, var_ned: np.ndarray, info: dict | None = None) -> ModeResult:
    """(E,) epochs at POS + offset_ned (E,3) with diagonal NED variances var_ned (E,3)."""
    E = len(offset_ned)
    at = np.tile(POS, (E, 1))
    pos = at + ned2ecef_vec(offset_ned, at)
    cov = ned2ecef_cov(np.einsum("ei,ij->eij", var_ned, np.eye(3)), pos)
    return ModeResult(pos=pos, valid=np.ones(E, bool), cov=cov, info=info or {})


def test_an_axis_takes_the_squared_disagreement_beyond_the_combined_sigma():
    """Per NED axis: |d| > n * sqrt(var + var_ref) adds d^2; within it, and outside the rows, nothing changes."""
    res = _result(np.array([[10.0, 1.0, 0.0], [10.0, 0.0, 0.0], [0.5, 0.5, 0.5]]), np.full((3, 3), 4.0))
    ref = _result(np.zeros((3, 3)), np.full((3, 3), 5.0))
    before = res.cov.copy()
    n = widen_by_disagreement(res, ref, np.array([True, False, True]), 1.0)
    assert n == 1
    var = np.diagonal(ecef2ned_cov(res.cov, res.pos), axis1=1, axis2=2)
    # epoch 0: north 10 m > 1 x sqrt(4 + 5) = 3 m -> 4 + 100; east 1 m and down 0 m stay
    np.testing.assert_allclose(var[0], [104.0, 4.0, 4.0], atol=1e-6)
    np.testing.assert_array_equal(res.cov[1], before[1])      # not a row
    np.testing.assert_allclose(res.cov[2], before[2], atol=1e-9)   # within the combined sigma
    res2 = _result(np.array([[10.0, 1.0, 0.0]]), np.full((1, 3), 4.0))
    assert widen_by_disagreement(res2, _result(np.zeros((1, 3)), np.full((1, 3), 5.0)), np.ones(1, bool), 4.0) == 0


def test_a_reference_epoch_without_a_solution_leaves_the_epoch_alone():
    res = _result(np.array([[10.0, 0.0, 0.0]]), np.ones((1, 3)))
    ref = _result(np.zeros((1, 3)), np.ones((1, 3)))
    ref.valid[:] = False
    before = res.cov.copy()
    assert widen_by_disagreement(res, ref, np.ones(1, bool), 1.0) == 0
    np.testing.assert_array_equal(res.cov, before)


def test_only_bridged_epochs_with_doppler_are_checked():
    info = {"bridged": np.array([True, True, False]), "bridged_without_doppler": np.array([False, True, False])}
    res = _result(np.zeros((3, 3)), np.ones((3, 3)), info)
    np.testing.assert_array_equal(bridged_with_doppler(res), [True, False, False])
    assert not bridged_with_doppler(_result(np.zeros((2, 3)), np.ones((2, 3)))).any()


@pytest.fixture(scope="module")
def doppler_outage():
    """A simulated trace with Doppler, 2 satellites at epochs 40-49."""
    from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
    from fusion.sim.simulate import SimConfig, simulate

    tr = simulate(n_epochs=80, nav=read_rinex_nav(default_nav_path()), seed=12,
                  config=SimConfig(doppler=True, carrier=False)).trace
    mask = tr.mask.copy()
    mask[40:50] &= np.cumsum(mask[40:50], axis=1) <= 2
    return dataclasses.replace(tr, mask=mask)


def _run(tr, **change):
    from fusion.modes import run_modes

    opts = RunOptions()
    return run_modes(tr, ["fused-nodnn"], dataclasses.replace(opts, graph=dataclasses.replace(opts.graph, **change)))[
        "fused-nodnn"]


def test_the_check_moves_no_position_and_only_widens_bridged_epochs(doppler_outage):
    off, on = _run(doppler_outage, bridged_check_sigmas=0.0), _run(doppler_outage, bridged_check_sigmas=1.0)
    assert "bridged_widened" not in off.info and isinstance(on.info["bridged_widened"], int)
    np.testing.assert_array_equal(off.pos, on.pos)
    rows = bridged_with_doppler(on)
    assert rows[40:50].all() and rows.sum() == 10
    np.testing.assert_array_equal(off.cov[~rows], on.cov[~rows])
    grown = np.linalg.eigvalsh(on.cov[rows] - off.cov[rows])
    assert (grown > -1e-6).all()
    # widened epochs are exactly those whose covariance changed
    changed = ~np.all(np.isclose(on.cov[rows], off.cov[rows], rtol=0, atol=1e-12), axis=(1, 2))
    assert changed.sum() == on.info["bridged_widened"]


def test_no_second_solve_without_doppler_or_without_calibration(doppler_outage, monkeypatch):
    """The graph without Doppler and carrier is solved only where there is something to check."""
    import fusion.estimate.graph.fuse as fuse_module
    from fusion.modes import run_modes

    calls = []
    real = fuse_module.estimate_fused_nodnn
    monkeypatch.setattr(fuse_module, "estimate_fused_nodnn", lambda *a: calls.append(1) or real(*a))
    res = _run(doppler_outage, use_doppler=False)
    assert "bridged_widened" not in res.info and not bridged_with_doppler(res).any()
    run_modes(doppler_outage, ["fused-nodnn"], RunOptions(sigma_calibration=False))
    assert len(calls) == 2                  # the two modes' own solves, no second one
    run_modes(doppler_outage, ["fused-nodnn"], RunOptions())
    assert len(calls) == 4                  # its own solve and the check's
