"""What ``gnssfuse adapt`` does once :mod:`fusion.cli.adapt` has parsed its arguments: check them, build
the run options the teacher solves with, adapt (:mod:`learned.adapt`) and print what was learned from."""
from __future__ import annotations

import argparse
import sys

import torch

from fusion.errors import DataError
from fusion.run_types import RunOptions
from fusion.options import parse_signals
from fusion.parallel import check_pace
from learned.adapt import AdaptConfig, adapt


def check_args(args: argparse.Namespace) -> None:
    """One-line errors for values no run can use, before any log is read."""
    if args.epochs < 1 or args.batch < 1:
        raise DataError("need --epochs >= 1 and --batch >= 1")
    if not args.lr > 0 or not args.max_teacher_sigma > 0:
        raise DataError("need --lr > 0 and --max-teacher-sigma > 0")
    if not args.loo >= 0 or not args.agree >= 0 or not args.loo + args.agree > 0:
        raise DataError("need --loo >= 0 and --agree >= 0, not both 0")
    if not args.anchor >= 0:
        raise DataError("need --anchor >= 0")
    if not -1 <= args.margin < 1:
        raise DataError("need -1 <= --margin < 1")
    if not -1 <= args.graph_margin < 1:
        raise DataError("need -1 <= --graph-margin < 1")
    if not args.min_teacher_sigma >= 0:
        raise DataError("need --min-teacher-sigma >= 0")
    if not 0 <= args.max_carrier_share <= 1:
        raise DataError("need 0 <= --max-carrier-share <= 1")
    if args.block < 1 or args.every < 2:
        raise DataError("need --block >= 1 and --every >= 2")
    if args.max_epochs is not None and args.max_epochs < 1:
        raise DataError("need --max-epochs >= 1")
    check_pace(args.jobs, args.scheduler)
    if args.clk is not None and args.sp3 is None:
        raise DataError("--clk needs --sp3")
    for p in args.trace_dirs:
        if not p.exists():
            raise DataError(f"{p}: trace folder does not exist")


def run_options(args: argparse.Namespace) -> RunOptions:
    """The run options of the teacher (as ``gnssfuse run`` builds them from the same flags)."""
    return RunOptions(elev_mask_deg=args.elev_mask, signals=parse_signals(args.signals), nav=tuple(args.nav),
                      sp3=args.sp3, clk=args.clk)


def describe(record: dict) -> str:
    """One line per log: how many epochs the teacher solved and was trusted on."""
    lines = []
    for name, c in record["traces"].items():
        med = c["teacher_sigma_h_median_m"]
        lines.append(f"  {name}: {c['teacher_trusted']}/{c['epochs']} epochs trusted (teacher median horizontal "
                     f"sigma {'-' if med is None else f'{med:.2f}'} m; Doppler {'yes' if c['doppler'] else 'no'}, "
                     f"carrier {'yes' if c['carrier'] else 'no'}, tying {c['carrier_linked']} epochs), "
                     f"{c.get('samples', 0)} samples")
    return "\n".join(lines)


def run(args: argparse.Namespace, prog: str = "gnssfuse adapt", progress: bool = True) -> int:
    """Adapt and write the checkpoint; ``args`` as :mod:`fusion.cli.adapt` parses them. Returns the exit code."""
    check_args(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = AdaptConfig(epochs=args.epochs, lr=args.lr, batch=args.batch, seed=args.seed,
                      max_teacher_sigma_m=args.max_teacher_sigma, max_epochs=args.max_epochs, loo=args.loo,
                      teacher=args.teacher, elev_mask_deg=args.elev_mask, part=args.part, agree=args.agree,
                      anchor=args.anchor, margin=args.margin, block=args.block, every=args.every,
                      graph_check=args.graph_check, graph_margin=args.graph_margin,
                      min_teacher_sigma_m=args.min_teacher_sigma, max_carrier_share=args.max_carrier_share)
    record = adapt(args.trace_dirs, args.out, weights=args.weights, cfg=cfg, opts=run_options(args), jobs=args.jobs,
                   progress=progress, log=lambda s: print(f"{prog}: {s}", file=sys.stderr), scheduler=args.scheduler)
    print(f"{verdict(record, args.out)}\n{describe(record)}")
    return 0


def verdict(record: dict, out) -> str:
    """The one line saying whether the adaptation was kept, from what, and why."""
    head = (f"{len(record['traces'])} log(s) without ground truth, {record['samples']} samples "
            f"({record['heldout_samples']} held out; teacher {record['teacher_s']:.0f} s, training "
            f"{record['train_s']:.0f} s)")
    if record["decision"] == "declined":
        return (f"adaptation DECLINED: {out} holds the base weights {record['from']} unchanged ({head}; "
                f"{record['reason']})")
    g = record.get("graph_check")
    graph = "" if g is None else (f"; graph check: held-out satellites' error {g['base_m']:.3f} -> "
                                  f"{g['adapted_m']:.3f} m")
    return (f"adapted {record['from']} on {head}: kept epoch {record['best_epoch']} of {record['epochs']} "
            f"({record['reason']}{graph}) -> {out}")
