"""Simulator throughput: epochs per second for a training-sized batch, and one urban trace.

    OMP_NUM_THREADS=2 PYTHONPATH=. python benchmarks/bench_simulate.py [--epochs 100000] [--per-trace 100]

1. Simulates ``--epochs`` epochs as random drives of ``--per-trace`` epochs at random origins and
   start times (``simulate_dataset``, default settings: GPS L1, sigma 6 m, <= 10 satellites, NLOS
   on) and prints the wall time and epochs/s. Target: 100,000 epochs in < 10 s on 2 cores.
2. One 600-epoch trace of the ``urban`` scenario (GPS + GLONASS + Galileo + BeiDou, L1 + L5/E5a,
   C/N0, Doppler, street canyon; ``simulate``), simulated and written as device_gnss.csv with
   labels (``write_device_gnss``), each timed as the best of three runs. Target: a few seconds.
   The same for the ``urban`` scenario in ``simulate_dataset`` (throughput).
3. ``--scenarios``: what each preset produces (mean over seeds of 600-epoch drives at Mountain View):
   signals per epoch, NLOS and diffracted shares, C/N0 of LOS and NLOS signals, median NLOS extra
   path, and the plain WLS 3-D error (mean, 95th percentile) - a Markdown table.
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

import tempfile  # noqa: E402

from fusion.io.rinex_nav import default_nav_path, read_rinex_nav  # noqa: E402
from fusion.sim.simulate import SimConfig, scenario_config, simulate, simulate_dataset  # noqa: E402
from fusion.sim.write import write_device_gnss  # noqa: E402

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


def _best_of(fn, n: int = 3) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(n):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def bench_urban(epochs: int = 600, dataset_epochs: int = 20_000, seed: int = 0) -> list[dict]:
    """One urban-canyon multi-constellation trace: simulate and write times; urban dataset throughput."""
    nav = read_rinex_nav(default_nav_path())
    cfg = scenario_config("urban")
    t_sim, res = _best_of(lambda: simulate(n_epochs=epochs, nav=nav, seed=seed, config=cfg))
    tr = res.trace
    with tempfile.TemporaryDirectory() as tmp:
        t_write, _ = _best_of(lambda: write_device_gnss(res, tmp, "bench-urban"))
    n_traces = max(1, dataset_epochs // 100)
    t0 = time.perf_counter()
    traces = simulate_dataset(n_traces, 100, seed=seed, nav=nav, config=cfg)
    t_ds = time.perf_counter() - t0
    n_ds = sum(t.n_epochs for t in traces)
    nlos = float((res.los_class[tr.mask] != 0).mean())
    print(f"urban scenario, {tr.n_epochs} epochs x {tr.n_sats.mean():.1f} signals (4 systems, "
          f"{100 * nlos:.0f}% NLOS/diffracted): simulate {t_sim:.3f} s, write device_gnss {t_write:.3f} s; "
          f"simulate_dataset {n_ds} epochs in {t_ds:.2f} s: {n_ds / t_ds:,.0f} epochs/s")
    env = f"cpu, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}"
    note = f"{tr.n_epochs} epochs, {tr.n_sats.mean():.1f} signals/epoch, GPS+GLO+GAL+BDS, seed {seed}, best of 3, {env}"
    return [{"name": f"urban scenario trace, {epochs} epochs: simulate", "value": round(t_sim, 3), "unit": "s",
             "note": note},
            {"name": f"urban scenario trace, {epochs} epochs: write device_gnss + labels", "value": round(t_write, 3),
             "unit": "s", "note": note},
            {"name": "simulate_dataset throughput, urban scenario", "value": round(n_ds / t_ds, 1), "unit": "epochs/s",
             "note": f"{n_ds} epochs = {n_traces} traces x 100, seed {seed}, {env}"}]


def scenario_table(seeds: int = 10, epochs: int = 600) -> str:
    """Markdown table of the presets' statistics (see module docstring), mean over ``seeds`` drives."""
    import warnings

    import numpy as np

    from fusion.estimate.wls import solve_wls
    nav = read_rinex_nav(default_nav_path())
    lines = ["| scenario | signals/epoch | NLOS % | diffracted % | C/N0 LOS [dB-Hz] | C/N0 NLOS [dB-Hz] | "
             "NLOS extra path, median [m] | WLS 3-D error mean [m] | WLS 3-D p95 [m] |", "|---" * 9 + "|"]
    for name in ("open", "suburban", "urban"):
        rows = []
        for seed in range(seeds):
            res = simulate(n_epochs=epochs, nav=nav, seed=seed, config=scenario_config(name))
            tr, m = res.trace, res.trace.mask
            cls = res.los_class[m]
            err = np.linalg.norm(solve_wls(tr, robust="none").pos - tr.truth, axis=1)
            nlos = cls == 1
            pick = lambda a: a[nlos].mean() if nlos.any() else np.nan  # noqa: E731
            rows.append([tr.n_sats.mean(), 100 * nlos.mean(), 100 * (cls == 2).mean(), tr.cn0[m][cls == 0].mean(),
                         pick(tr.cn0[m]), np.median(res.nlos_delay_m[m][nlos]) if nlos.any() else np.nan,
                         np.nanmean(err), np.nanpercentile(err, 95)])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # open sky has no NLOS column to average
            a = np.nanmean(np.array(rows), axis=0)
        lines.append(f"| {name} | " + " | ".join("-" if np.isnan(v) else f"{v:.1f}" for v in a) + " |")
    return "\n".join(lines)


def run(quick: bool = False) -> list[dict]:
    """Records for ``benchmarks/run_all.py``; quick simulates 20,000 epochs instead of 100,000."""
    return bench(QUICK_EPOCHS if quick else 100_000) + bench_urban(dataset_epochs=5_000 if quick else 20_000)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=100_000)
    ap.add_argument("--per-trace", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenarios", action="store_true", help="print the presets' statistics table instead")
    args = ap.parse_args(argv)
    if args.scenarios:
        print(scenario_table())
        return 0
    bench(args.epochs, args.per_trace, args.seed)
    bench_urban(seed=args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
