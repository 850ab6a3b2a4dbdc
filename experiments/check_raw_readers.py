"""Agreement of the raw readers with Google's own processed values, on ../shared/data samples.

    python experiments/check_raw_readers.py

1. GnssLogger ``Pixel4_GnssLog.txt`` (GSDC 2021 samples) against ``Pixel4_derived.csv``'s ``rawPrM``
   / ``rawPrUncM`` for the same epoch and satellite/signal (derived times are 1 s late).
2. GnssLogger ``gnss_log.txt`` (GSDC 2023 sample, pixel7pro) against its ``device_gnss.csv``:
   pseudorange (up to one offset common to all satellites of an epoch; see ``read_gnss_log``'s
   ``fixed_full_bias``), pseudorange rate, ADR (where valid) and C/N0.
3. RINEX ``Pixel5_GnssLog.21o``: what the reader keeps and skips.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.io.gnss_log import C_MPS, read_gnss_log  # noqa: E402
from fusion.io.rinex_obs import read_rinex_obs  # noqa: E402
from fusion.trace import SIGNALS, signal_index  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))


def check_2021() -> None:
    s = SHARED / "gsdc2021/samples"
    f = read_gnss_log(s / "Pixel4_GnssLog.txt").frame
    d = pd.read_csv(s / "Pixel4_derived.csv")
    d["sat_id"] = d.constellationType * 1000 + d.svid
    m = f.assign(ms=f.t_ns // 10**6 + 1000).merge(
        d, left_on=["ms", "sat_id", "signal"], right_on=["millisSinceGpsEpoch", "sat_id", "signalType"])
    print(f"2021 Pixel4 log: {len(f)} rows read, {len(m)} matched to derived rows; "
          f"max |pr - rawPrM| = {1e3 * np.abs(m.pr_m - m.rawPrM).max():.3f} mm, "
          f"max |pr_sigma - rawPrUncM| = {1e3 * np.abs(m.pr_sigma_m - m.rawPrUncM).max():.3f} mm")


def check_2023() -> None:
    s = SHARED / "gsdc2023/samples/2023-09-07-18-59-us-ca/pixel7pro"
    d = pd.read_csv(s / "device_gnss.csv")
    d["sat_id"] = d.ConstellationType * 1000 + d.Svid
    d["signal"] = [SIGNALS[i] if i >= 0 else None for i in signal_index(d.SignalType)]
    d["ep"] = np.searchsorted(np.unique(d.TimeNanos), d.TimeNanos)
    for fixed in (False, True):
        f = read_gnss_log(s / "gnss_log.txt", fixed_full_bias=fixed).frame
        m = f.assign(ep=np.searchsorted(np.unique(f.t_ns), f.t_ns)).merge(d, on=["ep", "sat_id", "signal"])
        diff = m.pr_m - m.RawPseudorangeMeters
        spread = diff.groupby(m.ep).agg(np.ptp).max() if not fixed else np.ptp(diff)
        ok = m.adr_ok
        print(f"2023 pixel7pro log (fixed_full_bias={fixed}): {len(f)} rows, {len(m)} matched of {len(d)}; "
              f"pr - RawPseudorangeMeters: offsets {np.unique(np.round(diff / C_MPS * 1e9, 1))} ns, "
              f"spread within {'the log' if fixed else 'an epoch'} {1e3 * spread:.3f} mm; "
              f"max |d prr| {np.abs(m.prr_mps - m.PseudorangeRateMetersPerSecond).max():.1e} m/s, "
              f"max |d adr| {np.abs(m.adr_m - m.AccumulatedDeltaRangeMeters)[ok].max():.1e} m over {ok.sum()} valid, "
              f"max |d cn0| {np.abs(m.cn0 - m.Cn0DbHz).max():.1e} dB-Hz")


def check_rinex() -> None:
    raw = read_rinex_obs(SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5/supplemental/Pixel5_GnssLog.21o")
    f = raw.frame
    per = f.groupby("signal").agg(rows=("pr_m", "size"), pr=("pr_m", "count"), prr=("prr_mps", "count"),
                                  adr=("adr_ok", "sum"), slips=("adr_slip", "sum"))
    print(f"RINEX Pixel5: {raw.n_epochs} epochs, {len(f)} rows, skipped {raw.skipped}\n{per.to_string()}")


if __name__ == "__main__":
    if not SHARED.is_dir():
        sys.exit(f"shared data not found at {SHARED} (set GNSSFUSE_SHARED_DATA)")
    check_2021()
    check_2023()
    check_rinex()
