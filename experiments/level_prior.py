"""Does a zero-mean prior on the vertical velocity (GraphConfig.cv_level_sigma_mps with Doppler,
cv_level_sigma_no_doppler_mps without: a softened altitude hold) help the graph where the satellites cannot
place it? The same sigma in every graph here; ``fused-nodnn`` GSDC score per level sigma on: the
twelve GSDC training drives as logged and thinned to 3 satellites in 120 s of every 180 s
(experiments/few_satellites.py), smartLoc's canyon (with ``fused``, the shipped network, which never saw it),
and with ``--sim DIR`` the simulated city traces of experiments/sim_city_traces.py (Doppler, every signal)
as simulated and thinned. Those decide; ``--pixel5`` then reports the Pixel5 RINEX test trace (GPS
broadcast navigation, Doppler and carrier), as logged and thinned, without the prior and with the defaults.

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/level_prior.py --sim /tmp/sim    # ~3 min
    GNSSFUSE_SHARED_DATA=../shared/data python experiments/level_prior.py --pixel5         # ~1 min
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from few_satellites import NAV, PIXEL5, SHARED, thinned  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SIGMAS = (0.0, 0.3, 0.5, 1.0, 2.0)


def scores(trace, mode: str, opts: RunOptions) -> list[float]:
    """GSDC score of ``mode`` on ``trace`` at each level sigma of :data:`SIGMAS`."""
    out = []
    for s in SIGMAS:
        o = replace(opts, graph=replace(opts.graph, cv_level_sigma_mps=s, cv_level_sigma_no_doppler_mps=s))
        out.append(mode_metrics(trace, run_modes(trace, [mode], o)[mode])["gsdc_score"])
    return out


def table(title: str, rows: dict[str, list[float]]) -> None:
    """Per-trace scores and their ratio to no prior; the mean and worst ratio last."""
    print(f"\n{title}\n\n| trace | " + " | ".join(f"{s:g} m/s" if s else "none" for s in SIGMAS) + " |")
    print("|---" * (len(SIGMAS) + 1) + "|")
    for name, v in rows.items():
        print(f"| {name} | " + " | ".join(f"{x:.2f}" for x in v) + " |")
    a = np.array(list(rows.values()))
    print("| mean | " + " | ".join(f"{x:.2f}" for x in a.mean(0)) + " |")
    print("| worst / none | " + " | ".join(f"{x:.3f}" for x in (a / a[:, :1]).max(0)) + " |", flush=True)


def pixel5() -> int:
    """The test trace, reported: GSDC score without the prior and with the shipped settings."""
    base = RunOptions(signals=None, nav=(NAV,))
    full = load_trace(PIXEL5, min_sats=1, **load_options(base))
    none = replace(base, graph=replace(base.graph, cv_level_sigma_mps=0.0, cv_level_sigma_no_doppler_mps=0.0))
    print("| Pixel5 RINEX (test), Doppler + carrier | mode | no level prior [m] | shipped settings [m] |")
    print("|---|---|---|---|")
    for name, trace in (("as logged", full), ("thinned", thinned(full, 3, 0)[0])):
        for mode in ("fused-nodnn", "fused"):
            got = [mode_metrics(trace, run_modes(trace, [mode], opts)[mode])["gsdc_score"] for opts in (none, base)]
            print(f"| {name} | {mode} | {got[0]:.2f} | {got[1]:.2f} |", flush=True)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=Path, help="the simulated city traces' folder (experiments/sim_city_traces.py)")
    ap.add_argument("--pixel5", action="store_true", help="report the Pixel5 test trace instead")
    args = ap.parse_args()
    if args.pixel5:
        return pixel5()
    print("Level sigmas:", ", ".join(f"{s:g}" for s in SIGMAS), "(0: no prior); fused-nodnn GSDC score [m]")
    logged, thin = {}, {}
    for k, folder in enumerate(sorted((SHARED / "gsdc2021/train").glob("2020-*/Pixel4"))):
        full = load_trace(folder, min_sats=1)
        logged[folder.parent.name] = scores(full, "fused-nodnn", RunOptions())
        thin[folder.parent.name] = scores(thinned(full, 3, k)[0], "fused-nodnn", RunOptions())
    table("GSDC training drives as logged", logged)
    table("GSDC training drives thinned (3 satellites in 120 s of every 180 s)", thin)
    if args.sim:
        sim, sim_thin = {}, {}
        opts = RunOptions(signals=("all",))
        for k, folder in enumerate(sorted(args.sim.glob("*/SimPhone"))):
            tr = load_trace(folder, signals=("all",), min_sats=1)
            sim[folder.parent.name] = scores(tr, "fused-nodnn", opts)
            sim_thin[folder.parent.name] = scores(thinned(tr, 3, k)[0], "fused-nodnn", opts)
        table("Simulated city traces (Doppler)", sim)
        table("Simulated city traces thinned", sim_thin)
    drive = SHARED / "smartloc" / "Berlin_Potsdamer_Platz"
    if drive.is_dir():
        tr = load_trace(drive, min_sats=1, signals=None)
        opts = RunOptions(signals=None)
        table("smartLoc (no odometry); fused = the shipped network",
              {"fused-nodnn": scores(tr, "fused-nodnn", opts), "fused": scores(tr, "fused", opts)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
