"""Leave-drives-out cross-validation of the learned correction on the GSDC 2021 training drives.

Four folds of three drives, grouped by date so that neighbouring days never straddle a fold. For each fold
a network is trained on the other nine drives (``learned.train``, the shipped recipe unless options say
otherwise) and every mode runs on the fold's unseen drives with the honest protocol (guess from WLS or the
graph, clock estimated, no truth): ``wls``, ``dnn`` (learned-weight least squares), ``dnn-paper`` (the
paper's correction head), ``fused-nodnn``, ``fused`` and its ablations ``fused-prior`` (learned prior only),
``fused-sigmas`` (learned per-satellite sigmas only) and ``fused-nobias`` (the per-satellite head's sigmas
without its biases, the prior kept), and ``wls-prunc`` (a non-learned reference: WLS
weighted by the phone's reported pseudorange uncertainty). Printed and written to ``<out>/crossval.md``:
per-fold and pooled GSDC score, p50, p95, MAE N/E/D, and the share of errors within 1 and 2 sigma per axis,
both with each checkpoint's own calibration and cross-fitted (the scale fitted on the other folds' unseen
drives, applied to this fold's). ``--store-calibration CKPT`` writes the pooled unseen-drive scales into a
checkpoint (the shipped one is calibrated this way).

    python experiments/crossval.py --data ../shared/data/gsdc2021/train --out /tmp/cv --jobs 2

Quicker, on a busy machine: ``--two-fold`` (two folds of six drives), ``--modes wls,dnn,fused-nodnn,fused``,
``--epochs 8``; ``--feature-version 2`` trains the previous release's recipe on the same folds, and
``--weights CKPT`` evaluates one checkpoint on every fold (in-sample if it was trained on them);
``--reuse --graph-config G.toml`` re-evaluates the fold networks with other graph settings, ``--elev-mask`` with
another elevation mask; ``--canyon ordinary:1000,deep:1001`` adds each fold's own training drives seen from
simulated streets to its training data (``experiments/results/canyon_on_gsdc.md``).
``--ensemble-of RUN1 RUN2 ...`` evaluates, per fold, the ensemble of those runs' fold networks
(:mod:`learned.ensemble`; a manifest ``<out>/fold_<F>.json`` per fold), and ``--store-calibration`` then
takes an ensemble manifest (the shipped weights are one).
"""
from __future__ import annotations

import argparse
import json
import pickle
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.estimate.graph.config import GraphConfig, load_graph_config  # noqa: E402
from fusion.eval.metrics import ned_errors, summarize  # noqa: E402
from fusion.geometry import ecef2ned_cov  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import parse_signals  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.augment import parse_guess_mix  # noqa: E402
from learned.calibrate import sigma_scale  # noqa: E402
from learned.data import concat_samples, samples_from_trace, split_traces  # noqa: E402
from learned.features import FEATURE_VERSION, SUPPORTED_VERSIONS, FeatureConfig  # noqa: E402
from learned.train import LossWeights, TrainConfig, train  # noqa: E402
from learned.train_command import default_inputs, parse_dropout  # noqa: E402

FOLDS = {
    "A": ("2020-05-14-US-MTV-1", "2020-05-14-US-MTV-2", "2020-07-08-US-MTV-1"),
    "B": ("2020-05-21-US-MTV-1", "2020-05-21-US-MTV-2", "2020-09-04-US-SF-2"),
    "C": ("2020-05-29-US-MTV-1", "2020-05-29-US-MTV-2", "2020-06-11-US-MTV-1"),
    "D": ("2020-06-04-US-MTV-1", "2020-06-05-US-MTV-1", "2020-06-05-US-MTV-2"),
}
#: ``--two-fold``: two folds of six drives (A+B, C+D), a quicker check on a busy machine.
FOLDS2 = {"AB": FOLDS["A"] + FOLDS["B"], "CD": FOLDS["C"] + FOLDS["D"]}
#: mode label -> (pipeline mode, RunOptions changes)
MODES = {
    "wls": ("wls", {}), "wls-prunc": ("wls", {"wls_weighting": "uncertainty"}),
    "dnn": ("dnn", {"dnn_output": "wls"}), "dnn-paper": ("dnn", {"dnn_output": "correction"}),
    "fused-nodnn": ("fused-nodnn", {}), "fused": ("fused", {}),
    "fused-prior": ("fused", {"learned_sigmas": False}), "fused-sigmas": ("fused", {"learned_prior": False}),
    "fused-nobias": ("fused", {"learned_bias": False}),
}
CALIBRATED = ("dnn", "fused")


