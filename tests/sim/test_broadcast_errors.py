"""The range errors broadcast corrections leave (fusion.sim.broadcast_errors): off by default, slowly varying per
satellite, sized per constellation, code and carrier apart by twice the ionosphere, nothing else moved."""
from __future__ import annotations

import numpy as np
import pytest

from fusion.io.rinex_nav import default_nav_path, read_rinex_nav
from fusion.sim.broadcast_errors import IONO_SCALE, gauss_markov
from fusion.sim.config import config_from_options, scenario_config
from fusion.trace import SIGNALS


@pytest.fixture(scope="module")
def pair():
    """The same seeded urban drives (carrier phase; three traces of 300 epochs, simulated in three chunks) without
    and with the errors."""
    import fusion.sim.measurements as meas
    import fusion.sim.simulate as sim
    nav = read_rinex_nav(default_nav_path())
    chunk = meas.CHUNK_EPOCHS
    meas.CHUNK_EPOCHS = sim.CHUNK_EPOCHS = 300
    try:
        return [sim.simulate_dataset(3, 300, seed=11, nav=nav, results=True, concatenate=True, origins=[(37.4, -122.1)],
                                     config=scenario_config("urban", carrier=True, broadcast_errors=on))
                for on in (False, True)]
    finally:
        meas.CHUNK_EPOCHS = sim.CHUNK_EPOCHS = chunk


def test_off_by_default_and_on_from_the_command_line_options():
    assert not scenario_config("urban").broadcast_errors
    assert config_from_options("urban", broadcast_errors=True).broadcast_errors


def test_only_code_and_carrier_move(pair):
    off, on = (r.trace for r in pair)
    for k in ("sat_id", "signal", "mask", "cn0", "prr", "adr_slip", "truth"):
        np.testing.assert_array_equal(getattr(off, k), getattr(on, k))
    code = np.where(off.mask, on.pr - off.pr, 0.0)
    assert np.abs(code[off.mask]).min() > 0 and np.abs(code[off.mask]).std() > 0.3


def test_errors_vary_slowly_per_satellite_and_by_constellation(pair):
    off, on = (r.trace for r in pair)
    code = on.pr - off.pr
    l1 = off.mask & np.isin(off.signal, [SIGNALS.index(s) for s in ("GPS_L1", "GLO_G1", "GAL_E1", "BDS_B1I")])
    both = l1[1:] & l1[:-1] & (off.sat_id[1:] == off.sat_id[:-1]) & ~off.clock_reset[1:, None]
    step = np.abs(code[1:] - code[:-1])[both]
    assert np.median(step) < 0.05 * np.std(code[l1])              # metres between traces, centimetres a second
    # code plus carrier is twice the orbit and clock error (and troposphere): GLONASS's far above Galileo's
    orbit = (code + on.adr - off.adr) / 2
    glo, gal = (off.mask & (off.signal == SIGNALS.index(s)) for s in ("GLO_G1", "GAL_E1"))
    assert orbit[glo].std() > 2.5 * orbit[gal].std()
    # code minus carrier is twice the ionosphere left, larger on L5 than on L1 by (f_L1 / f_L5)^2
    cmc = code - (on.adr - off.adr)
    l1, l5 = (off.mask & (off.signal == SIGNALS.index(s)) for s in ("GPS_L1", "GPS_L5"))
    same_sat = l1[:, :, None] & l5[:, None, :] & (off.sat_id[:, :, None] == off.sat_id[:, None, :])   # (E, L1, L5)
    e, j1, j5 = np.nonzero(same_sat & (np.abs(cmc) > 0.1)[:, :, None])
    ratios = cmc[e, j5] / cmc[e, j1]
    assert ratios.size > 100
    assert np.allclose(ratios, IONO_SCALE[SIGNALS.index("GPS_L5")], rtol=1e-6)


def test_gauss_markov_holds_its_sigma_and_restarts_per_trace():
    rng = np.random.default_rng(0)
    t = np.tile(np.arange(200.0), 50)
    start = np.zeros(t.size, bool)
    start[::200] = True
    x = gauss_markov(t, start, 40, np.full(40, 2.0), 100.0, rng)
    assert abs(x.std() - 2.0) < 0.1
    lag1 = np.corrcoef(x[1:200].ravel(), x[:199].ravel())[0, 1]
    assert abs(lag1 - np.exp(-1 / 100)) < 0.01
    across = np.corrcoef(x[199::200][:-1].ravel(), x[200::200].ravel())[0, 1]   # last epoch vs next trace's first
    assert abs(across) < 0.1


def test_the_labels_hold_the_error_and_the_pseudorange_decomposes(pair, tmp_path):
    """pr = range + clock + noise + NLOS path + multipath + broadcast error, to the micrometre; sim_labels.csv
    carries the last as BroadcastErrorM (and only when the errors are on)."""
    import pandas as pd

    from fusion.geometry import line_of_sight
    from fusion.sim.write import LABELS_FILE, write_device_gnss
    off, on = pair
    assert off.broadcast_m is None and on.broadcast_m is not None
    tr = on.trace
    rng_m, _ = line_of_sight(tr.sat_pos, tr.truth)
    resid = tr.pr - rng_m - on.clock_m[:, None] - on.noise_m - on.nlos_delay_m - on.multipath_m - on.broadcast_m
    assert np.abs(resid[tr.mask]).max() < 1e-6
    write_device_gnss(on, tmp_path, "c", "P")
    write_device_gnss(off, tmp_path, "d", "P")
    labels = pd.read_csv(tmp_path / "c" / "P" / LABELS_FILE)
    np.testing.assert_allclose(labels["BroadcastErrorM"], np.round(on.broadcast_m[tr.mask], 4), atol=1e-9)
    assert "BroadcastErrorM" not in pd.read_csv(tmp_path / "d" / "P" / LABELS_FILE)
