"""Experiment 2 (paper Sec. 5.2): the held-out real trace 2021-04-28-US-MTV-1/Pixel4 (GPS L1), vs WLS.

For each checkpoint NAME=PATH (default: the shipped weights as "shipped"):
- paper protocol: initial guess = truth + U(-eta, eta) per NED axis (eta from the checkpoint, or
  --paper-eta); this uses the truth to make the guess and is reported only to compare with the paper;
- honest protocol: initial guess = our WLS position, the DNN applied 1, 2 and 3 times (features
  recomputed at each corrected position; the clock is always re-estimated from the measurements).
Errors in the NED frame of the truth over epochs solved by both WLS and the DNN; MAE N/E/D, horizontal
p50/p95 and the 1/2-sigma coverage of the output's covariance (honest protocol), raw and with the
checkpoint's calibration of that output (fitted on its own validation split, never on this trace; "-" when
it has none). ``--output`` picks the output (``wls``: learned-weight least squares, ``correction``: the
paper's correction head; default: each checkpoint's).
Checkpoints trained with a box / WLS guess mix (``--guess-mix``) are run the same way; the table's
method column names each checkpoint's mix.

    PYTHONPATH=. python experiments/real_correction.py [--ckpt noaug=/tmp/noaug.pt] [--output correction]
    PYTHONPATH=. python experiments/real_correction.py --no-shipped --ckpt loo=/tmp/lt2/loo_sf2.pt \
        --trace ../shared/data/gsdc2021/train/2020-09-04-US-SF-2/Pixel4   # leave-one-trace-out
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from fusion.prepare.load import load_trace
from fusion.eval.metrics import ned_errors, summarize
from fusion.estimate.wls import solve_wls
from learned.augment import draw_guesses, epoch_generator
from learned.forward import OUTPUTS
from learned.infer import SHIPPED_WEIGHTS, Corrector, calibration

#: The held-out test trace, as shipped in the repository.
TEST = Path(__file__).resolve().parents[1] / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"


def _cov(cal: dict | None) -> str:
    if cal is None:
        return "- | -"
    return ("/".join(f"{v:.2f}" for v in cal["within_1sigma"]) + " | "
            + "/".join(f"{v:.2f}" for v in cal["within_2sigma"]))


def row(name: str, est: np.ndarray, truth: np.ndarray, ok: np.ndarray, cal: dict | None = None,
        cal2: dict | None = None) -> str:
    s = summarize(ned_errors(est[ok], truth[ok]))
    return (f"| {name} | {int(ok.sum())} | {s['mae_n']:.2f} / {s['mae_e']:.2f} / {s['mae_d']:.2f} | "
            f"{s['h_p50']:.2f} | {s['h_p95']:.2f} | {_cov(cal)} | {_cov(cal2)} |")


def mix_label(config: dict) -> str:
    mix = config.get("guess_mix") or {"box": 1.0}
    return ",".join(f"{k}={v:g}" for k, v in mix.items() if v > 0)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--trace", type=Path, default=TEST)
    p.add_argument("--ckpt", nargs="*", default=[], help="NAME=PATH; the shipped weights are included unless "
                                                          "--no-shipped")
    p.add_argument("--no-shipped", action="store_true")
    p.add_argument("--paper-eta", type=float, nargs="*", default=None, help="default: each checkpoint's eta")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--output", choices=OUTPUTS, default=None, help="default: each checkpoint's output")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    tr = load_trace(a.trace)
    wls = solve_wls(tr)
    has = np.isfinite(tr.truth).all(1)
    ckpts = [("shipped", SHIPPED_WEIGHTS)] if SHIPPED_WEIGHTS.is_file() and not a.no_shipped else []
    ckpts += [tuple(c.split("=", 1)) for c in a.ckpt]
    print(f"trace {tr.name}: {tr.n_epochs} epochs, {int(wls.valid.sum())} WLS-valid, {int(has.sum())} with truth\n")
    print("| method | epochs | MAE N / E / D [m] | horiz. p50 [m] | horiz. p95 [m] | raw: within 1 sigma "
          "N/E/D | 2 sigma | calibrated: within 1 sigma N/E/D | 2 sigma |")
    print("|---|---|---|---|---|---|---|---|---|")
    base_ok = wls.valid & has
    print(row("WLS (ours, elevation-weighted, 10 deg mask)", wls.pos, tr.truth, base_ok))
    truth_t = torch.as_tensor(np.where(has[:, None], tr.truth, 0.0))
    for name, path in ckpts:
        corr = Corrector.load(Path(path))
        raw = Corrector.load(Path(path), calibrated=False)
        output = a.output or corr.output
        has_cal = bool(((corr.config.get("calibration") or {}).get(output) or {}).get("scale_ned"))
        name = f"{name} ({mix_label(corr.config)}, output {output})"
        etas = a.paper_eta or [float(corr.config["eta"])]
        for eta in etas:
            guess = draw_guesses(truth_t, eta, epoch_generator(a.seed, 20_000)).numpy()
            c = corr.predict(tr, guess, has, output=output)
            ok = c.valid & base_ok
            print(row(f"{name}: PAPER PROTOCOL guess = truth + U(+-{eta:g} m)", c.mean_ecef, tr.truth, ok))
        pos, valid = wls.pos, wls.valid
        for k in (1, 2, 3):
            c_raw = raw.predict(tr, pos, valid, output=output)    # same means; only the variances differ
            c = corr.predict(tr, pos, valid, output=output)
            pos, valid = c.mean_ecef, c.valid
            ok = valid & base_ok
            err = np.full((tr.n_epochs, 3), np.nan)
            err[ok] = ned_errors(pos[ok], tr.truth[ok])
            # Coverage in the NED frame of the truth vs covariance in the NED frame of the guess: the
            # frames differ by micro-radians at these distances.
            print(row(f"{name}: honest, guess = WLS, {k} pass{'es' if k > 1 else ''}", pos, tr.truth, ok,
                      calibration(err, c_raw.cov_ned), calibration(err, c.cov_ned) if has_cal else None))


if __name__ == "__main__":
    main()
