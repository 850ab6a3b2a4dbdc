"""``gnssfuse evaluate``: compare modes on traces -> a report folder (the job: :mod:`fusion.evaluate`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fusion.cli.common import out_folder, show_progress
from fusion.errors import GnssfuseError
from fusion.options import TRACE_DIR_HELP, add_run_options, add_scheduler_option, options_from_args


def build_parser(prog: str = "gnssfuse evaluate") -> argparse.ArgumentParser:
    from fusion.modes import MODES

    p = argparse.ArgumentParser(prog=prog, description="Compare modes on traces: tables, CDFs, box "
                                "plots, trajectories and report.md.")
    p.add_argument("trace_dirs", type=Path, nargs="+", metavar="TRACE_DIR", help=TRACE_DIR_HELP + "; several allowed")
    p.add_argument("--modes", default="wls", help=f"comma-separated, from {','.join(MODES)} (default wls)")
    p.add_argument("--out", type=Path, required=True, help="report folder (created if missing)")
    add_run_options(p)
    p.add_argument("--max-epochs", type=int, default=None,
                   help="use only the first N epochs of each trace (quick looks, tests)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars (there are none anyway when stderr is not a terminal)")
    p.add_argument("--jobs", type=int, default=1,
                   help="traces in this many parallel processes (one thread each; default 1)")
    add_scheduler_option(p, "the traces")
    return p


def main(argv: list[str], prog: str = "gnssfuse evaluate") -> int:
    from fusion.eval.report import ALL, markdown_table
    from fusion.evaluate import evaluate

    args = build_parser(prog).parse_args(argv)
    opts = options_from_args(args)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes:
        raise GnssfuseError("--modes is empty")
    df, failures = evaluate(args.trace_dirs, modes, out_folder(args.out), opts, max_epochs=args.max_epochs,
                            fix_truth_height=not args.no_truth_height_fix,
                            progress=show_progress(not args.no_progress), argv=argv, jobs=args.jobs,
                            scheduler=args.scheduler)
    print(markdown_table(df))
    print(f"wrote {args.out / 'report.md'}, metrics.csv, metrics.md and figures/")
    # The report for the good part is written; still exit non-zero so scripts notice the rest.
    for path, msg in failures.items():
        print(f"{prog}: error: could not evaluate {path}: {msg}", file=sys.stderr)
    bad_modes = df[df.status.str.startswith("failed") & (df.trace != ALL)]
    for r in bad_modes.itertuples(index=False):
        print(f"{prog}: error: mode {r.mode} on {r.trace}: {r.status}", file=sys.stderr)
    return 2 if failures or len(bad_modes) else 0
