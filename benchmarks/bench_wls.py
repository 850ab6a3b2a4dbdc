"""Benchmark: our batched WLS against gnss_lib_py's per-epoch ``solve_wls`` on one real trace.

Both solvers get the *same* measurements: gnss_lib_py's own GSDC 2021 parser
(``AndroidDerived2021``: one-epoch timestamp shift, hosts' timing-outlier filter, corrected
pseudoranges) restricted to GPS L1; we pack its rows into padded arrays for ours. Timings cover the
solve only (parsing and packing excluded, packing reported separately). Accuracy is horizontal
(p50 / p95 / GSDC score against ``ground_truth.csv``; horizontal errors do not depend on the
GSDC 2021 truth-height defect). Every ratio comes from timings taken in the same process.

Usage (gnss_lib_py needs pandas < 3, so it lives in its own venv; our package only needs numpy
and pymap3d there):

    python -m venv /tmp/glpvenv && /tmp/glpvenv/bin/pip install gnss-lib-py pymap3d
    PYTHONPATH=. /tmp/glpvenv/bin/python benchmarks/bench_wls.py [--trace DIR] [--repeat N]
    GNSSFUSE_GLP_PYTHON=/tmp/glpvenv/bin/python python benchmarks/bench_wls.py   # same, re-run there

When gnss_lib_py is not importable, ``$GNSSFUSE_GLP_PYTHON`` (an interpreter that has it) is used
to re-run this script as a whole; without it the script says "gnss_lib_py not installed: ours
only" and times ours alone, loading with ``fusion.prepare.load``. ``run(quick)`` follows the
``benchmarks/README.md`` convention (records; quick = one timing repeat instead of 10).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.run_all import JSON_PREFIX, parse_records  # noqa: E402  (imports only numpy at top)
from fusion.geometry import geodetic2ecef  # noqa: E402
from fusion.io.truth import match_nearest, read_truth_csv  # noqa: E402
from fusion.eval.metrics import ned_errors, summarize  # noqa: E402
from fusion.trace import pack_rows  # noqa: E402
from fusion.estimate.wls import solve_wls_arrays  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
SHARED_TRACE = SHARED / "gsdc2021" / "train" / "2020-05-14-US-MTV-1" / "Pixel4"
SHIPPED_TRACE = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
DEFAULT_TRACE = SHARED_TRACE if SHARED_TRACE.is_dir() else SHIPPED_TRACE
HELD_OUT_TRACE = SHARED / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
#: Interpreter with gnss_lib_py, used to re-run this script when the current one lacks it.
GLP_PYTHON_ENV = "GNSSFUSE_GLP_PYTHON"
NO_GLP = "gnss_lib_py not installed: ours only"


def truth_at(folder: Path, t_ms: np.ndarray) -> np.ndarray:
    """(E, 3) ECEF truth at receive times t_ms (nearest ground-truth row within 10 ms, else NaN).
    Heights as in the file: only horizontal errors are reported here."""
    gt = read_truth_csv(folder / "ground_truth.csv")
    llh = gt[["lat_deg", "lon_deg", "height_m"]].to_numpy(float)
    return match_nearest(np.asarray(t_ms), gt["t_ms"].to_numpy(np.int64), geodetic2ecef(llh), tol_ms=10)


def accuracy(pos: np.ndarray, truth: np.ndarray) -> tuple[str, dict]:
    """(printable line, summarize() dict) of the horizontal accuracy of ``pos`` (E, 3)."""
    s = summarize(ned_errors(pos, truth))
    return (f"h p50 {s['h_p50']:6.2f} m  h p95 {s['h_p95']:6.2f} m  GSDC score {s['gsdc_score']:6.2f} m"
            f"  (n={s['n']}, unscored {s['n_excluded']})"), s


def time_ours(arrays: tuple, repeat: int, **kw) -> tuple[float, object]:
    """Best-of-``repeat`` wall time [s] of our solve and its result."""
    best, res = np.inf, None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        res = solve_wls_arrays(*arrays, **kw)
        best = min(best, time.perf_counter() - t0)
    return best, res


def _acc_records(label: str, s: dict, note: str) -> list[dict]:
    return [{"name": f"{label} h p50", "value": round(float(s["h_p50"]), 3), "unit": "m", "note": note},
            {"name": f"{label} h p95", "value": round(float(s["h_p95"]), 3), "unit": "m", "note": note},
            {"name": f"{label} GSDC score", "value": round(float(s["gsdc_score"]), 3), "unit": "m",
             "note": note}]


def _ours_only(trace: Path, repeat: int, why: str) -> list[dict]:
    """Ours alone on the trace as ``fusion.prepare.load`` loads it (no gnss_lib_py parser)."""
    from fusion.prepare.load import load_trace
    print(f"{NO_GLP} ({why})")
    tr = load_trace(trace)
    arrays = (tr.sat_pos, tr.pr, tr.mask, tr.pr_sigma)
    recs = []
    for w in ("elevation", "none"):
        t_ours, res = time_ours(arrays, repeat, weighting=w)
        line, s = accuracy(res.pos, tr.truth)
        print(f"ours ({w:9s}): {tr.n_epochs / t_ours:10.0f} epochs/s  ({t_ours:.4f} s)  {line}")
        note = (f"{NO_GLP}; {trace.parent.name}/{trace.name} via fusion.prepare.load, {tr.n_epochs} epochs, "
                f"best of {repeat}, cpu")
        recs += [{"name": f"ours WLS ({w} weights) throughput", "value": round(tr.n_epochs / t_ours, 1),
                  "unit": "epochs/s", "note": note},
                 *_acc_records(f"ours WLS ({w} weights)", s, note)]
    return recs


def _with_glp(trace: Path, repeat: int, derived: Path) -> list[dict]:
    """gnss_lib_py and ours on gnss_lib_py's parse of ``derived``, timed in this process."""
    from gnss_lib_py.algorithms.snapshot import solve_wls as glp_solve_wls
    from gnss_lib_py.parsers.google_decimeter import AndroidDerived2021

    nav = AndroidDerived2021(str(derived))
    nav = nav.where("gnss_id", "gps").where("signal_type", "l1")
    t_rows = np.asarray(nav["gps_millis"], np.int64)
    epochs, idx = np.unique(t_rows, return_inverse=True)
    E = len(epochs)
    tname = f"{trace.parent.name}/{trace.name}"
    print(f"trace {tname}: {E} epochs, {len(t_rows)} GPS L1 rows (gnss_lib_py AndroidDerived2021 parser)")
    truth = truth_at(trace, epochs)

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

    base = f"{tname}, {E} epochs GPS L1 (gnss_lib_py parser), cpu"
    line, s = accuracy(glp_pos, truth)
    print(f"gnss_lib_py solve_wls (unweighted) : {E / t_glp:10.0f} epochs/s  ({t_glp:.3f} s)  {line}")
    glp_note = f"{base}; per-epoch loop, unweighted, 1 run"
    recs = [{"name": "gnss_lib_py solve_wls throughput", "value": round(E / t_glp, 1), "unit": "epochs/s",
             "note": glp_note},
            {"name": "gnss_lib_py solve_wls time", "value": round(t_glp, 4), "unit": "s", "note": glp_note},
            *_acc_records("gnss_lib_py solve_wls", s, glp_note),
            {"name": "ours packing time", "value": round(t_pack * 1e3, 2), "unit": "ms",
             "note": f"{base}; rows -> padded (E, S) arrays"}]
    for w in ("elevation", "none"):
        t_ours, res = time_ours(arrays, repeat, weighting=w)
        line, s = accuracy(res.pos, truth)
        print(f"ours solve_wls_arrays ({w:9s}): {E / t_ours:10.0f} epochs/s  ({t_ours:.4f} s)  "
              f"{line}  [{res.summary()}]")
        print(f"    speed-up over gnss_lib_py: {t_glp / t_ours:.0f}x solve only, "
              f"{t_glp / (t_ours + t_pack):.0f}x including packing ({t_pack * 1e3:.1f} ms)")
        note = f"{base}; best of {repeat}"
        label = f"ours WLS ({w} weights)"
        recs += [{"name": f"{label} throughput", "value": round(E / t_ours, 1), "unit": "epochs/s", "note": note},
                 {"name": f"{label} time", "value": round(t_ours, 5), "unit": "s", "note": note},
                 *_acc_records(label, s, note),
                 {"name": f"{label} speed-up over gnss_lib_py, solve only", "value": round(t_glp / t_ours, 1),
                  "unit": "x", "note": f"{note}; same process"},
                 {"name": f"{label} speed-up over gnss_lib_py, incl. packing",
                  "value": round(t_glp / (t_ours + t_pack), 1), "unit": "x", "note": f"{note}; same process"}]
    return recs