def drive_dir(data: Path, drive: str, phone: str = "Pixel4") -> Path:
    return data / drive / phone


def cached_samples(f: Path, trace, slow_s: float = 0.0):
    """Training samples (with graph positions; with the pseudoranges' fast error part where ``slow_s`` > 0,
    ``--slow-target``) of the trace ``trace()`` makes, kept in ``f``: they cost a graph solve."""
    if slow_s > 0:
        f = f.with_name(f"{f.stem}_slow{slow_s:g}{f.suffix}")
    if f.is_file():
        return pickle.loads(f.read_bytes())
    s = samples_from_trace(trace(), real=True, with_graph=True, slow_window_s=slow_s)
    f.write_bytes(pickle.dumps(s))
    return s


def drive_samples(data: Path, drive: str, cache: Path, phone: str = "Pixel4", signals=("GPS_L1",),
                  slow_s: float = 0.0):
    """Training samples of one drive, cached (:func:`cached_samples`)."""
    return cached_samples(cache / f"{drive}_{phone}_{'-'.join(signals)}.pkl",
                          lambda: load_trace(drive_dir(data, drive, phone), signals=signals), slow_s)


def canyon_samples(data: Path, drive: str, cache: Path, kind: str, seed: int, signals=("GPS_L1",),
                   cn0: bool = False, slow_s: float = 0.0):
    """Training samples of one drive seen from simulated streets (``canyon_on_phone.in_canyon``: "ordinary" the
    simulator's default streets, "deep" its high-rise core; ``seed`` the layout), cached like
    :func:`drive_samples`. Only the fold's own training drives are so used, so no fold sees its unseen drives.
    ``cn0``: the drive first gets the simulator's C/N0 (``canyon_on_phone.with_model_cn0``), which the streets
    then lower for reflections, as a phone log would show them."""
    from canyon_on_phone import DEEP, in_canyon, with_model_cn0
    from fusion.sim.canyon import CanyonModel

    def trace():
        logged = load_trace(drive_dir(data, drive), signals=signals)
        return in_canyon(with_model_cn0(logged, seed) if cn0 else logged, DEEP if kind == "deep" else CanyonModel(),
                         seed)[0]
    return cached_samples(cache / f"{drive}_Pixel4_{'-'.join(signals)}_canyon-{kind}-{seed}{'-cn0' if cn0 else ''}.pkl",
                          trace, slow_s)


def train_fold(fold: str, args) -> Path:
    ckpt = args.out / f"fold_{fold}.pt"
    if ckpt.is_file() and args.reuse:
        return ckpt
    import torch
    torch.set_num_threads(1)
    table = fold_table(args)
    drives = [d for f, ds in table.items() if f != fold for d in ds]
    parts = [drive_samples(args.data, d, args.out / "cache", signals=args.signals, slow_s=args.slow_target)
             for d in drives]
    parts += [drive_samples(x.parent.parent, x.parent.name, args.out / "cache", x.name, args.signals,
                            args.slow_target) for x in args.extra]
    parts += [canyon_samples(args.data, d, args.out / "cache", kind, seed, args.signals, args.canyon_cn0,
                             args.slow_target)
              for d in drives for kind, seed in args.canyon]
    samples = concat_samples([replace(p, trace=np.zeros(len(p), int)) for p in parts])
    # validation: one whole drive of the nine, so the best epoch is the one that generalises
    tr, va = split_traces(samples, 0.1, np.random.default_rng(args.seed))
    cfg = recipe(args, {"drives": drives})
    hist = train(tr, va, cfg, ckpt, progress=False)
    print(f"fold {fold}: {len(tr)} training samples, {len(hist)} epochs in {sum(h['time_s'] for h in hist):.0f} s, "
          f"best validation {min(h['val_score_m'] for h in hist):.2f} m", file=sys.stderr, flush=True)
    return ckpt


