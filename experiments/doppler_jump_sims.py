"""The Doppler's own drift jump (``GraphConfig.doppler_jump_from_log``) on simulated traces given a phone's
clock: the held-out simulated city traces (``sim_city_traces.py --held-out``, and its ``deep`` ones) with a
white jump of ``--jump`` m/s added to each epoch's Dopplers (the Pixel5's drift, as its log shows it: 0.47),
as simulated and thinned to three satellites in 120 s of every 180 s (``few_satellites.thinned``). The
simulator's own clock drift is steady, so without the added jump the estimate finds none and nothing changes.

Per trace set: the mean GSDC score [m] of ``fused-nodnn`` with pseudoranges only, and with Doppler and carrier
without and with the jump; and the jump the graph took (mean over traces; "-" where unknown).

    python experiments/sim_city_traces.py --out /tmp/simho --held-out
    python experiments/sim_city_traces.py --out /tmp/simdeepho --held-out --scenarios deep --first-seed 300
    python experiments/doppler_jump_sims.py --sims /tmp/simho /tmp/simdeepho [--jump 0.47] [--graph-config FILE.toml]

``--graph-config``: every variant on those settings (GraphConfig fields as ``name = value`` lines) instead of the
shipped ones.
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

from few_satellites import thinned  # noqa: E402
from fusion.estimate.graph.config import load_graph_config  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.doppler_carrier import with_drift_jumps  # noqa: E402
from fusion.trace import Trace  # noqa: E402

VARIANTS = {"pseudoranges only": {"use_doppler": False, "use_carrier": False},
            "Doppler + carrier, no jump": {"doppler_jump_from_log": False},
            "Doppler + carrier, the log's jump": {}}


def scores(trace: Trace, opts: RunOptions) -> tuple[dict[str, float], float | None]:
    """fused-nodnn's GSDC score per variant, and the jump the last variant took (None: unknown)."""
    wls = solve_initial(trace, opts)
    out, jump = {}, None
    for name, change in VARIANTS.items():
        res = run_modes(trace, ["fused-nodnn"], replace(opts, graph=replace(opts.graph, **change)), wls=wls)
        out[name] = mode_metrics(trace, res["fused-nodnn"])["gsdc_score"]
        jump = res["fused-nodnn"].info.get("doppler_drift_jump_mps")
    return out, jump


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sims", type=Path, nargs="+", required=True, help="folders of held-out simulated traces")
    p.add_argument("--jump", type=float, default=0.47, help="the added white jump of the Doppler's drift [m/s]")
    p.add_argument("--graph-config", type=Path, default=None, metavar="FILE.toml",
                   help="the graph's settings (GraphConfig fields as 'name = value' lines; default: the shipped)")
    args = p.parse_args()
    opts = RunOptions(signals=parse_signals("all"), sigma_calibration=False)
    if args.graph_config is not None:
        opts = replace(opts, graph=load_graph_config(args.graph_config))
    paths = [q for folder in args.sims for q in sorted(folder.glob("*/SimPhone"))]
    print("| traces | added jump [m/s] | " + " | ".join(VARIANTS) + " | jump taken [m/s] |")
    print("|---|---|" + "---|" * (len(VARIANTS) + 1))
    for group in ("ordinary", "deep"):
        mine = [load_trace(q, min_sats=1, **load_options(opts)) for q in paths
                if ("-deep-" in q.parent.name) == (group == "deep")]
        for thin in (False, True):
            for added in (0.0, args.jump):
                rows, jumps = [], []
                for k, trace in enumerate(mine):
                    trace = thinned(trace, 3, k)[0] if thin else trace
                    s, j = scores(with_drift_jumps(trace, added, k) if added else trace, opts)
                    rows.append(s)
                    jumps.append(np.nan if j is None else j)
                mean = {v: np.mean([r[v] for r in rows]) for v in VARIANTS}
                taken = f"{np.nanmean(jumps):.2f}" if np.isfinite(jumps).any() else "-"
                label = f"{len(mine)} {group}{', thinned' if thin else ''}"
                print(f"| {label} | {added:.2f} | " + " | ".join(f"{mean[v]:.2f}" for v in VARIANTS)
                      + f" | {taken} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
