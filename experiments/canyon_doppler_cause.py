"""Why Doppler makes the graph worse than pseudoranges alone in a deep canyon over the real phone log
(``experiments/canyon_on_phone.py --height 30 100 --width 12 25``): three checks of where it comes from.

1. **Is it the reflections' Doppler?** The graph with Doppler (no carrier) is solved again without the
   Doppler of every reflected or bent signal (an oracle: the canyon's own classes say which).
2. **Does the graph fit the Doppler it has?** In each epoch with two or more satellites' Doppler, the spread
   (largest minus smallest) of ``rhs - g . v`` over its satellites: the clock drift is common to them and
   cancels, so at the true velocity the spread is the Dopplers' own error. Of the epochs whose Dopplers agree
   at the true velocity, the share where the graph's velocity leaves a spread over 1 m/s: correct Dopplers its
   robust loss set aside. And the graph with a non-robust Doppler loss (``rate_robust_k`` 1000).
3. **How steady is the phone's clock drift?** The drift of each epoch's least-squares fit of velocity and drift
   to its Doppler (at least six, at the WLS position: no truth), the robust spread of its change from one
   epoch to the next per sqrt(s), less what the fits' own noise explains; against the graph's drift walk
   (``GraphConfig.drift_rw_mps``); and the graph whose Dopplers see the drift plus a white jump of the size the
   log shows (``GraphConfig.doppler_jump_from_log``, :mod:`fusion.estimate.graph.drift_noise`): the model the
   log itself asks for, nothing tuned. The other columns are without the jump.

The truth places the streets and scores; nothing solved sees it. GSDC score [m].

    python experiments/canyon_doppler_cause.py [--seeds 0 1 2]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from canyon_on_phone import DEEP, canyon_classes, in_canyon, reflected  # noqa: E402
from few_satellites import NAV, PIXEL5  # noqa: E402
from fusion.estimate.graph.consistency import mad_sigma  # noqa: E402
from fusion.estimate.graph.drift_noise import drift_change  # noqa: E402
from fusion.estimate.graph.drift_noise import KNOWN_SD_MPS, epoch_drifts  # noqa: E402
from fusion.estimate.graph.factors import doppler_rows  # noqa: E402
from fusion.estimate.graph.inputs import prepare_inputs  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.trace import Trace  # noqa: E402


def graph(trace: Trace, opts: RunOptions, wls, doppler: bool, **cfg):
    """The fused-nodnn result with Doppler or not, no carrier, no Doppler drift jump (``cfg`` may turn it on),
    graph settings ``cfg`` replaced."""
    o = replace(opts, graph=replace(opts.graph, **{"use_doppler": doppler, "use_carrier": False,
                                                   "doppler_jump_from_log": False, **cfg}))
    return run_modes(trace, ["fused-nodnn"], o, wls=wls)["fused-nodnn"]


def doppler_spread(trace: Trace, vel: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E,) the spread (largest minus smallest) of ``rhs - g . v`` over each epoch's Doppler satellites (each
    satellite's signals averaged) at velocities vel (E,3) and positions at (E,3), NaN with fewer than two
    satellites; and (E,) the epoch's count of satellites with Doppler."""
    use = trace.mask & trace.prr_ok
    ks, ss = np.nonzero(use)
    g, rhs = doppler_rows(trace.prr[ks, ss], trace.sat_pos[ks, ss], trace.sat_vel[ks, ss], at[ks])
    r = rhs - np.einsum("ij,ij->i", g, vel[ks])
    key = ks.astype(np.int64) * 100_000 + trace.sat_id[ks, ss]
    sats, inv = np.unique(key, return_inverse=True)
    mean = np.bincount(inv, weights=r) / np.bincount(inv)
    ep = sats // 100_000
    E = trace.n_epochs
    hi, lo = np.full(E, -np.inf), np.full(E, np.inf)
    np.maximum.at(hi, ep, mean)
    np.minimum.at(lo, ep, mean)
    n = np.bincount(ep, minlength=E)
    return np.where(n >= 2, hi - lo, np.nan), n


