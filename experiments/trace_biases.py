"""Can a drive's offset be estimated from its own pseudoranges? Trace-level biases estimated jointly with every
epoch's position and clock, on the GSDC 2021 training drives (the truth scores the result, nothing else).

The learned part's gain on these drives is a shift of each whole drive (``experiments/results/bias_share.md``),
and the 0.93 x target needs most of each drive's own offset. Two physical models of an error that lasts longer
than an epoch are tried here, each as extra unknowns beside every epoch's free position and clock, with a
zero-mean prior, around the robust WLS solution (one linear step; ``WLS`` below):

- ``arc``: a constant bias per satellite arc (orbit and clock errors, multipath that lasts), prior sigma
  ``--arc-sigma``;
- ``iono`` / ``iono+tropo``: one scale per drive on the file's modelled ionospheric (and tropospheric) delay
  (a broadcast model that misses a share of the day's ionosphere), prior sigma ``--scale-sigma``; and, for
  comparison, the ionospheric scale fixed at the median of the other drives' scales at the truth (what a constant
  learned from the training drives would do; each drive's own scale at the truth is printed beside its estimate).

An epoch's position and clock are eliminated (its weighted projector ``P = W - W A (A'WA)^-1 A'W``), the biases
solved from the sum over epochs, and each epoch's position moved by what the biases take out of its
pseudoranges. Epochs of fewer than five satellites add nothing (their residuals fit exactly).

    python experiments/trace_biases.py [--drives NAME ...] [--arc-sigma 0.5 1 2] [--scale-sigma 0.5]

Prints a markdown table of GSDC scores [m] per drive and pooled (``experiments/results/trace_biases.md``).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from few_satellites import SHARED  # noqa: E402
from fusion.estimate.variance_factor import sigma_model  # noqa: E402
from fusion.estimate.wls import solve_wls  # noqa: E402
from fusion.eval.metrics import ned_errors, summarize  # noqa: E402
from fusion.geometry import line_of_sight  # noqa: E402
from fusion.io.gsdc import DERIVED_DELAY_MS  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.trace import Trace  # noqa: E402

TRAIN = SHARED / "gsdc2021" / "train"
#: A satellite's arc ends where its measurements stop for longer than this [ms].
ARC_GAP_MS = 10_000
#: Epochs with fewer used satellites add nothing (four fit exactly).
MIN_SATS = 5


def drives(names: list[str] | None) -> list[Path]:
    """The training drives' Pixel4 folders (the 2021-04-28 test drives excluded), or those ``names``."""
    found = sorted(p / "Pixel4" for p in TRAIN.iterdir() if p.name < "2021" and (p / "Pixel4").is_dir())
    return [p for p in found if names is None or p.parent.name in names]


def atmosphere(folder: Path, trace: Trace) -> np.ndarray:
    """(E,S,2) the derived file's modelled ionospheric and tropospheric delay [m] of each slot, NaN where none."""
    df = pd.read_csv(next(folder.glob("*_derived.csv*")), usecols=["millisSinceGpsEpoch", "svid", "signalType",
                                                                     "ionoDelayM", "tropoDelayM"])
    df = df[df.signalType == "GPS_L1"]
    key = pd.MultiIndex.from_arrays([df.millisSinceGpsEpoch - DERIVED_DELAY_MS, df.svid])
    table = df.set_index(key)[["ionoDelayM", "tropoDelayM"]]
    table = table[~table.index.duplicated()]
    E, S = trace.pr.shape
    slots = pd.MultiIndex.from_arrays([np.repeat(trace.t_ms[:, None], S, 1).ravel(), (trace.sat_id % 1000).ravel()])
    return table.reindex(slots).to_numpy().reshape(E, S, 2)


def arcs(trace: Trace, used: np.ndarray) -> tuple[np.ndarray, int]:
    """(E,S) arc number of each used slot (-1 elsewhere) and the number of arcs: a satellite's signal's run of
    used epochs without a gap over :data:`ARC_GAP_MS`."""
    out, last, n = -np.ones(used.shape, int), {}, 0
    for e, s in zip(*np.nonzero(used)):
        key = (int(trace.sat_id[e, s]), int(trace.signal[e, s]))
        t_prev, arc = last.get(key, (None, -1))
        if t_prev is None or trace.t_ms[e] - t_prev > ARC_GAP_MS:
            arc, n = n, n + 1
        out[e, s] = arc
        last[key] = (trace.t_ms[e], arc)
    return out, n


