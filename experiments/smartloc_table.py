"""smartLoc Berlin Potsdamer Platz (u-blox receiver, deep urban canyon; the shipped network never saw it):
every mode, with and without the vehicle odometry.

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/smartloc_table.py
"""
from __future__ import annotations

import os
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
DRIVE = SHARED / "smartloc" / "Berlin_Potsdamer_Platz"


def main() -> int:
    if not DRIVE.is_dir():
        print(f"{DRIVE} not found: skipped")
        return 0
    base = RunOptions(signals=None)
    trace = load_trace(DRIVE, min_sats=1, signals=None)
    n_truth = int(sum(1 for row in trace.truth if all(v == v for v in row)))
    print("| mode | odometry | GSDC score [m] | h p50 | h p95 | solved / truth epochs |")
    print("|---|---|---|---|---|---|")
    for odo in (False, True):
        opts = replace(base, graph=replace(base.graph, use_odometry=odo))
        modes = ["fused-nodnn", "fused"] if odo else ["wls", "dnn", "fused-nodnn", "fused"]
        for mode, res in run_modes(trace, modes, opts).items():
            m = mode_metrics(trace, res)
            flag = ("on" if odo else "off") if mode.startswith("fused") else "-"
            print(f"| {mode} | {flag} | {m['gsdc_score']:.2f} | {m['h_p50']:.2f} | {m['h_p95']:.2f} | "
                  f"{m['n']} / {n_truth} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