def drift_steadiness(trace: Trace, opts: RunOptions) -> tuple[float, float]:
    """The clock drift's epoch-to-epoch change [m/s per sqrt(s)] from the log alone (check 3): its robust sigma
    as the one-epoch fits give it, and that less the fits' own noise
    (:func:`fusion.estimate.graph.drift_noise.drift_change`, what the graph takes)."""
    wls = solve_initial(trace, opts)
    inp = prepare_inputs(trace, wls, replace(opts.graph, use_carrier=False), opts.elev_mask_deg)
    drift, _ = epoch_drifts(trace, inp)
    dt = np.diff(trace.t_ms / 1000.0)
    return mad_sigma(np.diff(drift) / np.sqrt(dt)), drift_change(trace, inp)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = p.parse_args()
    opts = RunOptions(signals=None, nav=(NAV,), sigma_calibration=False)
    trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    raw, change = drift_steadiness(trace, opts)
    jump = {"doppler_jump_from_log": True}
    print("| Pixel5 | pseudoranges only | + Doppler | + Doppler, reflected ones removed (oracle) "
          "| + Doppler, non-robust loss | + Doppler, seeing the drift's jumps |")
    print("|---|---|---|---|---|---|")
    wls = solve_initial(trace, opts)
    s = {k: mode_metrics(trace, graph(trace, opts, wls, d, **c))["gsdc_score"]
         for k, d, c in (("pr", False, {}), ("dop", True, {}), ("jump", True, jump))}
    print(f"| as logged | {s['pr']:.2f} | {s['dop']:.2f} | - | - | {s['jump']:.2f} |")
    spreads = []
    for seed in args.seeds:
        canyon, _ = in_canyon(trace, DEEP, seed)
        bent = reflected(trace, canyon_classes(trace, DEEP, seed))
        wls = solve_initial(canyon, opts)
        runs = {"pr": graph(canyon, opts, wls, False), "dop": graph(canyon, opts, wls, True),
                "oracle": graph(replace(canyon, prr_ok=canyon.prr_ok & ~bent), opts, wls, True),
                "l2": graph(canyon, opts, wls, True, rate_robust_k=1000.0),
                "jump": graph(canyon, opts, wls, True, **jump)}
        s = {k: mode_metrics(canyon, r)["gsdc_score"] for k, r in runs.items()}
        print(f"| deep canyon, streets seed {seed} | {s['pr']:.2f} | {s['dop']:.2f} | {s['oracle']:.2f} | {s['l2']:.2f} "
              f"| {s['jump']:.2f} |")
        truth_vel = np.gradient(canyon.truth, canyon.t_ms / 1000.0, axis=0)
        at_truth, n = doppler_spread(canyon, truth_vel, canyon.truth)
        at_graph, _ = doppler_spread(canyon, runs["dop"].info["vel"], runs["dop"].pos)
        spreads.append((at_truth, at_graph, n))
    truth, est, n = (np.concatenate(a) for a in zip(*spreads))
    print("\n| Doppler satellites in the epoch (all layouts) | epochs | share whose Dopplers agree at the true velocity "
          "(spread < 0.5 m/s) | of those, share the graph's velocity contradicts (spread > 1 m/s) |")
    print("|---|---|---|---|")
    for name, sel in (("2-3", (n >= 2) & (n <= 3)), ("4-5", (n >= 4) & (n <= 5)), ("6 or more", n >= 6)):
        agree = sel & (truth < 0.5)
        print(f"| {name} | {int(sel.sum())} | {agree.sum() / max(sel.sum(), 1):.2f} "
              f"| {(agree & (est > 1.0)).sum() / max(agree.sum(), 1):.3f} |")
    print(f"\nThe Pixel5's clock drift (as logged, no truth): changes by {raw:.2f} m/s per sqrt(s) from epoch to "
          f"epoch over every epoch with six Dopplers; the graph's estimate (epochs whose drift is known to "
          f"{KNOWN_SD_MPS} m/s, the fits' own noise taken off) is {change:.2f}; the configured drift walk is "
          f"{opts.graph.drift_rw_mps:.2f}.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
