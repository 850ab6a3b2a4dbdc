"""Example 3: simulate GNSS traces, train the correction network on them, test on a new simulated drive.

    python examples/03_simulate_and_train.py                       # 50 drives x 200 epochs, 20 epochs
    python examples/03_simulate_and_train.py --quick               # a minute-sized smoke run
    python examples/03_simulate_and_train.py --bias-scenario       # multipath/NLOS biases, as the paper

Simulated drives come from :func:`fusion.sim.simulate.simulate_dataset` (broadcast GPS orbits, random
origins and start times); the test drive uses a different seed, so it is not in the training data.
Both WLS and the trained DNN start from the same WLS solution with the clock estimated.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from fusion.eval.metrics import format_table, mode_metrics  # noqa: E402
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate, simulate_dataset  # noqa: E402
from learned.data import build_samples, split_random  # noqa: E402
from learned.features import RECIPE_INPUTS, FeatureConfig  # noqa: E402
from learned.train import TrainConfig, train  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--traces", type=int, default=50, help="simulated training drives")
    ap.add_argument("--epochs-per-trace", type=int, default=200)
    ap.add_argument("--epochs", type=int, default=20, help="training epochs")
    ap.add_argument("--test-epochs", type=int, default=300, help="length of the test drive")
    ap.add_argument("--bias-scenario", action="store_true", help="add NLOS biases (paper's 2nd scenario)")
    ap.add_argument("--quick", action="store_true", help="4 drives x 50 epochs, 1 training epoch")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "sim_dnn.pt", help="checkpoint path")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.quick:
        args.traces, args.epochs_per_trace, args.epochs, args.test_epochs = 4, 50, 1, 100

    sim_cfg = SimConfig(nlos=args.bias_scenario)
    traces = simulate_dataset(args.traces, args.epochs_per_trace, seed=args.seed, config=sim_cfg)
    samples = build_samples(traces)
    train_s, val_s = split_random(samples, 0.1, np.random.default_rng(args.seed))
    print(f"simulated {len(traces)} drives -> {len(train_s)} training / {len(val_s)} validation epochs")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    cfg = TrainConfig(epochs=args.epochs, seed=args.seed, features=FeatureConfig(inputs=RECIPE_INPUTS),
                      data={"sources": ["sim"], "traces": args.traces, "bias": args.bias_scenario})
    history = train(train_s, val_s, cfg, args.out, progress=False)
    best = min(history, key=lambda r: r["val_score_m"])
    print(f"best epoch {best['epoch']} (val horizontal error {best['val_score_m']:.2f} m) -> {args.out}")

    # A fresh drive (seed never used for training) to test on.
    test = simulate(n_epochs=args.test_epochs, config=sim_cfg, seed=args.seed + 10_000, name="sim-test").trace
    results = run_modes(test, ["wls", "dnn"], RunOptions(weights=args.out))
    print(f"on the simulated test drive ({test.n_epochs} epochs):")
    print(format_table({m: mode_metrics(test, r) for m, r in results.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
