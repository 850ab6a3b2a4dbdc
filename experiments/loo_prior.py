"""Leave-one-trace-out check of what the learned prior adds to the graph, on every training trace.

For one training trace and a checkpoint trained WITHOUT it, prints horizontal p50 / p95 and the GSDC
score of wls, fused-nodnn and fused (all pipeline defaults), then fused with the prior's down variance
inflated (x4, x100, and a horizontal-only prior), to test whether the network's weak vertical drags
the horizontal solution. The network is asked once, at the no-prior graph solution, as ``fused`` does.

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/loo_prior.py 2020-09-04-US-SF-2 LOO_NO_SF2.pt

Data: ``$GNSSFUSE_SHARED_DATA`` (default ``<repo>/../shared/data``). Results and the training commands
of the leave-one-out checkpoints: ``experiments/results/loo_prior.md``.
"""
import argparse
import os
from pathlib import Path

import numpy as np

from fusion.geometry import ned_rotation
from fusion.estimate.graph.batch import solve_batch
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.estimate.graph.priors import LearnedGraphInputs
from fusion.prepare.load import load_trace
from fusion.eval.metrics import mode_metrics
from fusion.modes import run_modes, solve_initial
from fusion.run_types import ModeResult, RunOptions
from learned.data import check_not_forbidden
from learned.infer import Corrector

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def down_inflated(cov_ned: np.ndarray, factor: float | None) -> np.ndarray:
    """(E,3,3) NED covariance with the down variance times ``factor``; None = horizontal-only
    (down decoupled and given a 1 km sigma, i.e. no vertical information)."""
    c = cov_ned.copy()
    if factor is None:
        c[:, 2, :2] = c[:, :2, 2] = 0.0
        c[:, 2, 2] = 1e6
    else:
        c[:, 2, :] *= np.sqrt(factor)
        c[:, :, 2] *= np.sqrt(factor)
    return c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trace", help="training collection name, e.g. 2020-09-04-US-SF-2 (its Pixel4 folder is used)")
    ap.add_argument("weights", type=Path, help="checkpoint trained without that trace")
    args = ap.parse_args()
    folder = SHARED / "gsdc2021" / "train" / args.trace / "Pixel4"
    check_not_forbidden(folder)                                # tune on training traces only
    trace = load_trace(folder, min_sats=1)
    opts = RunOptions(weights=args.weights)
    wls = solve_initial(trace, opts)
    out = run_modes(trace, ["wls", "fused-nodnn", "fused"], opts, wls=wls)
    rows = dict(out)

    # the same question fused asks, then the same graph with only the prior's down axis changed
    nodnn = out["fused-nodnn"]
    guess = np.where(nodnn.valid[:, None], nodnn.pos, out["wls"].pos)
    c = Corrector.load(args.weights).predict(trace, guess, (trace.n_sats >= 1) & np.isfinite(guess).all(axis=1))
    R = ned_rotation(np.nan_to_num(guess))                    # cov_ned is in the guess's NED frame
    cfg = GraphConfig()
    for label, factor in (("fused, down var x4", 4.0), ("fused, down var x100", 100.0),
                          ("fused, horizontal-only prior", None)):
        cov_ecef = np.einsum("eji,ejk,ekl->eil", R, down_inflated(c.cov_ned, factor), R)
        prior = (c.mean_ecef, cov_ecef, c.valid)
        inp = prepare_inputs(trace, wls, cfg, opts.elev_mask_deg, LearnedGraphInputs(*prior))
        pos, valid, _, _ = solve_batch(trace, inp, cfg, want_cov=False)
        rows[label] = ModeResult(pos=pos, valid=valid)

    print(f"{trace.name}, network {args.weights} (never trained on this trace)")
    print(f"| mode | h p50 [m] | h p95 [m] | GSDC score [m] |\n|---|---|---|---|")
    for label, r in rows.items():
        m = mode_metrics(trace, r)
        print(f"| {label} | {m['h_p50']:.2f} | {m['h_p95']:.2f} | {m['gsdc_score']:.2f} |")


if __name__ == "__main__":
    main()
