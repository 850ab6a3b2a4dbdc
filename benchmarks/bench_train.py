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

from fusion.estimate.wls import solve_wls
from learned.data import build_samples, split_random
from learned.infer import Corrector
from learned.toy import toy_dataset, toy_trace
from learned.train import TrainConfig, train


def measure(samples: int = 4096, epochs: int = 2, threads: int = 1, device: str = "cpu",
            infer_epochs: int = 2000, repeats: int = 5) -> tuple[list[dict], list[str]]:
    """Train on toy data, then time ``Corrector.predict`` on an ``infer_epochs`` toy trace.
    Returns (records per benchmarks/README.md, human-readable lines)."""
    torch.set_num_threads(threads)
    s = build_samples(toy_dataset(max(1, samples // 200), 200, seed=0))
    tr, va = split_random(s, 0.05, np.random.default_rng(0))
    recs, lines = [], []
    note = f"{device}, {threads} torch thread(s), toy data"
    with tempfile.TemporaryDirectory() as d:
        hist = train(tr, va, TrainConfig(epochs=epochs, device=device, warmup_epochs=1), Path(d) / "b.pt",
                     progress=False)
        for h in hist:
            outside = 1.0 - h["model_s"] / h["time_s"]
            lines.append(f"train epoch {h['epoch']} ({'MSE+NLL' if h['nll'] else 'MSE'}): "
                         f"{h['samples'] / h['time_s']:.0f} samples/s, features+augmentation {h['feature_s']:.3f} s, "
                         f"outside forward/backward/step {100 * outside:.1f} % of {h['time_s']:.2f} s")
        last = hist[-1]
        recs += [{"name": f"training throughput ({last['samples']} samples, epoch {last['epoch']})",
                  "value": round(last["samples"] / last["time_s"], 1), "unit": "samples/s", "note": note},
                 {"name": "training time outside forward/backward/step", "unit": "%", "note": note + "; target < 20 %",
                  "value": round(100 * (1.0 - last["model_s"] / last["time_s"]), 1)}]
        corr = Corrector.load(Path(d) / "b.pt", device=device)
        trace = toy_trace(infer_epochs, seed=1)
        wls = solve_wls(trace)
        t0 = time.perf_counter()
        corr.predict(trace, wls.pos, wls.valid)
        cold = time.perf_counter() - t0
        warm = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            c = corr.predict(trace, wls.pos, wls.valid)
            warm.append(time.perf_counter() - t0)
    lines.append(f"inference, {trace.n_epochs} epochs ({int(c.valid.sum())} solved), {threads} thread(s): "
                 f"first call {cold:.3f} s, warm median {np.median(warm):.3f} s (target < 0.5 s for 2,000)")
    recs += [{"name": f"DNN inference (Corrector.predict), {trace.n_epochs} epochs, warm median",
              "value": round(float(np.median(warm)), 4), "unit": "s", "note": note + "; target < 0.5 s for 2,000"},
             {"name": f"DNN inference, {trace.n_epochs} epochs, first call", "value": round(cold, 4), "unit": "s",
              "note": note}]
    return recs, lines


def run(quick: bool = False) -> list[dict]:
    """benchmarks/README.md entry point; ``quick``: 1,024 training samples, 1 epoch (well under a minute)."""
    recs, _ = measure(samples=1024, epochs=1) if quick else measure()
    return recs


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--samples", type=int, default=4096)
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    a = p.parse_args()
    _, lines = measure(a.samples, a.epochs, a.threads, a.device)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