def _rerun_elsewhere(python: str, trace: Path, repeat: int) -> list[dict]:
    """Re-run this script under ``python`` (which has gnss_lib_py); relay its table, return its records.

    Raises RuntimeError with the reason when that interpreter fails or prints no records."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in [str(REPO), os.environ.get("PYTHONPATH")] if p))
    env.pop(GLP_PYTHON_ENV, None)  # the child must never re-run itself again
    cmd = [python, str(Path(__file__).resolve()), "--trace", str(trace), "--repeat", str(repeat), "--json"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    except OSError as exc:
        raise RuntimeError(f"${GLP_PYTHON_ENV}={python}: {exc}") from exc
    for line in proc.stdout.splitlines():
        if not line.startswith(JSON_PREFIX):
            print(line)
    try:
        recs = parse_records(proc.stdout)
    except ValueError as exc:  # json.JSONDecodeError included
        raise RuntimeError(f"${GLP_PYTHON_ENV}={python}: bad {JSON_PREFIX.strip()} line: {exc}") from exc
    if proc.returncode != 0 or recs is None:
        tail = (proc.stderr.strip().splitlines() or ["(no stderr)"])[-1]
        raise RuntimeError(f"${GLP_PYTHON_ENV}={python} exited {proc.returncode}: {tail}")
    print(f"(gnss_lib_py comparison run under {python})")
    return [dict(r, note=f"{r['note']}; run under ${GLP_PYTHON_ENV}={python}") for r in recs]


def bench(trace: Path = DEFAULT_TRACE, repeat: int = 10) -> list[dict]:
    """Print the table and return records (see module docstring for what is compared)."""
    derived = sorted(Path(trace).glob("*_derived.csv*"))
    if not derived:
        from fusion.errors import DataError
        raise DataError(f"bench_wls: no *_derived.csv[.gz] in {trace}")
    try:
        import gnss_lib_py  # noqa: F401
    except ImportError as exc:
        python = os.environ.get(GLP_PYTHON_ENV)
        if not python:
            return _ours_only(trace, repeat, f"{exc}; set ${GLP_PYTHON_ENV} to an interpreter that has it")
        try:
            return _rerun_elsewhere(python, trace, repeat)
        except RuntimeError as err:
            return _ours_only(trace, repeat, str(err))
    return _with_glp(trace, repeat, derived[0])


def run(quick: bool = False) -> list[dict]:
    """Records for ``benchmarks/run_all.py``; quick times ours once instead of best of 10.

    With the shared data, the accuracy rows are repeated on the held-out test trace: how hard that
    trace is for any WLS (gnss_lib_py's too), independently of our solver."""
    recs = bench(DEFAULT_TRACE, repeat=1 if quick else 10)
    if HELD_OUT_TRACE.is_dir():
        accuracy_rows = ("h p50", "h p95", "GSDC score")
        recs += [dict(r, name=f"{r['name']}, held-out 2021-04-28-US-MTV-1")
                 for r in bench(HELD_OUT_TRACE, repeat=1) if r["name"].endswith(accuracy_rows)]
    return recs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trace", type=Path, default=DEFAULT_TRACE,
                    help="GSDC 2021 <collection>/<phone> folder with *_derived.csv and ground_truth.csv")
    ap.add_argument("--repeat", type=int, default=10, help="runs of our solver (best time kept)")
    ap.add_argument("--json", action="store_true", help=f"also print a last '{JSON_PREFIX.strip()}' line")
    args = ap.parse_args(argv)
    try:
        recs = bench(args.trace, args.repeat)
    except ValueError as exc:  # GnssfuseError and friends: one line, no traceback
        print(exc, file=sys.stderr)
        return 2
    if args.json:
        print(JSON_PREFIX + json.dumps(recs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
