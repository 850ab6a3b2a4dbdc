"""``gnssfuse adapt``: fine-tune the learned measurement models on a phone's own logs, without ground
truth (the graph without anything learned is the teacher); the work is ``learned.adapt_command:run``.

``fusion`` never imports ``learned``: the work is named by a ``"module:function"`` string, so
``gnssfuse adapt --help`` and a bad option answer without importing torch.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from fusion.options import TRACE_DIR_HELP, add_nav_options, add_scheduler_option, add_signals_option

#: The library call that does the work once the arguments are parsed.
WORK = "learned.adapt_command:run"


def build_parser(prog: str = "gnssfuse adapt") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Adapt the learned models to logs without ground truth "
                                "(never reads a ground-truth file); use the result with run --weights.")
    p.add_argument("trace_dirs", type=Path, nargs="+", metavar="TRACE_DIR", help=TRACE_DIR_HELP)
    p.add_argument("--out", type=Path, required=True,
                   help="adapted checkpoint (.pt), or manifest (.json) when --weights is an ensemble")
    p.add_argument("--weights", type=Path, default=None,
                   help="base checkpoint (.pt) or ensemble manifest (.json) (default: the shipped ensemble)")
    p.add_argument("--epochs", type=int, default=5, help="passes over the logs (default 5); the best on the "
                   "held-out blocks is kept")
    p.add_argument("--lr", type=float, default=3e-4, help="learning rate (default 3e-4)")
    p.add_argument("--batch", type=int, default=64, help="batch size (default 64)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the guesses and the batch order")
    p.add_argument("--max-teacher-sigma", type=float, default=3.0, metavar="M",
                   help="learn only at epochs where the teacher's horizontal 1-sigma is at most M metres "
                        "(default 3)")
    p.add_argument("--teacher", default="fused", choices=("fused", "fused-nodnn"),
                   help="the trajectory learned from: the graph with the base network (default) or without "
                        "anything learned")
    p.add_argument("--loo", type=float, default=1.0, metavar="W",
                   help="weight of the leave-one-satellite-out consistency loss on the per-satellite head "
                        "(default 1; 0: off)")
    p.add_argument("--part", default="sat", choices=("sat", "all"),
                   help="what is fine-tuned: the per-satellite head alone (default; the position prior stays "
                        "the base's) or the whole network")
    p.add_argument("--agree", type=float, default=0.0, metavar="W",
                   help="weight of the training losses against the teacher's trajectory (default 0: "
                        "consistency alone)")
    p.add_argument("--anchor", type=float, default=10.0, metavar="W",
                   help="weight of the pull of each epoch's mean sigma and of the biases to the base's "
                        "(default 10; what the log's own consistency cannot check)")
    p.add_argument("--margin", type=float, default=0.02, metavar="F",
                   help="relative gain on the held-out blocks' leave-one-satellite-out error needed to keep "
                        "the adaptation (default 0.02); below it the base weights are written unchanged "
                        "(negative: keep the best epoch even where it is worse)")
    p.add_argument("--block", type=int, default=60, metavar="N",
                   help="self-check: blocks of N teacher-trusted epochs (default 60) ...")
    p.add_argument("--every", type=int, default=4, metavar="K",
                   help="... every K-th of which is held out of the fine-tuning (default 4)")
    p.add_argument("--graph-margin", type=float, default=-0.01, metavar="F",
                   help="an adaptation the self-check accepts is kept only if the fused graph, solved with "
                        "each quarter of the satellites held out, predicts their pseudoranges better by more "
                        "than this relative gain (default -0.01: no more than 1 %% worse; in a street canyon the "
                        "held-out satellites share the reflections the adaptation learns to distrust)")
    p.add_argument("--no-graph-check", dest="graph_check", action="store_false",
                   help="keep what the self-check accepts without the graph check (saves 8 graph solves per log)")
    p.add_argument("--min-teacher-sigma", type=float, default=0.5, metavar="M",
                   help="decline where the teacher's median horizontal 1-sigma is below M metres (default 0.5; "
                        "0: off): a track carrier phase places to decimetres is beyond what the checks can judge")
    p.add_argument("--max-carrier-share", type=float, default=0.5, metavar="S",
                   help="decline where time-differenced carrier phase ties more than this share of the teacher's "
                        "epochs (default 0.5; 1: off): both checks score pseudoranges, which cannot show where "
                        "re-weighting them moves a carrier-shaped track")
    p.add_argument("--max-epochs", type=int, default=None, metavar="N", help="use only each log's first N epochs")
    add_signals_option(p, "the signals the teacher uses (default: GPS_L1 for GSDC files, every signal with "
                          "ephemerides for RINEX / GnssLogger logs); the network reads its own")
    add_nav_options(p)
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg]")
    p.add_argument("--jobs", type=int, default=1, help="solve the teachers of N logs at a time (processes)")
    add_scheduler_option(p, "the teachers (the fine-tuning itself runs here)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar (there is none anyway when stderr is not a terminal)")
    return p


def main(argv: list[str], prog: str = "gnssfuse adapt") -> int:
    from fusion.cli.common import learned_work

    return learned_work(WORK, build_parser(prog).parse_args(argv), prog)