def fold_table(args) -> dict:
    return FOLDS2 if args.two_fold else FOLDS


def recipe(args, data: dict) -> TrainConfig:
    """The training recipe under test (the shipped one by default)."""
    w = LossWeights(**{k: float(v) for k, v in (kv.split("=") for kv in args.loss.split(",") if kv)})
    inputs = args.inputs or default_inputs(args.feature_version)
    return TrainConfig(epochs=args.epochs, batch=args.batch, seed=args.seed, data=data, loss=w,
                       guess_mix=parse_guess_mix(args.guess_mix), output="wls", dropout=parse_dropout(args.dropout),
                       features=FeatureConfig(version=args.feature_version, inputs=tuple(inputs.split(","))),
                       signals=args.signals, init=args.init, sat_dropout=args.sat_dropout,
                       slow_target_s=args.slow_target, ema_decay=args.ema,
                       hparams={"dropout": args.model_dropout} if args.model_dropout > 0 else {})


def eval_drive(drive: str, ckpt: Path, args) -> dict:
    """NED errors (E,3) and NED sigmas (E,3) per mode on one unseen drive."""
    import torch
    torch.set_num_threads(1)
    trace = load_trace(drive_dir(args.data, drive))
    # the pooled unseen-drive scales (--store-calibration) are fitted on the covariances before the variance
    # factor (fusion.estimate.variance_factor), which is tuned on top of them (experiments/sigma_calibration.py)
    base = RunOptions(weights=ckpt, graph=args.graph, sigma_calibration=False, elev_mask_deg=args.elev_mask)
    wls = solve_initial(trace, base)
    out = {}
    for label, (mode, changes) in ((k, MODES[k]) for k in args.modes.split(",")):
        opts = replace(base, **changes)
        w = wls if mode != "wls" or not changes else solve_initial(trace, opts)
        res = run_modes(trace, [mode], opts, wls=w)[mode]
        err = ned_errors(np.where(res.valid[:, None], res.pos, np.nan), trace.truth)
        sig = np.full_like(err, np.nan)
        if res.cov is not None:
            ok = res.valid & np.isfinite(trace.truth).all(1)
            sig[ok] = np.sqrt(np.diagonal(ecef2ned_cov(res.cov[ok], trace.truth[ok]), axis1=1, axis2=2))
        out[label] = {"err": err, "sigma": sig}
    return out


def ensemble_fold(fold: str, args) -> Path:
    """The manifest of the ``--ensemble-of`` runs' networks for ``fold``."""
    from learned.ensemble import write_manifest
    few = (args.few_below, [r / f"fold_{fold}.pt" for r in args.few_satellite_of]) if args.few_satellite_of else None
    return write_manifest(args.out / f"fold_{fold}.json", [r / f"fold_{fold}.pt" for r in args.ensemble_of],
                          few=few)


def fold_network(folder: Path, fold: str) -> Path:
    """The weights a cross-validation folder holds for ``fold``: the ensemble manifest ``fold_<F>.json``
    (``--ensemble-of``) where there is one, else the network ``fold_<F>.pt``."""
    ens = folder / f"fold_{fold}.json"
    return ens if ens.is_file() else folder / f"fold_{fold}.pt"


