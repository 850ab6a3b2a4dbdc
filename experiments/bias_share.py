"""How much of the learned part's gain is a shift of the whole trace (a bias), and how much is the error
inside it: `fused` against `fused-nodnn` with each trace's own mean horizontal error removed.

An analysis of errors against the truth, after the fact; nothing here feeds a model. On the GSDC drives it
reads the unseen-drive errors of cross-validation runs (``experiments/crossval.py``'s ``results.pkl``); on
the raw logs (the Pixel5 RINEX test trace, reported only, and smartLoc, never trained on) it runs both modes
with the given networks.

    python experiments/bias_share.py --cv RUN [RUN ...] [--weights A.pt ...]
"""
from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from experiments.learned_raw_logs import LOGS  # noqa: E402
from fusion.eval.metrics import summarize, trace_errors  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

MODES = ("fused-nodnn", "fused")


def score(ne: list[np.ndarray]) -> float:
    """GSDC score [m] of (E,2) N/E errors pooled (:func:`fusion.eval.metrics.summarize`; the down axis plays
    no part in it)."""
    e = np.concatenate(ne)
    return float(summarize(np.c_[e, np.zeros(len(e))])["gsdc_score"])


def demeaned(ne: np.ndarray) -> np.ndarray:
    """(E,2) errors less their own mean (the trace's constant shift)."""
    return ne - np.nanmean(ne, axis=0)


def cv_errors(run: Path) -> dict[str, dict[str, np.ndarray]]:
    """drive -> mode -> (E,2) N/E errors of one cross-validation run's unseen drives."""
    res = pickle.loads((run / "results.pkl").read_bytes())
    return {d: {m: r[m]["err"][:, :2] for m in MODES} for fold in res.values() for d, r in fold.items()}


def log_errors(path: Path, kw: dict, weights: Path | None) -> dict[str, np.ndarray]:
    """mode -> (E,2) N/E errors on one raw log (the pipeline's defaults, the given network)."""
    opts = RunOptions(weights=weights, sigma_calibration=False, **kw)
    trace = load_trace(path, min_sats=1, **load_options(opts))
    out = run_modes(trace, list(MODES), opts, wls=solve_initial(trace, opts))
    return {m: trace_errors(trace, out[m])[:, :2] for m in MODES}


def row(name: str, errs: list[dict[str, np.ndarray]]) -> str:
    """One table row: both modes' scores as they are and with each trace's mean removed."""
    cells = []
    for fix in (lambda e: e, demeaned):
        s = [score([fix(e[m]) for e in errs]) for m in MODES]
        cells.append(f"{s[0]:.2f} / {s[1]:.2f} ({s[1] / s[0]:.3f} x)")
    return f"| {name} | " + " | ".join(cells) + " |"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cv", type=Path, nargs="*", default=[], help="crossval.py output folders (results.pkl)")
    p.add_argument("--weights", type=Path, nargs="*", default=[], help="checkpoints for the raw logs")
    args = p.parse_args(argv)
    print("| traces | fused-nodnn / fused | each trace's mean removed |\n|---|---|---|")
    for run in args.cv:
        drives = cv_errors(run)
        print(row(f"GSDC drives pooled, {run}", list(drives.values())), flush=True)
    for name, (path, kw) in LOGS.items():
        for w in args.weights if path.exists() else []:
            print(row(f"{name}, {w}", [log_errors(path, kw, w)]), flush=True)
    for run in args.cv:
        print(f"\nMean N / E error [m] per drive, {run}:\n\n| drive | fused-nodnn | fused |\n|---|---|---|")
        for d, e in cv_errors(run).items():
            print(f"| {d} | " + " | ".join("{:+.2f} / {:+.2f}".format(*np.nanmean(e[m], 0)) for m in MODES) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
