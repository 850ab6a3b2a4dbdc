"""Where the graph without the network cannot place an epoch, should the network's prior place it?

``fused`` asks the network at the graph without anything learned; where that graph leaves an epoch unsolved (a
motion component with no epoch of four satellites: a dual-frequency phone's two or three satellites give the
network the four pseudoranges it needs, the graph too few), the guess there is the WLS track interpolated across
the gap, and the network's prior alone would place the epoch. Since 2026-12-07 the prior is withheld there
(``learned.modes.prior_where_determined``). This prints, per trace, ``fused-nodnn`` and ``fused`` with the prior
withheld (the default) and kept (the code before), their GSDC scores over the epochs each solved and the
horizontal error of the epochs only the kept prior placed, with and without Doppler and carrier; and the epochs
of fewer than 4 satellites each flags bridged (``fused`` flags them where its prior holds them too, since
2026-12-07: ``learned.modes.flag_few_satellites``) with the share of ``fused``'s errors within its 1 sigma there.

    python experiments/sim_city_traces.py --held-out --scenarios deep --first-seed 700 --carrier \\
        --constellations GPS --out /tmp/simgpsdeep
    python experiments/prior_undetermined.py /tmp/simgpsdeep/*/SimPhone [--signals all]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import learned.modes  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.geometry import ecef2ned_cov, ecef2ned_vec  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

WITHHOLD = learned.modes.prior_where_determined


def fused_kept_prior(trace, opts: RunOptions):
    """``fused`` as before: the network's prior wherever it was asked."""
    learned.modes.prior_where_determined = lambda inputs, solved: inputs
    try:
        return run_modes(trace, ["fused"], opts)["fused"]
    finally:
        learned.modes.prior_where_determined = WITHHOLD


def h_error(res, truth: np.ndarray) -> np.ndarray:
    """(E,) horizontal error [m], NaN where unsolved."""
    e = np.full(len(truth), np.nan)
    ok = res.valid
    d = ecef2ned_vec(res.pos[ok] - truth[ok], truth[ok])
    e[ok] = np.hypot(d[:, 0], d[:, 1])
    return e


def within_sigma(res, truth: np.ndarray, rows: np.ndarray) -> str:
    """Share of |error| within the 1-sigma N / E / D at the solved ``rows`` (E,) bool."""
    ok = rows & res.valid
    if not ok.any():
        return "-"
    d = ecef2ned_vec(res.pos[ok] - truth[ok], truth[ok])
    s = np.sqrt(np.diagonal(ecef2ned_cov(res.cov[ok], res.pos[ok]), axis1=1, axis2=2))
    return " / ".join(f"{v:.2f}" for v in (np.abs(d) <= s).mean(axis=0))


def row(trace, opts: RunOptions) -> str:
    """One table row: scores [m] and solved epochs of fused-nodnn, fused (withheld), fused (kept), the
    median / 95th percentile error of the epochs only the kept prior placed, the bridged flags of fused-nodnn and
    fused, and fused's errors within 1 sigma where it flags."""
    res = run_modes(trace, ["fused-nodnn", "fused"], opts)
    res["kept"] = fused_kept_prior(trace, opts)
    score = {m: mode_metrics(trace, r)["gsdc_score"] for m, r in res.items()}
    only = res["kept"].valid & ~res["fused-nodnn"].valid
    e = h_error(res["kept"], trace.truth)[only]
    extra = f"{np.percentile(e, 50):.1f} / {np.percentile(e, 95):.1f}" if e.size else "-"
    n = {m: int(r.valid.sum()) for m, r in res.items()}
    flags = f"{res['fused-nodnn'].info['epochs_bridged']} / {res['fused'].info['epochs_bridged']}"
    return (f"| {score['fused-nodnn']:.2f} ({n['fused-nodnn']}) | {score['fused']:.2f} ({n['fused']}) | "
            f"{score['kept']:.2f} ({n['kept']}) | {res['fused'].info.get('learned_prior_withheld', 0)} | {extra} | "
            f"{flags} | {within_sigma(res['fused'], trace.truth, res['fused'].info['bridged'])} |")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("traces", nargs="+", type=Path)
    p.add_argument("--signals", default="all", help="as gnssfuse run --signals (default: every signal)")
    a = p.parse_args()
    opts = RunOptions(signals=parse_signals(a.signals))
    print("GSDC score [m] over the epochs each solved (solved epochs); 'only the kept prior': horizontal error "
          "p50 / p95 [m] of the epochs the kept prior alone placed; 'bridged': epochs flagged, fused-nodnn / fused; "
          "'fused within 1 sigma': N / E / D at the epochs fused flags\n")
    print("| trace | measurements | fused-nodnn | fused, prior withheld (default) | fused, prior kept (before) "
          "| epochs withheld | only the kept prior | bridged | fused within 1 sigma, bridged |")
    print("|---|---|---|---|---|---|---|---|---|")
    for path in a.traces:
        trace = load_trace(path, signals=opts.signals)
        name = f"{path.parent.name}/{path.name}"
        for words, o in (("Doppler + carrier", opts),
                         ("pseudoranges only", replace(opts, graph=replace(opts.graph, use_doppler=False,
                                                                           use_carrier=False)))):
            print(f"| {name} | {words} {row(trace, o)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
