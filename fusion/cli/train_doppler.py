"""``gnssfuse train-doppler``: train the Doppler head on traces with Doppler and ground truth and write it into
a copy of a checkpoint; the work is ``learned.doppler_command:run`` (named by string: no torch for ``--help``)."""
from __future__ import annotations

import argparse
from pathlib import Path

from fusion.options import TRACE_DIR_HELP, add_nav_options, add_signals_option

#: The library call that does the work once the arguments are parsed.
WORK = "learned.doppler_command:run"


def build_parser(prog: str = "gnssfuse train-doppler") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Train the learned Doppler head (each pseudorange rate's "
                                "sigma) on traces with Doppler and ground truth; write it into a copy of --weights.")
    p.add_argument("trace_dirs", type=Path, nargs="+", metavar="TRACE_DIR", help=TRACE_DIR_HELP)
    p.add_argument("--out", type=Path, required=True,
                   help="checkpoint written: --weights with the Doppler head (a .json manifest for an ensemble)")
    p.add_argument("--weights", type=Path, default=None,
                   help="base checkpoint (.pt) or ensemble manifest (.json) (default: the shipped ensemble)")
    p.add_argument("--epochs", type=int, default=20, help="passes over the measurements (default 20)")
    p.add_argument("--hidden", type=int, default=32, help="width of the head's two hidden layers (default 32)")
    p.add_argument("--lr", type=float, default=1e-3, help="learning rate (default 1e-3)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    add_signals_option(p, "default: every signal")
    add_nav_options(p)
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg]")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--quiet", action="store_true", help="no per-epoch lines")
    return p


def main(argv: list[str], prog: str = "gnssfuse train-doppler") -> int:
    from fusion.cli.common import learned_work

    return learned_work(WORK, build_parser(prog).parse_args(argv), prog)