def run_fold(fold: str, args) -> dict:
    ckpt = args.weights or (ensemble_fold(fold, args) if args.ensemble_of else train_fold(fold, args))
    return {d: eval_drive(d, ckpt, args) for d in fold_table(args)[fold]}


def pooled(results: dict, folds, label: str) -> dict:
    err = np.concatenate([results[f][d][label]["err"] for f in folds for d in results[f]])
    return summarize(err)


def coverage(results: dict, folds, label: str, scale=np.ones(3)) -> dict:
    z = np.concatenate([np.abs(results[f][d][label]["err"]) / results[f][d][label]["sigma"]
                        for f in folds for d in results[f]]) / scale
    z = z[np.isfinite(z).all(1)]
    return {"within_1sigma": (z <= 1).mean(0).tolist(), "within_2sigma": (z <= 2).mean(0).tolist(), "n": len(z)}


def cross_fitted(results: dict, label: str) -> dict:
    """Coverage of each fold with the sigma scale fitted on the other folds' unseen drives, pooled."""
    z_all = []
    if len(results) < 2:
        return {"within_1sigma": [float("nan")] * 3, "within_2sigma": [float("nan")] * 3, "n": 0}
    for f in results:
        others = [g for g in results if g != f]
        zo = np.concatenate([np.abs(results[g][d][label]["err"]) / results[g][d][label]["sigma"]
                             for g in others for d in results[g]])
        s = np.asarray(sigma_scale(zo)["scale_ned"])
        z_all.append(np.concatenate([np.abs(results[f][d][label]["err"]) / results[f][d][label]["sigma"]
                                     for d in results[f]]) / s)
    z = np.concatenate(z_all)
    z = z[np.isfinite(z).all(1)]
    return {"within_1sigma": (z <= 1).mean(0).tolist(), "within_2sigma": (z <= 2).mean(0).tolist(), "n": len(z)}


def tables(results: dict) -> str:
    lines = ["| fold | mode | GSDC score | h p50 | h p95 | MAE N | MAE E | MAE D | epochs |", "|---|---|---|---|---|---|---|---|---|"]
    for name, folds in [*((f, [f]) for f in results), ("pooled", list(results))]:
        for label in labels(results):
            s = pooled(results, folds, label)
            lines.append(f"| {name} | {label} | {s['gsdc_score']:.2f} | {s['h_p50']:.2f} | {s['h_p95']:.2f} | "
                         f"{s['mae_n']:.2f} | {s['mae_e']:.2f} | {s['mae_d']:.2f} | {s['n']} |")
    lines += ["", *pooled_ratios(results), "", *drive_table(results)]
    lines += ["", "| mode | calibration | within 1 sigma N / E / D | within 2 sigma N / E / D | n |", "|---|---|---|---|---|"]
    for label in (m for m in CALIBRATED if m in labels(results)):
        for how, c in (("checkpoint's", coverage(results, list(results), label)),
                       ("cross-fitted", cross_fitted(results, label))):
            lines.append(f"| {label} | {how} | {' / '.join(f'{v:.2f}' for v in c['within_1sigma'])} | "
                         f"{' / '.join(f'{v:.2f}' for v in c['within_2sigma'])} | {c['n']} |")
    return "\n".join(lines)


#: Per-drive ratios printed where both modes were run: (mode, its baseline).
RATIOS = (("dnn", "wls"), ("fused", "fused-nodnn"))


def pooled_ratios(results: dict) -> list[str]:
    """Lines: each of the :data:`RATIOS` pooled over every fold, its two GSDC scores to the millimetre (the table's
    two decimals hide the differences recipes make)."""
    have, lines = labels(results), []
    for m, b in ((m, b) for m, b in RATIOS if m in have and b in have):
        g = {k: pooled(results, list(results), k)["gsdc_score"] for k in (m, b)}
        lines.append(f"pooled {m} / {b}: {g[m]:.3f} / {g[b]:.3f} m = {g[m] / g[b]:.4f} x")
    return lines


