"""The pseudorange loss of a graph with learned sigmas (GraphConfig.learned_robust / learned_robust_k, at epochs
of at least robust_min_sats satellites; the others keep robust / robust_k): Cauchy at 1.5 (the loss
before) and wider, against Geman-McClure, which redescends. GSDC score [m] of ``fused`` (the shipped network,
which never saw these logs) on smartLoc's canyon and, with ``--sims``, on held-out simulated city traces
(``sim_city_traces.py --held-out``; the mean per street kind). Those decide, with the GSDC drives cross-validated
(``crossval.py --ensemble-of ... --graph-config``, see ``experiments/results/learned_robust.md``); ``--pixel5`` then
reports the Pixel5 RINEX test trace (GPS broadcast navigation).

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/learned_robust.py --sims /tmp/simho /tmp/simdeepho
    GNSSFUSE_SHARED_DATA=../shared/data python experiments/learned_robust.py --pixel5
"""
from __future__ import annotations

import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from few_satellites import NAV, PIXEL5, SHARED  # noqa: E402
from unlearned_robust import KINDS, parse_args, score, table  # noqa: E402

#: name -> GraphConfig changes
VARIANTS = {
    "Cauchy 1.5 (before)": {"learned_robust": "cauchy", "learned_robust_k": 1.5},
    "Cauchy 2": {"learned_robust": "cauchy", "learned_robust_k": 2.0},
    "Cauchy 3": {"learned_robust": "cauchy", "learned_robust_k": 3.0},
    "Geman-McClure 3": {"learned_robust": "gm", "learned_robust_k": 3.0},
    "Geman-McClure 4": {"learned_robust": "gm", "learned_robust_k": 4.0},
    "Geman-McClure 5": {"learned_robust": "gm", "learned_robust_k": 5.0},
}


def main() -> int:
    args = parse_args(__doc__.splitlines()[0])
    if args.pixel5:
        traces, nav = [PIXEL5], (NAV,)
    else:
        traces = [p for d in args.sims for p in sorted(d.glob("*/SimPhone"))]
        traces, nav = traces + [SHARED / "smartloc" / "Berlin_Potsdamer_Platz"], ()
    jobs = [(p, v, c, "fused", nav) for p in traces for v, c in VARIANTS.items()]
    with ProcessPoolExecutor(args.jobs) as pool:
        got = list(pool.map(score, jobs))
    rows = {}
    for v in VARIANTS:
        mine = {name: s for name, vv, _, s in got if vv == v}
        if args.pixel5:
            rows[v] = {"Pixel5 fused": next(iter(mine.values()))}
            continue
        r = {"smartLoc fused": next(s for n, s in mine.items() if n.startswith("smartloc"))}
        for kind in KINDS if args.sims else ():
            r[f"sims {kind} fused"] = np.mean([s for n, s in mine.items() if f"-{kind}-" in n])
        rows[v] = r
    table("GSDC score [m]" + (", the Pixel5 RINEX test trace (GPS broadcast navigation)" if args.pixel5 else ""),
          rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
