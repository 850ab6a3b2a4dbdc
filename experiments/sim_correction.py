"""Experiment 1 (paper Sec. 5.1): simulated data, initial guess = truth + U(-eta, eta) per NED axis.

Trains one network per row on simulated traces (fusion.sim.simulate, Gaussian sigma 6 m, optionally the
Gaussian + bias scenario) and tests it on *other* simulated traces (different seed) with fresh guesses
from the same box. Prints MAE (+- std of |error|) N/E/D before (initial guess) and after correction,
and the variance head's 1/2-sigma coverage. A second table tests the same networks under the honest
protocol (guess = WLS of the test epoch's own measurements), including networks trained with the
box / WLS guess mix (``--mix``), with the checkpoint's variance calibration applied.

Row ``leak`` ("paper protocol + true clock (paper's leak)") REPRODUCES THE PAPER'S LEAKY PROTOCOL: its
network is trained and evaluated with the simulator's TRUE receiver clock removed from the residuals
(``FeatureConfig(clock="given")``), as the paper's released code did at evaluation. It exists only to
measure what that leak is worth; :class:`learned.infer.Corrector` refuses such checkpoints, so this
experiment evaluates it with its own forward pass below, never through the product's inference path.

    PYTHONPATH=. python experiments/sim_correction.py [--traces 20] [--epochs 30] [--eta 5 15 30]
        [--rows gaussian,leak,bias,eta,mix]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from fusion.errors import CheckpointError
from fusion.geometry import ned_rotation
from fusion.eval.metrics import ned_errors
from learned.augment import draw_guesses, epoch_generator, parse_guess_mix
from learned.checkpoint import load_model
from learned.data import simulated_samples_with_clock, split_random
from learned.features import FeatureConfig, elevation_mask, features_torch
from learned.infer import Corrector, calibration
from learned.train import TrainConfig, train

LEAK = "paper protocol + true clock (paper's leak)"


@torch.no_grad()
def predict_given_clock(ckpt: Path, samples, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """EXPERIMENT ONLY forward pass of a ``clock="given"`` checkpoint fed the simulator's TRUE clock
    (``samples.clock``). Same masking as Corrector.predict (elevation at the guess, >= 4 satellites).
    Returns mean_ecef (N,3), cov_ned (N,3,3) in the NED frame of the guess, valid (N,)."""
    model, blob = load_model(ckpt)
    fcfg = FeatureConfig.from_dict(blob["config"]["features"])
    if fcfg.clock != "given" or samples.clock is None:
        raise CheckpointError(f"{ckpt}: predict_given_clock needs a clock='given' checkpoint (got "
                              f"{fcfg.clock!r}) and samples with a true clock")
    mask = elevation_mask(samples.sat_pos, samples.mask, guess, fcfg.elev_mask_deg)
    valid = mask.sum(1) >= 4
    f64 = dict(dtype=torch.float64)
    x, _ = features_torch(torch.as_tensor(samples.sat_pos, **f64), torch.as_tensor(samples.pr, **f64),
                          torch.as_tensor(mask), torch.as_tensor(guess, **f64), fcfg,
                          torch.as_tensor(samples.clock, **f64))
    mu, logvar, _ = model(x, torch.as_tensor(mask))
    out = mu.double().numpy() * fcfg.out_scale
    var = torch.exp(logvar).double().numpy() * fcfg.out_scale ** 2
    cal = ((blob["config"].get("calibration") or {}).get("correction") or {})
    scale = np.asarray(cal.get("scale_ned", [1.0, 1.0, 1.0]))
    mean = guess + np.einsum("nji,nj->ni", ned_rotation(guess), out)
    cov = np.einsum("ni,ij->nij", var * scale ** 2, np.eye(3))
    mean[~valid] = np.nan
    cov[~valid] = np.nan
    return mean, cov, valid


def evaluate(ckpt: Path, samples, eta: float, seed: int, honest: bool = False, leak: bool = False) -> dict:
    """Held-out samples: MAE before/after per NED axis over the epochs the network corrected, coverage. Paper protocol (guess = truth + box) or,
    with ``honest``, guess = the sample's WLS position (epochs where WLS failed are left out)."""
    truth = torch.as_tensor(samples.truth)
    if honest:
        keep = np.isfinite(samples.wls).all(1)
        samples = samples.subset(np.flatnonzero(keep))
        guess = samples.wls
    else:
        guess = draw_guesses(truth, eta, epoch_generator(seed, 10_000)).numpy()
    if leak:
        mean, cov_ned, valid = predict_given_clock(ckpt, samples, guess)
    else:
        from fusion.trace import Trace, empty_trace
        kw = empty_trace(len(samples), samples.mask.shape[1], name="test", with_truth=True)
        kw.update(sat_pos=samples.sat_pos, pr=samples.pr, mask=samples.mask, truth=samples.truth,
                  t_ms=np.arange(len(samples), dtype=np.int64))
        c = Corrector.load(ckpt).predict(Trace(**kw), guess, np.ones(len(samples), bool), output="correction")
        mean, cov_ned, valid = c.mean_ecef, c.cov_ned, c.valid
    # Before and after over the same epochs: those the network corrected (``valid``).
    before = np.abs(ned_errors(guess, samples.truth))
    err = ned_errors(mean, samples.truth)
    return {"before": before[valid], "after": np.abs(err[valid]), "cal": calibration(err, cov_ned)}