class EpochSystem:
    """The WLS solution's residuals and geometry, with every epoch's position and clock ready to eliminate.

    pos (E,3) ECEF the WLS positions; used (E,S) the slots it used above the mask; per epoch e of at least
    :data:`MIN_SATS` used slots: its slots, residuals r (n,), projector P (n,n) and gain G (4,n) (position and
    clock from pseudorange errors). ``at_truth``: the residuals at the true positions instead, only each epoch's
    clock eliminated (what the biases are when the position is known: a diagnosis, never an estimate)."""

    def __init__(self, trace: Trace, at_truth: bool = False):
        w, self.at_truth = solve_wls(trace), at_truth
        self.pos = np.where(w.valid[:, None], w.pos, np.nan)
        sel, sigma = sigma_model(trace, self.pos, 10.0)
        self.used = np.asarray(w.used, bool) & sel
        at = trace.truth if at_truth else self.pos
        rng, los = line_of_sight(trace.sat_pos, np.nan_to_num(at))
        resid = trace.pr - rng - (0.0 if at_truth else w.clock_m[:, None])
        self.epochs = {}
        for e in np.nonzero((self.used.sum(axis=1) >= MIN_SATS) & np.isfinite(at).all(axis=1))[0]:
            s = np.nonzero(self.used[e])[0]
            A = np.ones((len(s), 1)) if at_truth else np.column_stack([-los[e, s], np.ones(len(s))])
            W = np.diag(1.0 / sigma[e, s] ** 2)
            G = np.linalg.solve(A.T @ W @ A, A.T @ W)
            self.epochs[e] = (s, resid[e, s], W - W @ A @ G, G)

    def solve(self, design, n_params: int, prior_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Biases b (n_params,) of the model ``design(e, slots) -> (X (n,k), columns (k,))`` (pseudorange error
        ``X @ b[columns]``) under a zero-mean prior of ``prior_sigma``, their sigmas from the data alone (the
        marginal of the normal matrix without the prior; inf where the data say nothing), and the positions (E,3)
        with what they take out of each epoch (``at_truth``: the WLS positions as they are)."""
        N, rhs = np.zeros((n_params, n_params)), np.zeros(n_params)
        for e, (s, r, P, _) in self.epochs.items():
            X, cols = design(e, s)
            N[np.ix_(cols, cols)] += X.T @ P @ X
            rhs[cols] += X.T @ P @ r
        b = np.linalg.solve(N + np.eye(n_params) / prior_sigma ** 2, rhs)
        sd = np.sqrt(np.abs(np.diag(np.linalg.pinv(N))))
        sd[np.diag(N) == 0] = np.inf
        return b, sd, self.pos if self.at_truth else self.apply(design, b)

    def apply(self, design, b: np.ndarray) -> np.ndarray:
        """(E,3) the WLS positions with what the biases ``b`` of ``design`` (:meth:`solve`) take out of each
        epoch's pseudoranges."""
        pos = self.pos.copy()
        for e, (s, _, _, G) in self.epochs.items():
            X, cols = design(e, s)
            pos[e] = self.pos[e] - (G @ (X @ b[cols]))[:3]
        return pos


def score(err: np.ndarray) -> float:
    """GSDC score [m] of (n,3) NED errors (NaN rows skipped)."""
    return summarize(err)["gsdc_score"]


def variants(folder: Path, args) -> tuple[dict[str, tuple[np.ndarray, str]], float, Callable]:
    """For one drive: name -> (NED errors (n,3), a note) for WLS and every bias model; the ionospheric scale at
    the truth; and a function of a fixed scale k giving the NED errors of WLS with (1 + k) x the modelled
    ionosphere."""
    trace = load_trace(folder)
    sysm = EpochSystem(trace)
    out = {"WLS": (ned_errors(sysm.pos, trace.truth), "")}
    arc, n_arcs = arcs(trace, sysm.used)
    for sb in args.arc_sigma:
        b, _, pos = sysm.solve(lambda e, s: (np.eye(len(s)), arc[e, s]), n_arcs, sb)
        note = f"90 % of arcs within {np.percentile(np.abs(b), 90):.2f} m"
        out[f"arc, sigma {sb:g} m"] = (ned_errors(pos, trace.truth), note)
    atm = np.nan_to_num(atmosphere(folder, trace))
    truth = EpochSystem(trace, at_truth=True)
    k_iono = np.nan
    for name, cols in (("iono", [0]), ("iono+tropo", [0, 1])):
        design = lambda e, s, cols=cols: (atm[e, s][:, cols], np.arange(len(cols)))   # noqa: E731
        k, sd, pos = sysm.solve(design, len(cols), args.scale_sigma)
        k_true = truth.solve(design, len(cols), 1e3)[0]
        k_iono = k_true[0] if name == "iono" else k_iono
        note = "; ".join(f"{c} {v:+.2f} +- {d:.2f} (at the truth {t:+.2f})"
                         for c, v, d, t in zip(("iono", "tropo"), k, sd, k_true))
        out[f"{name} scale"] = (ned_errors(pos, trace.truth), note)
    iono = lambda e, s: (atm[e, s][:, :1], np.array([0]))                            # noqa: E731
    return out, k_iono, lambda k: ned_errors(sysm.apply(iono, np.array([k])), trace.truth)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--drives", nargs="+", default=None, help="drive names (default: the twelve training drives)")
    p.add_argument("--arc-sigma", type=float, nargs="+", default=[0.5, 1.0, 2.0], help="arc bias prior sigmas [m]")
    p.add_argument("--scale-sigma", type=float, default=0.5, help="prior sigma of the delay scales")
    args = p.parse_args()
    rows, pooled = [], {}
    found = [(folder.parent.name, *variants(folder, args)) for folder in drives(args.drives)]
    for i, (drive, res, _, fixed) in enumerate(found):
        others = [k for j, (_, _, k, _) in enumerate(found) if j != i]
        if others:
            # a constant the other drives' truth sets, as training would (leave this drive out)
            k = float(np.median(others))
            res["iono scale fixed"] = (fixed(k), f"{k:+.2f}, the median of the other drives' at the truth")
        for name, (err, _) in res.items():
            pooled.setdefault(name, []).append(err)
        rows.append((drive, res))
    names = list(pooled)
    print("| drive | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
    for drive, res in rows:
        cells = [f"{score(err):.2f}" + (f" ({note})" if note else "") for err, note in res.values()]
        print(f"| {drive} | " + " | ".join(cells) + " |")
    print("| pooled | " + " | ".join(f"{score(np.concatenate(pooled[n])):.3f}" for n in names) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
