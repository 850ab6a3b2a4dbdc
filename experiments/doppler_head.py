"""What the learned Doppler head (``learned/doppler_head.py``) buys, on its own.

The only traces with Doppler and ground truth here are the eight simulated city traces of
``experiments/sim_city_traces.py`` (four tracks, each replayed urban and suburban) and the Pixel5 RINEX test
trace (never trained on). So:

- leave-track-out on the simulated traces: a head trained on the six traces of three tracks, evaluated on the
  two of the fourth (``fused-nodnn``, and the same graph with the head's Doppler sigmas and nothing else
  learned);
- the Pixel5 RINEX trace (GPS broadcast navigation), with a head trained on all eight simulated traces:
  ``fused-nodnn`` with and without the head, and ``fused`` (the shipped network) with and without it.

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/doppler_head.py --sim /tmp/sim
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.estimate.graph.fuse import fuse  # noqa: E402
from fusion.estimate.graph.priors import LearnedGraphInputs  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.checkpoint import load_model, save_checkpoint  # noqa: E402
from learned.doppler_head import DopplerNoise  # noqa: E402
from learned.doppler_train import HeadConfig, fit, head_dict, trace_rows  # noqa: E402
from learned.infer import SHIPPED_WEIGHTS  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
PIXEL5 = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
NAV = SHARED / "ephemeris/gps_nav/hour1180.21n"


def train_head(rows: dict[str, dict], names: list[str]) -> dict:
    part = {k: np.concatenate([rows[n][k] for n in names]) for k in rows[names[0]]}
    cfg = HeadConfig()
    net, _ = fit(part, cfg)
    return head_dict(net, part, cfg, names)


def scores(trace, opts: RunOptions, head: dict) -> tuple[float, float, float]:
    """GSDC scores of fused-nodnn with pseudoranges only, with Doppler (and carrier), and with the head."""
    wls = solve_initial(trace, opts)
    pr_only = replace(opts, graph=replace(opts.graph, use_doppler=False, use_carrier=False))
    a = mode_metrics(trace, fuse(trace, wls, pr_only))["gsdc_score"]
    b = mode_metrics(trace, fuse(trace, wls, opts))["gsdc_score"]
    c = mode_metrics(trace, fuse(trace, wls, opts, learned=LearnedGraphInputs(doppler_noise=DopplerNoise(head))))
    return a, b, c["gsdc_score"]


def simulated(sim: Path) -> tuple[list[str], dict]:
    """The leave-track-out table's lines, and the head trained on every simulated trace."""
    # in the order a shell's glob gives ``gnssfuse train-doppler`` (the shipped head's), seeds 2k-1 and 2k replay
    # the k-th track (experiments/sim_city_traces.py)
    dirs = sorted(sim.glob("sim-*"))
    opts = RunOptions(signals="all")
    traces = {d.name: load_trace(d / "SimPhone", **load_options(opts)) for d in dirs}
    rows = {n: trace_rows(t, opts) for n, t in traces.items()}
    names = list(traces)
    track = {n: (int(n.rsplit("-", 1)[1]) + 1) // 2 for n in names}
    out = ["## Leave-track-out on the simulated city traces", "",
           "| held out | pseudoranges only | + Doppler | + Doppler, learned head | head / without |", "|---|---|---|---|---|"]
    ratios = []
    for k in sorted(set(track.values())):
        test = [n for n in names if track[n] == k]
        head = train_head(rows, [n for n in names if track[n] != k])
        for n in test:
            a, b, c = scores(traces[n], opts, head)
            ratios.append(c / b)
            out.append(f"| {n} | {a:.2f} | {b:.2f} | {c:.2f} | {c / b:.3f} |")
            print(out[-1], flush=True)
    out += ["", f"Mean ratio {np.mean(ratios):.3f}, best {min(ratios):.3f}, worst {max(ratios):.3f}.", ""]
    return out, train_head(rows, names)


def pixel5(head: dict, tmp: Path) -> list[str]:
    opts = RunOptions(signals=None, nav=(NAV,))
    trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    out = ["## Pixel5 RINEX test trace (GPS broadcast; head trained on all eight simulated traces)", "",
           "| measurements | pseudoranges only | fused-nodnn | fused-nodnn + head | ratio |", "|---|---|---|---|---|"]
    for label, graph in (("Doppler + carrier", {}), ("Doppler, no carrier", {"use_carrier": False})):
        a, b, c = scores(trace, replace(opts, graph=replace(opts.graph, **graph)), head)
        out.append(f"| {label} | {a:.2f} | {b:.2f} | {c:.2f} | {c / b:.3f} |")
        print(out[-1], flush=True)
    model, blob = load_model(SHIPPED_WEIGHTS)
    weights = save_checkpoint(tmp / "with_head.pt", model, dict(blob["config"], doppler_head=head))
    with_head = run_modes(trace, ["fused"], replace(opts, weights=weights))["fused"]
    without = run_modes(trace, ["fused"], replace(opts, weights=weights, learned_doppler=False))["fused"]
    a, b = (mode_metrics(trace, r)["gsdc_score"] for r in (without, with_head))
    out += ["", "| mode | without head | with head | ratio |", "|---|---|---|---|",
            f"| fused (shipped network), Doppler + carrier | {a:.2f} | {b:.2f} | {b / a:.3f} |", ""]
    print(out[-1], flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sim", type=Path, required=True, help="folder of experiments/sim_city_traces.py's traces")
    p.add_argument("--tmp", type=Path, default=Path("/tmp/doppler_head"), help="scratch folder for a checkpoint")
    args = p.parse_args(argv)
    lines, head = simulated(args.sim)           # the last head: all eight traces, the shipped recipe
    if PIXEL5.is_dir():
        lines += pixel5(head, args.tmp)
    print("\n".join(["# The learned Doppler head, on its own", "", "GSDC score [m].", ""] + lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
