"""Three satellites on two frequencies in WLS: satellites, not slots, decide "three" and "four".

WLS solves an epoch of exactly three satellites with the receiver clock interpolated from the valid epochs
within 3 s on both sides (:mod:`fusion.estimate.clock_bridge`). It used to count slots: three satellites on
two frequencies are six slots, so such an epoch went to the four-unknown fit, whose rank is three, and was
refused as ``degenerate``; two satellites on two frequencies (four slots) too. Counting satellites, the first is
solved as a single-frequency three-satellite epoch is, and the second is ``few_sats``.

The held-out simulated city traces (every signal: GPS L1/L5, Galileo E1/E5a, GLONASS, BeiDou), thinned to 3
satellites (all their signals) for 2 s of every 6 s (``--good 4 --period 6``: short gaps, where a clock can be
interpolated) or for 120 s of every 180 s (the defaults of ``experiments/few_satellites.py``). Per trace: the
epochs WLS solves and its GSDC score over them, and `fused-nodnn`'s score, counting slots (every slot given
satellite number 0, which counts as a satellite of its own) and satellites (the code since 2026-11-27).

    python experiments/sim_city_traces.py --out /tmp/simho --held-out
    python experiments/sim_city_traces.py --out /tmp/simdeepho --held-out --scenarios deep --first-seed 300
    python experiments/dual_frequency_wls.py /tmp/simdeepho/*/SimPhone /tmp/simho/*/SimPhone [--good 4 --period 6]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from few_satellites import thinned  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402


def row(trace, opts: RunOptions) -> str:
    """'WLS epochs | WLS score | fused-nodnn score' of one way of counting."""
    res = run_modes(trace, ["wls", "fused-nodnn"], opts)
    w = res["wls"]
    return (f"{int(w.valid.sum())} | {mode_metrics(trace, w)['gsdc_score']:.2f} | "
            f"{mode_metrics(trace, res['fused-nodnn'])['gsdc_score']:.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("traces", nargs="+", help="<collection>/<phone> folders of simulated traces")
    ap.add_argument("--good", type=float, default=60.0, help="seconds of each period left whole")
    ap.add_argument("--period", type=float, default=180.0)
    args = ap.parse_args(argv)
    opts = RunOptions(signals=parse_signals("all"))
    print(f"Thinned to 3 satellites for {args.period - args.good:g} s of every {args.period:g} s.\n")
    print("| trace | epochs | slots: WLS solved | WLS score [m] | fused-nodnn [m] "
          "| satellites: WLS solved | WLS score [m] | fused-nodnn [m] |")
    print("|---|---|---|---|---|---|---|---|")
    for d in args.traces:
        trace = load_trace(d, min_sats=1, **load_options(opts))
        th, _ = thinned(trace, 3, seed=1, good_s=args.good, period_s=args.period)
        slots = replace(th, sat_id=np.zeros_like(th.sat_id))
        print(f"| {Path(d).parent.name} | {th.n_epochs} | {row(slots, opts)} | {row(th, opts)} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
