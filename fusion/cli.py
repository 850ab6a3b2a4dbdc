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
from fusion.run_types import RunOptions
from fusion.trace import SIGNALS, resolve_signals

#: subcommand -> ("module:function", one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("fusion.cli:run_main", "solve one trace in one mode (wls, dnn, fused, fused-nodnn)"),
    "evaluate": ("fusion.evaluate:main", "compare modes on traces: tables, CDFs, box plots, report.md"),
    "simulate": ("fusion.sim.simulate:main", "simulate a GNSS trace (GSDC 2021 derived format + truth)"),
    "train": ("learned.train_cli:main", "train the set-transformer correction network"),
}


def add_run_options(p: argparse.ArgumentParser) -> None:
    """Options shared by ``gnssfuse run`` and ``gnssfuse evaluate`` (read by :func:`options_from_args`)."""
    p.add_argument("--weights", type=Path, default=None, help="DNN checkpoint (default: shipped weights)")
    p.add_argument("--signals", default=None,
                   help=f"comma-separated, from {','.join(SIGNALS)} (2023 spellings such as GPS_L1_CA "
                        "too), or all; default GPS_L1 for GSDC files, every signal with ephemerides "
                        "for RINEX / GnssLogger logs")
    p.add_argument("--nav", type=Path, nargs="+", default=(), metavar="FILE",
                   help="RINEX / GnssLogger traces: broadcast navigation file(s) (RINEX 2 .YYn/.YYg, "
                        "RINEX 3 *_MN.rnx; default: those in the trace folder or supplemental/)")
    p.add_argument("--sp3", type=Path, default=None, metavar="FILE",
                   help="RINEX / GnssLogger traces: precise orbits (SP3) instead of broadcast ones")
    p.add_argument("--clk", type=Path, default=None, metavar="FILE",
                   help="with --sp3: precise satellite clocks (RINEX clock file)")
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg]")
    p.add_argument("--dnn-passes", type=int, default=1, help="apply the DNN iteratively this many times")
    p.add_argument("--incremental", action="store_true", help="fused modes: incremental smoother instead of batch")
    p.add_argument("--wls-plain", action="store_true",
                   help="plain WLS, the paper's baseline (default: WLS with fault detection and exclusion)")
    p.add_argument("--no-doppler", action="store_true",
                   help="fused modes: ignore the trace's Doppler (pseudorange rates)")
    p.add_argument("--no-carrier", action="store_true",
                   help="fused modes: ignore the trace's carrier phase (accumulated delta ranges)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-learned-prior", action="store_true", help="fused: without the network's position prior")
    p.add_argument("--no-learned-sigmas", action="store_true",
                   help="fused: without the per-satellite head's pseudorange sigmas and biases")
    p.add_argument("--dnn-output", choices=("wls", "correction"), default=None,
                   help="dnn: learned-weight least squares or the paper's correction head (default: the checkpoint's)")
    p.add_argument("--no-truth-height-fix", action="store_true",
                   help="keep GSDC 2021 truth heights as published (~63 m too high)")


def options_from_args(args: argparse.Namespace) -> RunOptions:
    """The :class:`RunOptions` of parsed :func:`add_run_options` arguments."""
    # The loader's vocabulary: our names, GSDC 2023 spellings (GPS_L1_CA, ...) or "all".
    signals = None
    if args.signals is not None:
        names = [s.strip() for s in args.signals.split(",") if s.strip()]
        signals = tuple(SIGNALS[i] for i in resolve_signals(names))
    if args.dnn_passes < 1:
        raise GnssfuseError("--dnn-passes must be >= 1")
    if args.clk is not None and args.sp3 is None:
        raise GnssfuseError("--clk needs --sp3 (precise clocks go with precise orbits)")
    return RunOptions(weights=args.weights, elev_mask_deg=args.elev_mask, device=args.device,
                      dnn_passes=args.dnn_passes, incremental=args.incremental, signals=signals,
                      wls_robust=False if args.wls_plain else "exclude", learned_prior=not args.no_learned_prior,
                      learned_sigmas=not args.no_learned_sigmas, dnn_output=args.dnn_output,
                      use_doppler=not args.no_doppler, use_carrier=not args.no_carrier,
                      nav=tuple(args.nav), sp3=args.sp3, clk=args.clk)


def load_options(opts: RunOptions) -> dict:
    """Keyword arguments of :func:`fusion.io.load.load_trace` that come from the run options."""
    from fusion.io.raw_load import RawSources

    return {"signals": opts.signals, "raw_sources": RawSources(opts.nav, opts.sp3, opts.clk)}


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
