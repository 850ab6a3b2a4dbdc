"""Does a clock-drift state, or a tighter clock or motion model, stop the graph's drift through long
stretches with too few satellites? ``fused-nodnn`` GSDC score on the twelve training drives, untouched and thinned as
experiments/few_satellites.py thins them (3 satellites in 120 s of every 180 s), per setting; and per drive,
the clock chain before drift states without Doppler (GraphConfig.clock_drift_states "doppler"), with and
without a tighter velocity walk into the epochs only the motion model places (bridged_accel_scale), against
the shipped settings. With ``--sim DIR`` (the simulated city traces of experiments/sim_city_traces.py,
which have Doppler), whether the tighter walk pays also where Doppler measures the velocity.

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/few_satellites_models.py    # ~7 min
    python experiments/few_satellites_models.py --sim /tmp/sim                        # ~30 s
"""
from __future__ import annotations

import argparse
import sys
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from few_satellites import SHARED, thinned  # noqa: E402
import fusion.estimate.graph.build as build  # noqa: E402
import fusion.estimate.graph.vector_graph as vector_graph  # noqa: E402
from fusion.estimate.graph.inputs import motion_only, pseudorange_gap  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

#: the clock chain before drift states without Doppler (GraphConfig.clock_drift_states "doppler")
BEFORE = {"clock_drift_states": "doppler"}
SETTINGS = {"shipped": {}, "no drift states without Doppler (before)": BEFORE,
            "drift_clock_rw_no_doppler_m 1": dict(drift_clock_rw_no_doppler_m=1.0),
            "drift_clock_rw_no_doppler_m 2": dict(drift_clock_rw_no_doppler_m=2.0),
            "drift_clock_rw_no_doppler_m 3": dict(drift_clock_rw_no_doppler_m=3.0),
            "bridged_accel_scale 1": dict(bridged_accel_scale=1.0),
            "bridged_accel_scale 0.25": dict(bridged_accel_scale=0.25),
            "before, bridged_accel_scale 1": dict(BEFORE, bridged_accel_scale=1.0),
            "before, clock_rw_m 1": dict(BEFORE, clock_rw_m=1.0),
            "before, clock_rw_m 2": dict(BEFORE, clock_rw_m=2.0), "cv_accel_h 0.5": dict(cv_accel_h=0.5)}


@contextmanager
def walk_tightened_where(which):
    """Both graph builders tighten the walk into the epochs ``which(inp)`` marks (shipped: motion_only)."""
    build.motion_only = vector_graph.motion_only = which
    try:
        yield
    finally:
        build.motion_only = vector_graph.motion_only = motion_only


def with_doppler(sim: Path) -> int:
    """Thinned simulated traces (Doppler, all signals): the walk tightened at motion-only epochs (shipped)
    against at every pseudorange gap, Doppler or not."""
    print("| simulated trace, thinned | none | motion-only epochs x0.5 (shipped) | every gap x0.5 | every gap x0.25 |")
    print("|---|---|---|---|---|")
    runs = {"none": (motion_only, 1.0), "shipped": (motion_only, 0.5), "gap 0.5": (pseudorange_gap, 0.5),
            "gap 0.25": (pseudorange_gap, 0.25)}
    means = {name: [] for name in runs}
    for k, folder in enumerate(sorted(sim.glob("*/SimPhone"))):
        opts = RunOptions(signals=("all",))
        thin, _ = thinned(load_trace(folder, signals=("all",), min_sats=1), 3, k)
        for name, (which, scale) in runs.items():
            with walk_tightened_where(which):
                o = replace(opts, graph=replace(opts.graph, bridged_accel_scale=scale))
                means[name].append(mode_metrics(thin, run_modes(thin, ["fused-nodnn"], o)["fused-nodnn"])["gsdc_score"])
        print(f"| {folder.parent.name} | " + " | ".join(f"{v[-1]:.1f}" for v in means.values()) + " |")
    print("| mean | " + " | ".join(f"{np.mean(v):.1f}" for v in means.values()) + " |")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=Path, help="simulated traces with Doppler instead of the GSDC drives")
    args = ap.parse_args()
    if args.sim:
        return with_doppler(args.sim)
    scores = {name: ([], []) for name in SETTINGS}
    drives = sorted((SHARED / "gsdc2021/train").glob("2020-*/Pixel4"))
    for k, folder in enumerate(drives):
        full = load_trace(folder, min_sats=1)                  # as gnssfuse run and evaluate load it
        thin, _ = thinned(full, 3, k)
        for name, change in SETTINGS.items():
            opts = RunOptions()
            opts = replace(opts, graph=replace(opts.graph, **change))
            for got, tr in zip(scores[name], (full, thin)):
                got.append(mode_metrics(tr, run_modes(tr, ["fused-nodnn"], opts)["fused-nodnn"])["gsdc_score"])
    before = np.array(scores["no drift states without Doppler (before)"][0])
    print("| setting | mean GSDC score, untouched drives [m] | worst untouched drive / before | ... thinned [m] |")
    print("|---|---|---|---|")
    for name, (full, thin) in scores.items():
        print(f"| {name} | {np.mean(full):.2f} | {np.max(np.array(full) / before):.3f} | {np.mean(thin):.1f} |")
    cols = ("before, bridged_accel_scale 1", "no drift states without Doppler (before)", "bridged_accel_scale 1",
            "shipped")
    print("\n| drive | as logged, before [m] | as logged, shipped [m] | thinned: " + " [m] | ".join(cols) + " [m] |")
    print("|---" * (len(cols) + 3) + "|")
    for k, folder in enumerate(drives):
        logged = [scores[c][0][k] for c in ("no drift states without Doppler (before)", "shipped")]
        print(f"| {folder.parent.name} | " + " | ".join(f"{v:.2f}" for v in logged) + " | "
              + " | ".join(f"{scores[c][1][k]:.1f}" for c in cols) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
