"""The robust WLS in a street canyon: down-weighting instead of exclusion where exclusion costs geometry,
the reported sigma (C/N0) in the M-estimator, a gross fault still excluded, and the screen of the
measurements the learned snapshot must not see (:func:`fusion.estimate.neighbour_fde.gross_outliers`)."""
from __future__ import annotations

import numpy as np
import pytest

from fusion.errors import DataError
from fusion.estimate.neighbour_fde import gross_outliers
from fusion.estimate.raim import m_weights
from fusion.estimate.wls import TRACE_DEFAULTS, reported_sigma_factor, solve_wls, solve_wls_arrays
from fusion.geometry import geodetic2ecef, ned2ecef_vec
from fusion.trace import Trace, empty_trace
from tests.estimate.test_wls import RX_LLH, pseudoranges, sats_at

#: A street running north-south: satellites high or along it, one low across it to the east (index 6)
#: and one to the west: the two that fix the east coordinate.
CANYON = np.array([(80, 0), (60, 10), (55, 185), (40, 355), (35, 175), (70, 200), (20, 90), (30, 275)], float)
#: NLOS delays of one canyon epoch [m] (positive, tens of metres on every satellite; the largest on the
#: low east satellite): the test fails and the single-fault search names the east satellite.
DELAYS = np.array([19.0, 3.0, 14.0, 11.0, 2.0, 21.0, 30.0, 23.0])


def _epochs(bias: np.ndarray, E: int = 1):
    rx = geodetic2ecef(RX_LLH)
    sat = np.broadcast_to(sats_at(rx, CANYON), (E, len(CANYON), 3)).copy()
    pr = pseudoranges(sat, np.broadcast_to(rx, (E, 3)), 1000.0) + bias
    return sat, pr, np.ones(pr.shape, bool), rx


def test_canyon_satellite_kept_down_weighted_beats_its_exclusion():
    """Multipath on every satellite: excluding the one the test blames (the low east one, most of the
    east geometry) leaves a worse fix than keeping it down-weighted, as the default does."""
    sat, pr, mask, rx = _epochs(DELAYS[None])
    # the trace calibration would see only this epoch: test at the a-priori variance
    excl = solve_wls_arrays(sat, pr, mask, None, settings=TRACE_DEFAULTS.replace(exclude_above_m=float("inf"),
                                                                                 test_scale=1.0))
    default = solve_wls_arrays(sat, pr, mask, None, settings=TRACE_DEFAULTS.replace(test_scale=1.0))
    assert not excl.used[0, 6] and excl.n_excluded[0] == 1
    assert default.used[0, 6] and default.flagged[0] and default.n_excluded[0] == 0
    err_excl, err_default = (np.linalg.norm(r.pos[0] - rx) for r in (excl, default))
    assert err_default < 0.75 * err_excl


def test_gross_fault_still_excluded_in_the_canyon_geometry():
    """A +200 m fault (a wrong ephemeris, a code error) on clean measurements is excluded by the default."""
    sat, pr, mask, rx = _epochs(np.random.default_rng(4).normal(0, 1.0, (3, len(CANYON))), E=3)
    pr[:, [0, 3, 6]] += np.diag([200.0, 200.0, 200.0])
    res = solve_wls_arrays(sat, pr, mask, None, settings=TRACE_DEFAULTS.replace(test_scale=1.0))
    assert res.n_excluded.tolist() == [1, 1, 1] and not res.flagged.any()
    assert not res.used[[0, 1, 2], [0, 3, 6]].any()
    assert res.excluded[[0, 1, 2], [0, 3, 6]].all() and res.excluded.sum() == 3
    assert np.linalg.norm(res.pos - rx, axis=1).max() < 5.0


