"""Command-line flags defined once for every subcommand that takes them: the run options (``gnssfuse
run`` and ``evaluate``), the navigation sources (``run``, ``evaluate`` and ``train``) and the trace
folder argument.

Apart from the subcommands (:mod:`fusion.cli`) so that the ``evaluate`` job, which worker processes
preload, does not import the module the command line runs as ``__main__``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from dataclasses import replace

from fusion.errors import DataError, GnssfuseError
from fusion.estimate.graph.config import GraphConfig, load_graph_config
from fusion.run_types import RunOptions
from fusion.trace import SIGNALS, resolve_signals


#: What a trace folder may hold (the positional argument of ``run`` and ``evaluate``).
TRACE_DIR_HELP = ("a <collection>/<phone> folder (GSDC 2021 derived, 2022/23 device_gnss, or a RINEX "
                  "observation file / GnssLogger log, directly or in supplemental/; a smartLoc drive folder), "
                  "or one such file")


def add_nav_options(p: argparse.ArgumentParser) -> None:
    """``--nav``, ``--sp3``, ``--clk``: where RINEX / GnssLogger traces get their satellite orbits and
    clocks (read by :func:`options_from_args`, or by ``gnssfuse train`` as they are)."""
    p.add_argument("--nav", type=Path, nargs="+", default=(), metavar="FILE",
                   help="RINEX / GnssLogger traces: broadcast navigation file(s), RINEX 2, 3 or 4, any name "
                        "(found by their header; gzip too); default: those in the trace folder or supplemental/")
    p.add_argument("--sp3", type=Path, default=None, metavar="FILE",
                   help="RINEX / GnssLogger traces: precise orbits (SP3) instead of broadcast ones")
    p.add_argument("--clk", type=Path, default=None, metavar="FILE",
                   help="with --sp3: precise satellite clocks (RINEX clock file)")


def add_signals_option(p: argparse.ArgumentParser, default: str) -> None:
    """``--signals`` (read by :func:`parse_signals`); ``default`` says what its absence means."""
    p.add_argument("--signals", default=None,
                   help=f"comma-separated, from {','.join(SIGNALS)} (2023 spellings such as GPS_L1_CA "
                        f"too), or all; {default}")


def add_scheduler_option(p: argparse.ArgumentParser, what: str) -> None:
    """``--scheduler ADDRESS`` (a Dask scheduler); ``what`` says what runs on the cluster's workers."""
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help=f"run {what} on the Dask cluster whose scheduler is at ADDRESS (e.g. tcp://host:8786; "
                        "needs gnssfuse[cluster]; the workers must see every input and output path as given "
                        "here, relative ones resolved from this directory)")


def parse_signals(text: str | None) -> tuple[str, ...] | None:
    """The loader's signal names of a ``--signals`` value (our names, GSDC 2023 spellings or "all"); None
    for None."""
    if text is None:
        return None
    return tuple(SIGNALS[i] for i in resolve_signals([s.strip() for s in text.split(",") if s.strip()]))


def add_run_options(p: argparse.ArgumentParser) -> None:
    """Options shared by ``gnssfuse run`` and ``gnssfuse evaluate`` (read by :func:`options_from_args`)."""
    p.add_argument("--weights", type=Path, default=None,
                   help="DNN checkpoint (.pt) or ensemble manifest (.json) (default: the shipped ensemble)")
    add_signals_option(p, "default GPS_L1 for GSDC files, every signal with ephemerides for RINEX / GnssLogger logs")
    add_nav_options(p)
    p.add_argument("--iono-free", action="store_true",
                   help="RINEX / GnssLogger traces: ionosphere-free combination where a satellite has an L1-class "
                        "and a second-frequency pseudorange (L2C / E5b / B2I, else L5 / E5a) instead of both")
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg]")
    p.add_argument("--dnn-passes", type=int, default=1, help="apply the DNN iteratively this many times")
    p.add_argument("--incremental", action="store_true",
                   help="fused modes: incremental smoother (ISAM2, epoch by epoch) instead of batch")
    p.add_argument("--graph-config", type=Path, default=None, metavar="FILE.toml",
                   help="fused modes: the graph's settings (GraphConfig fields as 'name = value' lines, e.g. "
                        "robust_k = 3.0; see the README); the flags above override it")
    p.add_argument("--wls-plain", action="store_true",
                   help="plain WLS, the paper's baseline (default: WLS with fault detection and exclusion)")
    p.add_argument("--no-doppler", action="store_true",
                   help="fused modes: ignore the trace's Doppler (pseudorange rates)")
    p.add_argument("--no-carrier", action="store_true",
                   help="fused modes: ignore the trace's carrier phase (accumulated delta ranges)")
    p.add_argument("--odometry", action="store_true", help="fused modes: use the trace's vehicle odometry (smartLoc odom3)")
    p.add_argument("--device", default="cpu",
                   help="ignored at run time (kept for old scripts): the network runs in numpy on the CPU; "
                        "gnssfuse train takes its own --device")
    p.add_argument("--no-learned-prior", action="store_true", help="fused: without the network's position prior")
    p.add_argument("--no-learned-sigmas", action="store_true",
                   help="fused: without the per-satellite head's pseudorange sigmas and biases")
    p.add_argument("--no-learned-bias", action="store_true",
                   help="fused: the per-satellite head's pseudorange sigmas without its biases")
    p.add_argument("--no-learned-doppler", action="store_true",
                   help="fused: without the Doppler head's pseudorange-rate sigmas (the physical model's)")
    p.add_argument("--dnn-output", choices=("wls", "correction"), default=None,
                   help="dnn: learned-weight least squares or the paper's correction head (default: the checkpoint's)")
    p.add_argument("--raw-sigmas", action="store_true",
                   help="report each mode's covariance as it comes, without the windowed variance-factor "
                        "calibration (fusion/estimate/variance_factor.py); positions are the same either way")
    p.add_argument("--no-truth-height-fix", action="store_true",
                   help="keep GSDC 2021 truth heights as published (~63 m too high)")


