"""A clock per signal: the receiver guess of a raw log none of whose signals solves an epoch alone."""
from __future__ import annotations

import numpy as np

from fusion.geometry import geodetic2ecef, line_of_sight, ned2ecef_vec
from fusion.prepare.multi_clock import multi_clock_positions

RX = geodetic2ecef(np.array([[37.4, -122.1, 30.0]]))[0]


def _sky(rng, n):
    """(n,3) satellites 20,200 km from RX in random directions 15-85 degrees above its horizon."""
    el, az = np.radians(rng.uniform(15, 85, n)), rng.uniform(0, 2 * np.pi, n)
    ned = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)]
    return RX + 2.02e7 * ned2ecef_vec(ned, RX)


def test_positions_and_a_clock_per_signal_from_exact_ranges():
    """Three epochs of three signals with clocks 100 m apart: position to the millimetre and each signal's
    clock; an epoch with nothing to spare beyond its unknowns (3 + 2 with five satellites) is not solved, and
    a signal absent from an epoch has no clock there."""
    rng = np.random.default_rng(0)
    counts = [(3, 3, 2), (4, 2, 0), (3, 2, 0)]             # satellites of signals 0, 1, 2 per epoch
    clocks = np.array([1234.0, 1334.0, 1434.0])
    S = max(sum(c) for c in counts)
    sat_pos, pr = np.zeros((3, S, 3)), np.zeros((3, S))
    mask, group = np.zeros((3, S), bool), np.zeros((3, S), int)
    for e, c in enumerate(counts):
        g = np.repeat(np.arange(3), c)
        sat_pos[e, :g.size] = _sky(rng, g.size)
        pr[e, :g.size] = line_of_sight(sat_pos[e, :g.size], RX)[0] + clocks[g]     # with the Earth's rotation
        mask[e, :g.size], group[e, :g.size] = True, g
    pos, clk = multi_clock_positions(sat_pos, pr, mask, group)
    np.testing.assert_allclose(pos[:2], np.broadcast_to(RX, (2, 3)), atol=1e-3)
    np.testing.assert_allclose(clk[0], clocks, atol=1e-3)
    np.testing.assert_allclose(clk[1, :2], clocks[:2], atol=1e-3)
    assert np.isnan(clk[1, 2]) and np.isnan(pos[2]).all() and np.isnan(clk[2]).all()


def test_an_implausible_fit_is_not_kept():
    """Pseudoranges that no point explains (one of them 50 km off) leave the epoch unsolved, not wrong."""
    rng = np.random.default_rng(1)
    sat = _sky(rng, 7)[None]
    pr = line_of_sight(sat[0], RX)[0][None] + 100.0
    pr[0, 3] += 5.0e4
    pos, _ = multi_clock_positions(sat, pr, np.ones((1, 7), bool), np.array([[0, 0, 0, 0, 1, 1, 1]]))
    assert np.isnan(pos).all()