def test_reported_sigma_directs_the_down_weighting():
    """Two satellites with NLOS delays the receiver reports as weak (3x the epoch's median sigma, as at a
    low C/N0): with the reported sigma in the IRLS the fix is closer than with elevation alone."""
    rng = np.random.default_rng(5)
    E = 40
    sat, pr, mask, rx = _epochs(rng.normal(0, 1.0, (E, len(CANYON))), E=E)
    bad = np.stack([rng.choice(len(CANYON), 2, replace=False) for _ in range(E)])
    rows = np.arange(E)[:, None]
    pr[rows, bad] += rng.uniform(25.0, 45.0, (E, 2))
    sigma = np.full(pr.shape, 4.0)
    sigma[rows, bad] = 12.0
    f = reported_sigma_factor(sigma, mask)
    assert f.min() == 1.0 and np.allclose(f[rows, bad], 3.0)
    s = TRACE_DEFAULTS.replace(test_scale=1.0, neighbour_weak=False)
    with_rep = solve_wls_arrays(sat, pr, mask, sigma, settings=s)
    without = solve_wls_arrays(sat, pr, mask, sigma, settings=s.replace(irls_reported=False))
    flagged = with_rep.flagged
    assert flagged.sum() >= E // 4 and np.array_equal(flagged, without.flagged)
    err = {k: np.linalg.norm(r.pos[flagged] - rx, axis=1).mean() for k, r in (("rep", with_rep), ("elev", without))}
    assert err["rep"] < 0.7 * err["elev"]


def test_reported_sigma_moves_the_fix_even_where_no_residual_is_down_weighted():
    """The reported sigma weights a flagged epoch's re-solve even when the M-estimator leaves every weight
    at 1 (threshold out of reach): the position moves with the weights its covariance reports."""
    sat, pr, mask, rx = _epochs(DELAYS[None])
    sigma = np.full(pr.shape, 4.0)
    sigma[0, 6] = 16.0                                     # the low east satellite reported weak
    s = TRACE_DEFAULTS.replace(test_scale=1.0, neighbour_weak=False, huber_k=1e9)
    with_rep = solve_wls_arrays(sat, pr, mask, sigma, settings=s)
    without = solve_wls_arrays(sat, pr, mask, sigma, settings=s.replace(irls_reported=False))
    assert with_rep.flagged[0] and without.flagged[0]
    assert np.linalg.norm(with_rep.pos[0] - without.pos[0]) > 0.5


def test_gross_dop_growth_keeps_a_gross_fault_whose_exclusion_costs_the_geometry():
    """``gross_dop_growth`` (off by default): a +200 m fault on the low east satellite (most of the east
    geometry) is excluded by default; with a DOP growth limit its exclusion is undone, the satellite kept
    (Huber-weighted) and the epoch flagged, at a cost here (the fault is real)."""
    sat, pr, mask, rx = _epochs(np.random.default_rng(4).normal(0, 1.0, (1, len(CANYON))))
    pr[0, 6] += 200.0
    s = TRACE_DEFAULTS.replace(test_scale=1.0)
    default, limited = (solve_wls_arrays(sat, pr, mask, None, settings=s.replace(gross_dop_growth=g))
                        for g in (float("inf"), 1.01))
    assert not default.used[0, 6] and default.n_excluded[0] == 1 and not default.flagged[0]
    assert limited.used[0, 6] and limited.n_excluded[0] == 0 and limited.flagged[0]
    assert np.linalg.norm(default.pos[0] - rx) < 2.0 < np.linalg.norm(limited.pos[0] - rx)


def test_m_estimator_weights_and_settings_checked():
    z = np.array([0.0, 1.0, 2.0, 4.0, 40.0])
    np.testing.assert_allclose(m_weights(z, 2.0, "huber"), [1.0, 1.0, 1.0, 0.5, 0.05])
    np.testing.assert_allclose(m_weights(z, 2.0, "cauchy"), [1.0, 0.8, 0.5, 0.2, 1.0 / 401.0])
    for bad in (dict(irls_scale="median"), dict(m_estimator="tukey"), dict(gross_dop_growth=0.5)):
        with pytest.raises(DataError):
            TRACE_DEFAULTS.replace(**bad)


