"""What the one-epoch factor API (``learned.factor.learned_prior``) loses against the whole-trace prediction
the ``dnn`` mode makes: a lone epoch has no history (residual change, arc age), and a caller may leave out
the reported pseudorange sigma. On the two held-out test traces (never trained or tuned on), from the same
robust WLS guesses the ``dnn`` mode uses; GSDC score (mean of horizontal p50 and p95) [m].

    python experiments/lone_epoch.py > experiments/results/lone_epoch.md
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.errors import GeometryError  # noqa: E402
from fusion.eval.metrics import ned_errors, summarize  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.factor import learned_prior  # noqa: E402
from learned.infer import Corrector  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRACES = ("2021-04-28-US-MTV-1/Pixel4", "2021-04-28-US-SJC-1/Pixel4")


def per_epoch(corrector: Corrector, trace, guess: np.ndarray, ok: np.ndarray, with_sigma: bool) -> np.ndarray:
    """(E,3) ECEF: ``learned_prior`` epoch by epoch, the guess where it declines."""
    out = guess.copy()
    for k in np.flatnonzero(ok):
        sigma = trace.pr_sigma[k] if with_sigma else np.ones(trace.mask.shape[1])
        try:
            out[k] = learned_prior(corrector, trace.sat_pos[k], trace.pr[k], trace.mask[k], guess[k],
                                   pr_sigma=sigma, cn0=None if trace.cn0 is None else trace.cn0[k],
                                   signal=trace.signal[k])[0]
        except GeometryError:
            pass
    return out


def score(pos: np.ndarray, trace) -> str:
    s = summarize(ned_errors(pos, trace.truth))
    return f"{s['gsdc_score']:.2f} | {s['h_p50']:.2f} | {s['h_p95']:.2f}"


def main() -> None:
    corrector = Corrector.load()
    print("| trace | estimate | GSDC score | h p50 | h p95 |\n|---|---|---|---|---|")
    for name in TRACES:
        trace = load_trace(SHARED / "gsdc2021/train" / name)
        wls = solve_initial(trace, RunOptions())
        whole = corrector.predict(trace, wls.pos, wls.valid)
        rows = {"wls (the guess)": wls.pos,
                "dnn: whole trace (Corrector.predict)": np.where(whole.valid[:, None], whole.mean_ecef, wls.pos),
                "one epoch at a time, with pr_sigma": per_epoch(corrector, trace, wls.pos, wls.valid, True),
                "one epoch at a time, pr_sigma left at 1 m": per_epoch(corrector, trace, wls.pos, wls.valid, False)}
        for label, pos in rows.items():
            print(f"| {name} | {label} | {score(pos, trace)} |")


if __name__ == "__main__":
    main()
