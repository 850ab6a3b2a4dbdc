"""How stiff should the horizontal motion model be where the graph has Doppler? (``GraphConfig.cv_accel_h`` on traces
that all have Doppler: what a separate setting for graphs with Doppler would choose.)

Doppler measures the velocity, so a stiffer random walk on it costs nothing where enough satellites agree, and
where one or two satellites are left in a street canyon it keeps a reflection's rate error from steering the
velocity (``experiments/results/canyon_on_phone.md``). Without Doppler the walk is all that follows a turn, and
there a stiffer one costs (``experiments/results/graph_tuning.md``). ``fused-nodnn`` and ``fused`` GSDC score per
horizontal walk on the simulated city traces (every signal, Doppler), as simulated and thinned to 3 and to 2
satellites in 120 s of every 180 s (experiments/few_satellites.py). ``--canyon`` then reports the Pixel5 test
trace as logged and under the street canyons of ``experiments/canyon_on_phone.py``.

    python experiments/doppler_motion.py --sim /tmp/sim /tmp/simho        # the simulated traces (tuning)
    python experiments/doppler_motion.py --canyon                        # the Pixel5 test trace (reported)
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from canyon_on_phone import DEEP, in_canyon  # noqa: E402
from few_satellites import NAV, PIXEL5, thinned  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import CanyonModel  # noqa: E402

WALKS = (1.0, 0.7, 0.5, 0.35, 0.25)
MODES = ("fused-nodnn", "fused")


def scores(trace, opts: RunOptions) -> dict[str, list[float]]:
    """mode -> GSDC score at each horizontal walk of :data:`WALKS`."""
    wls = solve_initial(trace, opts)
    out = {m: [] for m in MODES}
    for a in WALKS:
        o = replace(opts, graph=replace(opts.graph, cv_accel_h=a))
        res = run_modes(trace, list(MODES), o, wls=wls)
        for m in MODES:
            out[m].append(mode_metrics(trace, res[m])["gsdc_score"])
    return out


def table(title: str, rows: dict[str, dict[str, list[float]]]) -> None:
    """Per trace and mode, the scores and, last, each mode's mean and worst ratio to the default walk (1)."""
    print(f"\n{title}\n\n| trace | mode | " + " | ".join(f"{a:g}" for a in WALKS) + " |")
    print("|---|---" + "|---" * len(WALKS) + "|")
    for name, by_mode in rows.items():
        for m, v in by_mode.items():
            print(f"| {name} | {m} | " + " | ".join(f"{x:.2f}" for x in v) + " |")
    for m in MODES:
        a = np.array([r[m] for r in rows.values()])
        print(f"| mean | {m} | " + " | ".join(f"{x:.2f}" for x in a.mean(0)) + " |")
        print(f"| worst / 1 | {m} | " + " | ".join(f"{x:.3f}" for x in (a / a[:, :1]).max(0)) + " |", flush=True)


def simulated(folders: list[Path]) -> None:
    opts = RunOptions(signals=("all",), sigma_calibration=False)
    logged, thin3, thin2 = {}, {}, {}
    for k, folder in enumerate(folders):
        tr = load_trace(folder, signals=("all",), min_sats=1)
        logged[folder.parent.name] = scores(tr, opts)
        thin3[folder.parent.name] = scores(thinned(tr, 3, k)[0], opts)
        thin2[folder.parent.name] = scores(thinned(tr, 2, k)[0], opts)
    table("Simulated city traces as simulated", logged)
    table("Simulated city traces thinned to 3 satellites", thin3)
    table("Simulated city traces thinned to 2 satellites", thin2)


def canyon() -> None:
    opts = RunOptions(signals=None, nav=(NAV,), sigma_calibration=False)
    trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    rows = {"as logged": scores(trace, opts)}
    for label, model in (("canyon", CanyonModel()), ("deep canyon", DEEP)):
        for seed in (0, 1, 2):
            rows[f"{label}, streets seed {seed}"] = scores(in_canyon(trace, model, seed)[0], opts)
    table("Pixel5 RINEX (test trace, reported), broadcast GPS L1 + L5", rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=Path, nargs="+", help="folders of simulated city traces (*/SimPhone)")
    ap.add_argument("--canyon", action="store_true", help="report the Pixel5 test trace instead")
    args = ap.parse_args()
    print("Horizontal walks [m/s per sqrt(s)]:", ", ".join(f"{a:g}" for a in WALKS), "(1: the default)")
    if args.canyon:
        canyon()
    if args.sim:
        simulated(sorted(f for d in args.sim for f in d.glob("*/SimPhone")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
