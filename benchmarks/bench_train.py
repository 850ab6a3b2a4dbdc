"""Training throughput (augmentation included) and CPU inference time over a 2,000-epoch trace.

    PYTHONPATH=. python benchmarks/bench_train.py [--samples 4096] [--epochs 2] [--threads 1]

Targets: share of training step time outside the model forward/backward/optimizer step < 20 %;
inference (features + network, all epochs batched) < 0.5 s for 2,000 epochs on CPU.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from fusion.wls import solve_wls
from learned.data import build_samples, split_random
from learned.infer import Corrector
from learned.toy import toy_dataset, toy_trace
from learned.train import TrainConfig, train


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--samples", type=int, default=4096)
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    s = build_samples(toy_dataset(max(1, a.samples // 200), 200, seed=0))
    tr, va = split_random(s, 0.05, np.random.default_rng(0))
    with tempfile.TemporaryDirectory() as d:
        hist = train(tr, va, TrainConfig(epochs=a.epochs, device=a.device, warmup_epochs=1), Path(d) / "b.pt",
                     progress=False)
        for h in hist:
            outside = 1.0 - h["model_s"] / h["time_s"]
            print(f"train epoch {h['epoch']} ({'MSE+NLL' if h['nll'] else 'MSE'}): {h['samples'] / h['time_s']:.0f} "
                  f"samples/s, features+augmentation {h['feature_s']:.3f} s, outside forward/backward/step "
                  f"{100 * outside:.1f} % of {h['time_s']:.2f} s")
        corr = Corrector.load(Path(d) / "b.pt", device=a.device)
        trace = toy_trace(2000, seed=1)
        wls = solve_wls(trace)
        t0 = time.perf_counter()
        corr.predict(trace, wls.pos, wls.valid)
        cold = time.perf_counter() - t0
        warm = []
        for _ in range(5):
            t0 = time.perf_counter()
            c = corr.predict(trace, wls.pos, wls.valid)
            warm.append(time.perf_counter() - t0)
        print(f"inference, {trace.n_epochs} epochs ({int(c.valid.sum())} solved), {a.threads} thread(s): "
              f"first call {cold:.3f} s, warm median {np.median(warm):.3f} s (target < 0.5 s)")


if __name__ == "__main__":
    main()
