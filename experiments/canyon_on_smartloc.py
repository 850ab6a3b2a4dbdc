"""smartLoc seen from the simulator's streets: does the learned part still help when a real receiver's
multi-constellation canyon loses more satellites?

smartLoc (a u-blox in Berlin's Potsdamer Platz, GPS + GLONASS with C/N0, no Doppler or carrier; no network
trained on it) is a tuning log. Its real canyon is laid, as ``canyon_on_phone.py`` lays the Pixel5, in seeded
streets along its true track (:func:`canyon_on_phone.in_canyon`: blocked satellites removed, a reflected or
bent signal's extra path added to its pseudorange and its C/N0 lowered). The truth places the streets only.
``fused-nodnn`` and ``fused`` (shipped weights, or ``--weights``) are scored per layout [m, GSDC score].

    python experiments/canyon_on_smartloc.py [--deep] [--seeds 0 1 2] [--graph-config F.toml]
        [--without prior sigmas bias]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from adapt_eval import SMARTLOC  # noqa: E402
from canyon_on_phone import DEEP, in_canyon  # noqa: E402
from fusion.estimate.graph.config import GraphConfig, load_graph_config  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import CanyonModel  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--deep", action="store_true", help="buildings 30-100 m, streets 12-25 m (else the defaults)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="the street layouts' seeds")
    p.add_argument("--graph-config", type=Path, default=None, metavar="FILE.toml", help="the graph's settings")
    p.add_argument("--weights", type=Path, default=None, help="the network (default: the shipped)")
    p.add_argument("--without", nargs="+", default=(), choices=("prior", "sigmas", "bias"),
                   help="learned parts fused leaves out (its ablation)")
    a = p.parse_args()
    graph = GraphConfig() if a.graph_config is None else load_graph_config(a.graph_config)
    opts = RunOptions(signals=None, graph=graph, **({"weights": a.weights} if a.weights else {}),
                      **{f"learned_{part}": False for part in a.without})
    trace = load_trace(SMARTLOC, signals=None)       # None: GPS and GLONASS, as gnssfuse evaluate reads it
    model = DEEP if a.deep else CanyonModel()
    print("| smartLoc | blocked | reflected or bent | fused-nodnn | fused | fused / fused-nodnn |")
    print("|---|---|---|---|---|---|")
    ratios, fused = [], []
    for seed in a.seeds:
        canyon, share = in_canyon(trace, model, seed)
        res = run_modes(canyon, ["fused-nodnn", "fused"], opts, wls=solve_initial(canyon, opts))
        s0, s1 = (mode_metrics(canyon, res[m])["gsdc_score"] for m in ("fused-nodnn", "fused"))
        ratios.append(s1 / s0)
        fused.append(s1)
        print(f"| streets seed {seed} | {share['blocked']:.2f} | {share['reflected']:.2f} | {s0:.2f} | {s1:.2f} "
              f"| {s1 / s0:.3f} |", flush=True)
    print(f"\nmean fused {sum(fused) / len(fused):.2f} m; mean ratio {sum(ratios) / len(ratios):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