def fmt(a: np.ndarray) -> str:
    return " | ".join(f"{m:5.2f} +- {s:4.2f}" for m, s in zip(a.mean(0), a.std(0)))


def _header(before: str) -> str:
    """Markdown header: one column per axis, before and after (mean +- std of |error|)."""
    cols = [f"MAE {k} before ({before}) [m]" for k in "NED"] + [f"MAE {k} after [m]" for k in "NED"]
    return ("| scenario | guess mix (training) | eta [m] | " + " | ".join(cols)
            + " | within 1 sigma N/E/D | within 2 sigma N/E/D |\n" + "|---" * 11 + "|")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--traces", type=int, default=20, help="simulated training traces (200 epochs each)")
    p.add_argument("--test-traces", type=int, default=5)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--eta", type=float, nargs="+", default=[5.0, 15.0, 30.0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mix", default="box=0.5,wls=0.5", help="guess mix of the extra rows trained on it")
    p.add_argument("--rows", default="gaussian,leak,bias,eta,mix",
                   help="row groups: gaussian (eta 15), leak (same + true clock, the paper's leak), bias, "
                        "eta (the other --eta values), mix (both scenarios with --mix)")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    want = set(a.rows.split(","))
    rows = ([("gaussian", 15.0, "box=1")] * ("gaussian" in want)
            + [(LEAK, 15.0, "box=1")] * ("leak" in want)
            + [("gaussian+bias", 15.0, "box=1")] * ("bias" in want)
            + [("gaussian", e, "box=1") for e in a.eta if e != 15.0 and "eta" in want]
            + [("gaussian", 15.0, a.mix), ("gaussian+bias", 15.0, a.mix)] * ("mix" in want))
    data: dict[bool, tuple] = {}
    honest_rows = []
    print(f"train: {a.traces} sim traces x 200 epochs, {a.epochs} epochs; test: {a.test_traces} other traces\n")
    print("Paper protocol (guess = truth + U(+-eta) per NED axis)\n")
    print(_header("initial guess"))
    with tempfile.TemporaryDirectory() as d:
        for scen, eta, mix in rows:
            bias, leak = scen.endswith("bias"), scen == LEAK
            if bias not in data:   # same traces as simulated_traces(...), plus the true clock (leak row only)
                s = simulated_samples_with_clock(a.traces, 200, seed=a.seed, bias=bias)
                data[bias] = (*split_random(s, 0.1, np.random.default_rng(a.seed)),
                              simulated_samples_with_clock(a.test_traces, 200, seed=a.seed + 1000, bias=bias))
            tr, va, test = data[bias]
            ck = Path(d) / f"row{len(honest_rows)}.pt"
            fcfg = FeatureConfig(clock="given" if leak else "median")
            train(tr, va, TrainConfig(epochs=a.epochs, eta=eta, seed=a.seed, guess_mix=parse_guess_mix(mix),
                                      features=fcfg, output="correction"), ck, progress=False)
            for honest in (False, True):
                r = evaluate(ck, test, eta, a.seed, honest=honest, leak=leak)
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
    print(_header("WLS"))
    print("\n".join(honest_rows))


if __name__ == "__main__":
    main()
