"""Robust WLS (fault detection and exclusion, the default) against the paper's plain WLS, with and
without simulated non-line-of-sight faults: +200 m on a seeded random 5% of the pseudoranges.

Prints, per trace and mode (``wls``; ``dnn`` too with ``--dnn``): the GSDC score (mean of horizontal
p50 and p95) of the plain and the robust WLS guess on the clean trace, and on the faulty trace for
each seed, plus the *oracle* (the faulty measurements simply removed, plain WLS) that bounds what any
exclusion can reach: losing 5% of the satellites costs geometry.

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/robust_wls.py --seeds 0 1 2 3 4 --dnn

Data: ``$GNSSFUSE_SHARED_DATA`` (default ``<repo>/../shared/data``). Results: ``experiments/results/robust_wls.md``.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

import numpy as np

from fusion.eval.metrics import mode_metrics
from fusion.prepare.load import load_trace
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from fusion.trace import Trace

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
#: Training traces only (the test traces 2021-04-28-* are not used to choose anything).
TRACES = ("gsdc2021/train/2020-05-14-US-MTV-1/Pixel4", "gsdc2021/train/2020-06-05-US-MTV-1/Pixel4",
          "gsdc2021/train/2020-09-04-US-SF-2/Pixel4")
FAULT_M, FAULT_RATE = 200.0, 0.05


def with_faults(trace: Trace, seed: int) -> tuple[Trace, np.ndarray]:
    """The trace with +200 m on a random 5% of its real slots; also the (E, S) bool fault mask."""
    hit = trace.mask & (np.random.default_rng(seed).random(trace.mask.shape) < FAULT_RATE)
    return dataclasses.replace(trace, pr=trace.pr + FAULT_M * hit), hit


def scores(trace: Trace, modes: list[str], robust) -> dict[str, float]:
    opts = RunOptions(wls_robust=robust)
    return {m: mode_metrics(trace, r)["gsdc_score"] for m, r in run_modes(trace, modes, opts).items()}


def trace_rows(rel: str, modes: list[str], seeds: list[int]) -> list[str]:
    trace = load_trace(SHARED / rel, min_sats=1)           # as the CLI loads it
    clean = {k: scores(trace, modes, k) for k in (False, "exclude")}
    faulty = {k: [] for k in (False, "exclude", "oracle")}
    for seed in seeds:
        bad, hit = with_faults(trace, seed)
        faulty[False].append(scores(bad, modes, False))
        faulty["exclude"].append(scores(bad, modes, "exclude"))
        faulty["oracle"].append(scores(dataclasses.replace(trace, mask=trace.mask & ~hit), modes, False))
    rows = []
    for m in modes:
        f = {k: np.array([s[m] for s in v]) for k, v in faulty.items()}
        rows.append(
            f"| {rel.split('/', 2)[2]} | {m} | {clean[False][m]:.2f} | {clean['exclude'][m]:.2f} "
            f"| {clean['exclude'][m] - clean[False][m]:+.2f} | {f[False].mean():.2f} | {f['oracle'].mean():.2f} "
            f"| {f['exclude'].mean():.2f} ({f['exclude'].min():.2f}-{f['exclude'].max():.2f}) "
            f"| {(f['exclude'] - clean['exclude'][m]).mean():+.2f} | {(f['exclude'] - clean[False][m]).mean():+.2f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--dnn", action="store_true", help="also the dnn mode (shipped weights)")
    ap.add_argument("--traces", nargs="+", default=list(TRACES), help="paths under the shared data folder")
    args = ap.parse_args()
    modes = ["wls", "dnn"] if args.dnn else ["wls"]
    print(f"GSDC score [m]; faulty: +{FAULT_M:.0f} m on {FAULT_RATE:.0%} of pseudoranges, mean over seeds "
          f"{args.seeds} (min-max)\n")
    print("| trace | mode | clean plain | clean robust | clean change | faulty plain | faulty oracle "
          "| faulty robust | robust: faulty - clean | faulty robust - clean plain |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for rel in args.traces:
        for row in trace_rows(rel, modes, args.seeds):
            print(row, flush=True)


if __name__ == "__main__":
    main()
