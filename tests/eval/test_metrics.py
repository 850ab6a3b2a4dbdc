"""Metrics on hand-made cases: known offsets in known NED frames, hand-computed percentiles."""
from __future__ import annotations

import numpy as np
import pytest

from fusion.errors import DataError
from fusion.geometry import geodetic2ecef
from fusion.eval.metrics import cdf, format_summary, ned_errors, summarize


def test_ned_errors_at_equator_and_pole():
    # At lat 0, lon 0: north = +z, east = +y, down = -x.
    truth = np.array([geodetic2ecef(np.array([0.0, 0.0, 0.0])),
                      geodetic2ecef(np.array([90.0, 0.0, 0.0])),
                      geodetic2ecef(np.array([0.0, 90.0, 0.0]))])
    offset = np.array([[1.0, 2.0, 3.0],     # x y z at (0, 0): down -1, east 2, north 3
                       [0.0, 0.0, 5.0],     # +z at the north pole: 5 m up
                       [4.0, 0.0, 0.0]])    # +x at lon 90: west
    err = ned_errors(truth + offset, truth)
    np.testing.assert_allclose(err[0], [3.0, 2.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(err[1], [0.0, 0.0, -5.0], atol=1e-6)
    np.testing.assert_allclose(err[2], [0.0, -4.0, 0.0], atol=1e-6)


def test_ned_errors_in_mountain_view_match_a_local_offset():
    from fusion.geometry import ned2ecef_vec
    truth = geodetic2ecef(np.array([[37.4, -122.1, 20.0]] * 2))
    ned = np.array([[3.0, -4.0, 1.5], [-0.2, 0.1, -7.0]])
    err = ned_errors(truth + ned2ecef_vec(ned, truth), truth)
    np.testing.assert_allclose(err, ned, atol=1e-6)


def test_ned_errors_nan_rows_propagate():
    truth = geodetic2ecef(np.array([[37.4, -122.1, 20.0]] * 3))
    est = truth + 1.0
    est[0] = np.nan
    truth[2] = np.nan
    err = ned_errors(est, truth)
    assert np.isnan(err[[0, 2]]).all() and np.isfinite(err[1]).all()


def test_summarize_hand_made():
    # horizontal errors 0, 1, 2, ..., 10 (3-4-5 triangles scaled), down errors -1 / +1 alternating
    h = np.arange(11.0)
    err = np.stack([0.6 * h, -0.8 * h, np.where(np.arange(11) % 2, 1.0, -1.0)], axis=1)
    err = np.vstack([err, [np.nan, 0, 0]])  # an unsolved epoch
    s = summarize(err)
    assert s["n"] == 11 and s["n_excluded"] == 1
    assert s["h_p50"] == pytest.approx(5.0)
    assert s["h_p95"] == pytest.approx(9.5)           # linear interpolation between 9 and 10
    assert s["gsdc_score"] == pytest.approx(7.25)
    assert s["mae_n"] == pytest.approx(0.6 * 5.0)
    assert s["mae_e"] == pytest.approx(0.8 * 5.0)
    assert s["mae_d"] == pytest.approx(1.0) and s["std_d"] == pytest.approx(0.0)
    assert s["std_n"] == pytest.approx(0.6 * np.std(h))
    assert "GSDC 7.25" in format_summary(s)


def test_summarize_nothing_scorable():
    s = summarize(np.full((4, 3), np.nan))
    assert s["n"] == 0 and s["n_excluded"] == 4 and np.isnan(s["gsdc_score"])


def test_bad_shapes_raise():
    with pytest.raises(DataError):
        summarize(np.zeros((4, 2)))
    with pytest.raises(DataError):
        ned_errors(np.zeros((4, 3)), np.zeros((3, 3)))


def test_cdf():
    v, f = cdf(np.array([3.0, np.nan, 1.0, 2.0, 2.0]))
    np.testing.assert_array_equal(v, [1.0, 2.0, 2.0, 3.0])
    np.testing.assert_allclose(f, [0.25, 0.5, 0.75, 1.0])
    v, f = cdf(np.array([np.nan]))
    assert v.size == 0 and f.size == 0


def test_within_sigma_reads_a_gaussian_as_calibrated_and_names_an_overconfident_axis():
    from fusion.eval.metrics import within_sigma
    from fusion.geometry import geodetic2ecef, ned2ecef_diag

    rng = np.random.default_rng(0)
    n = 20000
    pos = np.tile(geodetic2ecef(np.array([[37.4, -122.1, 10.0]])), (n, 1))
    sd = np.array([1.0, 2.0, 3.0])
    err = rng.standard_normal((n, 3)) * sd
    cov = ned2ecef_diag(np.tile(sd ** 2, (n, 1)), pos)
    got = within_sigma(err, pos, cov)
    for ax in "ned":
        assert abs(got[f"within1sigma_{ax}"] - 0.683) < 0.015 and abs(got[f"within2sigma_{ax}"] - 0.954) < 0.01
    err[:, 1] *= 3.0                                   # east three times worse than its sigma says
    assert within_sigma(err, pos, cov)["within1sigma_e"] < 0.35
    err[0] = np.nan
    assert within_sigma(err, pos, cov)["n_cov"] == n - 1
