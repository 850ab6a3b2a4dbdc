"""What ``gnssfuse train`` does once :mod:`fusion.cli.train` has parsed its arguments: data sources,
the training configuration, and the summary line (the loop is in :mod:`learned.train`). Runs unchanged
under ``torchrun --nproc_per_node N`` (:mod:`learned.distributed`)."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from fusion.errors import DataError
from fusion.eval.summary import skip_words
from fusion.options import parse_signals
from fusion.prepare.raw_load import RawSources
from learned import distributed as dist
from learned.augment import parse_guess_mix
from learned.checkpoint import read_checkpoint
from learned.data import (Samples, build_samples, load_real_traces, simulated_traces, split_blocks, split_random,
                          split_traces)
from learned.features import CHANNELS_V2, RECIPE_INPUTS, FeatureConfig
from learned.model import build_model, count_parameters
from learned.train import DEFAULT_DROPOUT, LossWeights, TrainConfig, pretrained_state, train

#: Inputs of the shipped recipe: the paper's (residual, line of sight) and every context channel but the opt-in
#: heading.
DEFAULT_INPUTS = ",".join(RECIPE_INPUTS)


def default_inputs(version: int) -> str:
    """The default ``--inputs`` when training feature version ``version`` (2: the previous release)."""
    return ",".join(CHANNELS_V2) if version == 2 else DEFAULT_INPUTS


def parse_loss(text: str) -> LossWeights:
    """``correction=1,sat=0.1,wls=1`` -> :class:`LossWeights` (unnamed weights keep their defaults)."""
    w = LossWeights()
    for item in filter(None, text.split(",")):
        key, _, val = item.partition("=")
        if not hasattr(w, key.strip()):
            raise DataError(f"--loss: unknown term {key!r} (known: {', '.join(vars(w))})")
        try:
            setattr(w, key.strip(), float(val))
        except ValueError:
            raise DataError(f"--loss: {item!r} is not name=number") from None
    return w


def load_training_data(sources: list[str], *, sim_traces: int, sim_epochs: int, seed: int, elev_mask_deg: float,
                       with_graph: bool = False, raw_sources: RawSources | None = None,
                       signals: tuple[str, ...] = ("GPS_L1",), slow_window_s: float = 0.0) -> tuple[Samples, dict]:
    """``sim`` / ``toy``: simulated Gaussian traces; ``sim-bias`` / ``toy-bias``: the Gaussian + NLOS-bias
    scenario (seed + 1, other drives); anything else: real trace folders. ``slow_window_s``: as
    :func:`learned.data.build_samples`."""
    traces, real, desc = [], [], {"sources": sources}
    for src in sources:
        if src in ("sim", "toy", "sim-bias", "toy-bias"):
            bias = src.endswith("-bias")
            sd = seed + 1 if bias else seed
            new = simulated_traces(sim_traces, sim_epochs, seed=sd, bias=bias, toy=src.startswith("toy"))
            desc[src] = {"traces": sim_traces, "epochs_per_trace": sim_epochs, "bias": bias, "seed": sd}
            real += [False] * len(new)
        else:
            new = load_real_traces([src], signals=signals, raw_sources=raw_sources)
            real += [True] * len(new)
        traces += new
    samples = build_samples(traces, elev_mask_deg, real=real, with_graph=with_graph, slow_window_s=slow_window_s)
    desc.update(traces=samples.names, n_samples=len(samples), skipped=samples.skipped)
    return samples, desc


def parse_dropout(text: str | None) -> dict:
    """``pr_sigma=0.25,signal=0.1`` -> the recipe's dropout with those rates replaced."""
    out = dict(DEFAULT_DROPOUT)
    for item in filter(None, (text or "").split(",")):
        key, _, val = item.partition("=")
        if key.strip() not in DEFAULT_DROPOUT:
            raise DataError(f"--dropout: unknown group {key!r} (known: {', '.join(DEFAULT_DROPOUT)})")
        try:
            rate = float(val)
        except ValueError:
            raise DataError(f"--dropout: {item!r} is not name=number") from None
        if not 0 <= rate <= 1:
            raise DataError(f"--dropout: {key} rate must be in [0, 1], got {rate}")
        out[key.strip()] = rate
    return out


