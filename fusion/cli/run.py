"""``gnssfuse run``: one trace, one mode -> OUT/estimates.csv and metrics.json (+ ``--export`` formats)."""
from __future__ import annotations

import argparse
from pathlib import Path

from fusion.cli.common import out_folder
from fusion.io.export import WRITERS, parse_formats
from fusion.options import TRACE_DIR_HELP, add_run_options, load_options, options_from_args


def build_parser(prog: str = "gnssfuse run") -> argparse.ArgumentParser:
    from fusion.modes import MODES

    p = argparse.ArgumentParser(prog=prog, description="Solve one trace in one mode and write estimates.csv "
                                "and metrics.json (heights: WGS84 ellipsoidal).")
    p.add_argument("trace_dir", type=Path, help=TRACE_DIR_HELP)
    p.add_argument("--mode", default="wls", choices=list(MODES), help="estimator (default wls)")
    p.add_argument("--out", type=Path, required=True, help="output folder (created if missing)")
    p.add_argument("--export", action="append", default=None, metavar="FORMATS",
                   help=f"also write OUT/estimates.<format> for each of these, comma-separated (or --export again): "
                        f"{','.join(WRITERS)} (GPX track, KML line + placemarks, NMEA GGA/RMC, RTKLIB .pos)")
    add_run_options(p)
    return p


def main(argv: list[str], prog: str = "gnssfuse run") -> int:
    from fusion.eval.metrics import format_table, mode_metrics
    from fusion.eval.summary import run_summary
    from fusion.io.estimates import export_frame, write_outputs
    from fusion.io.export import write_exports
    from fusion.prepare.load import load_trace
    from fusion.modes import run_modes

    args = build_parser(prog).parse_args(argv)
    opts = options_from_args(args)
    formats = parse_formats(",".join(args.export)) if args.export is not None else ()
    out = out_folder(args.out)
    # min_sats=1: keep epochs with 1-3 satellites; WLS/dnn leave them unsolved (counted in info),
    # the fused modes carry them with the prior and the motion model
    trace = load_trace(args.trace_dir, fix_truth_height=not args.no_truth_height_fix, min_sats=1,
                       **load_options(opts))
    result = run_modes(trace, [args.mode], opts)[args.mode]
    record = write_outputs(out, trace, args.mode, result, mode_metrics(trace, result))
    written = write_exports(export_frame(trace, result), out, formats, f"{trace.name} ({args.mode})")
    print(run_summary(record))
    if record["metrics"]:
        print(format_table({args.mode: record["metrics"]}))
    print(f"wrote {', '.join(str(p) for p in [out / 'estimates.csv', out / 'metrics.json', *written])}")
    return 0
