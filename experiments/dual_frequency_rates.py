"""Should a dual-frequency log give the graph one Doppler and one carrier phase per satellite? A reflection's extra
path changes at the same rate on both frequencies, so the second frequency's rate and phase might only count the
same error twice. ``fused-nodnn`` / ``fused`` GSDC score [m] with every signal's Doppler and carrier (as shipped) and
with the second frequency's dropped wherever the same satellite's first frequency is there: the Pixel5 RINEX test
trace (reported) with broadcast GPS (L1 + L5) and with SP3/CLK (every constellation), and with ``--sim`` the
simulated city traces.

    python experiments/dual_frequency_rates.py [--sim /tmp/simho]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from few_satellites import NAV, PIXEL5  # noqa: E402
from pixel5_table import ORBITS  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.trace import SIGNALS, Trace  # noqa: E402

SECOND = [SIGNALS.index(s) for s in ("GPS_L5", "GAL_E5A", "QZS_J5", "GPS_L2", "GAL_E5B", "BDS_B2I", "QZS_J2")]
MODES = ("fused-nodnn", "fused")


def first_frequency_rates(trace: Trace) -> Trace:
    """``trace`` without the Doppler and carrier of a second-frequency slot whose satellite has another (first
    frequency) slot in the same epoch."""
    second = trace.mask & np.isin(trace.signal, SECOND)
    first = trace.mask & ~second
    # (E,S,S): slot s is a second frequency of the satellite in slot r, which is a first frequency
    twin = (trace.sat_id[:, :, None] == trace.sat_id[:, None, :]) & first[:, None, :]
    drop = second & twin.any(axis=2)
    return replace(trace, prr_ok=None if trace.prr_ok is None else trace.prr_ok & ~drop,
                   adr_ok=None if trace.adr_ok is None else trace.adr_ok & ~drop)


def scores(trace: Trace, opts: RunOptions) -> dict[str, float]:
    wls = solve_initial(trace, opts)
    out = run_modes(trace, list(MODES), opts, wls=wls)
    return {m: mode_metrics(trace, out[m])["gsdc_score"] for m in MODES}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=Path, help="a folder of simulated city traces (*/SimPhone), every signal")
    args = ap.parse_args()
    runs = [("Pixel5, broadcast GPS", PIXEL5, RunOptions(signals=None, nav=(NAV,), sigma_calibration=False)),
            ("Pixel5, SP3/CLK", PIXEL5, RunOptions(signals=None, sigma_calibration=False,
                                                   **ORBITS["CODE SP3/CLK, multi-GNSS (+ hour1180.21n ionosphere)"]))]
    if args.sim:
        runs += [(f.parent.name, f, RunOptions(signals=("all",), sigma_calibration=False))
                 for f in sorted(args.sim.glob("*/SimPhone"))]
    print("| trace | " + " | ".join(f"{m}, every signal | {m}, one per satellite" for m in MODES) + " |")
    print("|---|" + "---|" * (2 * len(MODES)))
    for name, path, opts in runs:
        trace = load_trace(path, min_sats=1, **load_options(opts))
        a, b = scores(trace, opts), scores(first_frequency_rates(trace), opts)
        print(f"| {name} | " + " | ".join(f"{a[m]:.2f} | {b[m]:.2f}" for m in MODES) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
