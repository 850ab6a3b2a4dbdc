"""``gnssfuse`` command line: the dispatcher and the ``run`` subcommand.

Each other subcommand lives with the work it does and exposes ``main(argv, prog) -> int``; the
dispatcher names it by a ``"module:function"`` string and imports it only when that subcommand
runs, so ``gnssfuse run --mode wls`` never imports torch.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from fusion.errors import GnssfuseError
from fusion.options import add_run_options, load_options, options_from_args

#: subcommand -> ("module:function", one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("fusion.cli:run_main", "solve one trace in one mode (wls, dnn, fused, fused-nodnn)"),
    "evaluate": ("fusion.evaluate:main", "compare modes on traces: tables, CDFs, box plots, report.md"),
    "simulate": ("fusion.sim.simulate:main", "simulate a GNSS trace (GSDC 2021 derived format + truth)"),
    "train": ("learned.train_cli:main", "train the set-transformer correction network"),
}


def build_run_parser(prog: str = "gnssfuse run") -> argparse.ArgumentParser:
    from fusion.modes import MODES

    p = argparse.ArgumentParser(prog=prog, description="Solve one trace in one mode and write estimates.csv.")
    p.add_argument("trace_dir", type=Path, help="a <collection>/<phone> folder (GSDC 2021 derived, 2022/23 device_gnss, or a RINEX "
                   "observation file / GnssLogger log, directly or in supplemental/)")
    p.add_argument("--mode", default="wls", choices=list(MODES))
    p.add_argument("--out", type=Path, required=True, help="output folder")
    add_run_options(p)
    return p


def run_main(argv: list[str], prog: str = "gnssfuse run") -> int:
    """``gnssfuse run``: one trace, one mode -> estimates.csv (+ metrics.json with truth)."""
    from fusion.eval.metrics import format_table, mode_metrics
    from fusion.io.estimates import write_outputs
    from fusion.io.load import load_trace
    from fusion.modes import run_modes

    args = build_run_parser(prog).parse_args(argv)
    opts = options_from_args(args)
    # min_sats=1: keep epochs with 1-3 satellites; WLS/dnn leave them unsolved (counted in info),
    # the fused modes carry them with the prior and the motion model
    trace = load_trace(args.trace_dir, fix_truth_height=not args.no_truth_height_fix, min_sats=1,
                       **load_options(opts))
    result = run_modes(trace, [args.mode], opts)[args.mode]
    record = write_outputs(args.out, trace, args.mode, result, mode_metrics(trace, result))
    print(f"{trace.name}: {record['epochs_solved']}/{trace.n_epochs} epochs solved in mode {args.mode}"
          + (f"; skipped while loading: {record['skipped']}" if record["skipped"] else ""))
    info = result.info
    if info.get("excluded_measurements") or info.get("epochs_fault_undecided"):
        print(f"WLS fault detection: {info['excluded_measurements']} measurements excluded in "
              f"{info['epochs_with_exclusions']} epochs; {info['epochs_fault_undecided']} epochs undecided"
              " (see metrics.json 'info'; --wls-plain for the plain baseline)")
    print(format_table({args.mode: record["metrics"]}))
    print(f"wrote {args.out / 'estimates.csv'}" + (" and metrics.json" if record["metrics"] else ""))
    return 0


def _usage() -> str:
    lines = ["usage: gnssfuse COMMAND [options]   (gnssfuse COMMAND --help for each)", "", "commands:"]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gnssfuse: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module, func = COMMANDS[cmd][0].split(":")
    if cmd == "evaluate":
        from fusion.parallel import jobs_asked, start_early
        if jobs_asked(rest) > 1:
            start_early()        # the workers' imports then overlap this process's
    entry = getattr(importlib.import_module(module), func)
    try:
        return int(entry(rest, prog=f"gnssfuse {cmd}") or 0)
    except (GnssfuseError, OSError) as exc:
        # One line, no traceback: the message already names the file/epoch and the problem
        # (OSError: a missing input, an unwritable --out folder).
        print(f"gnssfuse {cmd}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
