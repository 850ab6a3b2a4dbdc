"""What each input group of the learned measurement models buys, one group left out at a time: the two-fold
cross-validation's pooled GSDC score on unseen drives (``fused-nodnn`` and ``fused``), and the same fold
networks on the raw logs none of them saw (smartLoc Berlin, never trained on; the Pixel5 RINEX with GPS
broadcast navigation, a test trace, reported only).

Each run folder is one ``experiments/crossval.py --two-fold`` run of the shipped recipe with ``--inputs``
naming the groups kept, e.g. (the full list: ``learned.features.CHANNELS``)::

    python experiments/crossval.py --data ../shared/data/gsdc2021/train --two-fold --out /tmp/abl_no_cn0 \\
        --epochs 8 --jobs 2 --dropout pr_sigma=0.25 --modes fused-nodnn,fused --extra /tmp/sim/*/SimPhone \\
        --signals all --inputs res,los,pr_sigma,dres,arc,cmd,carrier,system,signal
    python experiments/feature_ablation.py all=/tmp/cvall no_cn0=/tmp/abl_no_cn0 ...

Prints one Markdown row per run: the groups left out, pooled ``fused-nodnn`` / ``fused`` [m] and their ratio,
and ``fused`` [m] (ratio to ``fused-nodnn``) on each raw log with each fold's network.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.checkpoint import read_checkpoint  # noqa: E402
from learned.features import CHANNELS  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
RAW = {"smartLoc": (SHARED / "smartloc/Berlin_Potsdamer_Platz", {}),
       "Pixel5": (SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5",
                  {"nav": (SHARED / "ephemeris/gps_nav/hour1180.21n",)})}


def pooled(run: Path) -> dict[str, float]:
    """Pooled GSDC score per mode from the run's ``crossval.md`` (its first table)."""
    out = {}
    for line in (run / "crossval.md").read_text().splitlines():
        m = re.match(r"\| pooled \| ([\w-]+) \| ([\d.]+) \|", line)
        if m:
            out[m.group(1)] = float(m.group(2))
    return out


def left_out(run: Path) -> str:
    """The input groups the run's networks were trained without."""
    kept = read_checkpoint(run / "fold_AB.pt")["config"]["features"]["inputs"]
    return ", ".join(g for g in CHANNELS if g not in kept) or "nothing"


def load(path: Path, base: RunOptions) -> tuple:
    """(trace, its WLS, the options, ``fused-nodnn``'s score [m]) of one log: nothing learned, so the last is
    the same for every run and solved once."""
    trace = load_trace(path, min_sats=1, **load_options(base))
    wls = solve_initial(trace, base)
    return trace, wls, base, mode_metrics(trace, run_modes(trace, ["fused-nodnn"], base, wls=wls)["fused-nodnn"])["gsdc_score"]


def raw_scores(run: Path, loaded: dict) -> dict[str, tuple[float, float]]:
    """Per raw log (:func:`load`'s tuples) and fold network: (fused score, fused-nodnn score) [m]."""
    out = {}
    for log, (trace, wls, base, nodnn) in loaded.items():
        for fold in ("AB", "CD"):
            opts = replace(base, weights=run / f"fold_{fold}.pt")
            res = run_modes(trace, ["fused"], opts, wls=wls)["fused"]
            out[f"{log} {fold}"] = (mode_metrics(trace, res)["gsdc_score"], nodnn)
    return out


def print_runs(runs: list[str], cols: list[str], scores, extra: tuple[str, object] | None = None,
               digits: int = 2) -> None:
    """One Markdown row per ``LABEL=RUN_FOLDER`` of ``runs``: the label, an ``extra`` column (header, function of
    the run folder; None: none), the pooled GSDC ``fused-nodnn`` / ``fused`` and their ratio, and per column of
    ``cols`` the ``fused`` score (its ratio to ``fused-nodnn`` to ``digits``) from ``scores(run)`` -> {col:
    (fused, fused-nodnn)}."""
    head = f"| run | {extra[0]} |" if extra else "| run |"
    print(head + " GSDC fused-nodnn | GSDC fused | fused / fused-nodnn | "
          + " | ".join(f"{c}: fused (x fused-nodnn)" for c in cols) + " |")
    print("|---|" + ("---|" if extra else "") + "---|---|---|" + "---|" * len(cols))
    rows = {}
    for item in runs:
        label, run = item.split("=", 1)
        run = Path(run)
        g, s = pooled(run), scores(run)
        rows[label] = [(g["fused"], g["fused-nodnn"])] + [s[c] for c in cols]
        cells = " | ".join(f"{s[c][0]:.2f} ({s[c][0] / s[c][1]:.{digits}f})" for c in cols)
        first = f"| {label} | {extra[1](run)} |" if extra else f"| {label} |"
        print(f"{first} {g['fused-nodnn']:.2f} | {g['fused']:.2f} | {g['fused'] / g['fused-nodnn']:.3f} | {cells} |",
              flush=True)
    print_seed_means(rows, cols, digits)


def print_seed_means(rows: dict[str, list[tuple[float, float]]], cols: list[str], digits: int) -> None:
    """Where several runs differ only in a trailing ``_s<seed>`` of their labels, one more table: per recipe the
    mean over its seeds of each ``fused`` score and of its ratio to ``fused-nodnn``. rows: label -> [(fused,
    fused-nodnn) for the pooled GSDC drives, then per column of ``cols``]."""
    groups: dict[str, list[list[tuple[float, float]]]] = {}
    for label, values in rows.items():
        groups.setdefault(re.sub(r"_s\d+$", "", label), []).append(values)
    if len(groups) == len(rows):
        return
    print("\n| recipe (runs) | GSDC fused (x fused-nodnn) | "
          + " | ".join(f"{c}: fused (x fused-nodnn)" for c in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for name, runs in groups.items():
        pairs = np.array(runs)                                   # (runs, 1 + columns, 2)
        score, ratio = pairs[..., 0].mean(axis=0), (pairs[..., 0] / pairs[..., 1]).mean(axis=0)
        cells = [f"{score[0]:.2f} ({ratio[0]:.3f})"]
        cells += [f"{a:.2f} ({r:.{digits}f})" for a, r in zip(score[1:], ratio[1:])]
        print(f"| {name} ({len(runs)}) | " + " | ".join(cells) + " |", flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="LABEL=RUN_FOLDER")
    args = p.parse_args()
    loaded = {log: load(path, RunOptions(signals=None, **kw)) for log, (path, kw) in RAW.items()}
    cols = [f"{log} {fold}" for log in RAW for fold in ("AB", "CD")]
    print_runs(args.runs, cols, lambda run: raw_scores(run, loaded), extra=("left out", left_out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
