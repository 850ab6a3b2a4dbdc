"""How `fused`'s reported sigmas hold where a real phone meets buildings: the Pixel5 RINEX test trace laid in the
simulated street canyons of ``experiments/canyon_on_phone.py``, each axis's share of errors within 1 sigma with the
carrier-tied epochs' own setting (:data:`fusion.estimate.variance_factor.CARRIER_DEFAULTS`) and without it. A test
trace: reported, nothing chosen on it (``experiments/results/carrier_calibration.md``). The first row is the log
as it was written, without streets.

    python experiments/canyon_calibration.py [--seeds 0 1 2] [--sp3]

``--sp3``: CODE's multi-GNSS SP3/CLK instead of the broadcast GPS file (as ``canyon_on_phone.py --sp3``).
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from canyon_on_phone import DEEP, NAV, PIXEL5, in_canyon  # noqa: E402
from pixel5_table import ORBITS  # noqa: E402
from fusion.eval.metrics import mode_metrics, trace_errors  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import CanyonModel  # noqa: E402

#: the streets of canyon_on_phone.py's two runs: its default and the deep one (--height 30 100 --width 12 25)
STREETS = {"ordinary": CanyonModel(), "deep": DEEP}


def fused_with_and_without(trace, opts: RunOptions) -> tuple[dict, dict]:
    """``fused``'s :func:`~fusion.eval.metrics.mode_metrics` without and with CARRIER_DEFAULTS (the positions are
    the same either way) and, with them, the signed mean and spread of its NED errors [m] (``mean_*``, ``sd_*``)
    and how many epochs took the carrier setting (``carrier_calibrated``)."""
    wls = solve_initial(trace, opts)
    general = replace(opts, carrier_sigma_calibration=False)
    before = mode_metrics(trace, run_modes(trace, ["fused"], general, wls=wls)["fused"])
    res = run_modes(trace, ["fused"], opts, wls=wls)["fused"]
    err = trace_errors(trace, res)
    err = err[np.isfinite(err).all(axis=1)]
    after = dict(mode_metrics(trace, res), carrier_calibrated=int(res.info.get("carrier_calibrated", 0)),
                 **{f"mean_{a}": err[:, i].mean() for i, a in enumerate("ned")},
                 **{f"sd_{a}": err[:, i].std() for i, a in enumerate("ned")})
    return before, after


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--sp3", action="store_true", help="multi-GNSS SP3/CLK instead of broadcast GPS")
    args = p.parse_args()
    orbits = ORBITS["CODE SP3/CLK, multi-GNSS (+ hour1180.21n ionosphere)"] if args.sp3 else {"nav": (NAV,)}
    opts = RunOptions(signals=parse_signals(None), **orbits)
    trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    fmt = lambda m, key: " / ".join(f"{m[f'{key}_{a}']:.2f}" for a in "ned")  # noqa: E731
    print("| streets | seed | fused without the carrier setting | with it | carrier-calibrated epochs "
          "| error mean N / E / D [m] | error spread [m] |")
    print("|---|---|---|---|---|---|---|")
    rows = [("as logged", "-", trace)] + [(name, seed, in_canyon(trace, model, seed)[0])
                                          for name, model in STREETS.items() for seed in args.seeds]
    for name, seed, tr in rows:
        before, after = fused_with_and_without(tr, opts)
        print(f"| {name} | {seed} | {fmt(before, 'within1sigma')} | {fmt(after, 'within1sigma')} | "
              f"{after['carrier_calibrated']} | {fmt(after, 'mean')} | {fmt(after, 'sd')} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
