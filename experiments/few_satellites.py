"""Long stretches with too few satellites (a phone in a street canyon; a hidden dual-frequency phone solved
only 254 of its 787 epochs by WLS): how far the graph drifts there, whether it says so (the ``bridged``
flag: fewer than 4 satellites and no prior), and whether its sigmas there are honest.

Each trace is thinned the same seeded way: in the last 120 s of every 180 s only ``--keep`` satellites
(chosen at random per stretch) are left, so WLS solves about a third of the epochs. Per trace and mode:
the GSDC score, the horizontal error in the thinned stretches (median, max), the share of bridged epochs,
and the share of errors within the reported 1 sigma per NED axis on the bridged epochs and on the others.

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/few_satellites.py \\
        > experiments/results/few_satellites.md

The twelve GSDC training drives (pseudoranges only: the derived files have no Doppler) decide; the Pixel5
RINEX (a test trace, GPS broadcast navigation, with and without Doppler and carrier) is reported.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.eval.metrics import mode_metrics, sigma_ratios, trace_errors  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.trace import Trace  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
PIXEL5 = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
NAV = SHARED / "ephemeris/gps_nav/hour1180.21n"


def thinned(trace: Trace, keep: int, seed: int, good_s: float = 60.0, period_s: float = 180.0
            ) -> tuple[Trace, np.ndarray]:
    """The trace with only ``keep`` satellites (all their signals) in the last period_s - good_s seconds of
    every period_s, and (E,) bool those thinned epochs."""
    rng = np.random.default_rng(seed)
    t = (trace.t_ms - trace.t_ms[0]) / 1000.0
    block, poor = t // period_s, (t % period_s) >= good_s
    slots = np.ones(trace.mask.shape, bool)
    for b in np.unique(block[poor]):
        ep = poor & (block == b)
        sats = np.unique(trace.sat_id[ep][trace.mask[ep]])
        chosen = rng.choice(sats, size=min(keep, len(sats)), replace=False)
        slots[ep] = np.isin(trace.sat_id[ep], chosen)
    return trace.select_slots(slots), poor


def bridged_ratios(err: np.ndarray, res, rows: np.ndarray) -> np.ndarray | None:
    """(N,3) |error| / 1 sigma per NED axis over ``rows`` (E,) bool (None: no covariance, or no such row)."""
    if res.cov is None or not rows.any():
        return None
    z = sigma_ratios(err[rows], res.pos[rows], res.cov[rows])
    return z if len(z) else None


def coverage(ratios: np.ndarray | None, scale: float = 1.0) -> str:
    """Share of |error| within ``scale`` sigma, N / E / D."""
    return "-" if ratios is None else " / ".join(f"{v:.2f}" for v in (ratios <= scale).mean(axis=0))


#: |error| / sigma of fused-nodnn per trace on its bridged epochs without Doppler (where
#: GraphConfig.bridged_sigma_scale applies), measured with that scale at 1
BRIDGED: dict[str, np.ndarray] = {}


def rows_of(name: str, trace: Trace, poor: np.ndarray, variants: dict, base: RunOptions, modes: list[str]):
    base = replace(base, graph=replace(base.graph, bridged_sigma_scale=1.0, bridged_sigma_scale_down=1.0))
    for label, change in variants.items():
        opts = replace(base, graph=replace(base.graph, **change))
        for mode, res in run_modes(trace, modes, opts).items():
            m = mode_metrics(trace, res)
            err = trace_errors(trace, res)
            h = np.hypot(err[:, 0], err[:, 1])
            bridged = np.asarray(res.info.get("bridged", np.zeros(trace.n_epochs, bool)), bool)
            solved = np.isfinite(h)
            ratios = bridged_ratios(err, res, bridged)
            if mode == "fused-nodnn":
                alone = np.asarray(res.info.get("bridged_without_doppler", bridged), bool)
                BRIDGED[f"{name}, {label}"] = bridged_ratios(err, res, alone)
            thinned_h = (f"{np.nanmedian(h[poor]):.1f} | {np.nanmax(h[poor]):.1f}" if np.isfinite(h[poor]).any()
                         else "- | -")
            print(f"| {name} | {label} | {mode} | {m['gsdc_score']:.2f} | {thinned_h} | "
                  f"{int(solved.sum())} / {trace.n_epochs} | {int(bridged.sum())} | "
                  f"{coverage(ratios)} | {coverage(bridged_ratios(err, res, ~bridged))} |", flush=True)


def fit_table(training: list[str]) -> None:
    """The bridged sigma scales, horizontal and down: the 68th percentile of the training drives' pooled
    |error| / sigma on the north and east axes, and on the down axis; each drive's coverage with the scales
    fitted without it; the test trace with the full fit."""
    def fit(names):
        z = np.concatenate([BRIDGED[n] for n in names if BRIDGED[n] is not None])
        return np.array([np.percentile(z[:, :2], 68)] * 2 + [np.percentile(z[:, 2], 68)])
    full = fit(training)
    print(f"\nbridged_sigma_scale (north, east) and bridged_sigma_scale_down fitted on the {len(training)} training "
          f"drives: {full[0]:.2f}, {full[2]:.2f}\n")
    print("| trace (fused-nodnn, bridged epochs without Doppler) | epochs | scales h / down | within 1 sigma N / E / "
          "D, before | after |")
    print("|---|---|---|---|---|")
    for n, r in BRIDGED.items():
        held = [t for t in training if t != n]
        scale = fit(held) if n in training else full
        print(f"| {n}{'' if n in training else ' (test)'} | {0 if r is None else len(r)} | "
              f"{scale[0]:.2f} / {scale[2]:.2f}{' (held out)' if n in training else ''} | {coverage(r)} | "
              f"{coverage(r, scale)} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--training", type=int, default=12, help="how many training drives (0: none)")
    args = ap.parse_args()
    print("| trace | measurements | mode | GSDC score [m] | thinned h p50 [m] | thinned h max [m] | solved | "
          "bridged | within 1 sigma N / E / D, bridged | ... the other epochs |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    drives = sorted((SHARED / "gsdc2021/train").glob("2020-*/Pixel4"))[:args.training]
    for k, folder in enumerate(drives):
        trace, poor = thinned(load_trace(folder, min_sats=1), args.keep, args.seed + k)   # as gnssfuse loads it
        rows_of(folder.parent.name, trace, poor, {"pseudoranges": {}}, RunOptions(), ["wls", "fused-nodnn"])
    training = list(BRIDGED)
    base = RunOptions(signals=None, nav=(NAV,))
    trace, poor = thinned(load_trace(PIXEL5, min_sats=1, **load_options(base)), args.keep, args.seed)
    rows_of("Pixel5 RINEX (test)", trace, poor,
            {"pseudoranges only": {"use_doppler": False, "use_carrier": False}, "Doppler + carrier": {},
             "Doppler + carrier, no drift jump": {"doppler_jump_from_log": False}},
            base, ["wls", "fused-nodnn", "fused"])
    if training:
        fit_table(training)
    return 0


if __name__ == "__main__":
    sys.exit(main())
