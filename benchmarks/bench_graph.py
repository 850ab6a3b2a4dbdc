"""Factor-graph benchmark: accuracy of every mode side by side, and graph speed.

    PYTHONPATH=. python benchmarks/bench_graph.py                  # both parts, ../shared/data
    PYTHONPATH=. python benchmarks/bench_graph.py --part speed     # speed only (synthetic if no data)
    PYTHONPATH=. python benchmarks/bench_graph.py --part tune --weights LOO.pt
        # tuning, training traces only: GraphConfig variations for fused-nodnn on the three
        # training traces, then learned-prior settings on 2020-09-04-US-SF-2 with a checkpoint
        # trained WITHOUT that trace (LOO.pt, e.g. gnssfuse train --data sim <the other two> ...)
    PYTHONPATH=. python benchmarks/bench_graph.py --part prior --weights LOO.pt   # learned prior only
    PYTHONPATH=. python benchmarks/bench_graph.py --part prior --weights LOO2.pt --trace 2020-05-14-US-MTV-1
        # the same on another training trace (LOO2.pt trained without it)

Accuracy: wls / dnn / fused / fused-nodnn on the test traces 2021-04-28-US-MTV-1/Pixel4 (GPS L1)
and 2021-04-28-US-SJC-1/Pixel4 (multi-signal, 5 windows with gaps), identical inputs per trace:
loaded with ``min_sats=1`` and one ``fusion.modes.solve_initial`` WLS solve fed to every mode, as
``gnssfuse run`` / ``evaluate`` do, scored with ``fusion.eval.metrics.mode_metrics``. Graph settings (``GraphConfig`` defaults)
were tuned on the training traces only (``--part tune`` prints them).

Speed: batch build + solve (GraphConfig.batch_solver: the banded Gauss-Newton, Levenberg-Marquardt as its fallback) of a
~2,000-epoch trace (with and without the marginal covariances), ISAM2 milliseconds per epoch, and the
per-factor cost. (Record names keep "LM" for continuity with earlier results.)
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import os
import sys
import time
from pathlib import Path

import numpy as np

from fusion.errors import CheckpointError, ModeUnavailableError
from fusion.estimate.graph.build import build_graph
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.eval.metrics import ned_errors
from fusion.eval.metrics import format_table, mode_metrics
from fusion.modes import get_mode, solve_initial
from fusion.run_types import ModeResult, RunOptions
from fusion.estimate.wls import solve_wls

# The development data beside the checkout (../shared/data), or $GNSSFUSE_SHARED_DATA.
DATA = Path(os.environ.get("GNSSFUSE_SHARED_DATA",
                          Path(__file__).resolve().parents[2] / "shared" / "data")) / "gsdc2021" / "train"
TEST = {"2021-04-28-US-MTV-1": ("GPS_L1",),
        "2021-04-28-US-SJC-1": ("GPS_L1", "GLO_G1", "GAL_E1", "BDS_B1I")}
TRAIN = ("2020-05-14-US-MTV-1", "2020-06-05-US-MTV-1", "2020-09-04-US-SF-2")
MODES = ("wls", "dnn", "fused", "fused-nodnn")


def accuracy(root: Path, weights: Path | None) -> None:
    from fusion.prepare.load import load_trace

    for name, signals in TEST.items():
        d = root / name / "Pixel4"
        if not d.is_dir():
            print(f"{name}: not found under {root}, skipped")
            continue
        opts = RunOptions(weights=weights, signals=signals)
        trace = load_trace(d, signals=signals, min_sats=1)   # as gnssfuse run / evaluate
        wls = solve_initial(trace, opts)
        rows, notes = {}, []
        for mode in MODES:
            t0 = time.perf_counter()
            try:
                res = get_mode(mode)(trace, wls, opts)
            except (ModeUnavailableError, CheckpointError) as exc:   # a real failure propagates
                notes.append(f"  {mode}: unavailable ({str(exc).splitlines()[0][:150]})")
                continue
            rows[mode] = mode_metrics(trace, res)
            notes.append(f"  {mode}: {time.perf_counter() - t0:.2f} s, solved {int(res.valid.sum())}/{trace.n_epochs}"
                         + (f", info {_short(res.info)}" if mode.startswith("fused") else ""))
        print(f"\n{trace.name}  signals={','.join(signals)}  epochs={trace.n_epochs}  skipped={trace.skipped}")
        print(format_table(rows))
        print("\n".join(notes))


def _short(info: dict) -> dict:
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in info.items()
            if isinstance(v, (int, float)) and not k.endswith("_s")}


#: one-parameter-at-a-time variations around the defaults for the graph without the prior
GRAPH_GRID = (
    {}, {"pr_sigma_zenith_m": 1.0}, {"pr_sigma_zenith_m": 3.0}, {"pr_sigma_scale": 0.5},
    {"pr_sigma_scale": 2.0}, {"robust": "huber"}, {"robust_k": 0.5}, {"robust_k": 2.0},
    {"cv_accel_h": 0.5}, {"cv_accel_h": 2.0}, {"cv_pos_sigma_m": 0.2}, {"cv_pos_sigma_m": 1.0},
    {"cv_accel_v": 0.2}, {"clock_rw_m": 2.0}, {"clock_rw_m": 20.0}, {"motion": "rw"},
)

#: learned-prior settings tried on the held-out training trace
PRIOR_GRID = tuple(
    {"prior_cov_scale": sc, "prior_sigma_floor_m": fl, "prior_robust": rb, "prior_robust_k": k}
    for sc in (1.0, 2.0, 4.0, 16.0) for fl in (0.0, 2.0)
    for rb, k in (("none", 2.0), ("huber", 1.0), ("cauchy", 1.0)))


def tune_graph(root: Path, grid=GRAPH_GRID) -> None:
    """fused-nodnn on the three training traces for each variation of GraphConfig (defaults first)."""
    from fusion.prepare.load import load_trace

    data = []
    for name in TRAIN:
        trace = load_trace(root / name / "Pixel4", min_sats=1)
        wls = solve_wls(trace)
        data.append((trace, wls))
        w = mode_metrics(trace, wls)
        print(f"{trace.name}: wls h_p50 {w['h_p50']:.2f} h_p95 {w['h_p95']:.2f} score {w['gsdc_score']:.2f}")
    print("\nfused-nodnn, GSDC score per training trace and mean (variation of the defaults)")
    for change in grid:
        cfg = GraphConfig(**change)
        sc = [mode_metrics(tr, fuse(tr, wl, RunOptions(), cfg=cfg, want_cov=False))["gsdc_score"]
              for tr, wl in data]
        print(f"  {str(change or 'defaults'):<48} " + " ".join(f"{x:6.2f}" for x in sc) + f"   mean {np.mean(sc):.3f}")


def tune_prior(root: Path, weights: Path | None, trace_name: str = "2020-09-04-US-SF-2", grid=PRIOR_GRID) -> None:
    """fused vs fused-nodnn on one training trace, with a checkpoint trained WITHOUT that trace.

    The network is asked once per ``prior_at`` choice (at the no-prior graph solution, and at the
    WLS positions) and its output reused for every prior setting, so the table isolates the effect
    of the settings.
    """
    from fusion.prepare.load import load_trace
    from fusion.estimate.graph.batch import solve_batch
    from fusion.estimate.graph.priors import LearnedGraphInputs
    from learned.infer import Corrector, calibration

    if weights is None:
        print("tune_prior: pass --weights <checkpoint trained without the tuning trace>; skipped")
        return
    trace = load_trace(root / trace_name / "Pixel4", min_sats=1)
    wls = solve_wls(trace)
    nodnn = fuse(trace, wls, RunOptions(), want_cov=False)
    corr = Corrector.load(weights)
    ask = trace.n_sats >= 1
    guesses = {"graph": np.where(nodnn.valid[:, None], nodnn.pos, wls.pos), "wls": wls.pos}
    rows = {"wls": mode_metrics(trace, wls), "fused-nodnn": mode_metrics(trace, nodnn)}
    outs, cals = {}, {}
    for at, guess in guesses.items():
        c = corr.predict(trace, guess, ask & np.isfinite(guess).all(axis=1))
        ok = c.valid & np.isfinite(trace.truth).all(axis=1)
        cals[at] = calibration(ned_errors(c.mean_ecef[ok], trace.truth[ok]), c.cov_ned[ok])
        outs[at] = (c.mean_ecef, c.cov_ecef, c.valid)
        rows[f"dnn@{at}"] = mode_metrics(trace, ModeResult(pos=c.mean_ecef, valid=c.valid))
    print(f"\n{trace.name} with {weights} (network never saw this trace)")
    for at, cal in cals.items():
        print(f"  DNN calibration at the {at} guess: {cal}")
    print(format_table(rows))
    print(f"\n  {'prior at':>8} {'cov scale':>9} {'floor m':>7} {'robust':>10}  {'h p50':>6} {'h p95':>6} {'score':>6}")
    for at, out in outs.items():
        for change in grid:
            cfg = GraphConfig(**change)
            inp = prepare_inputs(trace, wls, cfg, 10.0, LearnedGraphInputs(*out))
            pos, valid, _, _ = solve_batch(trace, inp, cfg, want_cov=False)
            m = mode_metrics(trace, ModeResult(pos=pos, valid=valid))
            rb = "none" if change["prior_robust"] == "none" else f"{change['prior_robust']}({change['prior_robust_k']:g})"
            print(f"  {at:>8} {change['prior_cov_scale']:9g} {change['prior_sigma_floor_m']:7g} {rb:>10}  "
                  f"{m['h_p50']:6.2f} {m['h_p95']:6.2f} {m['gsdc_score']:6.2f}", flush=True)


def tune(root: Path, weights: Path | None) -> None:
    tune_graph(root)
    tune_prior(root, weights)


REPO_TRACE = Path(__file__).resolve().parents[1] / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"


def speed(root: Path, repeats: int) -> list[dict]:
    """Time the graph on 2021-04-28-US-MTV-1 (shared data, else the copy shipped in the repo, else a
    synthetic 2,000-epoch trace); prints a table and returns benchmark records."""
    d = root / "2021-04-28-US-MTV-1" / "Pixel4"
    d = d if d.is_dir() else REPO_TRACE
    if d.is_dir():
        from fusion.prepare.load import load_trace

        trace = load_trace(d)
    else:
        from fusion.sim.simulate import simulate

        trace = simulate(n_epochs=2000, seed=0, name="synthetic").trace
    wls = solve_wls(trace)
    cfg = GraphConfig()
    E = trace.n_epochs
    print(f"\nspeed on {trace.name}: {E} epochs, {int(trace.mask.sum())} measurements "
          f"(best of {repeats}; {os.cpu_count()} CPU cores)")

    def best(f):
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = f()
            ts.append(time.perf_counter() - t0)
        return min(ts), out

    t_prep, inp = best(lambda: prepare_inputs(trace, wls, cfg))
    t_build, (graph, values, _) = best(lambda: build_graph(trace, inp, cfg))
    t_batch, res = best(lambda: fuse(trace, wls, RunOptions(), cfg=cfg, want_cov=False))
    t_cov, res_c = best(lambda: fuse(trace, wls, RunOptions(), cfg=cfg, want_cov=True))
    t_inc, res_i = best(lambda: fuse(trace, wls, RunOptions(), cfg=replace(cfg, incremental=True)))
    n_f = graph.size()
    it = max(res.info["iterations"], 1)
    us_iter = 1e6 * res.info["solve_s"] / n_f / it
    print(f"  inputs (vectorised)            {1000 * t_prep:8.1f} ms")
    print(f"  graph build ({n_f} factors)   {1000 * t_build:8.1f} ms  = {1e6 * t_build / n_f:.1f} us/factor")
    print(f"  batch total (prep+build+solve) {t_batch:8.2f} s   ({res.info['iterations']} {cfg.batch_solver} iterations, "
          f"solve {res.info['solve_s']:.2f} s = {us_iter:.1f} us/factor/iteration)")
    print(f"  batch + marginal covariances   {t_cov:8.2f} s   (marginals {res_c.info['cov_s']:.2f} s)")
    print(f"  incremental ISAM2              {res_i.info['ms_per_epoch']:8.2f} ms/epoch "
          f"(total {t_inc:.2f} s incl. prep)")
    gap = np.linalg.norm(res_i.pos - res.pos, axis=1)
    print(f"  ISAM2 vs batch position difference: median {np.nanmedian(gap):.3f} m, max {np.nanmax(gap):.3f} m")
    note = f"{trace.name}, {E} epochs, {n_f} factors, fused-nodnn, best of {repeats}, CPU"
    return [
        {"name": "graph batch (prep+build+LM), per 2000 epochs", "value": t_batch * 2000 / E, "unit": "s", "note": note},
        {"name": "graph batch + marginal covariances, per 2000 epochs", "value": t_cov * 2000 / E, "unit": "s",
         "note": note},
        {"name": "graph incremental ISAM2", "value": res_i.info["ms_per_epoch"], "unit": "ms/epoch", "note": note},
        {"name": "graph build per factor", "value": 1e6 * t_build / n_f, "unit": "us", "note": note},
        {"name": "graph LM per factor per iteration", "value": us_iter, "unit": "us",
         "note": note + f", {res.info['iterations']} iterations"},
        {"name": "graph ISAM2 vs batch position difference, median", "value": float(np.nanmedian(gap)), "unit": "m",
         "note": note},
    ]


def run(quick: bool = False) -> list[dict]:
    """Benchmark records for ``benchmarks/run_all.py``: the speed part (one repeat when quick)."""
    return speed(DATA, repeats=1 if quick else 2)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=("all", "accuracy", "speed", "tune", "prior"), default="all")
    p.add_argument("--data", type=Path, default=DATA, help="a GSDC 2021 train/ folder")
    p.add_argument("--weights", type=Path, default=None, help="DNN checkpoint (default: shipped weights)")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--trace", default="2020-09-04-US-SF-2", choices=TRAIN,
                   help="--part prior: the training collection to tune on (the checkpoint must not have seen it)")
    args = p.parse_args(argv)
    if args.part in ("all", "accuracy"):
        accuracy(args.data, args.weights)
    if args.part == "tune":
        tune(args.data, args.weights)
    if args.part == "prior":
        tune_prior(args.data, args.weights, args.trace)
    if args.part in ("all", "speed"):
        speed(args.data, args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
