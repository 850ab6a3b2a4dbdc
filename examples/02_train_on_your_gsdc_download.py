"""Example 2: train the correction network on your own GSDC 2021 download, then try it.

    python examples/02_train_on_your_gsdc_download.py --gsdc-root ~/kaggle/gsdc2021/train \
        --epochs 50 --out runs/my_dnn.pt

``--gsdc-root`` is a Kaggle-layout ``train/`` folder (``<collection>/<phone>/*_derived.csv`` plus
``ground_truth.csv``). Held-out test traces (``learned.data.FORBIDDEN_TRACES``) are left out of
training. The trained checkpoint is then compared with WLS on ``--eval-trace`` (default: the shipped
trace, which is held out), WLS initial guess and estimated clock, as in ``gnssfuse evaluate``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from fusion.prepare.load import find_traces, load_trace  # noqa: E402
from fusion.eval.metrics import format_table, mode_metrics  # noqa: E402
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from learned.data import FORBIDDEN_TRACES, build_samples, load_real_traces, split_random  # noqa: E402
from learned.features import RECIPE_INPUTS, FeatureConfig  # noqa: E402
from learned.train import TrainConfig, train  # noqa: E402

SHIPPED = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gsdc-root", type=Path, required=True, help="Kaggle-layout train/ folder")
    ap.add_argument("--epochs", type=int, default=50, help="training epochs")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "gsdc_dnn.pt", help="checkpoint path")
    ap.add_argument("--eval-trace", type=Path, default=SHIPPED, help="held-out trace to try it on")
    ap.add_argument("--eval-epochs", type=int, default=None, help="first N epochs of it only")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    folders = find_traces(args.gsdc_root)
    held_out = [f for f in folders if any(b in Path(f).resolve().as_posix() for b in FORBIDDEN_TRACES)]
    folders = [f for f in folders if f not in held_out]
    for f in held_out:
        print(f"leaving out held-out test trace {f}")
    if not folders:
        print(f"no training trace under {args.gsdc_root}", file=sys.stderr)
        return 2
    samples = build_samples(load_real_traces(folders))
    train_s, val_s = split_random(samples, 0.1, np.random.default_rng(args.seed))
    print(f"{len(folders)} traces -> {len(train_s)} training / {len(val_s)} validation epochs")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    # the shipped recipe's inputs: the paper's (residual, line of sight) and every context channel
    cfg = TrainConfig(epochs=args.epochs, seed=args.seed, data={"sources": [str(args.gsdc_root)]},
                      features=FeatureConfig(inputs=RECIPE_INPUTS))
    history = train(train_s, val_s, cfg, args.out, progress=False)
    best = min(history, key=lambda r: r["val_score_m"])
    print(f"best epoch {best['epoch']} (val horizontal error {best['val_score_m']:.2f} m) -> {args.out}")

    trace = load_trace(args.eval_trace)
    if args.eval_epochs:
        trace = trace.select(np.arange(min(args.eval_epochs, trace.n_epochs)))
    results = run_modes(trace, ["wls", "dnn"], RunOptions(weights=args.out))
    print(f"on {trace.name} ({trace.n_epochs} epochs):")
    print(format_table({m: mode_metrics(trace, r) for m, r in results.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
