"""The learned sigmas' power in the graph (``GraphConfig.learned_sigma_power``) on the raw logs: the Pixel5
RINEX test trace (GPS broadcast navigation; reported only) and smartLoc Berlin (never trained on). Per log and
network, ``fused-nodnn`` once and ``fused`` at each power; the GSDC drives' figures come from
``experiments/crossval.py --reuse --graph-config`` (``experiments/results/sigma_power.md``).

    python experiments/sigma_power.py --powers 1,2,3,4 [--weights A.pt B.pt ...] [--traces DIR ...] [--no-logs]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from experiments.learned_raw_logs import LOGS, trace_logs  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402


def scores(path: Path, kw: dict, weights: Path | None, powers: list[float]) -> list[float]:
    """GSDC score [m] of fused-nodnn, then of fused at each power, on one log."""
    base = RunOptions(weights=weights, sigma_calibration=False, **kw)
    trace = load_trace(path, min_sats=1, **load_options(base))
    wls = solve_initial(trace, base)
    out = [mode_metrics(trace, run_modes(trace, ["fused-nodnn"], base, wls=wls)["fused-nodnn"])["gsdc_score"]]
    for p in powers:
        opts = replace(base, graph=replace(base.graph, learned_sigma_power=p))
        out.append(mode_metrics(trace, run_modes(trace, ["fused"], opts, wls=wls)["fused"])["gsdc_score"])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--powers", default="1,2,3,4")
    p.add_argument("--weights", type=Path, nargs="*", default=[None], help="checkpoints (default: the shipped one)")
    p.add_argument("--traces", nargs="*", type=Path, default=[],
                   help="more trace folders, read with every signal (e.g. held-out simulated city traces)")
    p.add_argument("--no-logs", action="store_true", help="only the --traces, not the Pixel5 and smartLoc")
    args = p.parse_args(argv)
    powers = [float(x) for x in args.powers.split(",")]
    print("| log | weights | fused-nodnn | " + " | ".join(f"fused, power {x:g}" for x in powers) + " |")
    print("|---|---|---|" + "---|" * len(powers))
    logs = {} if args.no_logs else dict(LOGS)
    logs |= trace_logs(args.traces)
    for name, (path, kw) in logs.items():
        if not path.exists():
            continue
        for w in args.weights:
            s = scores(path, kw, w, powers)
            cells = [f"{s[0]:.2f}"] + [f"{x:.2f} ({x / s[0]:.3f} x)" for x in s[1:]]
            print(f"| {name} | {w or 'shipped'} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
