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
