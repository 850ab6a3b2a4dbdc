"""``gnssfuse simulate``: a simulated drive written with ground_truth.csv, in the GSDC 2021 derived format
or (with C/N0, Doppler, several signals) the 2022/23 device_gnss format (the simulator:
:mod:`fusion.sim.simulate`; the writers: :mod:`fusion.io.gsdc_write`, :mod:`fusion.sim.write`)."""
from __future__ import annotations

import argparse
from datetime import datetime
from pathlib import Path

from fusion.cli.common import out_folder
from fusion.errors import GnssfuseError
from fusion.gpstime import format_gps_ms, gps_ms_from_calendar
from fusion.io.truth import GSDC2021_TRUTH_HEIGHT_ERROR_M
from fusion.sim.config import SCENARIOS
from fusion.sim.simulate import DEFAULT_ORIGIN, DEFAULT_START_MS
from fusion.sim.write import FORMATS


def _parse_origin(text: str) -> tuple[float, float, float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"origin must be LAT,LON[,H] in degrees/metres, got {text!r}")
    if len(vals) not in (2, 3) or not (-90 <= vals[0] <= 90 and -180 <= vals[1] <= 360):
        raise argparse.ArgumentTypeError(f"origin must be LAT,LON[,H] with a valid lat/lon, got {text!r}")
    return (vals[0], vals[1], vals[2] if len(vals) == 3 else 0.0)


def _parse_start(text: str) -> int:
    if text.strip().lstrip("-").isdigit():
        return int(text)
    try:
        d = datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"start must be GPS ms or an ISO date-time (GPS time), got {text!r}")
    return gps_ms_from_calendar(d.year, d.month, d.day, d.hour, d.minute, d.second + d.microsecond * 1e-6)


def build_parser(prog: str = "gnssfuse simulate") -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description=(
        "Simulate GNSS measurements along a random drive (or a replayed GSDC 2021 ground-truth "
        "track) and write them with ground_truth.csv: GPS L1 pseudoranges in the GSDC 2021 derived "
        "format by default; --scenario adds GLONASS, Galileo, BeiDou, C/N0, Doppler and street canyons."))
    ap.add_argument("--out", required=True, type=Path, help="output root; writes OUT/COLLECTION/PHONE/")
    ap.add_argument("--origin", type=_parse_origin, default=DEFAULT_ORIGIN,
                    help="LAT,LON[,H] start of the random drive (default Mountain View, CA; H ellipsoidal)")
    ap.add_argument("--epochs", type=int, default=None,
                    help="number of epochs (default 600; a replayed track: all of it)")
    ap.add_argument("--rate", type=float, default=1.0, help="epochs per second (default 1)")
    ap.add_argument("--start", type=_parse_start, default=DEFAULT_START_MS,
                    help="start time: GPS ms or ISO date-time in GPS time (default 2021-04-28T20:00:00)")
    ap.add_argument("--bias-scenario", action="store_true",
                    help="multipath/NLOS: per epoch Poisson(1) satellites get a bias U[50,200] m")
    ap.add_argument("--sigma", type=float, default=None,
                    help="fixed pseudorange noise sigma [m] (default 6; scenarios: from C/N0)")
    ap.add_argument("--elevation-noise", action="store_true", help="scale sigma by 1/sin(elevation)")
    ap.add_argument("--elev-mask", type=float, default=None, help="elevation mask [deg] (default 5; scenarios 10)")
    ap.add_argument("--max-sats", type=int, default=None,
                    help="signals per epoch at most, 0 = all (default 10; scenarios: all)")
    ap.add_argument("--scenario", choices=sorted(SCENARIOS), default=None,
                    help="multi-constellation preset with C/N0, Doppler and street canyons: open, suburban, urban, deep")
    ap.add_argument("--carrier", action="store_true",
                    help="carrier phase too (AccumulatedDeltaRange; a slip where an arc breaks or a signal "
                         "turns reflected or back)")
    ap.add_argument("--broadcast-errors", action="store_true",
                    help="also the slowly varying range errors broadcast corrections leave (orbit and clock, "
                         "ionosphere, troposphere) on code and carrier")
    ap.add_argument("--constellations", default=None,
                    help="GPS,GLO,GAL,BDS or all (default GPS; scenarios all); no records in --nav: synthetic")
    ap.add_argument("--format", choices=FORMATS, default="auto",
                    help="output: gsdc2021 derived or device_gnss (2022/23, carries C/N0 and Doppler); "
                         "auto: device_gnss when the trace has either")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--nav", type=Path, default=None, metavar="FILE",
                    help="the simulator's ephemerides: one RINEX 2/3/4 nav file (default: the shipped GPS one)")
    ap.add_argument("--trajectory", type=Path, default=None,
                    help="replay this GSDC 2021 ground_truth.csv (re-timed to --start) instead")
    ap.add_argument("--trajectory-height-error", type=float, default=GSDC2021_TRUTH_HEIGHT_ERROR_M,
                    help="metres subtracted from replayed heights (default 63.1, the GSDC 2021 error)")
    ap.add_argument("--collection", default=None, help="collection name (default <date>-US-SIM-<seed>)")
    ap.add_argument("--phone", default="SimPhone", help="phone name (default SimPhone)")
    return ap


