"""Simulator throughput: epochs per second for a training-sized batch.

    OMP_NUM_THREADS=2 PYTHONPATH=. python benchmarks/bench_simulate.py [--epochs 100000] [--per-trace 100]

Simulates ``--epochs`` epochs as random drives of ``--per-trace`` epochs at random origins and
start times (``simulate_dataset``, default settings: sigma 6 m, <= 10 satellites, NLOS on) and
prints the wall time and epochs/s. Target: 100,000 epochs in < 10 s on 2 cores.
"""
from __future__ import annotations

import argparse
import time

from fusion.rinex_nav import default_nav_path, read_rinex_nav
from fusion.simulate import SimConfig, simulate_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=100_000)
    ap.add_argument("--per-trace", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    nav = read_rinex_nav(default_nav_path())
    n_traces = max(1, args.epochs // args.per_trace)
    t0 = time.perf_counter()
    traces = simulate_dataset(n_traces, args.per_trace, seed=args.seed, nav=nav, config=SimConfig(nlos=True))
    dt = time.perf_counter() - t0
    n = sum(t.n_epochs for t in traces)
    sats = sum(int(t.mask.sum()) for t in traces) / max(n, 1)
    print(f"simulated {n} epochs ({n_traces} traces x {args.per_trace}, {sats:.2f} satellites/epoch) "
          f"in {dt:.2f} s: {n / dt:,.0f} epochs/s")


if __name__ == "__main__":
    main()
