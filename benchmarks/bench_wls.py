"""Benchmark: our batched WLS against gnss_lib_py's per-epoch ``solve_wls`` on one real trace.

Both solvers get the *same* measurements: gnss_lib_py's own GSDC 2021 parser
(``AndroidDerived2021``: one-epoch timestamp shift, hosts' timing-outlier filter, corrected
pseudoranges) restricted to GPS L1; we pack its rows into padded arrays for ours. Timings cover the
solve only (parsing and packing excluded, packing reported separately). Accuracy is horizontal
(p50 / p95 / GSDC score against ``ground_truth.csv``; horizontal errors do not depend on the
GSDC 2021 truth-height defect).

Usage (gnss_lib_py needs pandas < 3, so it lives in its own venv; our package only needs numpy
and pymap3d there):

    python -m venv /tmp/glpvenv && /tmp/glpvenv/bin/pip install gnss-lib-py pymap3d
    PYTHONPATH=. /tmp/glpvenv/bin/python benchmarks/bench_wls.py [--trace DIR] [--repeat N]

Without gnss_lib_py the script says so and times ours alone, loading with ``fusion.io_gsdc``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.geometry import geodetic2ecef  # noqa: E402
from fusion.metrics import ned_errors, summarize  # noqa: E402
from fusion.trace import pack_rows  # noqa: E402
from fusion.wls import solve_wls_arrays  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
DEFAULT_TRACE = SHARED / "gsdc2021" / "train" / "2020-05-14-US-MTV-1" / "Pixel4"


def truth_at(folder: Path, t_ms: np.ndarray) -> np.ndarray:
    """(E, 3) ECEF truth at receive times t_ms (nearest ground-truth row within 10 ms, else NaN)."""
    import pandas as pd
    gt = pd.read_csv(folder / "ground_truth.csv").sort_values("millisSinceGpsEpoch")
    gt_t = gt["millisSinceGpsEpoch"].to_numpy()
    j = np.clip(np.searchsorted(gt_t, t_ms), 1, len(gt_t) - 1)
    j = np.where(np.abs(gt_t[j - 1] - t_ms) < np.abs(gt_t[j] - t_ms), j - 1, j)
    llh = gt[["latDeg", "lngDeg", "heightAboveWgs84EllipsoidM"]].to_numpy()[j]
    return np.where((np.abs(gt_t[j] - t_ms) <= 10)[:, None], geodetic2ecef(llh), np.nan)


def accuracy(pos: np.ndarray, truth: np.ndarray) -> str:
    s = summarize(ned_errors(pos, truth))
    return (f"h p50 {s['h_p50']:6.2f} m  h p95 {s['h_p95']:6.2f} m  GSDC score {s['gsdc_score']:6.2f} m"
            f"  (n={s['n']}, unscored {s['n_excluded']})")


def time_ours(arrays: tuple, repeat: int, **kw) -> tuple[float, object]:
    """Best-of-``repeat`` wall time [s] of our solve and its result."""
    best, res = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = solve_wls_arrays(*arrays, **kw)
        best = min(best, time.perf_counter() - t0)
    return best, res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trace", type=Path, default=DEFAULT_TRACE,
                    help="GSDC 2021 <collection>/<phone> folder with *_derived.csv and ground_truth.csv")
    ap.add_argument("--repeat", type=int, default=10, help="runs of our solver (best time kept)")
    args = ap.parse_args(argv)
    derived = sorted(args.trace.glob("*_derived.csv"))
    if not derived:
        print(f"bench_wls: no *_derived.csv in {args.trace}", file=sys.stderr)
        return 2

    try:
        from gnss_lib_py.algorithms.snapshot import solve_wls as glp_solve_wls
        from gnss_lib_py.parsers.google_decimeter import AndroidDerived2021
    except ImportError as exc:
        print(f"gnss_lib_py is not importable ({exc}); timing ours only.")
        from fusion.io_gsdc import load_trace
        tr = load_trace(args.trace)
        arrays = (tr.sat_pos, tr.pr, tr.mask, tr.pr_sigma)
        for w in ("elevation", "none"):
            t_ours, res = time_ours(arrays, args.repeat, weighting=w)
            print(f"ours ({w:9s}): {tr.n_epochs / t_ours:10.0f} epochs/s  {accuracy(res.pos, tr.truth)}")
        return 0

    nav = AndroidDerived2021(str(derived[0]))
    nav = nav.where("gnss_id", "gps").where("signal_type", "l1")
    t_rows = np.asarray(nav["gps_millis"], np.int64)
    epochs, idx = np.unique(t_rows, return_inverse=True)
    E = len(epochs)
    print(f"trace {args.trace.parent.name}/{args.trace.name}: {E} epochs, {len(t_rows)} GPS L1 rows "
          f"(gnss_lib_py AndroidDerived2021 parser)")
    truth = truth_at(args.trace, epochs)

    # gnss_lib_py: its per-epoch Python loop, unweighted (weight_type=None), defaults otherwise.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        glp = glp_solve_wls(nav)
        t_glp = time.perf_counter() - t0
    glp_t = np.asarray(glp["gps_millis"], np.int64)
    glp_pos = np.full((E, 3), np.nan)
    glp_pos[np.searchsorted(epochs, glp_t)] = np.stack(
        [glp["x_rx_wls_m"], glp["y_rx_wls_m"], glp["z_rx_wls_m"]], axis=1)

    # Ours on the same rows, packed into padded (E, S) arrays.
    order = np.argsort(idx, kind="stable")
    t0 = time.perf_counter()
    packed = pack_rows(idx[order], E, {
        "sat_pos": np.stack([nav["x_sv_m"], nav["y_sv_m"], nav["z_sv_m"]], axis=1)[order],
        "pr": np.asarray(nav["corr_pr_m"], float)[order],
        "pr_sigma": np.asarray(nav["raw_pr_sigma_m"], float)[order],
    })
    t_pack = time.perf_counter() - t0
    arrays = (packed["sat_pos"], packed["pr"], packed["mask"], packed["pr_sigma"])

    print(f"gnss_lib_py solve_wls (unweighted) : {E / t_glp:10.0f} epochs/s  ({t_glp:.3f} s)  "
          f"{accuracy(glp_pos, truth)}")
    for w in ("elevation", "none"):
        t_ours, res = time_ours(arrays, args.repeat, weighting=w)
        print(f"ours solve_wls_arrays ({w:9s}): {E / t_ours:10.0f} epochs/s  ({t_ours:.4f} s)  "
              f"{accuracy(res.pos, truth)}  [{res.summary()}]")
        print(f"    speed-up over gnss_lib_py: {t_glp / t_ours:.0f}x solve only, "
              f"{t_glp / (t_ours + t_pack):.0f}x including packing ({t_pack * 1e3:.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
