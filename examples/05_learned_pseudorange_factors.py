"""Weight *your own* GTSAM pseudorange factors with the network's per-satellite head.

A minimal snapshot-plus-motion graph built by hand: per epoch an ECEF ``Point3`` position and a receiver
clock (seconds), one ``PseudorangeFactor`` per satellite whose sigma (and bias) the per-satellite head
predicts from that satellite's residual, geometry, reported uncertainty and history
(:func:`learned.factor.learned_pseudorange_factors`), and a loose random walk between positions and clocks.
The same graph with one fixed sigma for every satellite is solved beside it; both errors are printed.

    python examples/05_learned_pseudorange_factors.py [--trace DIR] [--weights CKPT] [--epochs 120] [--sigma-power P]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gtsam
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.estimate.wls import solve_wls  # noqa: E402
from fusion.eval.metrics import horizontal, ned_errors  # noqa: E402
from fusion.geometry import C_LIGHT  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from learned.factor import learned_pseudorange_factors  # noqa: E402
from learned.infer import Corrector  # noqa: E402

SHIPPED = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"


def solve(factors: list[list], wls, walk_m: float) -> np.ndarray:
    """(E,3) positions of the graph: the given pseudorange factors + random walks (walk_m per epoch)."""
    E = len(factors)
    graph, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    x, c = (lambda k: gtsam.symbol("x", k)), (lambda k: gtsam.symbol("c", k))
    for k in range(E):
        for f in factors[k]:
            graph.add(f)
        init.insert(x(k), np.asarray(wls.pos[k] if wls.valid[k] else wls.pos[wls.valid][0], float))
        init.insert(c(k), float(np.nan_to_num(wls.clock_m[k]) / C_LIGHT))
        if k:
            graph.add(gtsam.BetweenFactorPoint3(x(k - 1), x(k), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, walk_m)))
            graph.add(gtsam.BetweenFactorDouble(c(k - 1), c(k), 0.0, gtsam.noiseModel.Isotropic.Sigma(1, 1e-6)))
    res = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    return np.array([res.atPoint3(x(k)) for k in range(E)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trace", type=Path, default=SHIPPED)
    p.add_argument("--weights", type=Path, default=None, help="checkpoint (default: shipped weights)")
    p.add_argument("--epochs", type=int, default=120)
    p.add_argument("--walk", type=float, default=15.0, help="position random walk per epoch [m]")
    p.add_argument("--sigma-power", type=float, default=1.0,
                   help="the head's multiplier raised to this (the fused mode's graph takes 3)")
    args = p.parse_args(argv)
    trace = load_trace(args.trace)
    trace = trace.select(np.arange(min(args.epochs, trace.n_epochs)))
    wls = solve_wls(trace)                                    # guesses for the head (never the truth)
    keys = [gtsam.symbol("x", k) for k in range(trace.n_epochs)], [gtsam.symbol("c", k) for k in range(trace.n_epochs)]
    learned, sigma = learned_pseudorange_factors(Corrector.load(args.weights), trace, wls.pos, wls.valid, *keys,
                                                 sigma_power=args.sigma_power)
    fixed, _ = learned_pseudorange_factors(_NoOpinion(), trace, wls.pos, wls.valid, *keys)
    for name, factors in (("fixed 5 m sigma", fixed), ("learned sigmas", learned)):
        h = horizontal(ned_errors(solve(factors, wls, args.walk), trace.truth))
        print(f"{name:16s} horizontal error p50 {np.nanpercentile(h, 50):.2f} m  p95 {np.nanpercentile(h, 95):.2f} m")
    print(f"learned sigma per measurement: median {np.nanmedian(sigma):.1f} m, "
          f"range {np.nanmin(sigma):.1f}-{np.nanmax(sigma):.1f} m over {int(np.isfinite(sigma).sum())} measurements")
    return 0


class _NoOpinion:
    """A slot-noise source with no opinion: every factor gets the default sigma (the comparison graph)."""

    def slot_noise(self, elev_mask_deg=None):
        return lambda trace, init_pos, valid: (np.full(trace.mask.shape, np.nan),) * 2


if __name__ == "__main__":
    sys.exit(main())
