"""Experiment 1 (paper Sec. 5.1): simulated data, initial guess = truth + U(-eta, eta) per NED axis.

Trains one network per row on simulated traces (fusion.simulate, Gaussian sigma 6 m, optionally the
Gaussian + bias scenario) and tests it on *other* simulated traces (different seed) with fresh guesses
from the same box. Prints MAE (+- std of |error|) N/E/D before (initial guess) and after correction,
and the variance head's 1/2-sigma coverage. A second table tests the same networks under the honest
protocol (guess = WLS of the test epoch's own measurements), including networks trained with the
box / WLS guess mix (``--mix``), with the checkpoint's variance calibration applied.

    PYTHONPATH=. python experiments/sim_correction.py [--traces 20] [--epochs 30] [--eta 5 15 30]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from learned.augment import draw_guesses, epoch_generator, parse_guess_mix
from learned.data import build_samples, simulated_traces, split_random
from learned.infer import Corrector
from learned.train import TrainConfig, train


def evaluate(ckpt: Path, samples, eta: float, seed: int, honest: bool = False) -> dict:
    """Held-out samples: MAE before/after per NED axis, coverage. Paper protocol (guess = truth + box) or,
    with ``honest``, guess = the sample's WLS position (epochs where WLS failed are left out)."""
    corr = Corrector.load(ckpt)
    truth = torch.as_tensor(samples.truth)
    if honest:
        keep = np.isfinite(samples.wls).all(1)
        samples = samples.subset(np.flatnonzero(keep))
        guess = samples.wls
    else:
        guess = draw_guesses(truth, eta, epoch_generator(seed, 10_000)).numpy()
    from fusion.geometry import ecef2ned_vec
    from fusion.trace import Trace, empty_trace
    kw = empty_trace(len(samples), samples.mask.shape[1], name="test", with_truth=True)
    kw.update(sat_pos=samples.sat_pos, pr=samples.pr, mask=samples.mask, truth=samples.truth,
              t_ms=np.arange(len(samples), dtype=np.int64))
    c = corr.predict(Trace(**kw), guess, np.ones(len(samples), bool))
    before = np.abs(ecef2ned_vec(guess - samples.truth, samples.truth))
    err = ecef2ned_vec(c.mean_ecef - samples.truth, samples.truth)
    from learned.infer import calibration
    return {"before": before, "after": np.abs(err[c.valid]), "cal": calibration(err, c.cov_ned)}


def fmt(a: np.ndarray) -> str:
    return " | ".join(f"{m:5.2f} +- {s:4.2f}" for m, s in zip(a.mean(0), a.std(0)))


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--traces", type=int, default=20, help="simulated training traces (200 epochs each)")
    p.add_argument("--test-traces", type=int, default=5)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--eta", type=float, nargs="+", default=[5.0, 15.0, 30.0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mix", default="box=0.5,wls=0.5", help="guess mix of the extra rows trained on it")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    rows = ([("gaussian", 15.0, "box=1"), ("gaussian+bias", 15.0, "box=1")]
            + [("gaussian", e, "box=1") for e in a.eta if e != 15.0]
            + [("gaussian", 15.0, a.mix), ("gaussian+bias", 15.0, a.mix)])
    honest_rows = []
    print(f"train: {a.traces} sim traces x 200 epochs, {a.epochs} epochs; test: {a.test_traces} other traces\n")
    print("Paper protocol (guess = truth + U(+-eta) per NED axis)\n")
    print("| scenario | guess mix (training) | eta [m] | MAE N / E / D before (initial guess) [m] | "
          "MAE N / E / D after [m] | within 1 sigma N/E/D | within 2 sigma N/E/D |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as d:
        for scen, eta, mix in rows:
            bias = scen.endswith("bias")
            s = build_samples(simulated_traces(a.traces, 200, seed=a.seed, bias=bias))
            tr, va = split_random(s, 0.1, np.random.default_rng(a.seed))
            test = build_samples(simulated_traces(a.test_traces, 200, seed=a.seed + 1000, bias=bias))
            ck = Path(d) / f"{scen}_{eta}_{mix}.pt"
            train(tr, va, TrainConfig(epochs=a.epochs, eta=eta, seed=a.seed, guess_mix=parse_guess_mix(mix)), ck,
                  progress=False)
            for honest in (False, True):
                r = evaluate(ck, test, eta, a.seed, honest=honest)
                cal = r["cal"]
                line = (f"| {scen} | {mix} | {eta:g} | {fmt(r['before'])} | {fmt(r['after'])} | "
                        + "/".join(f"{v:.2f}" for v in cal["within_1sigma"]) + " | "
                        + "/".join(f"{v:.2f}" for v in cal["within_2sigma"]) + " |")
                if honest:
                    honest_rows.append(line)
                else:
                    print(line, flush=True)
    print("\nHonest protocol (guess = WLS of the test epoch's own measurements; 'before' = WLS; calibrated "
          "variances)\n")
    print("| scenario | guess mix (training) | eta [m] | MAE N / E / D before (WLS) [m] | MAE N / E / D after [m] | "
          "within 1 sigma N/E/D | within 2 sigma N/E/D |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(honest_rows))


if __name__ == "__main__":
    main()
