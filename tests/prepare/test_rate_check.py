"""Doppler and carrier phase against the pseudoranges' own rate: a signal written with the opposite sign is
reversed, one on another scale is left out, each with a warning and a count; consistent logs, and logs too
short to decide, pass untouched."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from fusion.prepare.rate_check import check_rates, consecutive_pairs


def _arcs(n_epochs=60, n_sats=8, seed=0):
    """Rows of GPS L1 and L5 arcs (one row per epoch x satellite x signal, 1 Hz) whose pseudorange,
    Doppler and carrier phase share each satellite's range rate plus a receiver drift of 150 m/s, with
    phone-like noise (5 m, 0.1 m/s, 1 cm); and the pseudoranges (N,) and epochs (N,)."""
    rng = np.random.default_rng(seed)
    rate = rng.uniform(-700.0, 700.0, n_sats) + 150.0
    e, s, g = np.meshgrid(np.arange(n_epochs), np.arange(n_sats), [0, 1], indexing="ij")
    e, s, g = e.ravel(), s.ravel(), g.ravel()
    n = e.size
    rows = pd.DataFrame({
        "t_ns": (1_300_000_000 + e).astype(np.int64) * 1_000_000_000, "sat_id": 1000 + s + 1,
        "signal": np.where(g == 0, "GPS_L1", "GPS_L5").astype(object),
        "prr_mps": rate[s] + rng.normal(0, 0.1, n), "adr_m": rate[s] * e + rng.normal(0, 0.01, n),
        "adr_ok": np.ones(n, bool), "adr_slip": np.zeros(n, bool)})
    pr = 2.2e7 + rate[s] * e + rng.normal(0, 5.0, n)
    return rows, pr, e


def _check(rows, pr, epoch):
    skipped: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = check_rates(rows, pr, epoch, "phone.23o", skipped)
    return out, skipped, [str(w.message) for w in caught]


def test_consistent_logs_pass_untouched():
    rows, pr, epoch = _arcs()
    out, skipped, said = _check(rows, pr, epoch)
    assert out is rows and skipped == {} and said == []


def test_a_clock_rate_the_pseudoranges_do_not_share_is_no_scale_error():
    """Pseudoranges whose clock bias was estimated anew each epoch (no drift left in them) against a Doppler
    and carrier phase that keep the oscillator's 300 m/s: the same satellites' rates, consistent."""
    rows, pr, epoch = _arcs()
    out, skipped, said = _check(rows, pr - 300.0 * epoch, epoch)
    assert out is rows and skipped == {} and said == []


@pytest.mark.parametrize("kind, column, signal", [("doppler", "prr_mps", "GPS_L5"), ("carrier", "adr_m", "GPS_L1")])
def test_a_reversed_signal_is_turned_back_and_said(kind, column, signal):
    rows, pr, epoch = _arcs()
    bad = rows.copy()
    these = (bad["signal"] == signal).to_numpy()
    bad.loc[these, column] *= -1.0
    out, skipped, said = _check(bad, pr, epoch)
    pd.testing.assert_frame_equal(out, rows)
    assert skipped == {f"{kind}_sign_reversed:{signal}": int(these.sum())}
    assert len(said) == 1 and "phone.23o" in said[0] and f"{kind} of {signal} has the opposite sign" in said[0]
    assert not bad[column].equals(out[column])                # the caller's rows are not changed


def test_a_doppler_on_another_scale_is_left_out():
    """A Doppler in cycles per second read as metres per second (a wavelength missing) contradicts the
    pseudoranges: that signal's Doppler is left out, its carrier and the other signal's Doppler kept."""
    rows, pr, epoch = _arcs()
    bad = rows.copy()
    l1 = (bad["signal"] == "GPS_L1").to_numpy()
    bad.loc[l1, "prr_mps"] /= 0.1903
    out, skipped, said = _check(bad, pr, epoch)
    assert out.loc[l1, "prr_mps"].isna().all()
    np.testing.assert_array_equal(out.loc[~l1, "prr_mps"], rows.loc[~l1, "prr_mps"])
    assert out["adr_ok"].all()
    assert skipped == {"doppler_rate_inconsistent:GPS_L1": int(l1.sum())}
    assert "disagrees with the pseudoranges' rate: left out" in said[0]


def test_a_carrier_on_another_scale_is_marked_invalid():
    rows, pr, epoch = _arcs()
    bad = rows.copy()
    bad["adr_m"] *= 3.0
    out, skipped, _ = _check(bad, pr, epoch)
    assert not out["adr_ok"].any() and out["prr_mps"].notna().all()
    assert skipped == {"carrier_rate_inconsistent:GPS_L1": len(rows) // 2,
                       "carrier_rate_inconsistent:GPS_L5": len(rows) // 2}


def test_slips_and_gaps_do_not_vote():
    """Carrier resets (flagged) at two epochs of every three: the pairs across them do not vote, so a
    consistent carrier stays consistent although its values jump by kilometres there."""
    rows, pr, epoch = _arcs()
    slip = (epoch % 3 != 0)
    rows.loc[slip, "adr_slip"] = True
    rows["adr_m"] += 7.0e3 * (epoch - epoch // 3)            # each reset starts the phase anew
    out, skipped, said = _check(rows, pr, epoch)
    assert out is rows and skipped == {} and said == []


def test_too_few_pairs_leave_a_signal_undecided():
    rows, pr, epoch = _arcs(n_epochs=3)
    rows["prr_mps"] *= -1.0
    out, skipped, said = _check(rows, pr, epoch)
    assert out is rows and skipped == {} and said == []


def test_pairs_are_consecutive_epochs_of_one_satellite_and_signal():
    """... at most 1.5 s apart: a Doppler averaged over a longer gap no longer matches the pseudoranges'
    mean rate where the receiver accelerates."""
    key = np.array([7, 7, 9, 7, 9, 7, 7])
    epoch = np.array([0, 1, 1, 3, 2, 4, 5])
    t_ns = epoch * 1_000_000_000 + np.where(epoch >= 5, 2_000_000_000, 0)
    i, j = consecutive_pairs(key, epoch, t_ns)
    assert sorted(zip(i.tolist(), j.tolist())) == [(0, 1), (2, 4), (3, 5)]


def test_pixel5_doppler_written_reversed_is_read_as_the_phone_meant(shared_data):
    """The Pixel5 RINEX with its GPS L1 Doppler negated (as a writer with the wrong sign convention would
    store it) gives the same trace as the file as published: every signal is consistent there."""
    from fusion.io.rinex_nav import read_nav
    from fusion.io.rinex_obs import read_rinex_obs
    from fusion.prepare.raw_trace import raw_to_trace

    folder = shared_data / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5/supplemental"
    nav = read_nav(shared_data / "ephemeris/gps_nav/hour1180.21n")
    raw = read_rinex_obs(next(folder.glob("*.21o")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                     # no navigation for Galileo and GLONASS
        clean = raw_to_trace(raw, nav)
    assert not any(k.startswith(("doppler_", "carrier_sign", "carrier_rate")) for k in clean.skipped)
    frame = raw.frame.copy()
    l1 = (frame["signal"] == "GPS_L1").to_numpy()
    frame.loc[l1, "prr_mps"] *= -1.0
    flipped = replace(raw, frame=frame)
    with pytest.warns(UserWarning, match="doppler of GPS_L1 has the opposite sign"):
        fixed = raw_to_trace(flipped, nav)
    np.testing.assert_allclose(fixed.prr, clean.prr, rtol=0, atol=1e-9)
    assert fixed.skipped["doppler_sign_reversed:GPS_L1"] > 10_000
