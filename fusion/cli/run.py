"""``gnssfuse run``: one trace, one mode -> OUT/estimates.csv and metrics.json (+ ``--export`` formats)."""
from __future__ import annotations

import argparse
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from fusion.cli.common import out_folder
from fusion.errors import GeometryError
from fusion.io.export import WRITERS, parse_formats
from fusion.options import TRACE_DIR_HELP, add_run_options, flags_without_effect, load_options, options_from_args


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


@contextmanager
def out_folder_kept_on_success(path: Path):
    """The output folder, made before any work (:func:`~fusion.cli.common.out_folder`), and removed again with
    the parents this run made if the work in the block fails before anything was written into them."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not p.exists()]      # innermost first
    out = out_folder(path)
    try:
        yield out
    except BaseException:
        for folder in made:
            if not folder.is_dir() or any(folder.iterdir()):
                break
            folder.rmdir()
        raise


def remove_stale_exports(out: Path, formats: tuple[str, ...]) -> list[Path]:
    """Remove ``out/estimates.<format>`` of the formats not written this time (an earlier run's, which would
    sit beside this run's estimates.csv disagreeing with it); the paths removed."""
    stale = [out / f"estimates.{fmt}" for fmt in WRITERS if fmt not in formats and (out / f"estimates.{fmt}").is_file()]
    for path in stale:
        path.unlink()
    return stale


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
    unused = flags_without_effect(args, [args.mode])
    if unused:
        warnings.warn(f"{', '.join(unused)} {'has' if len(unused) == 1 else 'have'} no effect in mode {args.mode}")
    with out_folder_kept_on_success(args.out) as out:
        # min_sats=1: keep epochs with 1-3 satellites; WLS/dnn leave them unsolved (counted in info),
        # the fused modes carry them with the prior and the motion model
        trace = load_trace(args.trace_dir, fix_truth_height=not args.no_truth_height_fix, min_sats=1,
                           **load_options(opts))
        result = run_modes(trace, [args.mode], opts)[args.mode]
        if not np.asarray(result.valid, bool).any():
            raise GeometryError(f"{args.trace_dir}: {args.mode} solved none of its {trace.n_epochs} epochs (no epoch "
                                f"with enough usable satellites above the {opts.elev_mask_deg:g} deg elevation mask); "
                                "nothing written")
    record = write_outputs(out, trace, args.mode, result, mode_metrics(trace, result))
    written = write_exports(export_frame(trace, result), out, formats, f"{trace.name} ({args.mode})")
    stale = remove_stale_exports(out, formats)
    print(run_summary(record))
    if stale:
        print(f"removed {', '.join(p.name for p in stale)} of an earlier run in {out} (not asked for this time)")
    if record["metrics"]:
        print(format_table({args.mode: record["metrics"]}))
    print(f"wrote {', '.join(str(p) for p in [out / 'estimates.csv', out / 'metrics.json', *written])}")
    return 0
