"""Pixel5 RINEX trace (2021-04-28-US-MTV-1/Pixel5, a test trace: nothing was tuned on it): wls,
fused-nodnn and fused with and without Doppler and carrier phase, broadcast GPS navigation or the CODE
multi-GNSS SP3/CLK. GSDC score (mean of horizontal p50 and p95) against the SPAN log interpolated at the
receiver epochs, and the share of truth epochs solved.

    python experiments/pixel5_table.py > experiments/results/pixel5.md
"""
from __future__ import annotations

import os
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.options import load_options  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRACE = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
PRECISE = SHARED / "ephemeris/precise"
ORBITS = {
    "broadcast GPS (hour1180.21n)": dict(nav=(SHARED / "ephemeris/gps_nav/hour1180.21n",)),
    # the navigation file adds the Klobuchar ionosphere (SP3/CLK carry none) and GPS group delays
    "CODE SP3/CLK, multi-GNSS (+ hour1180.21n ionosphere)": dict(
        sp3=PRECISE / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3",
        clk=PRECISE / "COD0MGXFIN_20211180000_01D_30S_CLK.CLK",
        nav=(SHARED / "ephemeris/gps_nav/hour1180.21n",)),
}
VARIANTS = {"Doppler + carrier": {}, "no carrier": {"use_carrier": False}, "no Doppler": {"use_doppler": False},
            "pseudoranges only": {"use_doppler": False, "use_carrier": False}}


def main() -> int:
    print("| orbits | measurements | mode | GSDC score [m] | h p50 | h p95 | solved / truth epochs |")
    print("|---|---|---|---|---|---|---|")
    for orbit, kw in ORBITS.items():
        base = RunOptions(signals=None, **kw)
        trace = load_trace(TRACE, min_sats=1, **load_options(base))
        n_truth = int(sum(1 for row in trace.truth if all(v == v for v in row)))
        for label, change in VARIANTS.items():
            opts = replace(base, graph=replace(base.graph, **change))
            modes = ["wls", "fused-nodnn", "fused"] if label == "Doppler + carrier" else ["fused-nodnn", "fused"]
            for mode, res in run_modes(trace, modes, opts).items():
                m = mode_metrics(trace, res)
                print(f"| {orbit} | {label if mode != 'wls' else '-'} | {mode} | {m['gsdc_score']:.2f} | "
                      f"{m['h_p50']:.2f} | {m['h_p95']:.2f} | {m['n']} / {n_truth} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