def config_from_args(args, desc: dict) -> TrainConfig:
    try:
        mix = parse_guess_mix(args.guess_mix)
        inputs = DEFAULT_INPUTS if args.inputs is None else args.inputs
        features = FeatureConfig(elev_mask_deg=args.elev_mask, inputs=tuple(inputs.split(",")))
    except ValueError as exc:
        raise DataError(f"--guess-mix / --inputs: {exc}") from None
    return TrainConfig(eta=args.eta, epochs=args.epochs, batch=args.batch, lr=args.lr, seed=args.seed,
                       model=args.model, augment=not args.no_augment, warmup_epochs=args.warmup_epochs,
                       val_frac=args.val_frac, device=args.device, features=features, data=desc, guess_mix=mix,
                       wls_jitter=args.wls_jitter, wls_max_err=args.wls_max_err, calibrate=not args.no_calibrate,
                       loss=parse_loss(args.loss), output=args.output, dropout=parse_dropout(args.dropout),
                       signals=signals_of(args), init=args.init, sat_dropout=args.sat_dropout,
                       slow_target_s=args.slow_target, ema_decay=args.ema)


def signals_of(args) -> tuple[str, ...]:
    """The signals training reads (``--signals``; GPS L1 when not given)."""
    return parse_signals(args.signals) or ("GPS_L1",)


def check_args(args) -> None:
    if args.epochs < 1 or args.batch < 1 or not (0 <= args.val_frac < 1) or not 0 < args.eta < math.inf:
        raise DataError("need --epochs >= 1, --batch >= 1, 0 <= --val-frac < 1, --eta > 0")
    if not 0 < args.lr < math.inf:
        raise DataError(f"--lr: a learning rate > 0, got {args.lr}")
    if args.wls_jitter < 0 or args.wls_max_err <= 0:
        raise DataError("need --wls-jitter >= 0 and --wls-max-err > 0")
    if not 0 <= args.sat_dropout <= 1:
        raise DataError(f"--sat-dropout: a rate in [0, 1], got {args.sat_dropout}")
    if args.slow_target < 0:
        raise DataError(f"--slow-target: a window in seconds >= 0, got {args.slow_target}")
    if not 0 <= args.ema < 1:
        raise DataError(f"--ema: a decay in [0, 1), got {args.ema}")


def summary(out: Path, hist: list[dict]) -> str:
    h = min(hist, key=lambda r: r["val_score_m"])
    ned = "/".join(f"{v:.2f}" for v in h.get("val_wls_mae_ned_m", [float("nan")] * 3))
    line = f"best epoch {h['epoch']}: val horizontal error {h['val_score_m']:.2f} m, learned-WLS MAE N/E/D {ned} m"
    cal = read_checkpoint(out)["config"].get("calibration", {})
    for name, c in cal.items():
        line += (f"\n{name} covariance scale N/E/D {'/'.join(f'{v:.2f}' for v in c['scale_ned'])}: within 1 sigma "
                 f"{'/'.join(f'{v:.2f}' for v in c['within_1sigma_after'])} (n={c['n']})")
    return line + f" -> {out}"


def run(args: argparse.Namespace, prog: str = "gnssfuse train", progress: bool = True) -> int:
    """Load the data, train, calibrate and write the checkpoint; ``args`` as :mod:`fusion.cli.train`
    parses them. Returns the exit code."""
    check_args(args)
    dist.init_from_env(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    sources = [s for item in args.data for s in item.split(",") if s]
    cfg = config_from_args(args, {})         # option errors before any data is loaded
    if cfg.init is not None:
        pretrained_state(Path(cfg.init), cfg, "cpu")     # ... a checkpoint that cannot start this run too
    samples, desc = load_training_data(sources, sim_traces=args.sim_traces, sim_epochs=args.sim_epochs,
                                       seed=args.seed, elev_mask_deg=args.elev_mask,
                                       with_graph=cfg.guess_mix.get("graph", 0.0) > 0,
                                       raw_sources=RawSources(tuple(args.nav), args.sp3, args.clk), signals=cfg.signals,
                                       slow_window_s=cfg.slow_target_s)
    split = {"blocks": split_blocks, "random": split_random, "traces": split_traces}[args.val_split]
    train_s, val_s = split(samples, args.val_frac, np.random.default_rng(args.seed))
    desc.update(n_train=len(train_s), n_val=len(val_s), val_split=args.val_split)
    cfg.data = desc
    if dist.is_main():
        n_par = count_parameters(build_model(args.model, d_in=cfg.features.n_inputs))
        print(f"{prog}: {len(train_s)} training / {len(val_s)} validation samples from {len(samples.names)} "
              f"traces; model {args.model} ({n_par} parameters); world size {dist.world_size()}; "
              f"skipped {skip_words(samples.skipped)}", file=sys.stderr)
    hist = train(train_s, val_s, cfg, args.out, resume=args.resume, progress=progress)
    if dist.is_main() and hist:
        print(summary(args.out, hist))
    dist.shutdown()
    return 0
