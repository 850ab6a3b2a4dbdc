"""Doppler and carrier gated per stretch by the graph on pseudoranges alone: does it keep them from making the
graph worse? (``experiments/results/doppler_carrier.md``, last section; not adopted.)

The idea: ``fused-nodnn`` with Doppler and carrier, and again on pseudoranges alone (each with its calibrated
sigmas). Where the two disagree on a horizontal axis by more than ``--k`` times their combined sigma, the
Doppler and carrier of those epochs, and of every epoch within ``--window`` s of one, are down-weighted
(sigmas x ``--scale``; 0 drops them) and the graph is solved again. Each trace's GSDC score [m] with
pseudoranges only, with Doppler and carrier, and gated; truth scores only.

    python experiments/doppler_gate.py TRACE_DIR... [--k 2] [--scale 3] [--window 10] --signals all
    python experiments/doppler_gate.py --pixel5-canyon     # the Pixel5 test trace in deep streets: reported only
"""
from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from fusion.estimate.graph.bridged_check import disagreement  # noqa: E402
from fusion.estimate.graph.fuse import estimate_fused_nodnn  # noqa: E402
from fusion.estimate.variance_factor import centred_sums  # noqa: E402
from fusion.eval.metrics import summarize, trace_errors  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.options import add_signals_option, load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import ModeResult, RunOptions  # noqa: E402
from fusion.trace import Trace  # noqa: E402


@dataclass(frozen=True)
class Gate:
    k: float = 2.0          # disagreement threshold, in combined calibrated sigmas
    scale: float = 3.0      # Doppler and carrier sigma multiplier where gated (0: dropped)
    window_s: float = 10.0  # how far the gate reaches from a disagreeing epoch


def disagreeing(a: ModeResult, b: ModeResult, k: float) -> np.ndarray:
    """(E,) bool epochs both solved where a horizontal axis differs by more than ``k`` combined sigmas."""
    out = np.zeros(len(a.valid), bool)
    rows, _, beyond = disagreement(a, b, np.ones(len(a.valid), bool), k)
    out[rows] = beyond[:, :2].any(axis=1)
    return out


def within(t_s: np.ndarray, rows: np.ndarray, window_s: float) -> np.ndarray:
    """(E,) bool epochs within ``window_s`` of a ``rows`` epoch; ``t_s`` (E,) sorted times [s]."""
    return centred_sums(t_s, rows, 2 * window_s) > 0


def down_weighted(trace: Trace, rows: np.ndarray, scale: float) -> Trace:
    """``trace`` with the Doppler and carrier of ``rows`` (E,) sigmas x ``scale`` (0: marked unusable)."""
    out = {}
    for sig, ok in (("prr_sigma", "prr_ok"), ("adr_sigma", "adr_ok")):
        if getattr(trace, sig) is None:
            continue
        if scale == 0:
            out[ok] = getattr(trace, ok) & ~rows[:, None]
        else:
            out[sig] = np.where(rows[:, None], getattr(trace, sig) * scale, getattr(trace, sig))
    return replace(trace, **out)


def scores(trace: Trace, opts: RunOptions, gate: Gate) -> dict:
    """GSDC scores of the three graphs, and the epochs gated."""
    wls = solve_initial(trace, opts)
    both = estimate_fused_nodnn(trace, wls, opts)
    plain = estimate_fused_nodnn(trace, wls, replace(opts, graph=replace(opts.graph, use_doppler=False,
                                                                          use_carrier=False)))
    rows = within(trace.t_ms / 1000.0, disagreeing(both, plain, gate.k), gate.window_s)
    gated = estimate_fused_nodnn(down_weighted(trace, rows, gate.scale), wls, opts) if rows.any() else both
    s = {name: summarize(trace_errors(trace, r))["gsdc_score"] for name, r in
         (("pseudoranges only", plain), ("Doppler and carrier", both), ("gated", gated))}
    return s | {"gated epochs": f"{int(rows.sum())}/{trace.n_epochs}"}


def folder_row(path: str, opts: RunOptions, gate: Gate) -> tuple[str, dict]:
    trace = load_trace(path, min_sats=1, **load_options(opts))
    return trace.name, scores(trace, opts, gate)


def canyon_rows(gate: Gate) -> list[tuple[str, dict]]:
    """The Pixel5 test trace with broadcast GPS, in the deep streets of ``canyon_on_phone.md`` (seeds 0-2)."""
    from canyon_on_phone import DEEP, in_canyon
    from few_satellites import NAV, PIXEL5

    opts = RunOptions(signals=None, nav=(NAV,))
    trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    return [(f"Pixel5, deep streets seed {s}", scores(in_canyon(trace, DEEP, s)[0], opts, gate)) for s in range(3)]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("traces", nargs="*")
    p.add_argument("--k", type=float, default=2.0)
    p.add_argument("--scale", type=float, default=3.0)
    p.add_argument("--window", type=float, default=10.0)
    add_signals_option(p, "default: the format's (GSDC-format simulated traces: GPS L1; give all)")
    p.add_argument("--pixel5-canyon", action="store_true")
    p.add_argument("--jobs", type=int, default=2)
    args = p.parse_args()
    gate = Gate(args.k, args.scale, args.window)
    opts = RunOptions(signals=parse_signals(args.signals))
    if args.pixel5_canyon:
        rows = canyon_rows(gate)
    else:
        with ProcessPoolExecutor(args.jobs) as ex:
            rows = list(ex.map(partial(folder_row, opts=opts, gate=gate), args.traces))
    print(f"k {gate.k}, scale {gate.scale}, window {gate.window_s} s\n")
    keys = ["pseudoranges only", "Doppler and carrier", "gated"]
    print("| trace | " + " | ".join(keys) + " | D+C / PR | gated / PR | gated epochs |")
    print("|---|" + "---|" * (len(keys) + 3))
    ratios = []
    for name, s in rows:
        r = (s[keys[1]] / s[keys[0]], s[keys[2]] / s[keys[0]])
        ratios.append(r)
        print(f"| {name} | " + " | ".join(f"{s[k]:.2f}" for k in keys) + f" | {r[0]:.3f} | {r[1]:.3f} | "
              f"{s['gated epochs']} |")
    r = np.array(ratios)
    print(f"\nmean D+C / PR {r[:, 0].mean():.3f}, gated / PR {r[:, 1].mean():.3f}; worse than PR: "
          f"{int((r[:, 0] > 1).sum())} and {int((r[:, 1] > 1).sum())} of {len(r)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
