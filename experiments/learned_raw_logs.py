"""The learned part on logs the 2021 training files do not resemble: the Pixel5 RINEX test trace (C/N0, no
reported sigma, GPS broadcast navigation) and smartLoc Berlin (u-blox in a street canyon: C/N0, reported
sigma, GPS + GLONASS). No network trains on either (smartLoc serves to choose graph settings; the Pixel5 is a
test trace). Per log: wls, dnn, fused-nodnn, fused, and fused's parts alone (fused-prior: the learned prior
only; fused-sigmas: the learned per-satellite sigmas only; fused-nobias: fused without the per-satellite head's
biases), with the guard's counts (what it handed to the physical model, or read as missing / unknown, and why).
``--traces`` adds other trace folders (read with every signal, e.g. held-out simulated city traces).

    python experiments/learned_raw_logs.py [--weights W.pt] > experiments/results/learned_raw_logs.md
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from crossval import MODES as CROSSVAL_MODES  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
LOGS = {
    "Pixel5 RINEX (broadcast GPS)": (SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5",
                                     dict(nav=(SHARED / "ephemeris/gps_nav/hour1180.21n",), signals=None)),
    "smartLoc Berlin Potsdamer Platz": (SHARED / "smartloc/Berlin_Potsdamer_Platz", dict(signals=None)),
}
#: label -> (pipeline mode, RunOptions changes); dnn with the checkpoint's own output (the paper's head for
#: feature version 2 weights)
MODES = {"wls": CROSSVAL_MODES["wls"], "dnn": ("dnn", {}),
         **{k: CROSSVAL_MODES[k] for k in ("fused-nodnn", "fused", "fused-prior", "fused-sigmas", "fused-nobias")}}
def trace_logs(traces: list[Path]) -> dict[str, tuple[Path, dict]]:
    """``--traces`` folders as logs (label -> (folder, RunOptions changes)), each read with every signal."""
    return {str(t): (t, dict(signals=parse_signals("all"))) for t in traces}


GUARD_KEYS = ("epochs_guard_off", "epochs_guard_shrunk", "meas_out_of_range", "meas_cn0_unseen_in_training",
              "meas_signal_unseen_in_training", "meas_pr_sigma_out_of_range", "meas_unseen_signal")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", type=Path, default=None, help="checkpoint (default: the shipped weights)")
    p.add_argument("--logs", default=",".join(LOGS), help="which logs (comma-separated labels; '' for none)")
    p.add_argument("--traces", nargs="*", type=Path, default=[], help="more trace folders, read with every signal")
    p.add_argument("--modes", default=",".join(MODES), help="which modes (comma-separated labels)")
    args = p.parse_args(argv)
    for flag, given, known in (("--logs", args.logs, LOGS), ("--modes", args.modes, MODES)):
        unknown = [x for x in filter(None, given.split(",")) if x not in known]
        if unknown:
            p.error(f"{flag}: unknown {', '.join(unknown)} (known: {', '.join(known)})")
    logs = {name: LOGS[name] for name in filter(None, args.logs.split(","))}
    logs |= trace_logs(args.traces)
    print(f"weights: {args.weights or 'shipped'}\n")
    print("| log | mode | GSDC score [m] | h p50 | h p95 | epochs | s | guard |")
    print("|---|---|---|---|---|---|---|---|")
    for name, (path, kw) in logs.items():
        if not path.exists():
            print(f"| {name} | (not present: {path}) | | | | | | |")
            continue
        base = RunOptions(weights=args.weights, **kw)
        trace = load_trace(path, min_sats=1, **load_options(base))
        wls = solve_initial(trace, base)
        for label in args.modes.split(","):
            mode, change = MODES[label]
            t0 = time.perf_counter()
            res = run_modes(trace, [mode], replace(base, **change), wls=wls)[mode]
            dt = time.perf_counter() - t0
            m = mode_metrics(trace, res)
            guard = ", ".join(f"{k} {res.info['learned_' + k]}" for k in GUARD_KEYS if res.info.get("learned_" + k))
            print(f"| {name} | {label} | {m['gsdc_score']:.2f} | {m['h_p50']:.2f} | {m['h_p95']:.2f} | {m['n']} | "
                  f"{dt:.1f} | {guard} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
