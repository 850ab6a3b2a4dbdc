"""Robust WLS (fault detection and exclusion, the default) against the paper's plain WLS, with and
without simulated non-line-of-sight faults: +200 m on a seeded random 5% of the pseudoranges.

Prints, per trace and mode (``wls``; ``dnn`` too with ``--dnn``): the GSDC score (mean of horizontal
p50 and p95) of the plain and the robust WLS guess on the clean trace, and on the faulty trace for
each seed, plus the *oracle* (the faulty measurements simply removed, plain WLS) that bounds what any
exclusion can reach: losing 5% of the satellites costs geometry.

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/robust_wls.py --seeds 0 1 2 3 4 --dnn

With ``--drives``: the GSDC score per drive of the plain WLS, the robust default of the last round
(:data:`PREVIOUS`) and the default robust WLS now, over the twelve training drives, the two test traces,
the Pixel5 RINEX trace (GPS broadcast navigation) and smartLoc's street-canyon proxies (:data:`PROXIES`).
With ``--tune``: the robust stage's settings (:data:`GRID`) chosen on half the training drives and
smartLoc and checked on the other half (the test traces are never used to choose).

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/robust_wls.py --drives --tune --seeds 0 1 2 3 4

Data: ``$GNSSFUSE_SHARED_DATA`` (default ``<repo>/../shared/data``). Results: ``experiments/results/robust_wls.md``.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

import numpy as np

from fusion.estimate.wls import TRACE_DEFAULTS, estimate_wls, solve_wls
from fusion.eval.metrics import mode_metrics
from fusion.prepare.load import load_trace
from fusion.prepare.raw_load import RawSources
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from fusion.trace import SIGNALS, Trace

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
#: Training traces only (the test traces 2021-04-28-* are not used to choose anything).
TRACES = ("gsdc2021/train/2020-05-14-US-MTV-1/Pixel4", "gsdc2021/train/2020-06-05-US-MTV-1/Pixel4",
          "gsdc2021/train/2020-09-04-US-SF-2/Pixel4")
FAULT_M, FAULT_RATE = 200.0, 0.05
#: The twelve training drives (``--drives``, ``--tune``) and the test traces (``--drives`` only).
TRAIN = tuple(f"gsdc2021/train/{d}/Pixel4" for d in (
    "2020-05-14-US-MTV-1", "2020-05-14-US-MTV-2", "2020-05-21-US-MTV-1", "2020-05-21-US-MTV-2",
    "2020-05-29-US-MTV-1", "2020-05-29-US-MTV-2", "2020-06-04-US-MTV-1", "2020-06-05-US-MTV-1",
    "2020-06-05-US-MTV-2", "2020-06-11-US-MTV-1", "2020-07-08-US-MTV-1", "2020-09-04-US-SF-2"))
TEST = ("gsdc2021/train/2021-04-28-US-MTV-1/Pixel4", "gsdc2021/train/2021-04-28-US-SJC-1/Pixel4")
PIXEL5, PIXEL5_NAV = "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5", "ephemeris/gps_nav/hour1180.21n"
FAULT_TRACE = TRAIN[0]
#: The robust WLS before the exclusion guard: every identified fault excluded.
BEFORE = TRACE_DEFAULTS.replace(exclude_above_m=float("inf"))
#: The robust default of the last round (guard, neighbour check of weak epochs, Huber on elevation sigmas).
PREVIOUS = TRACE_DEFAULTS.replace(neighbour_weak=True, irls_reported=False, irls_scale="prior", huber_k=1.5)
#: Settings searched by ``--tune`` (the exclusion guard fixed at 80 m / 1.0): (neighbour check of the epochs
#: that passed with few satellites, IRLS sigmas from the reported sigma, IRLS scale, Huber threshold).
GRID = tuple((nw, rep, sc, k) for nw in (True, False) for rep in (False, True) for sc in ("prior", "trace")
             for k in (1.5, 2.0, 3.0))
#: Tried at the chosen point: undo gross exclusions too where the DOP grows beyond the factor (rejected).
GROSS_DOP_GROWTH = (float("inf"), 3.0, 2.0, 1.6)
SMARTLOC = "smartloc/Berlin_Potsdamer_Platz"
#: smartLoc proxies of a phone in a street canyon: the whole log, GPS only (6-10 satellites, as a GPS-L1
#: GSDC phone), and both thinned to 1 Hz (the neighbour check then predicts over a second, as on a phone)
#: in five disjoint subsets.
PROXIES = ("smartLoc", "smartLoc GPS", "smartLoc 1 Hz (5 subsets)", "smartLoc GPS 1 Hz (5 subsets)")

def with_faults(trace: Trace, seed: int) -> tuple[Trace, np.ndarray]:
    """The trace with +200 m on a random 5% of its real slots; also the (E, S) bool fault mask."""
    hit = trace.mask & (np.random.default_rng(seed).random(trace.mask.shape) < FAULT_RATE)
    return dataclasses.replace(trace, pr=trace.pr + FAULT_M * hit), hit


def scores(trace: Trace, modes: list[str], robust) -> dict[str, float]:
    opts = RunOptions(wls_robust=robust)
    return {m: mode_metrics(trace, r)["gsdc_score"] for m, r in run_modes(trace, modes, opts).items()}


def trace_rows(rel: str, modes: list[str], seeds: list[int]) -> list[str]:
    trace = load_trace(SHARED / rel, min_sats=1)           # as the CLI loads it
    clean = {k: scores(trace, modes, k) for k in (False, "exclude")}
    faulty = {k: [] for k in (False, "exclude", "oracle")}
    for seed in seeds:
        bad, hit = with_faults(trace, seed)
        faulty[False].append(scores(bad, modes, False))
        faulty["exclude"].append(scores(bad, modes, "exclude"))
        faulty["oracle"].append(scores(dataclasses.replace(trace, mask=trace.mask & ~hit), modes, False))
    rows = []
    for m in modes:
        f = {k: np.array([s[m] for s in v]) for k, v in faulty.items()}
        rows.append(
            f"| {rel.split('/', 2)[2]} | {m} | {clean[False][m]:.2f} | {clean['exclude'][m]:.2f} "
            f"| {clean['exclude'][m] - clean[False][m]:+.2f} | {f[False].mean():.2f} | {f['oracle'].mean():.2f} "
            f"| {f['exclude'].mean():.2f} ({f['exclude'].min():.2f}-{f['exclude'].max():.2f}) "
            f"| {(f['exclude'] - clean['exclude'][m]).mean():+.2f} | {(f['exclude'] - clean[False][m]).mean():+.2f} |")
    return rows


def load(rel: str) -> Trace:
    """A trace as the CLI loads it (the Pixel5 RINEX log with its GPS broadcast navigation file)."""
    sources = RawSources(nav=(SHARED / PIXEL5_NAV,)) if rel == PIXEL5 else None
    # signals=None: the format's default, as the CLI (GPS L1 for the GSDC files, GPS L1 + L5 for the RINEX)
    return load_trace(SHARED / rel, min_sats=1, signals=None, raw_sources=sources)


def wls_score(trace: Trace, settings) -> float:
    """GSDC score of the WLS mode with ``settings`` (a :class:`fusion.estimate.wls_state.WlsSettings`)."""
    return mode_metrics(trace, estimate_wls(trace, solve_wls(trace, settings), RunOptions()))["gsdc_score"]


def drive_table(traces: dict[str, Trace], proxies: dict[str, list[Trace]]) -> None:
    """Per drive (and smartLoc proxy, mean over its traces): plain, the robust default of the last round
    (:data:`PREVIOUS`), robust now (the default), and the ratios to plain."""
    print("| drive | set | plain | robust, last round | robust now | last round / plain | now / plain |")
    print("|---|---|---|---|---|---|---|")
    rows = {**{rel: ("train" if rel in TRAIN else "test", [tr]) for rel, tr in traces.items()},
            **{n: ("canyon proxy", ts) for n, ts in proxies.items()}}
    for rel, (kind, ts) in rows.items():
        plain, before, now = (np.mean([wls_score(t, s) for t in ts])
                              for s in (TRACE_DEFAULTS.replace(robust=False), PREVIOUS, TRACE_DEFAULTS))
        name = rel.split('/', 2)[2] if rel.startswith("gsdc") else rel
        print(f"| {name} | {kind} | {plain:.2f} | {before:.2f} | {now:.2f} | {before / plain:.3f} "
              f"| {now / plain:.3f} |", flush=True)


def _setting(nw: bool, rep: bool, sc: str, k: float):
    return TRACE_DEFAULTS.replace(neighbour_weak=nw, irls_reported=rep, irls_scale=sc, huber_k=k)


def smartloc_proxies(trace: Trace) -> dict[str, list[Trace]]:
    """The :data:`PROXIES` of the smartLoc log (5 Hz, GPS + GLONASS): name -> traces."""
    gps = trace.select_slots(trace.signal == SIGNALS.index("GPS_L1"))
    thin = [np.flatnonzero(np.arange(trace.n_epochs) % 5 == k) for k in range(5)]
    return dict(zip(PROXIES, ([trace], [gps], [trace.select(e) for e in thin], [gps.select(e) for e in thin])))


def ratios(traces: dict[str, list[Trace]], settings) -> dict[str, float]:
    """name -> robust / plain GSDC score (mean over the name's traces) under ``settings``."""
    plain = settings.replace(robust=False)
    return {n: float(np.mean([wls_score(t, settings) / wls_score(t, plain) for t in ts])) for n, ts in traces.items()}


def tune(traces: dict[str, Trace], proxies: dict[str, list[Trace]], seeds: list[int]) -> None:
    """Each grid point's robust / plain ratios on the twelve training drives and the smartLoc proxies, and
    the fault-injection result (faulty robust - clean plain on :data:`FAULT_TRACE`). Leave half the drives
    out: on each half (alternate drives) and the proxies, the point with the least mean ratio among those
    keeping the fault result within 1 m; its ratios on the other half."""
    sets = {**{r: [traces[r]] for r in TRAIN}, **proxies}
    plain = wls_score(traces[FAULT_TRACE], TRACE_DEFAULTS.replace(robust=False))
    faulty = [with_faults(traces[FAULT_TRACE], s)[0] for s in seeds]
    ratio, fault = {}, {}
    print("| neighbour check of passed epochs | reported sigma in IRLS | IRLS scale | huber_k | train mean | train worst "
          "| " + " | ".join(PROXIES) + " | fault: faulty - clean plain [m] |")
    print("|---|---|---|---|---|---|" + "---|" * len(PROXIES) + "---|")
    for p in GRID:
        ratio[p] = ratios(sets, _setting(*p))
        fault[p] = np.mean([wls_score(f, _setting(*p)) for f in faulty]) - plain
        tr = np.array([ratio[p][r] for r in TRAIN])
        print(f"| {'yes' if p[0] else 'no'} | {'yes' if p[1] else 'no'} | {p[2]} | {p[3]:.1f} | {tr.mean():.4f} "
              f"| {tr.max():.3f} | " + " | ".join(f"{ratio[p][n]:.3f}" for n in PROXIES) + f" | {fault[p]:+.2f} |",
              flush=True)
    allowed = [p for p in GRID if fault[p] <= 1.0]
    print("\n| chosen on | setting (neighbour check, reported sigma, scale, huber_k) | held-out drives: mean ratio | worst |")
    print("|---|---|---|---|")
    for h in (0, 1):
        chosen, held = TRAIN[h::2], TRAIN[1 - h::2]
        best = min(allowed, key=lambda p: np.mean([ratio[p][n] for n in chosen + PROXIES]))
        out = np.array([ratio[best][r] for r in held])
        print(f"| drives {h + 1}, {h + 3}, ... of 12 + smartLoc | {best} | {out.mean():.4f} | {out.max():.3f} |")
    best = min(allowed, key=lambda p: np.mean([ratio[p][n] for n in TRAIN + PROXIES]))
    print(f"\nChosen on all twelve and smartLoc: {best}")
    print("\nAt the chosen point, gross exclusions also undone above a DOP growth (``gross_dop_growth``):\n")
    print("| gross_dop_growth | train mean | train worst | " + " | ".join(PROXIES) + " | fault [m] |")
    print("|---|---|---|" + "---|" * len(PROXIES) + "---|")
    for g in GROSS_DOP_GROWTH:
        st = _setting(*best).replace(gross_dop_growth=g)
        r = ratios(sets, st)
        tr = np.array([r[n] for n in TRAIN])
        f = np.mean([wls_score(x, st) for x in faulty]) - plain
        print(f"| {g:g} | {tr.mean():.4f} | {tr.max():.3f} | " + " | ".join(f"{r[n]:.3f}" for n in PROXIES)
              + f" | {f:+.2f} |", flush=True)


def exclusion_gains(traces: dict[str, Trace]) -> None:
    """Training drives, robust WLS before the guard: for the epochs where it excluded satellites (and
    was not left undecided), the change of the horizontal error against plain WLS, before and with
    the guard, by the growth of the weighted position DOP the exclusion caused and by the largest
    excluded residual."""
    from fusion.estimate.lsq import position_dop
    from fusion.eval.metrics import horizontal, ned_errors
    rows = []
    for rel in TRAIN:
        tr = traces[rel]
        plain, rob = solve_wls(tr, TRACE_DEFAULTS.replace(robust=False)), solve_wls(tr, BEFORE)
        now = solve_wls(tr, TRACE_DEFAULTS)
        sel = (plain.valid & rob.valid & now.valid & (rob.n_excluded > 0) & ~rob.flagged
               & np.isfinite(tr.truth).all(1))
        err0 = horizontal(ned_errors(plain.pos[sel], tr.truth[sel]))
        gain = horizontal(ned_errors(rob.pos[sel], tr.truth[sel])) - err0
        gain_now = horizontal(ned_errors(now.pos[sel], tr.truth[sel])) - err0
        x = np.concatenate([plain.pos[sel], plain.clock_m[sel, None]], axis=1)
        w = 1.0 / (3.0 / np.sin(np.radians(np.maximum(plain.elev_deg[sel], 1.0)))) ** 2
        growth = (position_dop(tr.sat_pos[sel], x, np.where(rob.used[sel], w, 0.0))
                  / position_dop(tr.sat_pos[sel], x, np.where(plain.used[sel], w, 0.0)))
        removed = np.where(plain.used[sel] & ~rob.used[sel], np.abs(rob.resid[sel]), 0.0).max(1)
        rows.append(np.stack([growth, removed, gain, gain_now], axis=1))
    R = np.concatenate(rows)
    print("| exclusions by | bin | epochs | before: mean change of horizontal error [m] | median [m] "
          "| worse by > 5 m | better by > 5 m | with the guard: mean change [m] |")
    print("|---|---|---|---|---|---|---|---|")
    for col, name, edges in ((0, "PDOP growth", (1.0, 1.05, 1.15, 1.3, 1.6, np.inf)),
                             (1, "largest excluded residual [m]", (0.0, 20.0, 30.0, 50.0, 80.0, 100.0, np.inf))):
        for lo, hi in zip(edges[:-1], edges[1:]):
            inside = (R[:, col] >= lo) & (R[:, col] < hi)
            b = R[inside, 2]
            if b.size:
                print(f"| {name} | [{lo:g}, {hi:g}) | {b.size} | {b.mean():+.2f} | {np.median(b):+.2f} "
                      f"| {np.sum(b > 5)} | {np.sum(b < -5)} | {R[inside, 3].mean():+.2f} |")


def dnn_drive_table(traces: dict[str, Trace], proxies: dict[str, list[Trace]]) -> None:
    """Per drive (and smartLoc proxy, mean over its traces): the GSDC score of ``wls`` and ``dnn`` (the
    shipped weights, with the fault screen of :func:`learned.modes.fault_screen`) on the clean trace."""
    print("| drive | wls | dnn | dnn / wls |")
    print("|---|---|---|---|")
    rows = {**{rel: [tr] for rel, tr in traces.items()}, **proxies}
    for rel, ts in rows.items():
        s = [scores(t, ["wls", "dnn"], "exclude") for t in ts]
        w, d = (float(np.mean([x[m] for x in s])) for m in ("wls", "dnn"))
        name = rel.split('/', 2)[2] if rel.startswith("gsdc") else rel
        print(f"| {name} | {w:.2f} | {d:.2f} | {d / w:.3f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--dnn", action="store_true", help="also the dnn mode (shipped weights)")
    ap.add_argument("--traces", nargs="+", default=list(TRACES), help="paths under the shared data folder")
    ap.add_argument("--drives", action="store_true", help="per-drive plain / robust last round / robust now table")
    ap.add_argument("--tune", action="store_true", help="choice of the robust stage on half the drives and smartLoc")
    ap.add_argument("--no-faults", action="store_true", help="skip the fault-injection table")
    ap.add_argument("--dnn-drives", action="store_true", help="per-drive clean wls / dnn table")
    args = ap.parse_args()
    if args.drives or args.tune or args.dnn_drives:
        rels = TRAIN + (TEST + ((PIXEL5,) if (SHARED / PIXEL5_NAV).exists() else ())
                        if args.drives or args.dnn_drives else ())
        traces = {rel: load(rel) for rel in rels}
        proxies = smartloc_proxies(load_trace(SHARED / SMARTLOC, min_sats=1, signals=None))
        if args.tune:
            exclusion_gains(traces)
            print()
            tune(traces, proxies, args.seeds)
            print()
        if args.drives:
            drive_table(traces, proxies)
            print()
        if args.dnn_drives:
            dnn_drive_table(traces, proxies)
            print()
    if args.no_faults:
        return
    modes = ["wls", "dnn"] if args.dnn else ["wls"]
    print(f"GSDC score [m]; faulty: +{FAULT_M:.0f} m on {FAULT_RATE:.0%} of pseudoranges, mean over seeds "
          f"{args.seeds} (min-max)\n")
    print("| trace | mode | clean plain | clean robust | clean change | faulty plain | faulty oracle "
          "| faulty robust | robust: faulty - clean | faulty robust - clean plain |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for rel in args.traces:
        for row in trace_rows(rel, modes, args.seeds):
            print(row, flush=True)


if __name__ == "__main__":
    main()
