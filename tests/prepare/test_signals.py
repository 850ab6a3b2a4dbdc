"""Second frequencies (GPS L2C here) as signals of their own: their group delay, their own bias
state in the graph and in WLS, and the ionosphere-free combination (``--iono-free``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fusion.estimate.graph.config import GraphConfig
from fusion.geometry import C_LIGHT, geodetic2ecef, line_of_sight
from fusion.gpstime import gps_ms_from_calendar
from fusion.io.raw import RawObs, finish_raw
from fusion.prepare.raw_trace import raw_to_trace
from fusion.io.rinex_nav import GAMMA_L2, default_nav_path, read_nav
from fusion.nav.orbits import select_ephemeris, transmit_states
from fusion.trace import SIGNALS

RX = geodetic2ecef(np.array([[37.3958, -122.103, -5.0]]))[0]
L2_BIAS_M = 7.5          # the receiver's L2C inter-signal bias
IONO_L1_M = 4.0          # zenith-free slant ionosphere at L1 for every satellite (L2: gamma times)


@pytest.fixture(scope="module")
def nav():
    n = read_nav(default_nav_path())
    n.klobuchar = None          # the synthetic ranges carry our own ionosphere, not Klobuchar's
    return n


def _frame(nav, n_epochs: int = 6) -> pd.DataFrame:
    """GPS L1 + L2C pseudoranges from RX of every satellite above 15 degrees, 1 s apart."""
    from fusion.geometry import elevation_azimuth
    cols: dict[str, list] = {k: [] for k in ("t_ns", "svid", "signal", "pr_m")}
    t0 = gps_ms_from_calendar(2021, 4, 28, 12, 0, 0.0)
    prns = np.arange(1, 33)
    for e in range(n_epochs):
        t = t0 + 1000 * e
        idx = select_ephemeris(nav.kepler, prns, t)
        ok = idx >= 0
        st, tau = transmit_states(nav.kepler, idx[ok], np.broadcast_to(RX, (ok.sum(), 3)), np.full(ok.sum(), t))
        el, _ = elevation_azimuth(line_of_sight(st["pos"], RX)[1], RX)
        up = el > 15
        tgd = nav.kepler.params["tgd"][idx[ok]][up]
        base = tau[up] * C_LIGHT + 100.0 - C_LIGHT * st["clock_s"][up]      # L1 clock has -TGD in it
        l2 = base - C_LIGHT * (tgd - GAMMA_L2 * tgd) + L2_BIAS_M + GAMMA_L2 * IONO_L1_M
        for sig, pr in (("GPS_L1", base + IONO_L1_M), ("GPS_L2", l2)):
            cols["t_ns"] += [t * 1_000_000 + round(100.0 / C_LIGHT * 1e9)] * int(up.sum())
            cols["svid"] += list(prns[ok][up])
            cols["signal"] += [sig] * int(up.sum())
            cols["pr_m"] += list(pr)
    n = len(cols["t_ns"])
    nan = np.full(n, np.nan)
    return finish_raw({"t_ns": np.array(cols["t_ns"], np.int64), "const": np.full(n, "G", object),
                       "svid": np.array(cols["svid"]), "signal": np.array(cols["signal"], object),
                       "pr_m": np.array(cols["pr_m"]), "pr_sigma_m": nan, "prr_mps": nan, "prr_sigma_mps": nan,
                       "adr_m": nan, "adr_sigma_m": nan, "adr_ok": np.zeros(n, bool), "adr_slip": np.zeros(n, bool),
                       "cn0": np.full(n, 40.0), "glo_k": np.zeros(n, np.int64), "clock_reset": np.zeros(n, bool)})


def _trace(nav, **kw):
    raw = RawObs(frame=_frame(nav), path=Path("dual.obs"))
    with pytest.warns(UserWarning, match="no ionosphere model"):
        return raw_to_trace(raw, nav, **kw)


def _tropo(tr):
    from fusion.geometry import ecef2geodetic, elevation_azimuth
    from fusion.nav.atmosphere import tropo_delay
    _, los = line_of_sight(tr.sat_pos, RX)
    el, _ = elevation_azimuth(los, RX)
    llh = ecef2geodetic(RX)
    return tropo_delay(llh[0], llh[2], el)


def test_l2_is_its_own_signal_with_its_group_delay_and_bias(nav):
    tr = _trace(nav)
    l1, l2 = SIGNALS.index("GPS_L1"), SIGNALS.index("GPS_L2")
    assert set(np.unique(tr.signal[tr.mask])) == {l1, l2}
    rng, _ = line_of_sight(tr.sat_pos, RX)
    resid = tr.pr + _tropo(tr) - rng - 100.0
    # L1 keeps its ionosphere (4 m); L2 has gamma times that, and the loader removed its
    # inter-signal bias (median over the trace) so that one receiver clock serves both
    np.testing.assert_allclose(resid[tr.mask & (tr.signal == l1)], IONO_L1_M, atol=2e-3)
    r2 = resid[tr.mask & (tr.signal == l2)]
    np.testing.assert_allclose(r2, r2.mean(), atol=2e-3)
    assert r2.mean() == pytest.approx(IONO_L1_M, abs=0.05)      # bias + (gamma - 1) iono removed


def test_iono_free_removes_the_ionosphere(nav):
    tr = _trace(nav, iono_free=True)
    l2 = SIGNALS.index("GPS_L2")
    assert set(np.unique(tr.signal[tr.mask])) == {l2}
    assert tr.skipped["rows_combined_iono_free"] == tr.mask.sum()
    rng, _ = line_of_sight(tr.sat_pos, RX)
    resid = (tr.pr + _tropo(tr) - rng - 100.0)[tr.mask]
    # the ionosphere is gone; what is left is the reference-clock offset of the combination
    # (a constant the loader folds into the clock), the same for every satellite
    np.testing.assert_allclose(resid, resid.mean(), atol=5e-3)
    assert np.all(tr.pr_sigma[tr.mask] > 2.9 * 3.0)           # about 3 x the L1 sigma


def test_wls_and_graph_use_the_second_frequency(nav):
    """A 20 m bias left on L2 (beyond the loader's removal) is the graph's GPS_L2 bias state:
    its positions do not move; WLS (one clock) still solves every epoch with both signals."""
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    opts = RunOptions(signals=None, graph=GraphConfig(use_doppler=False, use_carrier=False))
    tr = _trace(nav)
    base = run_modes(tr, ["fused-nodnn"], opts)["fused-nodnn"]
    l2 = tr.mask & (tr.signal == SIGNALS.index("GPS_L2"))
    tr.pr[l2] += 20.0
    res = run_modes(tr, ["wls", "fused-nodnn"], opts)
    fused = res["fused-nodnn"]
    assert set(fused.info["isb_m"]) == {"GPS_L2@0"}
    assert fused.info["isb_m"]["GPS_L2@0"] - base.info["isb_m"]["GPS_L2@0"] == pytest.approx(20.0, abs=0.2)
    np.testing.assert_allclose(fused.pos, base.pos, atol=0.05)
    assert np.isfinite(res["wls"].pos).all()


def test_signal_names_stay_and_new_ones_are_appended():
    """Stored indices of the first eight signals never move; GSDC 2023 spellings of the new ones
    map by their first two tokens; RINEX 2 L2 / E5b / B2I types become RINEX 3 codes of ours."""
    from fusion.io.rinex_obs import SIGNAL_CODES, v2_type_as_v3
    from fusion.trace import signal_index
    assert SIGNALS[:8] == ("GPS_L1", "GPS_L5", "GLO_G1", "GAL_E1", "GAL_E5A", "BDS_B1I", "QZS_J1", "QZS_J5")
    assert signal_index(["GPS_L2_C", "GAL_E5B_Q", "BDS_B2I", "QZS_J2", "SBS_L1_CA"]).tolist() == [8, 9, 10, 11, -1]
    codes = {(s, band + attr) for s, sigs in SIGNAL_CODES.items() for _, band, attrs in sigs for attr in attrs}
    for system, v2 in (("G", "C2"), ("G", "L2"), ("E", "C7"), ("C", "C7"), ("J", "C2")):
        assert (system, v2_type_as_v3(system, v2)[1:]) in codes
    assert ("G", v2_type_as_v3("G", "P2")[1:]) not in codes              # P(Y) is not L2C


def test_beidou_b1c_and_b2a_are_signals_of_their_own_through_every_mode():
    """BeiDou-3's B1C and B2a (indices past the network's one-hots) run through every mode, the learned part
    reading them as an unknown signal, and each has its own bias state in the graph: a 15 m receiver bias on
    B1C moves that state, not the positions. A simulated open-sky drive whose BeiDou satellites of odd svid
    log B1C and the others B2a."""
    from fusion.eval.summary import learned_words
    from fusion.modes import run_modes
    from fusion.run_types import RunOptions
    from fusion.sim.config import scenario_config
    from fusion.sim.simulate import simulate
    from fusion.trace import signal_index
    assert signal_index(["BDS_B1C", "BDS_B2A_P", "BDS_B1C_D"]).tolist() == [12, 13, 12]
    tr = simulate(n_epochs=60, nav=default_nav_path(), seed=3, config=scenario_config("open")).trace
    bds = tr.mask & (tr.signal == SIGNALS.index("BDS_B1I"))
    b1c = bds & (tr.sat_id % 2 == 1)
    tr.signal[b1c], tr.signal[bds & ~b1c] = SIGNALS.index("BDS_B1C"), SIGNALS.index("BDS_B2A")
    assert b1c.any() and (bds & ~b1c).any()
    opts = RunOptions(signals=None, graph=GraphConfig(use_doppler=False, use_carrier=False))
    res = run_modes(tr, ["wls", "fused-nodnn", "fused"], opts)
    for mode, r in res.items():
        err = np.linalg.norm(r.pos[r.valid] - tr.truth[r.valid], axis=1)
        assert r.valid.all() and np.median(err) < 3.0, mode
    # every BeiDou measurement the network was asked about (above its mask) read as an unknown signal, no other
    info = res["fused"].info
    assert 0.8 * bds.sum() < info["learned_meas_signal_read_as_unknown"] <= bds.sum()
    assert f"{info['learned_meas_signal_read_as_unknown']} read as an unknown signal" in learned_words(info)
    base = res["fused-nodnn"]
    tr.pr[b1c] += 15.0
    moved = run_modes(tr, ["fused-nodnn"], opts)["fused-nodnn"]
    assert {"BDS_B1C@0", "BDS_B2A@0"} <= set(moved.info["isb_m"])
    assert moved.info["isb_m"]["BDS_B1C@0"] - base.info["isb_m"]["BDS_B1C@0"] == pytest.approx(15.0, abs=0.3)
    np.testing.assert_allclose(moved.pos, base.pos, atol=0.05)
