"""The pseudorange loss of a graph without learned sigmas (GraphConfig.unlearned_robust / unlearned_robust_k, at
epochs of at least robust_min_sats satellites): Cauchy (the loss before) against Geman-McClure, which
redescends, at three scales, at every epoch whatever its satellites, and on every graph. GSDC score [m] of
``fused-nodnn`` on the twelve GSDC training drives (no network: the mean over drives), and of ``fused-nodnn``
and ``fused`` (the shipped network, which never saw them) on smartLoc's canyon and, with ``--sims``, on held-out
simulated city traces (``sim_city_traces.py --held-out``; the mean per street kind). Those decide; ``--pixel5``
then reports the Pixel5 RINEX test trace (GPS broadcast navigation).

    python experiments/sim_city_traces.py --out /tmp/simho --held-out
    python experiments/sim_city_traces.py --out /tmp/simdeepho --held-out --scenarios deep --first-seed 300
    GNSSFUSE_SHARED_DATA=../shared/data python experiments/unlearned_robust.py --sims /tmp/simho /tmp/simdeepho
    GNSSFUSE_SHARED_DATA=../shared/data python experiments/unlearned_robust.py --pixel5
"""
from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from few_satellites import NAV, PIXEL5, SHARED  # noqa: E402
from sim_city_traces import STREET_KINDS, street_kind  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

#: name -> GraphConfig changes
VARIANTS = {
    "Cauchy 1.5 (before)": {"unlearned_robust": "cauchy", "unlearned_robust_k": 1.5},
    "Geman-McClure 1.5": {"unlearned_robust_k": 1.5},
    "Geman-McClure 2 (shipped)": {},
    "Geman-McClure 2.5": {"unlearned_robust_k": 2.5},
    "Geman-McClure 2 at every epoch": {"robust_min_sats": 1},
    "Geman-McClure 2 on every graph": {"robust": "gm", "robust_k": 2.0, "learned_robust": "gm",
                                       "learned_robust_k": 2.0},
}


def score(job: tuple[Path, str, dict, str, tuple]) -> tuple[str, str, str, float]:
    """(trace name, variant, mode, GSDC score) of one trace, variant (its name and GraphConfig changes) and mode."""
    path, variant, changes, mode, nav = job
    opts = RunOptions(signals=None if nav or "smartloc" in str(path) else parse_signals("all"), nav=nav)
    opts = replace(opts, graph=replace(opts.graph, **changes), sigma_calibration=False)
    trace = load_trace(path, min_sats=1, **load_options(opts))
    return trace.name, variant, mode, mode_metrics(trace, run_modes(trace, [mode], opts)[mode])["gsdc_score"]


def table(title: str, rows: dict[str, dict[str, float]]) -> None:
    """One row per variant, one column per group."""
    cols = list(next(iter(rows.values())))
    print(f"\n{title}\n\n| variant | " + " | ".join(cols) + " |\n" + "|---" * (len(cols) + 1) + "|")
    for v, r in rows.items():
        print(f"| {v} | " + " | ".join(f"{r[c]:.3f}" for c in cols) + " |", flush=True)


def parse_args(description: str) -> argparse.Namespace:
    """The loss experiments' options: ``--sims`` folders, ``--pixel5`` (report it instead), ``--jobs``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--sims", type=Path, nargs="*", default=(), help="folders of held-out simulated traces")
    ap.add_argument("--pixel5", action="store_true", help="report the Pixel5 test trace instead")
    ap.add_argument("--jobs", type=int, default=2)
    return ap.parse_args()


def main() -> int:
    args = parse_args(__doc__.splitlines()[0])
    if args.pixel5:
        jobs = [(PIXEL5, v, c, m, (NAV,)) for v, c in VARIANTS.items() for m in ("fused-nodnn", "fused")]
    else:
        gsdc = sorted((SHARED / "gsdc2021/train").glob("2020-*/Pixel4"))
        sims = [p for d in args.sims for p in sorted(d.glob("*/SimPhone"))]
        smartloc = SHARED / "smartloc" / "Berlin_Potsdamer_Platz"
        jobs = [(p, v, c, "fused-nodnn", ()) for p in gsdc for v, c in VARIANTS.items()]
        jobs += [(p, v, c, m, ()) for p in sims + [smartloc] for v, c in VARIANTS.items()
                 for m in ("fused-nodnn", "fused")]
    with ProcessPoolExecutor(args.jobs) as pool:
        got = list(pool.map(score, jobs))
    if args.pixel5:
        table("Pixel5 RINEX test trace (GPS broadcast navigation), Doppler and carrier",
              {v: {m: s for _, vv, m, s in got if vv == v} for v in VARIANTS})
        return 0
    rows = {}
    for v in VARIANTS:
        mine = [(name, m, s) for name, vv, m, s in got if vv == v]
        r = {"GSDC fused-nodnn (mean of 12)": np.mean([s for n, m, s in mine if n.startswith("20")])}
        for m in ("fused-nodnn", "fused"):
            r[f"smartLoc {m}"] = next(s for n, mm, s in mine if n.startswith("smartloc") and mm == m)
            for kind in STREET_KINDS if args.sims else ():
                r[f"sims {kind} {m}"] = np.mean([s for n, mm, s in mine if street_kind(n) == kind and mm == m])
        rows[v] = r
    table("GSDC score [m]", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
