"""Adaptation without ground truth (``gnssfuse adapt``), measured: for each log, adapt the shipped
weights on that log alone (the adaptation never reads truth), then score ``fused`` with the shipped and
the adapted weights, and ``fused-nodnn``, against the truth (read here, for scoring only). Prints a
Markdown table: GSDC score (mean of horizontal p50 and p95) and the ratio adapted / shipped, the
decision, the self-check's held-out criterion by epoch, the graph check's held-out error (base -> adapted),
the epochs the teacher trusted, the pseudoranges the adapted network gave a sigma for, the guard's shrunk /
off epochs, and the times.

    python experiments/adapt_eval.py [--epochs N] [--lr X] [--max-teacher-sigma M] [--loo W] [--agree W] \
        [--part sat|all] [--margin F] [--block N] [--every K] [--no-widen] [--teacher fused|fused-nodnn] \
        [--no-graph-check] [--graph-margin F] [--fold-weights DIR] [LOG ...]

LOG: a GSDC 2021 training-folder name (``2020-05-29-US-MTV-1/Pixel4``) or any trace folder (the smartLoc
one). Default logs: the Pixel5 RINEX trace (GPS broadcast navigation; a test trace), the two GSDC 2021 test
drives (2021-04-28 MTV-1 Pixel4 and SJC-1 Pixel4: out of the shipped network's training), and one of its
training drives (2020-05-14-US-MTV-1: in-sample). Settings are chosen on the others (:data:`LOGS`).
``ADAPT_EVAL_CRITERIA=1`` also prints every held-out figure by epoch (stderr).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from crossval import FOLDS2, fold_network  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.prepare.raw_load import RawSources  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import parse_signals  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.adapt import AdaptConfig, adapt  # noqa: E402
from learned.ensemble import is_manifest  # noqa: E402
from learned.infer import SHIPPED_WEIGHTS  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRAIN = SHARED / "gsdc2021/train"
SMARTLOC = SHARED / "smartloc/Berlin_Potsdamer_Platz"
NAV = (SHARED / "ephemeris/gps_nav/hour1180.21n",)
#: log -> (navigation for raw logs, whether the shipped network was trained on it)
LOGS = {"2021-04-28-US-MTV-1/Pixel5": (NAV, False), "2021-04-28-US-MTV-1/Pixel4": ((), False),
        "2021-04-28-US-SJC-1/Pixel4": ((), False), "2020-05-14-US-MTV-1/Pixel4": ((), True),
        # settings are chosen on these (never on the test logs above): two training drives (05-29-MTV-1 the
        # validation drive of the ensemble's first member, trained on by the other two) and smartLoc (a u-blox
        # in a Berlin canyon, not trained on)
        "2020-05-29-US-MTV-1/Pixel4": ((), True), "2020-06-11-US-MTV-1/Pixel4": ((), True),
        str(SMARTLOC): ((), False)}
#: GSDC training-folder drives no network of the shipped ensemble was trained on (each of the twelve training
#: drives is in some member's training set: their validation drives differ, learned/weights/TRAINING.md).
NOT_TRAINED = ("2021-04-28-",)
#: The logs the script runs when given none: the test logs and one training drive.
DEFAULT_LOGS = list(LOGS)[:4]


def fold_weights(name: str, folder: Path | None) -> Path | None:
    """With ``--fold-weights DIR``: the two-fold cross-validation network that never saw this GSDC drive
    (``DIR/fold_AB.json``, an ensemble, where there is one, else ``DIR/fold_AB.pt``, for the AB drives, ...);
    None (the shipped weights) otherwise."""
    drive = name.split("/")[0]
    fold = next((f for f, drives in FOLDS2.items() if drive in drives), None) if folder else None
    return None if fold is None else fold_network(folder, fold)


def one(name: str, nav: tuple, cfg: AdaptConfig, folder: Path, base: Path | None = None, signals=None) -> dict:
    opts = RunOptions(signals=signals, nav=tuple(nav), weights=base)
    t0 = time.perf_counter()
    path = log_path(name)
    out = folder / ("w.json" if is_manifest(base or SHIPPED_WEIGHTS) else "w.pt")    # an ensemble adapts to one
    rec = adapt([path], out, weights=base, cfg=cfg, opts=opts)
    t_adapt = time.perf_counter() - t0
    trace = load_trace(path, signals=signals, min_sats=1, raw_sources=RawSources(tuple(nav)))
    shipped = run_modes(trace, ["fused-nodnn", "fused"], opts)
    adapted = run_modes(trace, ["fused"], RunOptions(signals=signals, nav=tuple(nav), weights=out))["fused"]
    score = {k: mode_metrics(trace, r)["gsdc_score"] for k, r in shipped.items()}
    score["adapted"] = mode_metrics(trace, adapted)["gsdc_score"]
    c = next(iter(rec["traces"].values()))
    if os.environ.get("ADAPT_EVAL_CRITERIA"):       # every held-out figure, to choose the criterion
        for k in ("nll", "mae", "huber", "mae_nb", "nll_nb", "huber_nb"):
            print(f"    {name} {k}: " + " ".join(f"{c[k]:.4f}" for c in rec["heldout_all"] if c), file=sys.stderr)
    return dict(score, trusted=f"{c['teacher_trusted']}/{c['epochs']}", sigmas=learned_sigmas(adapted.info),
                guard=guard(adapted.info), shipped_guard=guard(shipped["fused"].info), t_adapt=t_adapt,
                decision=decision_words(rec), graph=graph_words(rec),
                heldout=" -> ".join("-" if v is None else f"{v:.3f}" for v in rec["heldout"]))


def log_path(name: str) -> Path:
    """A GSDC training-folder name (collection/phone) or a folder (e.g. the smartLoc one) as given."""
    return TRAIN / name if (TRAIN / name).is_dir() else Path(name)


def learned_sigmas(info: dict) -> int:
    """Pseudoranges the network gave a sigma for (asked minus those its guard gave the physical model)."""
    return int(info.get("learned_meas_asked", 0)) - int(info.get("learned_meas_out_of_range", 0))


def decision_words(rec: dict) -> str:
    """The decision, the epoch kept and, for an ensemble, how many members' self-checks accepted."""
    members = rec.get("members") or [rec]
    took = sum(m["decision"] == "accepted" for m in members)
    return f"{rec['decision']} (epoch {rec['best_epoch']}; members {took}/{len(members)})"


