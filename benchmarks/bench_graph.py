"""Factor-graph benchmark: accuracy of every mode side by side, and graph speed.

    PYTHONPATH=. python benchmarks/bench_graph.py                  # both parts, /work/shared/data
    PYTHONPATH=. python benchmarks/bench_graph.py --part speed     # speed only (synthetic if no data)
    PYTHONPATH=. python benchmarks/bench_graph.py --part tune      # the training traces only (fused-nodnn)

Accuracy: wls / dnn / fused / fused-nodnn on the test traces 2021-04-28-US-MTV-1/Pixel4 (GPS L1)
and 2021-04-28-US-SJC-1/Pixel4 (multi-signal, 5 windows with gaps), identical inputs per trace
(one WLS solve fed to every mode, as ``gnssfuse run``). Graph settings (``GraphConfig`` defaults)
were tuned on the training traces only (``--part tune`` prints them).

Speed: batch build + Levenberg-Marquardt solve of a ~2,000-epoch trace (with and without the
marginal covariances), ISAM2 milliseconds per epoch, and the per-factor cost.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from fusion.errors import GnssfuseError
from fusion.graph import build_graph, fuse
from fusion.graph_build import GraphConfig, prepare_inputs
from fusion.metrics import ned_errors, summarize
from fusion.pipeline import RunOptions, format_table, get_mode
from fusion.wls import solve_wls

DATA = Path("/work/shared/data/gsdc2021/train")
TEST = {"2021-04-28-US-MTV-1": ("GPS_L1",),
        "2021-04-28-US-SJC-1": ("GPS_L1", "GLO_G1", "GAL_E1", "BDS_B1I")}
TRAIN = ("2020-05-14-US-MTV-1", "2020-06-05-US-MTV-1", "2020-09-04-US-SF-2")
MODES = ("wls", "dnn", "fused", "fused-nodnn")


def metrics(trace, res) -> dict:
    return summarize(ned_errors(np.where(res.valid[:, None], res.pos, np.nan), trace.truth))


def accuracy(root: Path, weights: Path | None) -> None:
    from fusion.io_gsdc import load_trace

    for name, signals in TEST.items():
        d = root / name / "Pixel4"
        if not d.is_dir():
            print(f"{name}: not found under {root}, skipped")
            continue
        opts = RunOptions(weights=weights, signals=signals)
        trace = load_trace(d, signals=signals)
        wls = solve_wls(trace, elev_mask_deg=opts.elev_mask_deg, weighting=opts.wls_weighting)
        rows, notes = {}, []
        for mode in MODES:
            t0 = time.perf_counter()
            try:
                res = get_mode(mode)(trace, wls, opts)
            except (GnssfuseError, ImportError) as exc:
                notes.append(f"  {mode}: unavailable ({str(exc).splitlines()[0][:150]})")
                continue
            rows[mode] = metrics(trace, res)
            notes.append(f"  {mode}: {time.perf_counter() - t0:.2f} s, solved {int(res.valid.sum())}/{trace.n_epochs}"
                         + (f", info {_short(res.info)}" if mode.startswith("fused") else ""))
        print(f"\n{trace.name}  signals={','.join(signals)}  epochs={trace.n_epochs}  skipped={trace.skipped}")
        print(format_table(rows))
        print("\n".join(notes))


def _short(info: dict) -> dict:
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in info.items()
            if isinstance(v, (int, float)) and not k.endswith("_s")}


def tune(root: Path) -> None:
    """fused-nodnn vs wls on the training traces with the current defaults (the tuning objective)."""
    from fusion.io_gsdc import load_trace

    scores = []
    for name in TRAIN:
        trace = load_trace(root / name / "Pixel4")
        wls = solve_wls(trace)
        rows = {"wls": metrics(trace, get_mode("wls")(trace, wls, RunOptions())),
                "fused-nodnn": metrics(trace, fuse(trace, wls, RunOptions(), want_cov=False))}
        scores.append(rows["fused-nodnn"]["gsdc_score"])
        print(f"\n{trace.name}\n{format_table(rows)}")
    print(f"\nmean fused-nodnn GSDC score over the training traces: {np.mean(scores):.3f}  ({GraphConfig()})")


def speed(root: Path, repeats: int) -> None:
    d = root / "2021-04-28-US-MTV-1" / "Pixel4"
    if d.is_dir():
        from fusion.io_gsdc import load_trace

        trace = load_trace(d)
    else:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from test_graph import synth_trace

        trace = synth_trace(E=2000)
    wls = solve_wls(trace)
    cfg = GraphConfig()
    print(f"\nspeed on {trace.name}: {trace.n_epochs} epochs, {int(trace.mask.sum())} measurements "
          f"(best of {repeats}; 2 shared CPU cores)")

    def best(f):
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = f()
            ts.append(time.perf_counter() - t0)
        return min(ts), out

    t_prep, inp = best(lambda: prepare_inputs(trace, wls, cfg))
    t_build, (graph, values, _) = best(lambda: build_graph(trace, inp, cfg, use_prior=False))
    t_batch, res = best(lambda: fuse(trace, wls, RunOptions(), cfg=cfg, want_cov=False))
    t_cov, res_c = best(lambda: fuse(trace, wls, RunOptions(), cfg=cfg, want_cov=True))
    t_inc, res_i = best(lambda: fuse(trace, wls, RunOptions(incremental=True), cfg=cfg))
    n_f = graph.size()
    print(f"  inputs (vectorised)            {1000 * t_prep:8.1f} ms")
    print(f"  graph build ({n_f} factors)   {1000 * t_build:8.1f} ms  = {1e6 * t_build / n_f:.1f} us/factor")
    print(f"  batch total (prep+build+LM)    {t_batch:8.2f} s   ({res.info['iterations']} LM iterations, "
          f"solve {res.info['solve_s']:.2f} s = {1e6 * res.info['solve_s'] / n_f / max(res.info['iterations'], 1):.1f} "
          f"us/factor/iteration)")
    print(f"  batch + marginal covariances   {t_cov:8.2f} s   (marginals {res_c.info['cov_s']:.2f} s)")
    print(f"  incremental ISAM2              {res_i.info['ms_per_epoch']:8.2f} ms/epoch "
          f"(total {t_inc:.2f} s incl. prep)")
    gap = np.linalg.norm(res_i.pos - res.pos, axis=1)
    print(f"  ISAM2 vs batch position difference: median {np.nanmedian(gap):.3f} m, max {np.nanmax(gap):.3f} m")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=("all", "accuracy", "speed", "tune"), default="all")
    p.add_argument("--data", type=Path, default=DATA, help="a GSDC 2021 train/ folder")
    p.add_argument("--weights", type=Path, default=None, help="DNN checkpoint (default: shipped weights)")
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args(argv)
    if args.part in ("all", "accuracy"):
        accuracy(args.data, args.weights)
    if args.part == "tune":
        tune(args.data)
    if args.part in ("all", "speed"):
        speed(args.data, args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
