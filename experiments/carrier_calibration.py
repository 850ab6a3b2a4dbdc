"""Calibration of the graph modes' sigmas where carrier phase ties an epoch to its neighbours, tuned
leave-traces-out on simulated city traces written with carrier phase, reported on the Pixel5 RINEX test trace.

The settings of :data:`fusion.estimate.variance_factor.DEFAULTS` were tuned on logs without carrier phase (the
GSDC 2021 derived files, smartLoc). Where the graph holds carrier, its track is precise to decimetres and its
marginals say so, but the terms added for a smoother fed by pseudoranges alone (a metre of horizontal floor, a
share of the one-epoch variance) are metres. This measures how far off those settings are at the epochs carrier
phase ties to a neighbour (``info["carrier_linked"]``) and what a setting of their own, chosen by the grid and
penalty of ``experiments/sigma_calibration.py`` over folds of traces (one level for north and east: a car drives
every way), would do there and on the Pixel5. Chosen on traces written with the range errors the broadcast
corrections leave (``--broadcast-errors``), the ``fused`` setting is shipped as
:data:`fusion.estimate.variance_factor.CARRIER_DEFAULTS` (``experiments/results/carrier_calibration.md``).

Two stages, as there. ``collect`` runs fused-nodnn and fused with the calibration OFF on each trace (shipped
weights: no network was trained on these traces) and keeps, per mode, what the tuning needs plus the carrier
epochs; ``tune`` chooses per mode by leave-fold-out over the carrier epochs and prints the table.

    python experiments/sim_city_traces.py --held-out --scenarios deep urban --first-seed 800 --carrier \\
        --broadcast-errors --out /tmp/simbe_car
    python experiments/sim_city_traces.py --held-out --scenarios suburban --first-seed 900 --carrier \\
        --broadcast-errors --out /tmp/simbe_sub
    python experiments/sim_city_traces.py --held-out --scenarios suburban urban --first-seed 1000 --carrier \\
        --broadcast-errors --constellations GPS --out /tmp/simbe_gps
    python experiments/carrier_calibration.py collect --out /tmp/carcal_be --jobs 2 \\
        /tmp/simbe_car/*/SimPhone /tmp/simbe_sub/*/SimPhone /tmp/simbe_gps/*/SimPhone
    python experiments/carrier_calibration.py tune --out /tmp/carcal_be --jobs 2
"""
from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from itertools import product
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from sigma_calibration import (BAND, GRID, TESTS, calibrated_var, disagreement, factor, fit_a, flag, fmt,  # noqa: E402
                               miss, mode_record, n_outside, scaled, within)
from fusion.estimate.variance_factor import (CARRIER_DEFAULTS, DEFAULTS, SigmaCalibration, epoch_chi2,  # noqa: E402
                                             whitened_residuals, wls_track)
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

MODES = ("fused-nodnn", "fused")
#: Tuning folds: every fourth trace of the sorted names, so that each fold holds street kinds of both phones.
N_FOLDS = 4
#: Floors [m] tried, horizontal and down: carrier-tied tracks are decimetres, so finer than sigma_calibration's.
FLOOR_H, FLOOR_V = (0.0, 0.1, 0.3, 1.0), (0.0, 0.3, 1.0, 2.0)
PIXEL5 = "test Pixel5 RINEX"


def name_of(folder: Path) -> str:
    """``<set>/<trace>`` of a simulated trace folder (``/tmp/simcarho2/ho-deep-401/SimPhone``)."""
    return f"{folder.parents[1].name}/{folder.parent.name}"


def collect_one(job) -> tuple[str, dict]:
    name, folder, change = job
    opts = RunOptions(sigma_calibration=False, **change)
    trace = load_trace(folder, min_sats=1, **load_options(opts))
    wls = solve_initial(trace, opts)
    out = {"t": trace.t_ms.astype(float) / 1000.0}
    pos, sel, sigma = wls_track(trace, wls, opts.elev_mask_deg)        # the factor some settings read
    z, dof = whitened_residuals(trace, pos, sel, sigma, None, fitted=True)
    out.update({"wls/chi2": epoch_chi2(z), "wls/dof": dof})
    for mode, res in run_modes(trace, list(MODES), opts, wls=wls).items():
        sel, sigma, bias = res.info["pr_noise"]
        for k, v in mode_record(trace, res, sel, sigma, bias, False).items():
            out[f"{mode}/{k}"] = v
        out[f"{mode}/carrier"] = res.info["carrier_linked"] & res.valid
    return name, out