def options_from_args(args: argparse.Namespace) -> RunOptions:
    """The :class:`RunOptions` of parsed :func:`add_run_options` arguments."""
    signals = parse_signals(args.signals)
    if args.dnn_passes < 1:
        raise GnssfuseError("--dnn-passes must be >= 1")
    if not 0.0 <= args.elev_mask < 90.0:
        raise GnssfuseError(f"--elev-mask {args.elev_mask:g}: an elevation mask is between 0 and 90 degrees")
    if args.clk is not None and args.sp3 is None:
        raise GnssfuseError("--clk needs --sp3 (precise clocks go with precise orbits)")
    for flag, paths in (("--nav", args.nav), ("--sp3", [args.sp3]), ("--clk", [args.clk])):
        for path in (p for p in paths if p is not None):
            if not Path(path).is_file():        # checked here: a trace that needs none would ignore it
                what = ("is a folder, not a file" if Path(path).is_dir() else "is not a regular file") \
                    if Path(path).exists() else "file not found"
                raise DataError(f"{path}: {flag} {what}")
    return RunOptions(weights=args.weights, elev_mask_deg=args.elev_mask, device=args.device,
                      dnn_passes=args.dnn_passes, signals=signals,
                      wls_robust=False if args.wls_plain else "exclude", learned_prior=not args.no_learned_prior,
                      learned_sigmas=not args.no_learned_sigmas,
                      learned_bias=not args.no_learned_bias, learned_doppler=not args.no_learned_doppler,
                      dnn_output=args.dnn_output,
                      sigma_calibration=not args.raw_sigmas, nav=tuple(args.nav), sp3=args.sp3, clk=args.clk,
                      iono_free=args.iono_free, graph=graph_config(args))


#: run options that act only in some modes: (attribute, flag, its default, the modes it acts in); the rest
#: (--wls-plain, --raw-sigmas, --signals, ...) act in every mode
MODE_FLAGS = (("incremental", "--incremental", False, ("fused-nodnn", "fused")),
              ("graph_config", "--graph-config", None, ("fused-nodnn", "fused")),
              ("no_doppler", "--no-doppler", False, ("fused-nodnn", "fused")),
              ("no_carrier", "--no-carrier", False, ("fused-nodnn", "fused")),
              ("odometry", "--odometry", False, ("fused-nodnn", "fused")),
              ("weights", "--weights", None, ("dnn", "fused")),
              ("dnn_passes", "--dnn-passes", 1, ("dnn",)),
              ("no_learned_prior", "--no-learned-prior", False, ("fused",)),
              ("no_learned_sigmas", "--no-learned-sigmas", False, ("fused",)),
              ("no_learned_bias", "--no-learned-bias", False, ("fused",)),
              ("no_learned_doppler", "--no-learned-doppler", False, ("fused",)),
              ("dnn_output", "--dnn-output", None, ("dnn",)))


def flags_without_effect(args: argparse.Namespace, modes: list[str]) -> list[str]:
    """The flags given (set away from their defaults) that act in none of ``modes``."""
    return [flag for attr, flag, default, acts_in in MODE_FLAGS
            if getattr(args, attr, default) != default and not set(acts_in) & set(modes)]


def graph_config(args: argparse.Namespace) -> GraphConfig:
    """The graph's settings: ``--graph-config`` (or the defaults), then the switches given as flags."""
    cfg = GraphConfig() if args.graph_config is None else load_graph_config(args.graph_config)
    flags = {"incremental": True} if args.incremental else {}
    flags.update({"use_doppler": False} if args.no_doppler else {})
    flags.update({"use_carrier": False} if args.no_carrier else {})
    flags.update({"use_odometry": True} if args.odometry else {})
    return replace(cfg, **flags)


def load_options(opts: RunOptions) -> dict:
    """Keyword arguments of :func:`fusion.prepare.load.load_trace` that come from the run options."""
    from fusion.prepare.raw_load import RawSources

    return {"signals": opts.signals, "raw_sources": RawSources(opts.nav, opts.sp3, opts.clk, opts.iono_free)}
