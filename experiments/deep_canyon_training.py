"""What a change to the training data buys the learned part, on everything none of the networks trained on.

The fold networks of ``experiments/crossval.py --two-fold`` runs, e.g. with and without ``--extra
/tmp/simdeep/*/SimPhone`` (simulated high-rise canyons added) or ``--init PRETRAINED.pt`` (pre-training on
simulated traces, ``experiments/results/pretraining.md``), scored on

- the GSDC drives, pooled over the unseen folds (each run's ``crossval.md``);
- smartLoc Berlin (a real deep urban canyon, never trained on) and the Pixel5 RINEX test trace (GPS broadcast,
  reported only), with each fold's network (:mod:`feature_ablation`'s logs);
- the held-out simulated traces (``sim_city_traces.py --held-out``: other drives' tracks, other seeds), the
  ordinary ones (``urban``, ``suburban``) and the ``deep`` ones, every signal read; the mean over the traces.

    python experiments/sim_city_traces.py --out /tmp/simdeep --scenarios deep --first-seed 200
    python experiments/sim_city_traces.py --out /tmp/simdeepho --held-out --scenarios deep --first-seed 300
    python experiments/crossval.py ... --extra /tmp/sim/*/SimPhone /tmp/simdeep/*/SimPhone --seed S --out RUN
    python experiments/deep_canyon_training.py --sims /tmp/simho /tmp/simdeepho -- base=RUN0 deep=RUN1 ...

One Markdown row per run: ``fused`` [m] and its ratio to ``fused-nodnn`` (the same graph without the network);
then, where labels differ only in a trailing ``_s<seed>``, each recipe's mean over its seeds.
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

from feature_ablation import RAW, load, print_runs, raw_scores  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import parse_signals  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402


def sim_scores(run: Path, sims: dict[str, list[tuple]]) -> dict[str, tuple[float, float]]:
    """Per group of simulated traces (:func:`feature_ablation.load`'s tuples): the mean ``fused`` and
    ``fused-nodnn`` scores [m] over its traces and both fold networks."""
    out = {}
    for group, loaded in sims.items():
        fused, nodnn = [], []
        for trace, wls, base, plain in loaded:
            for fold in ("AB", "CD"):
                res = run_modes(trace, ["fused"], replace(base, weights=run / f"fold_{fold}.pt"), wls=wls)["fused"]
                fused.append(mode_metrics(trace, res)["gsdc_score"])
                nodnn.append(plain)
        out[group] = (float(np.mean(fused)), float(np.mean(nodnn)))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sims", type=Path, nargs="*", default=[], help="folders of held-out simulated traces")
    p.add_argument("runs", nargs="+", help="LABEL=RUN_FOLDER")
    args = p.parse_args()
    raw = {log: load(path, RunOptions(signals=None, **kw)) for log, (path, kw) in RAW.items()}
    every = RunOptions(signals=parse_signals("all"))
    sims: dict[str, list[tuple]] = {}
    for folder in args.sims:
        for path in sorted(folder.glob("*/SimPhone")):
            group = "deep" if "-deep-" in path.parent.name else "ordinary"
            sims.setdefault(f"held-out sims, {group}", []).append(load(path, every))
    cols = [f"{log} {fold}" for log in RAW for fold in ("AB", "CD")] + list(sims)
    print_runs(args.runs, cols, lambda run: {**raw_scores(run, raw), **sim_scores(run, sims)}, digits=3)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
