"""What ``gnssfuse train-doppler`` does once :mod:`fusion.cli.train_doppler` has parsed its arguments: load the
traces, gather the head's rows (:mod:`learned.doppler_train`), fit, and write the head into a copy of the base
checkpoint (its ``.npz`` twin too), or into every member of an ensemble."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from fusion.errors import DataError
from fusion.options import load_options, parse_signals
from fusion.prepare.load import find_traces, load_trace
from fusion.run_types import RunOptions
from learned.checkpoint import load_model, save_checkpoint
from learned.data import check_not_forbidden
from learned.doppler_train import HeadConfig, fit, head_dict, trace_rows
from learned.ensemble import member_paths, write_derived_manifest
from learned.infer import SHIPPED_WEIGHTS


def check_args(args: argparse.Namespace) -> None:
    """One-line errors for values no run can use, before any log is read."""
    if args.epochs < 1 or args.hidden < 1 or not args.lr > 0:
        raise DataError("need --epochs >= 1, --hidden >= 1 and --lr > 0")
    if args.clk is not None and args.sp3 is None:
        raise DataError("--clk needs --sp3")
    for p in args.trace_dirs:
        if not p.exists():
            raise DataError(f"{p}: trace folder does not exist")


def gather(args: argparse.Namespace, opts: RunOptions) -> tuple[dict[str, np.ndarray], list[str]]:
    """The rows of every trace folder at or under ``args.trace_dirs``, concatenated, and the traces' names."""
    parts, names = [], []
    for d in args.trace_dirs:
        for folder in find_traces(d) or [d]:
            check_not_forbidden(folder)
            trace = load_trace(folder, **load_options(opts))
            parts.append(trace_rows(trace, opts))
            names.append(trace.name)
            if not args.quiet:
                print(f"  {trace.name}: {len(parts[-1]['err'])} Doppler measurements with a target", file=sys.stderr)
    rows = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    if not len(rows["err"]):
        raise DataError("no Doppler measurement with a truth target in the given traces")
    return rows, names


def run(args: argparse.Namespace, prog: str = "gnssfuse train-doppler", progress: bool = True) -> int:
    """Train the head and write the checkpoint; ``args`` as :mod:`fusion.cli.train_doppler` parses them."""
    check_args(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    opts = RunOptions(elev_mask_deg=args.elev_mask, signals=parse_signals(args.signals) or "all",
                      nav=tuple(args.nav), sp3=args.sp3, clk=args.clk)
    base = Path(args.weights or SHIPPED_WEIGHTS)
    bases, outs = member_paths(base, Path(args.out))
    models = [load_model(b) for b in bases]  # a bad base fails before the traces are read
    rows, names = gather(args, opts)
    cfg = HeadConfig(hidden=args.hidden, epochs=args.epochs, lr=args.lr, seed=args.seed)
    report = None if args.quiet else (lambda loss: print(f"  epoch loss {loss:.4f}", file=sys.stderr))
    net, hist = fit(rows, cfg, report)
    head = head_dict(net, rows, cfg, names)
    for (model, blob), out in zip(models, outs):     # an ensemble's members share the one head
        save_checkpoint(out, model, dict(blob["config"], doppler_head=head), epoch=blob.get("epoch", 0),
                        history=blob.get("history", []))
    write_derived_manifest(base, Path(args.out), outs)
    print(f"{prog}: {len(rows['err'])} Doppler measurements from {len(names)} traces, final loss {hist[-1]:.4f}; "
          f"head for {', '.join(head['systems'])} written into {args.out}")
    return 0
