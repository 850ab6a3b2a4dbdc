"""``gnssfuse evaluate --jobs N``: four traces with one worker process against two, same run.

Each setting runs the real command in a fresh process (``python -m fusion.cli evaluate ... --jobs N``,
imports and report writing included, ``OMP_NUM_THREADS=1`` so that one job is one core), twice,
alternating, and the better time counts (the machine may be shared; the CPU seconds of each setting,
workers included, and the load average are printed so that a slow wall clock can be told from
extra work). The metrics tables of the two settings must be
identical; the script says so.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_evaluate.py            # full traces
    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_evaluate.py --quick    # 300 epochs each

Traces: four GSDC 2021 training drives from ``$GNSSFUSE_SHARED_DATA`` (default ``<repo>/../shared/data``),
or four copies of the shipped trace when that folder is absent.
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRAIN = ("2020-05-14-US-MTV-1", "2020-06-05-US-MTV-1", "2020-09-04-US-SF-2", "2020-05-14-US-MTV-2")
SHIPPED = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
MODES = "wls,fused-nodnn"


def four_traces(tmp: Path) -> tuple[list[Path], str]:
    found = [SHARED / "gsdc2021" / "train" / t / "Pixel4" for t in TRAIN]
    if all(d.is_dir() for d in found):
        return found, "four GSDC 2021 training traces"
    copies = []
    for k in range(4):
        d = tmp / "data" / f"copy{k}" / "Pixel4"
        shutil.copytree(SHIPPED, d)
        copies.append(d)
    return copies, "four copies of the shipped trace"


def timed_evaluate(traces: list[Path], out: Path, jobs: int, max_epochs: int | None) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the command and its workers)."""
    cmd = [sys.executable, "-m", "fusion.cli", "evaluate", *map(str, traces), "--modes", MODES,
           "--out", str(out), "--no-progress", "--jobs", str(jobs)]
    if max_epochs:
        cmd += ["--max-epochs", str(max_epochs)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    elapsed = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    if proc.returncode != 0:
        raise RuntimeError(f"evaluate --jobs {jobs} failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    return elapsed, cpu


def run(quick: bool = False, repeats: int = 2) -> list[dict]:
    max_epochs = 300 if quick else None
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        traces, what = four_traces(tmp)
        # alternate the settings so that a change in the machine's load hits both alike
        runs = {1: [], 2: []}
        for k in range(repeats):
            for jobs in (1, 2):
                runs[jobs].append(timed_evaluate(traces, tmp / f"r{jobs}_{k}", jobs, max_epochs))
        times = {j: min(w for w, _ in r) for j, r in runs.items()}
        cpu = {j: min(c for _, c in r) for j, r in runs.items()}
        same = pd.read_csv(tmp / "r1_0" / "metrics.csv").equals(pd.read_csv(tmp / "r2_0" / "metrics.csv"))
    load = os.getloadavg()[0]
    note = (f"{what}, modes {MODES}, {'first 300 epochs' if quick else 'all epochs'}, {os.cpu_count()} CPUs, "
            f"load average {load:.1f} after the runs (best of {repeats}); metrics.csv identical: {same}")
    return [{"name": "evaluate --jobs 1", "value": round(times[1], 2), "unit": "s", "note": note},
            {"name": "evaluate --jobs 2", "value": round(times[2], 2), "unit": "s", "note": note},
            {"name": "evaluate speed-up --jobs 2 vs 1", "value": round(times[1] / times[2], 2), "unit": "x",
             "note": note},
            # --jobs 2's workers are the forkserver's children, not this script's: their CPU time is not
            # visible here, so only --jobs 1's is reported (wall time close to it = a core to itself)
            {"name": "evaluate CPU time --jobs 1", "value": round(cpu[1], 2), "unit": "s", "note": note}]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="first 300 epochs of each trace")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    recs = run(args.quick, args.repeats)
    for r in recs:
        print(f"{r['name']:<34} {r['value']:>8} {r['unit']}")
    print(recs[0]["note"])


if __name__ == "__main__":
    main()
