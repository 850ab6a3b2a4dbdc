"""Is more of the learned shift to be had from the drive's slow part? Two truth-free post-hoc shifts of ``fused``.

On the GSDC drives the learned part's whole gain is a shift of each drive (``results/bias_share.md``). Two ways to
take more of it, applied after the fact to a cross-validation's per-epoch errors (``crossval.py`` ``results.pkl``
with the modes ``dnn``, ``fused-nodnn`` and ``fused``; the difference of two modes' errors is the difference of their
positions, so neither shift reads the truth):

- *toward dnn*: ``fused + alpha * M_W(dnn - fused)``: the snapshot network's slow part, where the graph's
  pseudoranges may hold the drive's offset back;
- *further*: ``fused + alpha * M_W(fused - fused-nodnn)``: the graph's own learned move, taken further (alpha > 0)
  or back (alpha < 0).

``M_W`` is a centred moving mean over W epochs (1 s each on these drives; epochs without both estimates skipped), on
north and east only. Printed: the pooled GSDC score of each and its ratio to ``fused-nodnn``.

    python experiments/shift_lowpass.py /tmp/cv_ens5/results.pkl
"""
from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.estimate.variance_factor import centred_sums  # noqa: E402
from fusion.eval.metrics import summarize  # noqa: E402

WINDOWS = (60, 300, 900, 0)          # 0: the whole drive
ALPHAS = {"toward dnn": (0.25, 0.5, 1.0), "further": (-0.25, 0.25, 0.5, 1.0)}


def moving_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Centred moving mean over ``window`` rows (0: every row) of x (E,k), rows with a NaN skipped -> (E,k); NaN
    where the window holds no complete row."""
    ok = np.isfinite(x).all(1)
    sums = centred_sums(np.arange(len(x), dtype=float), np.c_[np.where(ok[:, None], x, 0.0), ok],
                        window if window > 0 else np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums[:, :-1] / sums[:, -1:]


def slow_move(toward: np.ndarray, away: np.ndarray, window: int) -> np.ndarray:
    """(E,3) the moving mean of (toward - away) (E,3) NED, horizontally only (0 down and where no window holds a
    complete row)."""
    move = moving_mean(toward - away, window)
    move[:, 2] = 0.0
    return np.where(np.isfinite(move), move, 0.0)


def shifted(fused: np.ndarray, toward: np.ndarray, away: np.ndarray, alpha: float, window: int) -> np.ndarray:
    """fused (E,3) NED errors moved by alpha x :func:`slow_move`."""
    return fused + alpha * slow_move(toward, away, window)


def scores(results: dict) -> list[tuple[str, int, float, float]]:
    """(variant, window, alpha, pooled GSDC score) of each variant, window and alpha."""
    drives = [results[f][d] for f in results for d in results[f]]
    rows = []
    for variant, alphas in ALPHAS.items():
        pairs = [(r["dnn"]["err"], r["fused"]["err"]) if variant == "toward dnn"
                 else (r["fused"]["err"], r["fused-nodnn"]["err"]) for r in drives]
        for window in WINDOWS:
            moves = [slow_move(toward, away, window) for toward, away in pairs]
            for a in alphas:
                err = np.concatenate([r["fused"]["err"] + a * m for r, m in zip(drives, moves)])
                rows.append((variant, window, a, summarize(err)["gsdc_score"]))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("results", type=Path, help="crossval.py's results.pkl (modes dnn, fused-nodnn, fused)")
    args = p.parse_args(argv)
    results = pickle.loads(args.results.read_bytes())
    pool = {m: summarize(np.concatenate([results[f][d][m]["err"] for f in results for d in results[f]]))["gsdc_score"]
            for m in ("fused-nodnn", "fused", "dnn")}
    print(" / ".join(f"{m} {s:.3f} m" for m, s in pool.items()))
    print("| shift | window [epochs] | alpha | GSDC score [m] | / fused-nodnn |\n|---|---|---|---|---|")
    for variant, window, a, s in scores(results):
        print(f"| {variant} | {window or 'drive'} | {a:+.2f} | {s:.3f} | {s / pool['fused-nodnn']:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
