import numpy as np
import pytest

from fusion.geometry import (C_LIGHT, OMEGA_E, ecef2geodetic, ecef2ned_vec, elevation_azimuth,
                             geodetic2ecef, line_of_sight, ned2ecef_vec, ned_rotation, sagnac_rotate)

MTV = np.array([37.42, -122.09, 10.0])


def test_geodetic_roundtrip_batched():
    llh = np.array([[37.42, -122.09, 10.0], [-33.9, 151.2, 50.0], [89.0, 10.0, -20.0]])
    back = ecef2geodetic(geodetic2ecef(llh))
    np.testing.assert_allclose(back, llh, atol=1e-7)


def test_ned_rotation_is_orthonormal_and_points_the_right_way():
    ref = geodetic2ecef(MTV)
    R = ned_rotation(ref)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # Moving up from the reference along the ellipsoid normal is "down" negative.
    up = geodetic2ecef(MTV + [0, 0, 100.0]) - ref
    np.testing.assert_allclose(ecef2ned_vec(up, ref), [0, 0, -100.0], atol=1e-6)
    north = geodetic2ecef(MTV + [1e-4, 0, 0]) - ref
    n = ecef2ned_vec(north, ref)
    assert n[0] > 11.0 and abs(n[1]) < 1e-3
    v = np.array([1.0, -2.0, 3.0])
    np.testing.assert_allclose(ned2ecef_vec(ecef2ned_vec(v, ref), ref), v, atol=1e-12)


def test_sagnac_rotation_matches_closed_form_size():
    rx = geodetic2ecef(MTV)
    sat = np.array([[15e6, -10e6, 20e6]])
    rot = sagnac_rotate(sat, rx)
    tau = np.linalg.norm(sat[0] - rx) / C_LIGHT
    # Displacement is omega * tau * horizontal radius of the satellite, tens of metres.
    expected = OMEGA_E * tau * np.hypot(sat[0, 0], sat[0, 1])
    assert np.linalg.norm(rot[0] - sat[0]) == pytest.approx(expected, rel=1e-6)
    assert rot[0, 2] == sat[0, 2]


def test_line_of_sight_and_elevation():
    rx = geodetic2ecef(MTV)
    overhead = geodetic2ecef(MTV + [0, 0, 20_200e3])
    rng, los = line_of_sight(overhead[None, :], rx)
    assert rng[0] == pytest.approx(20_200e3, abs=50.0)  # Sagnac moves it by tens of metres only
    el, _ = elevation_azimuth(los, rx)
    assert el[0] > 89.9


def test_elevation_azimuth_with_precomputed_rotation():
    rng = np.random.default_rng(4)
    rx = geodetic2ecef(np.array([[37.4, -122.1, 10.0], [-33.9, 151.2, 50.0]]))
    los = rng.normal(size=(2, 5, 3))
    los /= np.linalg.norm(los, axis=-1, keepdims=True)
    el, az = elevation_azimuth(los, rx)
    el2, az2 = elevation_azimuth(los, None, R=ned_rotation(rx))
    np.testing.assert_array_equal(el, el2)
    np.testing.assert_array_equal(az, az2)


def test_norm3_is_numpys_norm_bit_for_bit():
    """norm3 writes numpy's norm out on the columns: equal to the last bit, whatever the layout."""
    from fusion.geometry import norm3

    rng = np.random.default_rng(4)
    for shape in [(2000, 10, 3), (3,), (1, 3), (0, 3), (5, 1, 3), (4, 5, 6, 3)]:
        v = rng.normal(size=shape) * rng.choice([1.0, 1e3, 2.6e7], size=shape)
        moved = np.moveaxis(np.moveaxis(v, -1, 0).copy(), 0, -1)      # components far apart in memory
        for arr in (v, v[::-1], np.asfortranarray(v), moved):
            assert np.array_equal(norm3(arr), np.linalg.norm(arr, axis=-1)), shape
    ints = np.array([[3, 4, 12]])
    assert norm3(ints).tolist() == [13.0] and norm3(np.ones((2, 4))).shape == (2,)


def test_sagnac_rotation_and_line_of_sight_keep_their_bits():
    """The rotation is written into one array instead of stacked: the same bits as the formula, in
    float64 and float32."""
    rng = np.random.default_rng(6)
    for dtype in (np.float64, np.float32):
        sat = (rng.normal(size=(50, 9, 3)) * 2.0e7).astype(dtype)
        rx = (rng.normal(size=(50, 3)) * 6.4e6).astype(dtype)
        theta = OMEGA_E * np.linalg.norm(sat - rx[:, None, :], axis=-1) / C_LIGHT
        c, s = np.cos(theta), np.sin(theta)
        want = np.stack([c * sat[..., 0] + s * sat[..., 1], -s * sat[..., 0] + c * sat[..., 1], sat[..., 2]], -1)
        got = sagnac_rotate(sat, rx)
        assert got.dtype == want.dtype and np.array_equal(got, want)
        rng_m, los = line_of_sight(sat, rx)
        d = want - rx[:, None, :]
        assert np.array_equal(rng_m, np.linalg.norm(d, axis=-1))
        assert np.array_equal(los, d / np.maximum(np.linalg.norm(d, axis=-1), 1.0)[..., None])


def test_three_epochs_of_ned_variances_are_three_diagonal_covariances():
    """(3,3) variances of three epochs are not one 3x3 covariance (a three-epoch trace's motion model was
    built from such a misreading, non-symmetric, and the graph's Cholesky failed)."""
    from fusion.geometry import ecef2ned_cov, geodetic2ecef, ned2ecef_diag

    ref = geodetic2ecef(np.array([[37.4, -122.1, 10.0], [37.5, -122.0, 20.0], [-33.9, 151.2, 0.0]]))
    var = np.array([[1.0, 4.0, 9.0], [2.0, 3.0, 5.0], [0.5, 0.5, 0.1]])
    cov = ned2ecef_diag(var, ref)
    assert cov.shape == (3, 3, 3)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-12)
    np.testing.assert_allclose(ecef2ned_cov(cov, ref), var[:, :, None] * np.eye(3), atol=1e-12)