def collect(args) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    every = {"signals": parse_signals("all")}          # a derived file's default is GPS L1 alone
    todo = [(name_of(f), f, every) for f in map(Path, args.traces)]
    todo.append((PIXEL5, TESTS[PIXEL5][0], TESTS[PIXEL5][1]))
    todo = [j for j in todo if not (args.out / f"{slug(j[0])}.npz").is_file()]
    with ProcessPoolExecutor(args.jobs) as pool:
        for name, out in pool.map(collect_one, todo):
            np.savez_compressed(args.out / f"{slug(name)}.npz", **out)
            print(f"collected {name}", file=sys.stderr, flush=True)


def slug(name: str) -> str:
    """A file name for a trace name (the simulated traces' names hold no "_", so :func:`load` can invert it)."""
    return name.replace("/", "__").replace(" ", "_")


def load(out: Path) -> dict[str, dict]:
    """name -> the collected arrays, every trace in ``out``."""
    return {f.stem.replace("__", "/").replace("_", " "): dict(np.load(f)) for f in sorted(out.glob("*.npz"))}


def folds_of(names: list[str]) -> list[list[str]]:
    return [names[k::N_FOLDS] for k in range(N_FOLDS)]


def carrier_only(d: dict, mode: str, x: np.ndarray) -> np.ndarray:
    """``x`` (E,3) with the rows of epochs without carrier set to NaN (they count in no coverage)."""
    return np.where(d[f"{mode}/carrier"][:, None], x, np.nan)


def with_snapshot(d: dict, mode: str, cal: SigmaCalibration) -> np.ndarray:
    """(E,3) one trace's raw variances plus ``cal``'s share of its one-epoch variances."""
    return d[f"{mode}/var"] + cal.snapshot * np.nan_to_num(d[f"{mode}/snap"])


