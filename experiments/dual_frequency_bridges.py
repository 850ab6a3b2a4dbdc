"""Few satellites on two frequencies: which epochs the graph calls bridged, and which get the tighter walk.

A bridged epoch (flagged, counted, its calibrated sigmas widened where no Doppler measures the velocity) is one
whose position no prior and fewer than 4 satellites' pseudoranges fix; a second frequency adds a pseudorange
but no direction. ``GraphConfig.bridged_accel_scale`` (the velocity walk into epochs only the motion model
places) was tuned on single-frequency logs, where 4 pseudoranges are 4 satellites. Three rules, on the
held-out simulated city traces (every signal: GPS L1/L5, Galileo E1/E5a, GLONASS, BeiDou) thinned to 3
satellites, all their signals, in 120 s of every 180 s (``experiments/few_satellites.py``), pseudoranges only
(``fused-nodnn``, no Doppler or carrier: the graphs with Doppler are the same under all three, since there
Doppler measures the velocity):

- ``pseudoranges``: the flag and the walk by the count of pseudoranges (the code before 2026-11-28);
- ``shipped``: the flag by satellites, the walk by pseudoranges;
- ``satellites``: both by satellites.

Per trace: epochs bridged, GSDC score, and the share of |error| within the calibrated 1 sigma N / E / D over the
thinned stretches (the truth for scoring only). ``--with-doppler``: instead, the shipped graph with Doppler and
carrier, and those shares on its bridged epochs and on the others (pooled last).

    python experiments/sim_city_traces.py --out /tmp/simho --held-out
    python experiments/sim_city_traces.py --out /tmp/simdeepho --held-out --scenarios deep --first-seed 300
    python experiments/dual_frequency_bridges.py /tmp/simdeepho/*/SimPhone /tmp/simho/*/SimPhone [--with-doppler]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import fusion.estimate.graph.build as build  # noqa: E402
import fusion.estimate.graph.fuse as fuse  # noqa: E402
import fusion.estimate.graph.inputs as inputs  # noqa: E402
import fusion.estimate.graph.vector_graph as vector_graph  # noqa: E402
from few_satellites import thinned  # noqa: E402
from fusion.eval.metrics import mode_metrics, sigma_ratios, trace_errors  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHIPPED_GAP, SHIPPED_WALK = inputs.pseudorange_gap, inputs.motion_only


def gap_by_pseudoranges(inp):
    """(E,) bool: fewer than 4 pseudoranges and no prior (the rule before)."""
    return (inp.sel.sum(axis=1) < 4) & ~inp.prior_ok


def walk_by_satellites(inp):
    """(E,) bool: fewer than 4 satellites, no prior, no Doppler."""
    return SHIPPED_GAP(inp) & ~inputs.doppler_epochs(inp)


RULES = {"pseudoranges": (gap_by_pseudoranges, SHIPPED_WALK), "shipped": (SHIPPED_GAP, SHIPPED_WALK),
         "satellites": (SHIPPED_GAP, walk_by_satellites)}


def use_rule(name: str) -> None:
    """Point the graph's modules at rule ``name``'s bridged flag and walk."""
    gap, walk = RULES[name]
    fuse.pseudorange_gap = gap
    for module in (build, vector_graph):
        module.motion_only = walk


def row(trace, opts: RunOptions, thin: np.ndarray) -> list[str]:
    """Epochs bridged, GSDC score and the thinned stretches' share within 1 sigma, per rule."""
    wls = solve_initial(trace, opts)
    out = []
    for name in RULES:
        use_rule(name)
        res = run_modes(trace, ["fused-nodnn"], opts, wls=wls)["fused-nodnn"]
        err = trace_errors(trace, res)
        z = sigma_ratios(err[thin], res.pos[thin], res.cov[thin])
        out += [str(res.info["epochs_bridged"]), f"{mode_metrics(trace, res)['gsdc_score']:.2f}", within(z)]
    use_rule("shipped")
    return out


def within(z: np.ndarray) -> str:
    """Share of (N,3) |error| / sigma within 1, N / E / D."""
    return " / ".join(f"{x:.2f}" for x in (z <= 1.0).mean(axis=0))


def with_doppler(traces: list[str], keep: int) -> None:
    """The shipped graph with Doppler and carrier: shares within 1 sigma on bridged and other epochs."""
    opts = RunOptions(signals=parse_signals("all"))
    print("| trace | score [m] | bridged | bridged: within 1 sigma N / E / D | others: within 1 sigma N / E / D |")
    print("|---|---|---|---|---|")
    pooled = {"bridged": [], "others": []}
    for d in traces:
        trace, _ = thinned(load_trace(d, min_sats=1, **load_options(opts)), keep, 0)
        res = run_modes(trace, ["fused-nodnn"], opts)["fused-nodnn"]
        err, bridged = trace_errors(trace, res), res.info["bridged"]
        z = {k: sigma_ratios(err[rows], res.pos[rows], res.cov[rows])
             for k, rows in (("bridged", bridged), ("others", ~bridged & res.valid))}
        for k in z:
            pooled[k].append(z[k])
        print(f"| {Path(d).parent.name} | {mode_metrics(trace, res)['gsdc_score']:.2f} | {int(bridged.sum())} | "
              f"{within(z['bridged'])} | {within(z['others'])} |", flush=True)
    print(f"| pooled | | | {within(np.concatenate(pooled['bridged']))} | {within(np.concatenate(pooled['others']))} |")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("traces", nargs="+", help="simulated trace folders (experiments/sim_city_traces.py)")
    p.add_argument("--keep", type=int, default=3, help="satellites left in the thinned stretches")
    p.add_argument("--with-doppler", action="store_true", help="the shipped graph with Doppler and carrier")
    args = p.parse_args()
    if args.with_doppler:
        with_doppler(args.traces, args.keep)
        return 0
    base = RunOptions(signals=parse_signals("all"))
    opts = replace(base, graph=replace(base.graph, use_doppler=False, use_carrier=False))
    head = [f"{r}: {c}" for r in RULES for c in ("bridged", "score [m]", "within 1 sigma N / E / D")]
    print("| trace | " + " | ".join(head) + " |\n|---|" + "---|" * len(head))
    scores = []
    for d in args.traces:
        trace, thin = thinned(load_trace(d, min_sats=1, **load_options(opts)), args.keep, 0)
        cells = row(trace, opts, thin)
        scores.append([float(c) for c in cells[1::3]])
        print(f"| {Path(d).parent.name} | " + " | ".join(cells) + " |", flush=True)
    s = np.array(scores)
    ratio = s / s[:, :1]
    print("\nmean score [m]: " + ", ".join(f"{r} {m:.2f}" for r, m in zip(RULES, s.mean(axis=0))))
    print("geometric mean x pseudoranges: " + ", ".join(
        f"{r} {np.exp(np.log(c).mean()):.3f} ({(c > 1).sum()} of {len(c)} worse)" for r, c in zip(RULES, ratio.T)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
