"""Example 1: snapshot (WLS, DNN) and fused (factor graph) positioning on the shipped Android trace.

    python examples/01_snapshot_and_fused.py                 # whole trace, all modes
    python examples/01_snapshot_and_fused.py --max-epochs 200 --weights my.pt

Every mode gets the same trace and the same WLS solution (receiver clock estimated, never taken from
truth); the truth is used only for the printed accuracy table. A mode that cannot run here (its module
or the DNN weights are missing) is reported as unavailable, not faked.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from fusion.errors import CheckpointError, GnssfuseError, ModeUnavailableError  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.eval.metrics import format_table, mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial
from fusion.run_types import RunOptions

SHIPPED = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
MODES = ("wls", "dnn", "fused-nodnn", "fused")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trace", type=Path, default=SHIPPED, help="a <collection>/<phone> folder")
    ap.add_argument("--max-epochs", type=int, default=None, help="first N epochs only (quick look)")
    ap.add_argument("--weights", type=Path, default=None, help="DNN checkpoint (default: shipped)")
    ap.add_argument("--modes", default=",".join(MODES))
    args = ap.parse_args(argv)

    # min_sats=1, as `gnssfuse run` loads: epochs with 1-3 satellites reach the modes; WLS and dnn leave
    # them unsolved, the fused modes carry them on motion (and the prior)
    trace = load_trace(args.trace, min_sats=1)
    if args.max_epochs:
        trace = trace.select(np.arange(min(args.max_epochs, trace.n_epochs)))
    opts = RunOptions(weights=args.weights)
    wls = solve_initial(trace, opts)          # one WLS, shared by every mode
    print(f"{trace.name}: {trace.n_epochs} epochs, {int(wls.valid.sum())} solved by WLS")

    rows, unavailable, failed = {}, {}, {}
    for mode in args.modes.split(","):
        try:
            result = run_modes(trace, [mode], opts, wls=wls)[mode]
        except (ModeUnavailableError, CheckpointError) as exc:  # no torch / no weights
            unavailable[mode] = f"{type(exc).__name__}: {exc}"
            continue
        except GnssfuseError as exc:                   # a real failure on this trace
            failed[mode] = str(exc)
            continue
        rows[mode] = mode_metrics(trace, result)
    print(format_table(rows))
    for mode, why in unavailable.items():
        print(f"mode {mode} unavailable: {why}")
    for mode, why in failed.items():
        print(f"mode {mode} FAILED: {why}")
    return 1 if failed or not rows else 0


if __name__ == "__main__":
    sys.exit(main())
