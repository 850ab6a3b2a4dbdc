"""Are the sigmas of bridged epochs with Doppler honest, with and without their check against the graph without
Doppler and carrier (``GraphConfig.bridged_check_sigmas``, :mod:`fusion.estimate.graph.bridged_check`)?

``fused-nodnn`` with Doppler and carrier, calibrated; per trace the bridged epochs whose motion Doppler or
carrier measured, how many the check widened, and the share of |error| within 1 sigma N / E / D there without
and with the check (the truth for scoring only; positions are the same). The held-out simulated city traces,
every signal, thinned to 3 and to 2 satellites in 120 s of every 180 s (``experiments/few_satellites.py``), are
the tuning logs; ``--pixel5`` reports the Pixel5 RINEX test trace (broadcast GPS) seen from the seeded
ordinary and deep street canyons of ``experiments/canyon_on_phone.py``.

    python experiments/bridged_check.py /tmp/simdeepho/*/SimPhone /tmp/simho/*/SimPhone
    python experiments/bridged_check.py --pixel5
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from canyon_on_phone import DEEP, in_canyon  # noqa: E402
from few_satellites import NAV, PIXEL5, thinned  # noqa: E402
from fusion.estimate.graph.bridged_check import bridged_with_doppler  # noqa: E402
from fusion.eval.metrics import sigma_ratios, trace_errors  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import CanyonModel  # noqa: E402

BAND = (0.55, 0.80)


def shares(trace, opts: RunOptions) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Bridged epochs with Doppler, those widened, and (3,) shares within 1 sigma there without / with the check."""
    wls = solve_initial(trace, opts)
    out = []
    for n_sigma in (0.0, opts.graph.bridged_check_sigmas):
        res = run_modes(trace, ["fused-nodnn"], replace(opts, graph=replace(opts.graph, bridged_check_sigmas=n_sigma)),
                        wls=wls)["fused-nodnn"]
        rows = bridged_with_doppler(res)
        z = sigma_ratios(trace_errors(trace, res)[rows], res.pos[rows], res.cov[rows])
        out.append((z <= 1.0).mean(axis=0) if len(z) else np.full(3, np.nan))
    return int(rows.sum()), int(res.info.get("bridged_widened", 0)), out[0], out[1]


def fmt(a: np.ndarray) -> str:
    return " / ".join(f"{x:.2f}" for x in a)


def cases(args) -> list[tuple[str, object, RunOptions]]:
    """(name, trace, options) of the simulated traces thinned, or of the Pixel5 in canyons."""
    if args.pixel5:
        opts = RunOptions(nav=(NAV,))
        trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
        return [(f"Pixel5, {name} canyon, streets seed {seed}", in_canyon(trace, model, seed)[0], opts)
                for name, model in (("ordinary", CanyonModel()), ("deep", DEEP)) for seed in (0, 1, 2)]
    opts = RunOptions(signals=parse_signals("all"))
    out = []
    for d in args.traces:
        trace = load_trace(d, min_sats=1, **load_options(opts))
        out += [(f"{Path(d).parent.name}, {k} satellites", thinned(trace, k, 0)[0], opts) for k in (3, 2)]
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("traces", nargs="*", help="simulated trace folders (experiments/sim_city_traces.py)")
    p.add_argument("--pixel5", action="store_true", help="the Pixel5 test trace in street canyons (report)")
    args = p.parse_args()
    print("| trace | bridged with Doppler | widened | within 1 sigma N / E / D, no check | with the check |")
    print("|---|---|---|---|---|")
    before, after = [], []
    for name, trace, opts in cases(args):
        n, widened, off, on = shares(trace, opts)
        before.append(off)
        after.append(on)
        print(f"| {name} | {n} | {widened} | {fmt(off)} | {fmt(on)} |", flush=True)
    for label, a in (("no check", np.array(before)), ("with the check", np.array(after))):
        ok = a[np.isfinite(a).all(axis=1)]
        inside = ((ok >= BAND[0]) & (ok <= BAND[1])).sum()
        print(f"\n{label}: mean {fmt(ok.mean(axis=0))}; {inside} of {ok.size} trace-axes within {BAND[0]}-{BAND[1]}, "
              f"{(ok < BAND[0]).sum()} below, {(ok > BAND[1]).sum()} above")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