def drive_table(results: dict) -> list[str]:
    """Markdown lines: GSDC score per unseen drive and mode, and the :data:`RATIOS` between them."""
    have = labels(results)
    ratios = [(m, b) for m, b in RATIOS if m in have and b in have]
    lines = ["| fold | drive | " + " | ".join(have) + "".join(f" | {m} / {b}" for m, b in ratios) + " |",
             "|---|---|" + "---|" * (len(have) + len(ratios))]
    for f in results:
        for d in results[f]:
            g = {m: summarize(results[f][d][m]["err"])["gsdc_score"] for m in have}
            lines.append(f"| {f} | {d} | " + " | ".join(f"{g[m]:.2f}" for m in have)
                         + "".join(f" | {g[m] / g[b]:.3f}" for m, b in ratios) + " |")
    return lines


def labels(results: dict) -> list[str]:
    """The mode labels a results dict holds, in MODES order."""
    first = next(iter(next(iter(results.values())).values()))
    return [m for m in MODES if m in first]


def pooled_scales(results: dict) -> dict:
    """Sigma scales fitted on every fold's unseen drives, per calibrated mode (to store in a checkpoint)."""
    out = {}
    for label in (m for m in CALIBRATED if m in labels(results)):
        z = np.concatenate([np.abs(results[f][d][label]["err"]) / results[f][d][label]["sigma"]
                            for f in results for d in results[f]])
        out[label] = sigma_scale(z)
    return out


