"""What the pseudorange factors' robust losses cost where errors are Gaussian: simulated traces with Doppler and
no multipath (the simulator's default errors), the graph without carrier or anything learned, pseudoranges under
Cauchy at 1.5 and 2 and Geman-McClure at 2 (GraphConfig.unlearned_robust / unlearned_robust_k: shipped, Cauchy 1.5
before), Doppler under Cauchy at 2. Median / 95th percentile of the 3-D position error [m].

    python experiments/robust_scale_clean.py [--seeds 11,1,2,3,4,5]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fusion.estimate.graph.config import GraphConfig  # noqa: E402
from fusion.estimate.graph.fuse import fuse  # noqa: E402
from fusion.io.rinex_nav import default_nav_path, read_rinex_nav  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.simulate import SimConfig, simulate  # noqa: E402

#: the pseudorange losses compared: (GraphConfig.unlearned_robust, unlearned_robust_k)
LOSSES = (("cauchy", 1.5), ("cauchy", 2.0), ("gm", 2.0))


def errors(sim, wls, loss: tuple[str, float], doppler: bool) -> np.ndarray:
    """(E,) 3-D position error [m] of the graph with the pseudorange ``loss``, with or without Doppler."""
    cfg = GraphConfig(use_doppler=doppler, use_carrier=False, unlearned_robust=loss[0], unlearned_robust_k=loss[1],
                      rate_robust_k=2.0)
    res = fuse(sim.trace, wls, RunOptions(graph=cfg), want_cov=False)
    return np.linalg.norm(res.pos - sim.trace.truth, axis=1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="11,1,2,3,4,5")
    args = p.parse_args(argv)
    nav = read_rinex_nav(default_nav_path())
    cols = [(loss, d) for loss in LOSSES for d in (False, True)]
    print("| seed | " + " | ".join(f"{k} {s:g}, {'Doppler' if d else 'no Doppler'}" for (k, s), d in cols) + " |")
    print("|---|" + "---|" * len(cols))
    med, p95 = {c: [] for c in cols}, {c: [] for c in cols}
    for seed in (int(s) for s in args.seeds.split(",")):
        sim = simulate(n_epochs=200, nav=nav, seed=seed, config=SimConfig(doppler=True, carrier=True, slip_prob=0.005))
        wls = solve_initial(sim.trace, RunOptions())
        cells = []
        for c in cols:
            e = errors(sim, wls, *c)
            med[c].append(np.median(e))
            p95[c].append(np.percentile(e, 95))
            cells.append(f"{np.median(e):.2f} / {np.percentile(e, 95):.2f}")
        print(f"| {seed} | " + " | ".join(cells) + " |", flush=True)
    print("| mean | " + " | ".join(f"{np.mean(med[c]):.2f} / {np.mean(p95[c]):.2f}" for c in cols) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
