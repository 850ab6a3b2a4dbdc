"""How much could per-satellite pseudorange sigmas give the graph, and which part of the error they must
follow? An experiment with truth-derived ("oracle") sigmas: never a model input, never at inference.

Per GSDC training drive, ``fused-nodnn`` with the physical sigma model, and with slot sigmas
``sqrt(phys^2 + x^2)`` at the "relative" level (``GraphConfig.slot_noise_level``: satellites reweighted against
each other within an epoch, the level held at the physical model's, so only who is trusted changes) where x is:

- ``oracle |e|``: each pseudorange's error at the truth (clock removed: the epoch's median), what a perfect
  per-satellite head would know;
- ``oracle slow``: its centred 15 s mean along the satellite's arc (multipath that lasts);
- ``oracle fast``: the rest (``e`` minus the slow part);
- ``history 15 s`` / ``history 30 s``: no truth, the residual at the no-prior graph's own solution, averaged
  the same way (what a satellite's recent residuals could tell a model).

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/oracle_sigmas.py      # ~1 min
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.estimate.graph.config import GraphConfig  # noqa: E402
from fusion.estimate.graph.consistency import row_medians  # noqa: E402
from fusion.estimate.graph.fuse import fuse  # noqa: E402
from fusion.eval.metrics import ned_errors, summarize  # noqa: E402
from fusion.geometry import line_of_sight  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))


def arc_mean(x: np.ndarray, sat_id: np.ndarray, t: np.ndarray, half_s: float) -> np.ndarray:
    """(E,S) centred mean of x (E,S) over +-half_s along each satellite's track (NaN where x is)."""
    out = np.full_like(x, np.nan)
    for sid in np.unique(sat_id[np.isfinite(x)]):
        ks, ss = np.nonzero((sat_id == sid) & np.isfinite(x))
        order = np.argsort(ks)
        ks, ss = ks[order], ss[order]
        csum = np.r_[0.0, np.cumsum(x[ks, ss])]
        lo = np.searchsorted(t[ks], t[ks] - half_s)
        hi = np.searchsorted(t[ks], t[ks] + half_s, side="right")
        out[ks, ss] = (csum[hi] - csum[lo]) / (hi - lo)
    return out


def clock_free(trace, pos: np.ndarray) -> np.ndarray:
    """(E,S) pseudorange residuals at pos (E,3), each epoch's median removed (NaN off the mask)."""
    rng, _ = line_of_sight(trace.sat_pos, np.nan_to_num(pos))
    r = np.where(trace.mask & np.isfinite(pos).all(axis=1)[:, None], trace.pr - rng, np.nan)
    return r - row_medians(r)[:, None]


def provider(extra: np.ndarray):
    def slot_noise(trace, at, valid):
        phys = np.sqrt(trace.pr_sigma ** 2 + 1.0)
        return np.sqrt(phys ** 2 + np.nan_to_num(extra) ** 2), np.zeros_like(phys)
    return slot_noise


def main() -> int:
    opts = RunOptions(graph=GraphConfig(slot_noise_level="relative"))
    rows = []
    for folder in sorted((SHARED / "gsdc2021/train").glob("2020-*/Pixel4")):
        tr = load_trace(folder)
        wls = solve_initial(tr, opts)
        t = tr.t_ms / 1000.0
        base = fuse(tr, wls, opts, want_cov=False)
        e = clock_free(tr, tr.truth)
        slow = arc_mean(e, tr.sat_id, t, 7.5)
        own = clock_free(tr, np.where(base.valid[:, None], base.pos, np.nan))
        extras = {"oracle |e|": e, "oracle slow": slow, "oracle fast": e - slow,
                  "history 15 s": arc_mean(own, tr.sat_id, t, 7.5), "history 30 s": arc_mean(own, tr.sat_id, t, 15.0)}
        score = {"physical": summarize(ned_errors(base.pos, tr.truth))["gsdc_score"]}
        for name, x in extras.items():
            res = fuse(tr, wls, opts, want_cov=False, slot_noise=provider(x))
            score[name] = summarize(ned_errors(res.pos, tr.truth))["gsdc_score"]
        rows.append((folder.parent.name, score))
    names = list(rows[0][1])
    print("| drive | " + " | ".join(names) + " |")
    print("|---" * (len(names) + 1) + "|")
    for drive, score in rows:
        print(f"| {drive} | " + " | ".join(f"{score[n]:.2f}" for n in names) + " |")
    print("| mean | " + " | ".join(f"{np.mean([s[n] for _, s in rows]):.2f}" for n in names) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