def parse_canyon(item: str, parser: argparse.ArgumentParser) -> tuple[str, int]:
    """One ``--canyon`` item, ``KIND:SEED`` -> (KIND, SEED); anything else is the parser's error."""
    kind, _, seed = item.partition(":")
    if kind not in ("ordinary", "deep") or not seed.isdigit():
        parser.error(f"--canyon: {item!r} is not KIND:SEED with KIND ordinary or deep and SEED a whole number")
    return kind, int(seed)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "gsdc2021" / "train")
    p.add_argument("--out", type=Path, default=Path("/tmp/gnssfuse_cv"))
    p.add_argument("--folds", default=None, help="folds to run (default: all of the fold table)")
    p.add_argument("--two-fold", action="store_true", help="two folds of six drives (AB, CD) instead of four")
    p.add_argument("--modes", default=",".join(MODES), help=f"mode labels to evaluate, from {','.join(MODES)}")
    p.add_argument("--feature-version", type=int, default=FEATURE_VERSION, choices=SUPPORTED_VERSIONS,
                   help="input feature version of the recipe (2: the previous release's)")
    p.add_argument("--weights", type=Path, default=None,
                   help="evaluate this checkpoint on every fold instead of training one per fold")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--loss", default="correction=1,sat=0.1,wls=1,shrink=1")
    p.add_argument("--guess-mix", default="box=0.2,wls=0.5,graph=0.3")
    p.add_argument("--inputs", default=None, help="input groups (default: the shipped recipe's, gnssfuse train --inputs)")
    p.add_argument("--dropout", default=None, help="feature dropout rates (gnssfuse train --dropout)")
    p.add_argument("--slow-target", type=float, default=0.0, metavar="S",
                   help="train the per-satellite losses on each pseudorange's error averaged over a centred S s "
                        "along its arc (TrainConfig.slow_target_s; 0: one epoch's error, the recipe)")
    p.add_argument("--sat-dropout", type=float, default=0.0,
                   help="satellite dropout rate (gnssfuse train --sat-dropout)")
    p.add_argument("--model-dropout", type=float, default=0.0, metavar="P",
                   help="the set transformer's layers' dropout in training (0: none, the recipe)")
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="weight average's decay per step (gnssfuse train --ema; 0: off, the recipe)")
    p.add_argument("--jobs", type=int, default=1, help="folds in parallel processes")
    p.add_argument("--reuse", action="store_true", help="reuse fold checkpoints already in --out")
    p.add_argument("--init", type=Path, default=None,
                   help="each fold's network starts from this checkpoint's weights (pre-training; gnssfuse train "
                        "--init)")
    p.add_argument("--few-satellite-of", type=Path, nargs="*", default=[], metavar="RUN",
                   help="with --ensemble-of: runs whose fold networks answer at epochs of fewer than --few-below "
                        "satellites (learned.ensemble's few_satellites)")
    p.add_argument("--few-below", type=int, default=6)
    p.add_argument("--ensemble-of", type=Path, nargs="*", default=[],
                   help="cross-validation folders (one per seed) whose fold networks are evaluated as ensembles")
    p.add_argument("--from-results", action="store_true",
                   help="no training or evaluation: reprint the tables of <out>/results.pkl (and store calibration)")
    p.add_argument("--store-calibration", type=Path, default=None, help="write pooled unseen scales into this checkpoint")
    p.add_argument("--extra", type=Path, nargs="*", default=[],
                   help="<collection>/<phone> trace folders added to every fold's training data (e.g. simulated city traces)")
    p.add_argument("--graph-config", type=Path, default=None,
                   help="the fused modes' graph settings (TOML, as gnssfuse run --graph-config)")
    p.add_argument("--signals", default="GPS_L1", help="signals the training reads (gnssfuse train --signals)")
    p.add_argument("--canyon", default="", metavar="KIND:SEED,...",
                   help="add each fold's training drives seen from simulated streets (KIND ordinary or deep, SEED the "
                        "layout; experiments/canyon_on_phone.py)")
    p.add_argument("--canyon-cn0", action="store_true",
                   help="--canyon's drives get the simulator's C/N0 first, lowered for reflections")
    p.add_argument("--elev-mask", type=float, default=RunOptions.elev_mask_deg,
                   help="the evaluated modes' elevation mask [deg] (gnssfuse run --elev-mask)")
    args = p.parse_args(argv)
    args.signals = parse_signals(args.signals)
    args.canyon = [parse_canyon(item, p) for item in args.canyon.split(",") if item]
    args.graph = load_graph_config(args.graph_config) if args.graph_config else GraphConfig()
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    (args.out / "cache").mkdir(parents=True, exist_ok=True)
    folds = args.folds.split(",") if args.folds else list(fold_table(args))
    unknown = [m for m in args.modes.split(",") if m not in MODES]
    if unknown:
        raise SystemExit(f"--modes: unknown {unknown} (known: {', '.join(MODES)})")
    if args.from_results:
        results = pickle.loads((args.out / "results.pkl").read_bytes())
    else:
        with ProcessPoolExecutor(args.jobs) as ex:
            results = dict(zip(folds, ex.map(run_fold, folds, [args] * len(folds))))
    text = tables(results)
    print(text)
    (args.out / "crossval.md").write_text(text + "\n")
    (args.out / "results.pkl").write_bytes(pickle.dumps(results))
    scales = pooled_scales(results)
    (args.out / "scales.json").write_text(json.dumps(scales, indent=1))
    if args.store_calibration:
        store_unseen(args.store_calibration, scales)
        print(f"stored unseen-drive scales in {args.store_calibration}")
    return 0


def store_unseen(path: Path, scales: dict) -> None:
    """Write the pooled unseen-drive ``scales`` (mode -> :func:`learned.calibrate.sigma_scale` dict) into the
    checkpoint or ensemble manifest at ``path`` as ``unseen_<mode>``."""
    unseen = {f"unseen_{k}": v for k, v in scales.items()}
    from learned.ensemble import is_manifest, store_ensemble_calibration
    if is_manifest(path):
        store_ensemble_calibration(path, unseen)
        return
    from learned.calibrate import store_calibration
    from learned.checkpoint import read_checkpoint
    store_calibration(path, {**dict(read_checkpoint(path)["config"].get("calibration") or {}), **unseen})


if __name__ == "__main__":
    sys.exit(main())
