"""Several networks of one recipe (trained with different seeds) asked together: does averaging their answers
beat one network? Per cross-validation fold, each seed's network and the ensemble of all of them drive
``fused`` on the fold's unseen GSDC drives (pooled GSDC score over both folds), on smartLoc Berlin (never
trained on) and on the Pixel5 RINEX with GPS broadcast navigation (a test trace, reported only).

The ensemble is the product's (:mod:`learned.ensemble`): geometric mean of the per-satellite sigmas, mean
biases, mean prior with the members' spread added to the mean of their covariances; an epoch's prior is used
only where every member gives one.

    python experiments/crossval.py --data ../shared/data/gsdc2021/train --two-fold --out /tmp/cvs<k> \\
        --epochs 8 --jobs 2 --dropout pr_sigma=0.25 --modes fused-nodnn,fused --extra /tmp/sim/*/SimPhone \\
        --signals all --seed <k>                     # for each seed k
    python experiments/ensemble_eval.py /tmp/cvall /tmp/cvs1 /tmp/cvs2
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

import learned.modes  # noqa: E402
from crossval import FOLDS2  # noqa: E402
from fusion.eval.metrics import summarize, trace_errors  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.ensemble import Ensemble  # noqa: E402
from learned.infer import Corrector  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRAIN = SHARED / "gsdc2021/train"
RAW = {"smartLoc": (SHARED / "smartloc/Berlin_Potsdamer_Platz", {}),
       "Pixel5": (TRAIN / "2021-04-28-US-MTV-1/Pixel5", {"nav": (SHARED / "ephemeris/gps_nav/hour1180.21n",)})}


def fused_errors(trace, wls, opts: RunOptions, corrector) -> np.ndarray:
    """(E,3) NED errors of ``fused`` with ``corrector`` (a Corrector or an Ensemble)."""
    load = learned.modes.Corrector.load
    learned.modes.Corrector.load = staticmethod(lambda *a, **k: corrector)
    try:
        return trace_errors(trace, run_modes(trace, ["fused"], opts, wls=wls)["fused"])
    finally:
        learned.modes.Corrector.load = load


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path, help="cross-validation folders, one per seed")
    runs = p.parse_args().runs
    labels = [f"seed run {r.name}" for r in runs] + [f"ensemble of {len(runs)}"]
    gsdc = {k: [] for k in labels}
    raw = {}
    for fold, drives in FOLDS2.items():
        members = [Corrector.load(r / f"fold_{fold}.pt") for r in runs]
        who = members + [Ensemble(members)]
        for d in drives:
            trace = load_trace(TRAIN / d / "Pixel4", min_sats=1)
            wls = solve_initial(trace, RunOptions())
            for k, c in zip(labels, who):
                gsdc[k].append(fused_errors(trace, wls, RunOptions(), c))
        for log, (path, kw) in RAW.items():
            opts = RunOptions(signals=None, **kw)
            trace = load_trace(path, min_sats=1, **load_options(opts))
            wls = solve_initial(trace, opts)
            for k, c in zip(labels, who):
                raw[(log, fold, k)] = summarize(fused_errors(trace, wls, opts, c))["gsdc_score"]
    print("| networks | GSDC, unseen drives pooled | " + " | ".join(f"{log} {f}" for log in RAW for f in FOLDS2) + " |")
    print("|---|---|" + "---|" * (len(RAW) * len(FOLDS2)))
    for k in labels:
        cells = " | ".join(f"{raw[(log, f, k)]:.2f}" for log in RAW for f in FOLDS2)
        print(f"| {k} | {summarize(np.concatenate(gsdc[k]))['gsdc_score']:.3f} | {cells} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
