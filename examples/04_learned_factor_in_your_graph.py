"""Use the learned GNSS correction as one factor in *your own* GTSAM graph.

Here "your graph" is a vehicle pose chain: ``Pose3`` variables (translation = ECEF metres) tied by
odometry ``BetweenFactorPose3``. Each epoch, the learned corrector turns that epoch's pseudoranges
into a position estimate with a covariance, added as a ``PoseTranslationPrior3D`` on the pose's
translation. No pseudorange factors: the network already digested them.

The odometry is *simulated* from the ground truth plus noise (a stand-in for wheel odometry or
VIO, since the phone data set has none), and each pose's level orientation is the local NED frame
at the truth (a stand-in for a phone IMU's attitude); the truth is used for nothing else but the
final error. The learned factors themselves see only the pseudoranges and the WLS guesses.

    python examples/04_learned_factor_in_your_graph.py [--trace DIR] [--weights CKPT] [--epochs 60]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gtsam
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.errors import GeometryError  # noqa: E402
from fusion.geometry import ned_rotation  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.eval.metrics import horizontal, ned_errors  # noqa: E402
from fusion.estimate.wls import solve_wls  # noqa: E402
from learned.factor import learned_prior_factors  # noqa: E402
from learned.infer import Corrector  # noqa: E402

SHIPPED = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"


def odometry_from_truth(truth: np.ndarray, rot: list[gtsam.Rot3], sigma_m: float, seed: int) -> list[gtsam.Pose3]:
    """Relative poses k-1 -> k from truth, translation noise ``sigma_m`` per axis (simulated sensor)."""
    rng = np.random.default_rng(seed)
    poses = [gtsam.Pose3(r, t) for r, t in zip(rot, truth)]
    return [poses[k - 1].between(poses[k]).compose(gtsam.Pose3(gtsam.Rot3(), rng.normal(0, sigma_m, 3)))
            for k in range(1, len(poses))]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trace", type=Path, default=SHIPPED)
    p.add_argument("--weights", type=Path, default=None, help="checkpoint (default: shipped weights)")
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument("--odo-sigma", type=float, default=0.3, help="simulated odometry noise per step [m]")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    t0 = time.perf_counter()

    trace = load_trace(args.trace)
    trace = trace.select(np.arange(min(args.epochs, trace.n_epochs)))
    wls = solve_wls(trace)                     # initial guesses for the corrector (never the truth)
    corrector = Corrector.load(args.weights)
    E = trace.n_epochs
    truth_ok = np.isfinite(trace.truth).all(axis=1)
    if not truth_ok.all():
        raise GeometryError(f"{trace.name}: the simulated odometry needs truth at every epoch of the demo")
    if not wls.valid.any():
        raise GeometryError(f"{trace.name}: WLS solved none of the first {E} epochs: no initial positions")

    # Each pose's rotation is the local NED frame (a level vehicle); only the translation is used.
    rot = [gtsam.Rot3(R.T) for R in ned_rotation(trace.truth)]
    odo = odometry_from_truth(trace.truth, rot, args.odo_sigma, args.seed)

    graph, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    x = lambda k: gtsam.symbol("p", k)  # noqa: E731
    odo_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 0.01), np.full(3, args.odo_sigma)])
    # level rotation known (a phone IMU would give it); translation free
    graph.add(gtsam.PriorFactorPose3(x(0), gtsam.Pose3(rot[0], np.zeros(3)),
                                     gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 0.01), np.full(3, 1e6)])))
    # One batched network pass for all epochs; learned.factor.learned_pose_translation_factor is the
    # same thing for a single epoch (e.g. inside a real-time loop).
    priors, dnn, _, ok = learned_prior_factors(corrector, trace, wls.pos, wls.valid, [x(k) for k in range(E)],
                                               on_pose=True)
    dnn[~ok] = np.nan
    start = wls.pos[np.flatnonzero(wls.valid)[0]]
    for k in range(E):
        init.insert(x(k), gtsam.Pose3(rot[k], wls.pos[k] if wls.valid[k] else start))
        if k:
            graph.add(gtsam.BetweenFactorPose3(x(k - 1), x(k), odo[k - 1], odo_noise))
        if ok[k]:
            graph.add(priors[k])               # epochs without one are carried by the odometry

    result = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    fused = np.array([result.atPose3(x(k)).translation() for k in range(E)])

    print(f"{trace.name}: {E} epochs, {int(np.isfinite(dnn).all(1).sum())} learned factors, "
          f"odometry simulated from truth + {args.odo_sigma} m noise")
    for name, est in (("wls", np.where(wls.valid[:, None], wls.pos, np.nan)), ("dnn", dnn),
                      ("pose graph", fused)):
        e = horizontal(ned_errors(est, trace.truth))
        print(f"  {name:<11} horizontal error p50 {np.nanpercentile(e, 50):6.2f} m   p95 {np.nanpercentile(e, 95):6.2f} m")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
