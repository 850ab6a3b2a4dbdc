"""``gnssfuse train``: the arguments of the training run; the work is ``learned.train_command:run``.

``fusion`` never imports ``learned``, so the work is named by a ``"module:function"`` string as the
mode registry names the learned modes: ``gnssfuse train --help`` and a bad option answer without
importing torch. Runs unchanged under ``torchrun --nproc_per_node N -m fusion.cli train ...``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from fusion.options import add_nav_options, add_signals_option

#: The library call that does the work once the arguments are parsed.
WORK = "learned.train_command:run"
#: The network's outputs (learned.forward.OUTPUTS; a test keeps the two equal).
OUTPUTS = ("wls", "correction")


def build_parser(prog: str = "gnssfuse train") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Train the correction network and its per-satellite head.")
    p.add_argument("--data", nargs="+", required=True,
                   help="'sim', 'sim-bias' (fusion.sim.simulate), 'toy', and/or trace folders / Kaggle roots")
    p.add_argument("--out", type=Path, required=True, help="best checkpoint path (last state: <out>.last)")
    p.add_argument("--epochs", type=int, default=40, help="training epochs (passes over the data; default 40)")
    p.add_argument("--eta", type=float, default=15.0, help="box augmentation half-width per NED axis [m]")
    p.add_argument("--guess-mix", default="box=0.2,wls=0.5,graph=0.3",
                   help="initial-guess sources and fractions (box: truth + U(+-eta); wls / graph: the sample's "
                        "own WLS / no-prior graph solution + U(+-wls-jitter))")
    p.add_argument("--wls-jitter", type=float, default=2.0, help="[m] per NED axis around WLS / graph guesses")
    p.add_argument("--wls-max-err", type=float, default=100.0, help="[m] farther guess sources -> box guess")
    p.add_argument("--inputs", default=None,
                   help="comma-separated input channel groups from res,los,pr_sigma,cn0,dres,arc,cmd,carrier,"
                        "system,signal,heading (feature version 3; default: all of them but the opt-in heading)")
    p.add_argument("--output", default="wls", choices=OUTPUTS,
                   help="dnn output: learned-weight least squares (wls) or the paper's correction")
    p.add_argument("--loss", default="correction=1,sat=0.1,wls=1,shrink=1",
                   help="loss weights (correction, sat, wls, wls_scale, shrink)")
    p.add_argument("--dropout", default=None,
                   help="feature dropout (feature version 3): group=rate pairs, e.g. pr_sigma=0.25,signal=0.1; "
                        "groups not named keep the recipe's rates (learned/weights/TRAINING.md)")
    p.add_argument("--sat-dropout", type=float, default=0.0, metavar="RATE",
                   help="satellite dropout: per sample and epoch, the chance it keeps only 4..n of its n satellites "
                        "(as a street canyon leaves them; default 0, off)")
    p.add_argument("--slow-target", type=float, default=0.0, metavar="S",
                   help="score the per-satellite losses on each pseudorange's error averaged over a centred S s along "
                        "its arc, the part a smoother cannot average away (default 0: one epoch's error)")
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate and save an exponential moving average of the weights with this decay per step "
                        "(e.g. 0.999; default 0: the trained weights)")
    p.add_argument("--resume", action="store_true", help="continue from <out>.last")
    p.add_argument("--init", type=Path, default=None, metavar="CKPT",
                   help="start from this checkpoint's weights (pre-trained, e.g. on simulated traces; same network "
                        "and inputs) instead of the seed's")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="training device (default cpu)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the split, augmentation and model")
    p.add_argument("--model", default="set", choices=("set", "deepsets"),
                   help="set transformer (default) or deep sets")
    p.add_argument("--no-augment", action="store_true", help="draw guesses once and keep them (paper's baseline)")
    p.add_argument("--sim-traces", type=int, default=50, help="simulated traces per 'sim' / 'toy' source")
    p.add_argument("--sim-epochs", type=int, default=200, help="epochs per simulated trace")
    p.add_argument("--val-split", default="traces", choices=("random", "blocks", "traces"),
                   help="validation = random epochs, blocks of 60 epochs, or whole traces (drives)")
    p.add_argument("--val-frac", type=float, default=0.1, help="fraction held out for validation")
    p.add_argument("--no-calibrate", action="store_true", help="do not fit the covariance scales after training")
    p.add_argument("--batch", type=int, default=64, help="batch size per process")
    p.add_argument("--lr", type=float, default=3e-4, help="learning rate")
    p.add_argument("--warmup-epochs", type=int, default=None, help="epochs before the variance NLL term")
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg], at the truth")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads per process")
    add_signals_option(p, "default GPS_L1 (the 2021 files' only signal); the network learns every signal "
                          "it is given, e.g. all for simulated multi-constellation traces")
    add_nav_options(p)
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar (there is none anyway when stderr is not a terminal)")
    return p


def main(argv: list[str], prog: str = "gnssfuse train") -> int:
    from fusion.cli.common import learned_work

    return learned_work(WORK, build_parser(prog).parse_args(argv), prog)
