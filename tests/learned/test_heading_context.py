"""The direction of travel and each satellite's azimuth relative to it (learned.context: heading)."""
from __future__ import annotations

import numpy as np

from fusion.geometry import geodetic2ecef, ned2ecef_vec
from learned.guard import feature_guard
from learned.context import HEADING_WINDOW_S, relative_azimuth, travel_heading
from learned.features import FeatureConfig, context_channels
from learned.toy import toy_trace

REF = geodetic2ecef(np.array([37.4, -122.1, 10.0]))


def _track(t_s, vel_ne, noise_m=0.0, seed=0):
    """(E,3) ECEF positions moving at ``vel_ne`` (E,2) [m/s] north / east, with Gaussian noise."""
    step = np.diff(t_s, prepend=t_s[0])[:, None] * vel_ne
    ned = np.c_[np.cumsum(step, axis=0), np.zeros(len(t_s))]
    ned += np.random.default_rng(seed).normal(0.0, noise_m, ned.shape) * np.r_[1, 1, 0]
    return REF + ned2ecef_vec(ned, REF)


def test_heading_follows_the_track_and_is_absent_when_standing_still():
    t = np.arange(60.0)
    vel = np.zeros((60, 2))
    vel[:30] = [0.0, 10.0]                      # east at 10 m/s, then standing still
    pos = _track(t, vel, noise_m=1.0)
    heading, moving = travel_heading(t, pos)
    assert not moving[:2].any()                 # fewer than three fixes in the window
    assert moving[3:30].all()
    np.testing.assert_allclose(np.degrees(heading[3:30]), 90.0, atol=5.0)
    assert not moving[30 + int(HEADING_WINDOW_S) + 1:].any()


def test_heading_window_is_causal_and_skips_missing_fixes():
    t = np.arange(40.0)
    vel = np.tile([10.0, 0.0], (40, 1))          # north
    vel[20:] = [-10.0, 0.0]                      # then south
    pos = _track(t, vel)
    pos[5:8] = np.nan
    heading, moving = travel_heading(t, pos)
    assert not moving[5:8].any()
    np.testing.assert_allclose(np.degrees(heading[2:19][moving[2:19]]), 0.0, atol=1e-6)
    # a later epoch never changes an earlier heading
    h2, m2 = travel_heading(t[:25], pos[:25])
    np.testing.assert_array_equal(m2, moving[:25])
    np.testing.assert_allclose(h2[m2], heading[:25][m2], atol=1e-6)
    assert abs(abs(np.degrees(heading[-1])) - 180.0) < 1e-6


def test_relative_azimuth_of_satellites_ahead_and_to_the_side():
    tr = toy_trace(20, seed=3, n_sats=(6, 6))
    t = (tr.t_ms - tr.t_ms[0]) / 1000.0
    pos = _track(t, np.tile([0.0, 15.0], (len(t), 1)))          # east
    far = 2.0e7
    ned_dirs = np.array([[0, 1, -1], [1, 0, -1], [0, -1, -1], [-1, 0, -1], [0, 1, -0.2], [1, 1, -1]], float)
    ned_dirs /= np.linalg.norm(ned_dirs, axis=1, keepdims=True)
    tr.sat_pos[:] = pos[:, None, :] + ned2ecef_vec(ned_dirs * far, REF)[None]
    tr.mask[:] = True
    s, c, moving = relative_azimuth(tr, pos, t)
    assert moving[3:].all() and not moving[:2].any()
    rel = np.arctan2(s[5], c[5])
    want = np.radians([0.0, -90.0, 180.0, 90.0, 0.0, -45.0])
    np.testing.assert_allclose(np.degrees(np.angle(np.exp(1j * (rel - want)))), 0.0, atol=0.5)
    assert (s[~moving] == 0).all() and (c[~moving] == 0).all()
    ctx = {"heading_ok": tr.mask & moving[:, None], "rel_sin": s, "rel_cos": c}
    x = context_channels(ctx, tr.mask, FeatureConfig(inputs=("res", "los", "heading")),
                         missing={"heading": np.ones(tr.mask.shape, bool)})
    assert (x == 0).all()                        # dropped: read as missing, flag and values 0
    x = context_channels(ctx, tr.mask, FeatureConfig(inputs=("res", "los", "heading")))
    np.testing.assert_array_equal(x[..., 0], tr.mask & moving[:, None])


