"""The street canyon of ``canyon_on_phone.py`` laid over the GSDC training drives: does the learned part help in a
canyon when the log has no C/N0?

The GSDC 2021 derived files carry GPS L1 pseudoranges with the phone's reported uncertainty but no C/N0, Doppler or
carrier. Each drive is seen from seeded streets along its true track (:func:`canyon_on_phone.in_canyon`: blocked
satellites removed, a reflected or bent signal's extra path added to its pseudorange), and solved by
``fused-nodnn`` and by ``fused`` with the cross-validation ensemble that never saw the drive (``crossval.py
--ensemble-of``: ``fold_<F>.json`` for the drives of fold F). The truth places the streets only. GSDC score [m].

    python experiments/canyon_on_gsdc.py --folds /tmp/cv_ens_new [--deep] [--seed 0] [--cn0] [--graph-config F.toml]
        [--without prior sigmas bias]

``--cn0`` first gives each drive the simulator's C/N0 (line-of-sight model at the truth's geometry), which the
streets then lower for reflections: the same canyon as a phone log with C/N0 would show it.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from canyon_on_phone import DEEP, in_canyon, with_model_cn0  # noqa: E402
from crossval import FOLDS2  # noqa: E402
from few_satellites import SHARED  # noqa: E402
from fusion.estimate.graph.config import GraphConfig, load_graph_config  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import CanyonModel  # noqa: E402


def drive_row(drive: str, weights: Path, model: CanyonModel, seed: int, cn0: bool = False,
              graph: GraphConfig | None = None, without: tuple[str, ...] = ()) -> str:
    """One table row: the drive in the canyon, its shares blocked and reflected, both modes' scores, their ratio.
    cn0: the drive first gets the simulator's C/N0 (:func:`canyon_on_phone.with_model_cn0`); graph: the graph's
    settings (None: the shipped); without: learned parts ``fused`` leaves out (``prior``, ``sigmas``, ``bias``)."""
    trace = load_trace(SHARED / "gsdc2021/train" / drive / "Pixel4")
    trace, share = in_canyon(with_model_cn0(trace, seed) if cn0 else trace, model, seed)
    off = {f"learned_{part}": False for part in without}
    opts = RunOptions(weights=weights, sigma_calibration=False, graph=graph or GraphConfig(), **off)
    res = run_modes(trace, ["fused-nodnn", "fused"], opts, wls=solve_initial(trace, opts))
    a, b = (mode_metrics(trace, res[m])["gsdc_score"] for m in ("fused-nodnn", "fused"))
    return f"| {drive} | {share['blocked']:.2f} | {share['reflected']:.2f} | {a:.2f} | {b:.2f} | {b / a:.3f} |"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--folds", type=Path, required=True, help="a crossval.py --two-fold --ensemble-of output folder")
    p.add_argument("--deep", action="store_true", help="buildings 30-100 m, streets 12-25 m (else the defaults)")
    p.add_argument("--seed", type=int, default=0, help="the street layout's seed")
    p.add_argument("--cn0", action="store_true", help="give the drives the simulator's C/N0 first (as a phone log has)")
    p.add_argument("--graph-config", type=Path, default=None, metavar="FILE.toml",
                   help="the graph's settings (GraphConfig fields as 'name = value' lines; default: the shipped)")
    p.add_argument("--without", nargs="+", default=(), choices=("prior", "sigmas", "bias"),
                   help="learned parts fused leaves out (its ablation)")
    args = p.parse_args()
    graph = None if args.graph_config is None else load_graph_config(args.graph_config)
    model = DEEP if args.deep else CanyonModel()
    print("| drive | blocked | reflected or bent | fused-nodnn | fused | fused / fused-nodnn |")
    print("|---|---|---|---|---|---|")
    ratios = []
    for fold, drives in FOLDS2.items():
        for drive in drives:
            # fold_<F> was trained on the other fold's drives (crossval.train_fold)
            row = drive_row(drive, args.folds / f"fold_{fold}.json", model, args.seed, args.cn0, graph,
                            tuple(args.without))
            ratios.append(float(row.rsplit("|", 2)[-2]))
            print(row, flush=True)
    print(f"\nratio: mean {np.mean(ratios):.3f}, median {np.median(ratios):.3f}, "
          f"{sum(r <= 0.9 for r in ratios)} of {len(ratios)} drives at 0.9 x or better")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
