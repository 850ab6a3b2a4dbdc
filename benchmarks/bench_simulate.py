"""Simulator throughput: epochs per second for a training-sized batch.

    OMP_NUM_THREADS=2 PYTHONPATH=. python benchmarks/bench_simulate.py [--epochs 100000] [--per-trace 100]

Simulates ``--epochs`` epochs as random drives of ``--per-trace`` epochs at random origins and
start times (``simulate_dataset``, default settings: sigma 6 m, <= 10 satellites, NLOS on) and
prints the wall time and epochs/s. Target: 100,000 epochs in < 10 s on 2 cores.
``run(quick)`` follows the ``benchmarks/README.md`` convention (quick: 20,000 epochs).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fusion.io.rinex_nav import default_nav_path, read_rinex_nav  # noqa: E402
from fusion.sim.simulate import SimConfig, simulate_dataset  # noqa: E402

QUICK_EPOCHS = 20_000


def bench(epochs: int = 100_000, per_trace: int = 100, seed: int = 0) -> list[dict]:
    """Print one line and return records: epochs/s and total seconds (nav parsing excluded)."""
    nav = read_rinex_nav(default_nav_path())
    n_traces = max(1, epochs // per_trace)
    t0 = time.perf_counter()
    traces = simulate_dataset(n_traces, per_trace, seed=seed, nav=nav, config=SimConfig(nlos=True))
    dt = time.perf_counter() - t0
    n = sum(t.n_epochs for t in traces)
    sats = sum(int(t.mask.sum()) for t in traces) / max(n, 1)
    print(f"simulated {n} epochs ({n_traces} traces x {per_trace}, {sats:.2f} satellites/epoch) "
          f"in {dt:.2f} s: {n / dt:,.0f} epochs/s")
    note = (f"{n} epochs = {n_traces} traces x {per_trace}, {sats:.2f} sats/epoch, NLOS on, seed {seed}, "
            f"cpu, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}")
    return [{"name": "simulate_dataset throughput", "value": round(n / dt, 1), "unit": "epochs/s", "note": note},
            {"name": "simulate_dataset total time", "value": round(dt, 3), "unit": "s", "note": note}]


def run(quick: bool = False) -> list[dict]:
    """Records for ``benchmarks/run_all.py``; quick simulates 20,000 epochs instead of 100,000."""
    return bench(QUICK_EPOCHS if quick else 100_000)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=100_000)
    ap.add_argument("--per-trace", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    bench(args.epochs, args.per_trace, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