def _drive(E: int = 9, n_sats: int = 6):
    """E epochs 1 s apart at 10 m/s east, ``n_sats`` of the canyon sky (few: the test has little power)."""
    rx0 = geodetic2ecef(RX_LLH)
    rx = rx0 + 10.0 * np.arange(E)[:, None] * ned2ecef_vec(np.array([0.0, 1.0, 0.0]), rx0)
    sky = CANYON[:n_sats]
    sat = np.stack([sats_at(r, sky) for r in rx])
    pr = pseudoranges(sat, rx, 0.0) + 1000.0 + np.random.default_rng(2).normal(0, 1.0, (E, n_sats))
    kw = empty_trace(E, n_sats)
    kw.update(t_ms=1_000_000 + 1000 * np.arange(E), sat_pos=sat, pr=pr, mask=np.ones((E, n_sats), bool),
              sat_id=np.broadcast_to(np.arange(1, n_sats + 1, dtype=np.int32), (E, n_sats)).copy())
    return kw, rx


def test_gross_outliers_from_neighbours_find_an_absorbed_fault():
    """Five satellites: a +200 m fault is absorbed by the fit (the epoch passes, its position is off);
    the neighbours' prediction shows it. Clean epochs and a clean drive are left alone."""
    kw, rx = _drive(n_sats=5)
    kw["pr"][4, 2] += 200.0
    tr = Trace(**kw)
    wls = solve_wls(tr)
    assert wls.valid.all() and not wls.excluded.any() and np.linalg.norm(wls.pos[4] - rx[4]) > 50.0
    assert (wls.n_used <= 6).all()                       # every epoch weak: the test has little power
    settled = np.ones(9, bool)
    settled[[4, 8]] = False                               # 8: no settled epoch after it, no prediction
    far, decided, pred = gross_outliers(tr.t_ms, tr.sat_pos, tr.pr, wls.pos, ~settled, settled, tr.mask, 80.0,
                                        off_m=40.0)
    assert np.flatnonzero(decided).tolist() == [4] and far[4].tolist() == [False, False, True, False, False]
    assert far.sum() == 1 and np.linalg.norm(pred[4] - rx[4]) < 20.0 and np.isnan(pred[[0, 8]]).all()
    # an epoch whose fix stays near the prediction is not judged
    _, decided, _ = gross_outliers(tr.t_ms, tr.sat_pos, tr.pr, wls.pos, ~settled, settled, tr.mask, 80.0,
                                   off_m=np.linalg.norm(wls.pos[4] - rx[4]) + 10.0)
    assert not decided.any()
    kw, _ = _drive(n_sats=5)
    clean = Trace(**kw)
    w = solve_wls(clean)
    far, decided, _ = gross_outliers(clean.t_ms, clean.sat_pos, clean.pr, w.pos, ~settled, settled, clean.mask, 80.0)
    assert decided[4] and not far.any()


def test_an_epochs_robust_fix_does_not_depend_on_the_other_epochs():
    """Snapshot stages work per epoch (the IRLS re-solves only the epochs it down-weights): with the test's
    variance fixed, each epoch of a batch gets the fix it gets alone, to the bit."""
    rng = np.random.default_rng(8)
    E = 12
    sat, pr, mask, rx = _epochs(rng.normal(0, 1.0, (E, len(CANYON))), E=E)
    pr[::2] += DELAYS * rng.uniform(0.5, 1.5, (E // 2, 1))      # every other epoch in the canyon
    pr[1::4, 2] += 300.0                                            # and a gross fault now and then
    s = TRACE_DEFAULTS.replace(test_scale=1.0)
    batch = solve_wls_arrays(sat, pr, mask, None, settings=s)
    assert batch.flagged.sum() >= 3 and batch.n_excluded.sum() >= 3    # both robust stages at work
    for e in range(E):
        alone = solve_wls_arrays(sat[e:e + 1], pr[e:e + 1], mask[e:e + 1], None, settings=s)
        np.testing.assert_array_equal(alone.pos[0], batch.pos[e])
        np.testing.assert_array_equal(alone.used[0], batch.used[e])
