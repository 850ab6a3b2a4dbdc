"""Recipes compared where the learned part's gain is inside the trace: each recipe's cross-validation fold
networks, asked as one ensemble per fold (as the shipped weights are), drive ``fused`` on smartLoc Berlin (never
trained on), on simulated city traces (held out: written with ``sim_city_traces.py --held-out``) and on the
Pixel5 RINEX test trace with GPS broadcast navigation (reported, chooses nothing). Prints the mean GSDC score [m]
per log group, the mean of the two folds' ensembles (each fold's between brackets), beside ``fused-nodnn``.

    python experiments/fold_ensembles.py --recipe shipped /tmp/x_base_s0 /tmp/x_base_s1 /tmp/x_base_s2 \\
        --recipe ema /tmp/x_ema_s0 /tmp/x_ema_s1 /tmp/x_ema_s2 --sims /tmp/simho/*/SimPhone /tmp/simdeepho/*/SimPhone

A recipe's runs are ``crossval.py --two-fold`` folders holding ``fold_AB.pt`` and ``fold_CD.pt``; the manifests are
written beside the first run's (``fold_<F>_<recipe name>.json``). Simulated traces are grouped by the street kind in
their folder's name (suburban, urban, deep).
"""
from __future__ import annotations

import argparse
import re
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from adapt_eval import SMARTLOC  # noqa: E402
from crossval import FOLDS2  # noqa: E402
from few_satellites import NAV, PIXEL5  # noqa: E402
from fusion.eval.metrics import summarize, trace_errors  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.ensemble import write_manifest  # noqa: E402
from sim_city_traces import street_kind  # noqa: E402


def logs(sims: list[Path]) -> list[tuple[str, Path, RunOptions]]:
    """(group, folder, options) of every log: smartLoc, the simulated traces (every signal), the Pixel5."""
    out = [("smartLoc", SMARTLOC, RunOptions(signals=None))]
    for s in sims:
        out.append((street_kind(s.parent.name) or "simulated", s, RunOptions(signals=parse_signals("all"))))
    return out + [("Pixel5 (test)", PIXEL5, RunOptions(signals=None, nav=(NAV,)))]


def manifests(name: str, runs: list[Path]) -> dict[str, Path]:
    """Per fold, the manifest of the runs' fold networks as one ensemble, named for the recipe (recipes may share
    their first run)."""
    out, slug = {}, re.sub(r"[^A-Za-z0-9_.-]", "_", name)
    for fold in FOLDS2:
        out[fold] = runs[0] / f"fold_{fold}_{slug}.json"
        write_manifest(out[fold], [r / f"fold_{fold}.pt" for r in runs])
    return out


def scores(recipes: dict[str, list[Path]], sims: list[Path]) -> dict:
    """{(row, group): [GSDC score per log and fold]} for ``fused-nodnn`` and each recipe's ``fused``."""
    weights = {name: manifests(name, runs) for name, runs in recipes.items()}
    got: dict = {}
    for group, path, opts in logs(sims):
        trace = load_trace(path, min_sats=1, **load_options(opts))
        wls = solve_initial(trace, opts)
        nodnn = run_modes(trace, ["fused-nodnn"], opts, wls=wls)["fused-nodnn"]
        got.setdefault(("fused-nodnn", group), []).append(summarize(trace_errors(trace, nodnn))["gsdc_score"])
        for name, folds in weights.items():
            for fold, manifest in folds.items():
                res = run_modes(trace, ["fused"], replace(opts, weights=manifest), wls=wls)["fused"]
                got.setdefault((name, group, fold), []).append(summarize(trace_errors(trace, res))["gsdc_score"])
        print(f"{path}: done", file=sys.stderr, flush=True)
    return got


def table(got: dict, recipes: list[str], groups: list[str]) -> str:
    lines = ["| `fused` with | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups)]
    lines.append("| (`fused-nodnn`) | " + " | ".join(f"{np.mean(got[('fused-nodnn', g)]):.2f}" for g in groups) + " |")
    for name in recipes:
        cells = []
        for g in groups:
            per = [np.mean(got[(name, g, f)]) for f in FOLDS2]
            cells.append(f"{np.mean(per):.2f} ({' / '.join(f'{v:.2f}' for v in per)})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--recipe", nargs="+", action="append", required=True, metavar=("NAME", "RUN"),
                   help="a recipe's name and its runs (crossval.py --two-fold folders, one per seed)")
    p.add_argument("--sims", nargs="*", type=Path, default=[], help="held-out simulated traces (SimPhone folders)")
    args = p.parse_args(argv)
    recipes = {r[0]: [Path(x) for x in r[1:]] for r in args.recipe}
    if any(not runs for runs in recipes.values()):
        p.error("--recipe NAME RUN [RUN ...]: each recipe needs its runs")
    got = scores(recipes, args.sims)
    groups = list(dict.fromkeys(g for g, _, _ in logs(args.sims)))
    print(table(got, list(recipes), groups))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