def test_a_network_trained_with_heading_reads_it_and_guards_it(tmp_path):
    """Opt-in ``--inputs ...,heading``: trained, its training range kept, asked on a moving toy drive."""
    from fusion.cli.train import main
    from fusion.estimate.wls import solve_wls
    from learned.checkpoint import read_checkpoint
    from learned.infer import Corrector
    out = tmp_path / "h.pt"
    assert main(["--data", "toy", "--sim-traces", "2", "--sim-epochs", "40", "--epochs", "1", "--inputs",
                 "res,los,dres,arc,heading", "--out", str(out), "--quiet", "--seed", "1", "--threads", "1"],
                prog="gnssfuse train") == 0
    cfg = read_checkpoint(out)["config"]
    assert cfg["features"]["inputs"][-1] == "heading" and cfg["dropout"]["heading"] == 0.2
    flag = FeatureConfig.from_dict(cfg["features"]).slices()["heading"].start
    assert cfg["input_ranges"]["hi"][flag] == 1.0           # the toy drives move: heading was present
    tr = toy_trace(30, seed=8)
    wls = solve_wls(tr)
    c = Corrector.load(out).predict(tr, wls.pos, wls.valid)
    assert np.isfinite(c.mean_ecef[wls.valid]).all()


def test_heading_is_each_epochs_own_and_causal_on_a_long_drive():
    """Two hours due east along a parallel (1.6 degrees of longitude): every heading is east in its own local
    frame, and the first hour's headings do not change when the second hour is appended."""
    t = np.arange(7200.0)
    lon = -122.1 + t * 20.0 / (111_320.0 * np.cos(np.radians(37.4)))
    pos = geodetic2ecef(np.c_[np.full_like(t, 37.4), lon, np.full_like(t, 10.0)])
    heading, moving = travel_heading(t, pos)
    assert moving[3:].all()
    np.testing.assert_allclose(np.degrees(heading[3:]), 90.0, atol=0.01)
    early, m_early = travel_heading(t[:3600], pos[:3600])
    np.testing.assert_array_equal(m_early, moving[:3600])
    np.testing.assert_allclose(early[m_early], heading[:3600][m_early], atol=1e-9)


def test_the_guard_reads_heading_as_missing_where_training_never_had_it_and_checks_no_range():
    cfg = FeatureConfig(inputs=("res", "los", "heading"))
    mask = np.ones((4, 5), bool)
    x = np.zeros((4, 5, cfg.n_inputs))
    flag = cfg.slices()["heading"].start
    x[..., flag], x[..., flag + 1], x[..., flag + 2] = 1.0, 0.6, -0.8
    x[0, :, flag] = 0.0                                           # standing still: absent
    lo, hi = np.zeros(cfg.n_inputs), np.ones(cfg.n_inputs)
    hi[flag] = 0.0                                                # trained without a heading
    missing, core, counts = feature_guard(x, mask, {"lo": lo.tolist(), "hi": hi.tolist()}, cfg)
    np.testing.assert_array_equal(missing["heading"], mask & (x[..., flag] > 0.5))
    assert counts["meas_heading_unseen_in_training"] == 15 and not core.any()
    hi[flag] = 1.0                                                # trained with one: a cosine of -0.8 is no
    missing, _, counts = feature_guard(x, mask, {"lo": lo.tolist(), "hi": hi.tolist()}, cfg)   # range miss
    assert not np.any(missing.get("heading", False)) and "meas_heading_out_of_range" not in counts