def graph_words(rec: dict) -> str:
    """The graph check's held-out error base -> adapted [m], or why there is none."""
    g = rec.get("graph_check")
    if g is None:
        if rec["decision"] == "declined" and "carrier phase ties" in rec["reason"]:
            return f"not run (carrier ties {rec['teacher_carrier_share']:.0%} of the epochs)"
        if rec["decision"] == "declined" and "median horizontal sigma" in rec["reason"]:
            return f"not run (teacher sigma {rec['teacher_sigma_h_median_m']:.2f} m too tight)"
        return "not run (self-check declined)" if rec["decision"] == "declined" and "graph check" not in \
            rec["reason"] else "off"
    return f"{g['base_m']:.3f} -> {g['adapted_m']:.3f}"


def guard(info: dict) -> str:
    return f"{info.get('learned_epochs_guard_shrunk')}/{info.get('learned_epochs_guard_off')}"


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("logs", nargs="*", default=DEFAULT_LOGS)
    p.add_argument("--epochs", type=int, default=AdaptConfig.epochs)
    p.add_argument("--lr", type=float, default=AdaptConfig.lr)
    p.add_argument("--max-teacher-sigma", type=float, default=AdaptConfig.max_teacher_sigma_m)
    p.add_argument("--loo", type=float, default=AdaptConfig.loo)
    p.add_argument("--teacher", default=AdaptConfig.teacher)
    p.add_argument("--no-widen", dest="widen", action="store_false")
    p.add_argument("--anchor", type=float, default=AdaptConfig.anchor)
    p.add_argument("--part", default=AdaptConfig.part)
    p.add_argument("--agree", type=float, default=AdaptConfig.agree)
    p.add_argument("--margin", type=float, default=AdaptConfig.margin)
    p.add_argument("--block", type=int, default=AdaptConfig.block)
    p.add_argument("--every", type=int, default=AdaptConfig.every)
    p.add_argument("--no-graph-check", dest="graph_check", action="store_false")
    p.add_argument("--graph-margin", type=float, default=AdaptConfig.graph_margin)
    p.add_argument("--min-teacher-sigma", type=float, default=AdaptConfig.min_teacher_sigma_m)
    p.add_argument("--max-carrier-share", type=float, default=AdaptConfig.max_carrier_share)
    p.add_argument("--signals", default=None, help="as gnssfuse run --signals (default: the format's own)")
    p.add_argument("--fold-weights", type=Path, default=None,
                   help="adapt each GSDC training drive from the cross-validation network that never saw it")
    a = p.parse_args()
    cfg = AdaptConfig(epochs=a.epochs, lr=a.lr, max_teacher_sigma_m=a.max_teacher_sigma, loo=a.loo,
                      teacher=a.teacher, anchor=a.anchor, widen=a.widen, part=a.part, agree=a.agree, margin=a.margin, block=a.block, every=a.every,
                      graph_check=a.graph_check, graph_margin=a.graph_margin,
                      min_teacher_sigma_m=a.min_teacher_sigma, max_carrier_share=a.max_carrier_share)
    print(f"adapt: teacher {cfg.teacher}, epochs {cfg.epochs}, lr {cfg.lr}, max teacher sigma {cfg.max_teacher_sigma_m} m, "
          f"leave-one-out weight {cfg.loo}, teacher-agreement weight {cfg.agree}, fine-tuned: {cfg.part}, scale/bias anchor {cfg.anchor}, guard ranges widened: {cfg.widen}, held out every {cfg.every}th block of {cfg.block}, "
          f"margin {cfg.margin}, graph check {'on, margin ' + str(cfg.graph_margin) if cfg.graph_check else 'off'}, "
          f"least teacher sigma {cfg.min_teacher_sigma_m} m, most carrier-tied share {cfg.max_carrier_share}, "
          f"seed {cfg.seed}\n")
    if a.fold_weights:
        print(f"base networks: {a.fold_weights}/fold_*.pt, each GSDC drive adapted from the one that never saw it "
              "('fused, shipped' is that base)\n")
    print("| log | base trained on it | fused-nodnn | fused, shipped | fused, adapted | adapted / shipped "
          "| decision | held-out criterion [m] by epoch | graph check [m] | teacher-trusted epochs "
          "| learned sigmas (adapted) | guard shrunk / off: shipped, adapted | adapt [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    ratios = []
    for name in a.logs:
        in_train = not Path(name).is_absolute() and (TRAIN / name).is_dir()
        nav, insample = LOGS.get(name, ((), in_train and not name.startswith(NOT_TRAINED)))
        base = fold_weights(name, a.fold_weights)
        insample = insample and base is None
        with tempfile.TemporaryDirectory() as tmp:
            r = one(name, nav, cfg, Path(tmp), base, parse_signals(a.signals))
        ratios.append(r["adapted"] / r["fused"])
        print(f"| {name} | {'yes' if insample else 'no'} | {r['fused-nodnn']:.2f} | {r['fused']:.2f} | "
              f"{r['adapted']:.2f} | {ratios[-1]:.3f} | {r['decision']} | {r['heldout']} | {r['graph']} | {r['trusted']} | {r['sigmas']} | "
              f"{r['shipped_guard']}, {r['guard']} | {r['t_adapt']:.0f} |", flush=True)
    print(f"\nmean adapted / shipped: {sum(ratios) / len(ratios):.3f}; worst {max(ratios):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