def terms(d: dict, mode: str, cal: SigmaCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(base variances (E,3) with the snapshot share, factor F (E,), disagreement term (E,3)) of one trace."""
    base = with_snapshot(d, mode, cal)
    F = factor(d, mode, cal.window_s, cal.factor_from)
    extra = cal.disagreement * disagreement(d, mode, cal.window_s) if cal.disagreement else np.zeros_like(base)
    return base, F, extra


def carrier_items(data: dict, names: list[str], mode: str, cal: SigmaCalibration) -> dict:
    """trace -> (errors at the carrier epochs (E,3), NaN elsewhere; :func:`terms`) under ``cal``'s window, snapshot
    share, factor source and disagreement share (what the levels, exponent and floors act on)."""
    return {n: (carrier_only(data[n], mode, data[n][f"{mode}/err"]), *terms(data[n], mode, cal)) for n in names}


def held_out(items: dict, b: float, fl: np.ndarray) -> tuple[float, dict]:
    """Leave-fold-out over the carrier epochs of ``items`` (:func:`carrier_items`): the levels fitted on the other
    folds, each held-out trace's coverage (3,) and the summed penalty (:func:`sigma_calibration.miss`)."""
    cov, pen = {}, 0.0
    for held in folds_of(list(items)):
        a = fit_a([(e, v, F, x) for n, (e, v, F, x) in items.items() if n not in held], b, fl, tie_horizontal=True)
        for n in held:
            e, v, F, x = items[n]
            cov[n] = within(e, scaled(v, F, a, b, fl, x))
            pen += miss(cov[n])
    return pen, cov


def tune_mode(data: dict, names: list[str], mode: str) -> tuple[SigmaCalibration, float, dict]:
    """The grid point of least leave-fold-out penalty, its final levels fitted on every trace."""
    best = None
    dis_grid = GRID["disagreement"] if mode == "fused" else (0.0,)
    for c, w, src, dis in product(GRID["c"], GRID["window_s"], GRID["source"], dis_grid):
        items = carrier_items(data, names, mode, SigmaCalibration(window_s=w, snapshot=c, factor_from=src,
                                                                  disagreement=dis))
        for b, fh, fv in product(GRID["b"], FLOOR_H, FLOOR_V):
            pen, cov = held_out(items, b, np.array([fh, fh, fv]))
            if best is None or pen < best[1]:
                best = (SigmaCalibration(b=b, floor_m=(fh, fh, fv), window_s=w, snapshot=c, factor_from=src,
                                         disagreement=dis), pen, cov)
    cal, pen, cov = best
    a = fit_a(list(carrier_items(data, names, mode, cal).values()), cal.b, np.array(cal.floor_m),
              tie_horizontal=True)
    return replace(cal, a=tuple(round(float(x), 4) for x in a)), pen, cov


def shipped_scores(data: dict, names: list[str], mode: str) -> str | None:
    """The setting shipped in :data:`CARRIER_DEFAULTS` scored on these runs: its levels as they are, and refitted
    leave-fold-out as the grid's are (a line for the table's header; None: ``mode`` ships none)."""
    cal = CARRIER_DEFAULTS.get(mode)
    if cal is None:
        return None
    items, fl = carrier_items(data, names, mode, cal), np.array(cal.floor_m)
    as_is = {n: within(e, scaled(v, F, cal.a, cal.b, fl, x)) for n, (e, v, F, x) in items.items()}
    pen, held = held_out(items, cal.b, fl)
    return (f"the setting shipped in variance_factor.CARRIER_DEFAULTS, a N/E/D = {fmt(np.array(cal.a))}: its levels "
            f"as they are, penalty {sum(miss(c) for c in as_is.values()):.3f}, {n_outside(as_is)} trace-axes out; "
            f"its levels refitted leave-fold-out, penalty {pen:.3f}, {n_outside(held)} out")


def calibrated(d: dict, mode: str, cal: SigmaCalibration, carrier_cal: SigmaCalibration | None) -> np.ndarray:
    """(E,3) the variances as the pipeline would report them: ``carrier_cal`` at the carrier epochs (None: ``cal``)."""
    out = calibrated_var(d, with_snapshot(d, mode, cal), mode, cal)
    if carrier_cal is not None:
        carrier = calibrated_var(d, with_snapshot(d, mode, carrier_cal), mode, carrier_cal)
        out = np.where(d[f"{mode}/carrier"][:, None], carrier, out)
    return out


def tune(args) -> None:
    data = load(args.out)
    names = sorted(n for n in data if n != PIXEL5)
    print("# Sigma calibration where carrier phase ties the epochs (simulated city traces, leave-traces-out)\n")
    print("Share of |error| within the reported 1 sigma, N / E / D, at the epochs carrier phase ties to a neighbour")
    print("(target 0.55-0.80; (!) a miss), and over every epoch of the trace. *Before*: DEFAULTS alone. *Held out*:")
    print(f"the carrier setting chosen, its levels fitted without the trace's fold ({N_FOLDS} folds). *Final*: the")
    print("levels fitted on every trace. The Pixel5 RINEX test trace: reported, nothing tuned on it.\n")
    chosen = {}
    with ProcessPoolExecutor(args.jobs) as pool:
        tuned = dict(zip(MODES, pool.map(tune_mode, [data] * len(MODES), [names] * len(MODES), MODES)))
    for mode in MODES:
        cal, pen, held = tuned[mode]
        chosen[mode] = cal
        n_out = n_outside(held)
        before = {n: within(carrier_only(data[n], mode, data[n][f"{mode}/err"]),
                            calibrated(data[n], mode, DEFAULTS[mode], None)) for n in names}
        n_before = n_outside(before)
        print(f"## {mode}\n\nchosen: window {cal.window_s:g} s, b = {cal.b:g}, floor N/E/D "
              f"{fmt(np.array(cal.floor_m))} m, snapshot share {cal.snapshot:g}, factor from {cal.factor_from}, "
              f"disagreement share {cal.disagreement:g}, a N/E/D = {fmt(np.array(cal.a))} (leave-fold-out penalty "
              f"{pen:.3f}); held out, {n_out} of {3 * len(held)} trace-axes outside {BAND[0]}-{BAND[1]} at the "
              f"carrier epochs ({n_before} with DEFAULTS)\n")
        shipped = shipped_scores(data, names, mode)
        if shipped:
            print(f"{shipped}\n")
        print("| trace | carrier epochs | before, carrier epochs | held out, carrier epochs | final, carrier epochs "
              "| before, all epochs | final, all epochs |")
        print("|---|---|---|---|---|---|---|")
        for n in [*names, PIXEL5] if PIXEL5 in data else names:
            d = data[n]
            err, car = d[f"{mode}/err"], d[f"{mode}/carrier"]
            before, final = calibrated(d, mode, DEFAULTS[mode], None), calibrated(d, mode, DEFAULTS[mode], cal)
            cb, cf = within(carrier_only(d, mode, err), before), within(carrier_only(d, mode, err), final)
            ab, af = within(err, before), within(err, final)
            ho = held.get(n)
            print(f"| {n} | {int(car.sum())} / {len(car)} | {fmt(cb)}{flag(cb)} | "
                  f"{'-' if ho is None else fmt(ho) + flag(ho)} | {fmt(cf)}{flag(cf)} | {fmt(ab)}{flag(ab)} | "
                  f"{fmt(af)}{flag(af)} |")
        print()
    print("## The settings chosen\n\n```")
    print(json.dumps({m: c.__dict__ for m, c in chosen.items()}, indent=1))
    print("```")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("stage", choices=("collect", "tune"))
    p.add_argument("traces", nargs="*", help="collect: simulated trace folders written with --carrier")
    p.add_argument("--out", type=Path, required=True, help="cache folder (one .npz per trace)")
    p.add_argument("--jobs", type=int, default=1)
    args = p.parse_intermixed_args()
    collect(args) if args.stage == "collect" else tune(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