def _trajectory(args: argparse.Namespace, rng):
    """The drive to simulate: the replayed ``--trajectory`` (first ``--epochs``) or a random one."""
    from fusion.sim.trajectory import Trajectory, load_gsdc_trajectory, random_trajectory

    if args.trajectory is None:
        return random_trajectory(args.origin, args.epochs or 600, args.start, rng, rate_hz=args.rate)
    traj = load_gsdc_trajectory(args.trajectory, height_error_m=args.trajectory_height_error).retimed(args.start)
    if args.epochs is not None and args.epochs < len(traj):
        traj = Trajectory(traj.t_ms[:args.epochs], traj.ecef[:args.epochs], traj.name, dict(traj.skipped))
    return traj


def main(argv: list[str], prog: str = "gnssfuse simulate") -> int:
    import numpy as np

    from fusion.eval.summary import skip_words
    from fusion.sim.config import config_from_options
    from fusion.sim.simulate import _nav, simulate_trajectory
    from fusion.sim.write import write_trace

    ap = build_parser(prog)
    args = ap.parse_args(argv)
    if args.epochs is not None and args.epochs < 1:
        ap.error("--epochs must be >= 1")
    if args.seed < 0:
        ap.error(f"--seed must be >= 0, got {args.seed}")
    if not 0 < args.rate <= 100:
        ap.error(f"--rate: epochs per second in (0, 100], got {args.rate}")
    if not -1000 <= args.origin[2] <= 10_000:
        ap.error(f"--origin: a height of -1,000 to 10,000 m, got {args.origin[2]:g}")
    rng = np.random.default_rng(args.seed)
    try:
        cfg = config_from_options(args.scenario, args.constellations, sigma_m=args.sigma,
                                  elevation_noise=args.elevation_noise, elev_mask_deg=args.elev_mask,
                                  max_sats=args.max_sats, nlos=args.bias_scenario,
                                  carrier=args.carrier, broadcast_errors=args.broadcast_errors)
        cfg.validate()
        traj = _trajectory(args, rng)
    except ValueError as exc:
        if isinstance(exc, GnssfuseError):
            raise
        ap.error(str(exc))
    out = out_folder(args.out)
    res = simulate_trajectory(traj, nav=_nav(args.nav, cfg), config=cfg, seed=rng)
    collection = args.collection or f"{format_gps_ms(args.start)[:10]}-US-SIM-{args.seed}"
    paths = write_trace(res, out, collection, args.phone, args.format)
    tr = res.trace
    print(f"simulated {tr.n_epochs} epochs, {tr.n_sats.mean():.1f} satellites/epoch "
          f"(skipped: {skip_words(tr.skipped)}) -> {' , '.join(map(str, paths))}")
    return 0
