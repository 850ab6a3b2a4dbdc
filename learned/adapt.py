"""Adapt the learned measurement models to a phone's own logs without ground truth.

The teacher is the factor graph (pseudoranges + Doppler + time-differenced carrier where the log has
them + motion + clock), with the base network (``fused``, default) or without anything learned
(``fused-nodnn``); its trajectory is precise in shape where Doppler and carrier tie the epochs
together. Its positions stand in for the truth only at epochs where the graph's own marginal horizontal sigma is
at most ``max_teacher_sigma_m`` (the stretches the measurements constrain); the rest teaches nothing.

By default only the per-satellite head (sigma and bias of each pseudorange) is fine-tuned, and only from
the leave-one-satellite-out consistency loss (:mod:`learned.consistency`), for which the teacher is the
linearisation point: the position prior stays the base's byte for byte, and the student gains nothing
from copying the teacher (in a street canyon the teacher can be tens of metres off while claiming a
metre). What that loss cannot check is held to the base (``anchor``, :func:`scale_anchor`): each epoch's
common sigma scale (the residuals of the others fix only the ratios; left free, the sigmas shrink to the
residuals of carrier-smoothed pseudoranges, whose time-correlated errors the graph then over-trusts:
8-17 % worse ``fused`` on three training drives) and the biases. ``part="all"`` / ``agree > 0`` bring
back the whole network and the ordinary training losses against the teacher (:mod:`learned.train`), at guesses drawn as in training (the teacher plus jitter
standing in for the ``graph`` source, the point where ``fused`` asks the network).

Every adaptation is self-validated on the log itself (:mod:`learned.selfcheck`): interleaved blocks of
the teacher-trusted epochs are held out, the held-out criterion is measured before and after each epoch,
the best epoch is kept, and if none beats the base by the margin the adaptation is declined: the output
checkpoint then holds the base's weights and input ranges unchanged, with the decision and its reason in
``config["adapted"]``. An adaptation the self-check accepts must also place the ``fused`` graph better
(:mod:`learned.graph_check`: satellites held out of the graph, predicted at its positions), else it is
declined the same way: the self-check scores snapshots, and the graph weighs pseudoranges against
Doppler, carrier and motion over time. Nor is one kept where the teacher's track is tighter than either check can
judge (:data:`MIN_TEACHER_SIGMA_M`: carrier phase placing it to decimetres), nor where carrier phase ties most of
its epochs (:data:`MAX_CARRIER_SHARE`): both checks score pseudoranges, which there set only where the carrier-shaped
track sits, and no log with carrier has shown an adaptation they passed to be a gain.

Ground truth is never read: every trace is loaded with ``truth="none"`` and a trace that still carries
truth is refused. The adapted checkpoint keeps the base's calibration (nothing here can measure a new
one) and, when accepted, widens the guard's input ranges by the inputs it was adapted on; its config
records how it was adapted (traces by name, teacher, epochs, the held-out check), never a truth figure.

Entry points into the training machinery, for whoever re-points them: :func:`learned.data.build_samples`,
:func:`learned.train.sample_tensors`, :func:`learned.train.guesses_for`, :func:`learned.train.make_inputs`,
:func:`learned.train.batch_loss`, :func:`learned.forward.outputs`, :func:`learned.guard.input_ranges`,
:mod:`learned.checkpoint`.
"""
from __future__ import annotations

import copy
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from fusion.errors import DataError
from fusion.geometry import ecef2ned_cov
from fusion.prepare.load import load_trace
from fusion.prepare.raw_load import RawSources
from fusion.modes import run_modes
from fusion.run_types import RunOptions
from fusion.trace import SIGNALS, Trace
from learned.augment import epoch_generator
from learned.checkpoint import load_model, save_checkpoint
from learned.consistency import loo_nll
from learned.data import build_samples
from learned.features import FeatureConfig
from learned.forward import outputs, take
from learned.graph_check import FOLDS, MARGIN as GRAPH_MARGIN, graph_decision, graph_errors
from learned.guard import input_ranges, widened_ranges
from learned.ensemble import is_manifest, member_paths, write_derived_manifest
from learned.infer import SHIPPED_WEIGHTS
from learned.selfcheck import BLOCK, CRITERION, EVERY, MARGIN, criteria, decide, heldout_inputs, split
from learned.train import LossWeights, TrainConfig, batch_loss, guesses_for, make_inputs, sample_tensors

#: The teachers: the graph with the base network (``fused``: the best answer the base gives, so the
#: student starts from its own answer improved by Doppler / carrier / motion) or without anything learned.
TEACHERS = ("fused", "fused-nodnn")


#: An adaptation is declined where the teacher's median horizontal sigma over the logs is below this [m]: there
#: carrier phase already places the track to decimetres, and both checks score pseudoranges at metre level, so
#: neither can see what re-weighting them does to it. On twenty held-out simulated traces with carrier phase the
#: checks passed seven adaptations, all worse (1.09-2.05 x), their teachers at 0.07-0.27 m; every teacher at
#: 0.51 m or more was declined by the self-check; smartLoc's teacher is metres (experiments/results/adapt.md).
MIN_TEACHER_SIGMA_M = 0.5
#: An adaptation is declined where time-differenced carrier phase ties more than this share of the teacher's
#: solved epochs to a neighbour (``info["carrier_linked"]``). There carrier fixes the track's shape and the
#: pseudoranges only where it sits, to within their own drive-long errors, which the checks' pseudorange scores
#: share. Forced through on twenty held-out simulated traces with carrier (90-100 % tied) adaptation gave 0.64-2.59 x,
#: mean 1.17 x; the checks passed seven, all worse, and none that gained; on the Pixel5 test trace in simulated
#: multi-GNSS streets they passed all six layouts, four worse (the ordinary three 1.04-1.12 x), two better (0.96,
#: 0.88 x). Neither check tells these apart. smartLoc (no carrier) is untouched
#: (experiments/results/adapt.md, "Logs whose track carrier phase ties").
MAX_CARRIER_SHARE = 0.5


@dataclass
class AdaptConfig:
    """How to adapt. ``max_teacher_sigma_m``: teacher epochs used only where its horizontal 1-sigma
    (the graph's marginal) is at most this [m]; ``max_epochs``: use only each log's first N epochs.

    Defaults (chosen on smartLoc and six GSDC training-folder drives, ``experiments/results/adapt.md``):
    the per-satellite head alone, from the leave-one-satellite-out consistency alone (the teacher only
    linearises it and picks the epochs) with its scale and biases anchored to the base's, 5 epochs at
    3e-4, kept only if the held-out check accepts it (a 2 % gain, chosen on the twelve GSDC drives adapted
    from the cross-validation network that never saw them) and the graph check (``graph_*``) confirms it."""

    epochs: int = 5
    lr: float = 3e-4
    batch: int = 64
    seed: int = 0
    max_teacher_sigma_m: float = 3.0
    max_epochs: int | None = None
    elev_mask_deg: float = 10.0
    teacher: str = "fused"
    loo: float = 1.0          # weight of the leave-one-satellite-out consistency loss (0: off)
    part: str = "sat"         # what is fine-tuned: "all" weights, or the per-satellite head alone ("sat")
    agree: float = 0.0        # weight of the training losses against the teacher (0: consistency only)
    block: int = BLOCK        # self-validation: blocks of this many teacher-trusted epochs ...
    every: int = EVERY        # ... every this many-th of which is held out of the fine-tuning
    margin: float = MARGIN    # relative held-out gain needed to accept the adaptation
    anchor: float = 10.0      # weight of the pull of each epoch's mean log-sigma and the biases to the base's
    widen: bool = True        # widen the guard's input ranges by the adapted-on inputs (when accepted)
    graph_check: bool = True  # an accepted adaptation must also place the fused graph better (learned.graph_check)
    graph_folds: int = FOLDS  # ... judged on this many folds of satellites held out of the graph
    graph_margin: float = GRAPH_MARGIN  # ... by at least this relative gain (negative: a tolerance)
    min_teacher_sigma_m: float = MIN_TEACHER_SIGMA_M   # decline where the teacher is tighter than this (0: off)
    max_carrier_share: float = MAX_CARRIER_SHARE       # decline where carrier ties more of its epochs (1: off)


@dataclass
class Teacher:
    """One log and its teacher: ``pos`` (E,3) ECEF, NaN where unsolved; ``sigma_h`` (E,) horizontal
    1-sigma [m] (RMS of north and east), NaN where unsolved; ``doppler`` / ``carrier``: what the graph used;
    ``linked`` (E,) bool: solved epochs time-differenced carrier ties to a neighbour."""

    trace: Trace
    pos: np.ndarray
    sigma_h: np.ndarray
    doppler: bool
    carrier: bool
    seconds: float
    linked: np.ndarray


def load_log(path: str | Path, opts: RunOptions, max_epochs: int | None = None) -> Trace:
    """One log without its truth (``truth="none"``: no ground-truth file or SPAN log is opened), as
    ``gnssfuse run`` loads it (every epoch with >= 1 satellite); the first ``max_epochs`` when given."""
    trace = load_trace(path, signals=opts.signals, truth="none", min_sats=1,
                       raw_sources=RawSources(opts.nav, opts.sp3, opts.clk))
    if trace.truth is not None:       # the loader promised none: never let one reach the training loss
        raise DataError(f"{path}: the loader returned ground truth although asked for none")
    if max_epochs is not None and trace.n_epochs > max_epochs:
        trace = trace.select(np.arange(max_epochs))
    return trace


def teach(path: str | Path, opts: RunOptions, max_epochs: int | None = None, mode: str = "fused") -> Teacher:
    """Load one log (no truth) and solve its teacher trajectory (``mode``, with ``opts.weights`` for
    ``fused``) with the marginal covariance."""
    t0 = time.perf_counter()
    trace = load_log(path, opts, max_epochs)
    res = run_modes(trace, [mode], opts)[mode]
    sigma = np.full(trace.n_epochs, np.nan)
    if res.cov is not None and res.valid.any():
        ok = res.valid & np.isfinite(res.cov).all(axis=(1, 2))
        ned = ecef2ned_cov(res.cov[ok], res.pos[ok])
        sigma[ok] = np.sqrt(0.5 * (ned[:, 0, 0] + ned[:, 1, 1]))
    pos = np.where(res.valid[:, None], res.pos, np.nan)
    linked = res.valid & np.asarray(res.info.get("carrier_linked", np.zeros(trace.n_epochs, bool)), bool)
    return Teacher(trace, pos, sigma, opts.use_doppler and trace.has_doppler, opts.use_carrier and trace.has_carrier,
                   time.perf_counter() - t0, linked)


def teachers(paths: list[str | Path], opts: RunOptions, max_epochs: int | None, mode: str = "fused",
             jobs: int = 1, progress: bool = False, scheduler: str | None = None) -> list[Teacher]:
    """:func:`teach` for every log: in ``jobs`` worker processes (:func:`fusion.parallel.map_traces`) when
    more than one, on the Dask cluster at ``scheduler`` when given, else here; a log that fails is a
    :class:`DataError` naming it."""
    if scheduler is not None:       # a cluster's workers have working directories of their own
        paths, opts = [str(Path(p).absolute()) for p in paths], opts.with_absolute_paths()
    args = [(p, opts, max_epochs, mode) for p in paths]
    if scheduler is not None or (jobs > 1 and len(paths) > 1):
        from fusion.parallel import map_traces
        out = map_traces(teach, args, jobs, progress=progress, scheduler=scheduler)
    else:
        out = [teach(*a) for a in args]
    for p, r in zip(paths, out):
        if isinstance(r, str):
            raise DataError(f"{p}: {r}")
    return out


def teacher_trace(t: Teacher, signals: tuple[str, ...], max_sigma_m: float) -> tuple[Trace, dict]:
    """The log with the teacher in the truth's place at trusted epochs (NaN elsewhere), restricted to
    the network's ``signals``; and counts of what was kept."""
    trusted = np.isfinite(t.pos).all(axis=1) & (t.sigma_h <= max_sigma_m)
    keep = np.isin(t.trace.signal, [SIGNALS.index(s) for s in signals])
    tr = replace(t.trace, truth=np.where(trusted[:, None], t.pos, np.nan)).select_slots(keep)
    counts = {"epochs": int(t.trace.n_epochs), "teacher_solved": int(np.isfinite(t.pos).all(axis=1).sum()),
              "teacher_trusted": int(trusted.sum()),
              "teacher_sigma_h_median_m": float(np.nanmedian(t.sigma_h)) if np.isfinite(t.sigma_h).any() else None,
              "doppler": t.doppler, "carrier": t.carrier, "carrier_linked": int(t.linked.sum()),
              "teacher_s": round(t.seconds, 1)}
    return tr, counts


def train_config(base: dict, cfg: AdaptConfig) -> TrainConfig:
    """The base checkpoint's recipe (features, losses, guesses) with the adaptation's epochs, rate, seed."""
    return TrainConfig(eta=base["eta"], epochs=cfg.epochs, batch=cfg.batch, lr=cfg.lr, seed=cfg.seed,
                       model=base["model"]["kind"], hparams=dict(base["model"].get("hparams", {})),
                       warmup_epochs=0,          # the base is past its warm-up: the variance term from the start
                       features=FeatureConfig.from_dict(base["features"]), data=base.get("data", {}),
                       guess_mix=dict(base.get("guess_mix") or {"box": 1.0, "wls": 0.0}),
                       wls_jitter=base.get("wls_jitter", 2.0), wls_max_err=base.get("wls_max_err", 100.0),
                       signals=tuple(base.get("signals") or ("GPS_L1",)),
                       loss=LossWeights(**base.get("loss", {})), output=base.get("output", "wls"))


def adaptation_samples(taught: list[Teacher], signals: tuple[str, ...], cfg: AdaptConfig):
    """Training samples (:class:`learned.data.Samples`) from the teacher traces, with the teacher as the
    ``graph`` guess source (the point where ``fused`` asks), and the per-log counts."""
    traces, counts, keys = [], {}, []
    for t in taught:
        tr, c = teacher_trace(t, signals, cfg.max_teacher_sigma_m)
        key = t.trace.name if t.trace.name not in counts else f"{t.trace.name} #{len(keys) + 1}"
        counts[key] = c
        keys.append(key)
        traces.append(tr)
    if not any(c["teacher_trusted"] for c in counts.values()):
        n = sum(t.trace.n_epochs for t in taught)
        short = f"; the log(s) hold only {n} epochs in all, fewer than a held-out block" if n <= cfg.block else ""
        raise DataError(f"no epoch of {', '.join(counts)} has a teacher sigma <= {cfg.max_teacher_sigma_m} m "
                        f"(raise --max-teacher-sigma?){short}")
    samples = build_samples(traces, cfg.elev_mask_deg, real=[True] * len(traces))
    samples.graph = samples.truth.copy()
    for key, n in zip(keys, np.bincount(samples.trace, minlength=len(keys))):
        counts[key]["samples"] = int(n)
    return samples, counts


def adapt(paths: list[str | Path], out: str | Path, *, weights: str | Path | None = None,
          cfg: AdaptConfig | None = None, opts: RunOptions | None = None, jobs: int = 1,
          progress: bool = False, log=None, scheduler: str | None = None) -> dict:
    """Fine-tune ``weights`` (None: the shipped ones) on the logs ``paths`` without truth and write the
    checkpoint ``out``: the best epoch on the held-out blocks (:mod:`learned.selfcheck`), or the base
    weights unchanged when no epoch beats them by the margin or the graph check (:func:`check_in_graph`)
    finds the graph placed no better (``record["decision"] == "declined"``). The teachers are solved in
    ``jobs`` processes or on the Dask cluster at ``scheduler`` (:func:`teachers`); the fine-tuning and the
    graph check run here. An ensemble (:mod:`learned.ensemble`) is adapted member by member on the same
    samples (its teacher is the ensemble): ``out`` is then a manifest, its members written beside it.
    Returns the adaptation record stored in its config (``config["adapted"]``; an ensemble's: the record of
    the whole, each member's own in its checkpoint)."""
    cfg, opts = cfg or AdaptConfig(), opts or RunOptions()
    weights, out = Path(weights) if weights is not None else SHIPPED_WEIGHTS, Path(out)
    bases, outs = member_paths(weights, out)
    if {o.resolve() for o in outs} & {b.resolve() for b in bases}:
        raise DataError(f"{out}: would overwrite the base weights, which the graph check compares the adaptation "
                        "with; give --out another name")
    models = [load_model(b) for b in bases]      # a bad checkpoint fails before any log is solved
    tcfg = train_config(models[0][1]["config"], cfg)
    t0 = time.perf_counter()
    check_config(cfg)
    # the teacher's trust threshold (max_teacher_sigma_m) was set on the graph's raw marginals
    teacher_opts = replace(opts, elev_mask_deg=cfg.elev_mask_deg, weights=weights, sigma_calibration=False)
    taught = teachers([str(p) for p in paths], teacher_opts, cfg.max_epochs, cfg.teacher, jobs, progress, scheduler)
    samples, counts = adaptation_samples(taught, tcfg.signals, cfg)
    t_teacher = time.perf_counter() - t0
    if log:
        log(f"teacher ({cfg.teacher}) on {len(taught)} log(s) in {t_teacher:.0f} s: {len(samples)} samples "
            f"where its horizontal sigma <= {cfg.max_teacher_sigma_m} m")
    train_s, held_s = split(samples, cfg.block, cfg.every)
    done: list[Tuned] = []
    for (model, blob), base_path, o in zip(models, bases, outs):
        start = copy.deepcopy(model.state_dict())
        history, ranges, check = fine_tune(model, train_s, tcfg, cfg, held_s, progress)
        record = {"from": base_path.name, "teacher": cfg.teacher, "max_teacher_sigma_m": cfg.max_teacher_sigma_m,
                  "epochs": cfg.epochs, "lr": cfg.lr, "loo": cfg.loo, "anchor": cfg.anchor,
                  "part": cfg.part, "widen": cfg.widen, "agree": cfg.agree,
                  "batch": cfg.batch, "seed": cfg.seed, "max_epochs": cfg.max_epochs,
                  "traces": counts, "samples": len(samples), "teacher_s": round(t_teacher, 1),
                  "train_s": round(sum(h["time_s"] for h in history), 1), **check}
        ranges = ranges if cfg.widen else None
        write_adapted(o, model, blob["config"], record, ranges, history)
        done.append(Tuned(model, blob["config"], o, start, record, history, ranges))
    write_derived_manifest(weights, out, outs)
    record = whole_record(weights, [t.record for t in done])
    if record["decision"] == "accepted":
        check_teacher(record, taught, cfg)
        if record["decision"] == "accepted" and cfg.graph_check:
            check_in_graph(out, weights, [t.trace for t in taught], teacher_opts, cfg, record, log)
        if record["decision"] == "declined" or "graph_check" in record:
            settle(done, record)
    return record


def settle(done: list[Tuned], record: dict) -> None:
    """Rewrite each member with what the checks after its self-check found (``record``, the whole's): the graph
    check's figures, and where the whole was declined, the base weights and the decline's reason."""
    for t in done:
        if t.record is not record and "graph_check" in record:
            t.record["graph_check"] = record["graph_check"]
        if record["decision"] == "declined":
            t.record.update(decision="declined", best_epoch=0, reason=record["reason"])
            t.model.load_state_dict(t.start)
        write_adapted(t.out, t.model, t.base, t.record, t.ranges, t.history)   # widens only where still accepted


@dataclass
class Tuned:
    """One network as fine-tuned: the model (at its kept epoch), the base's config, where it is written, the
    base's weights (to go back to), its adaptation record, the training history and its inputs' ranges."""

    model: torch.nn.Module
    base: dict
    out: Path
    start: dict
    record: dict
    history: list[dict]
    ranges: dict | None


def check_config(cfg: AdaptConfig) -> None:
    """One-line errors for settings no adaptation can use."""
    if cfg.teacher not in TEACHERS:
        raise DataError(f"teacher must be one of {', '.join(TEACHERS)}, got {cfg.teacher!r}")
    if not (cfg.loo >= 0 and cfg.agree >= 0 and cfg.loo + cfg.agree > 0):
        raise DataError(f"need loo >= 0 and agree >= 0, not both 0 (got {cfg.loo}, {cfg.agree})")
    if cfg.block < 1 or cfg.every < 2:
        raise DataError(f"the self-check needs block >= 1 and every >= 2 (got {cfg.block}, {cfg.every})")
    if cfg.graph_check and cfg.graph_folds < 2:
        raise DataError(f"the graph check needs at least 2 satellite folds (got {cfg.graph_folds})")


def whole_record(weights: Path, records: list[dict]) -> dict:
    """One network's record, or an ensemble's: accepted when any member's self-check accepted (the graph
    check then judges the whole), with each member's decision under ``members``."""
    if not is_manifest(weights):
        return records[0]
    kept = [r for r in records if r["decision"] == "accepted"]
    rec = dict(kept[0] if kept else records[0], **{"from": weights.name})
    rec["reason"] = "; ".join(f"member {i}: {r['reason']}" for i, r in enumerate(records))
    rec["members"] = [{k: r[k] for k in ("from", "decision", "best_epoch", "heldout")} for r in records]
    rec["train_s"] = round(sum(r["train_s"] for r in records), 1)          # every member's fine-tuning
    return rec


def write_adapted(out: str | Path, model: torch.nn.Module, base: dict, record: dict, ranges: dict | None,
                  history: list[dict]) -> None:
    """Save ``model`` with the base's config plus the adaptation ``record``; the guard's input ranges
    widened by ``ranges`` only when the record says accepted."""
    config = copy.deepcopy(base)
    config["adapted"] = list(base.get("adapted") or []) + [record]      # adapting an adapted one keeps both
    if record["decision"] == "accepted" and ranges is not None:
        config["input_ranges"] = widened_ranges(base.get("input_ranges"), ranges)
    save_checkpoint(out, model, config, epoch=record["best_epoch"], history=history)


def check_teacher(record: dict, taught: list[Teacher], cfg: AdaptConfig) -> None:
    """Turns ``record`` into a decline where carrier phase ties more than ``cfg.max_carrier_share`` of the teachers'
    solved epochs (:data:`MAX_CARRIER_SHARE`: why), or where their median horizontal sigma (all their solved epochs)
    is below ``cfg.min_teacher_sigma_m`` (:data:`MIN_TEACHER_SIGMA_M`: why). Records both figures."""
    sigma = np.concatenate([t.sigma_h for t in taught])
    med = float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else float("nan")
    solved = sum(int(np.isfinite(t.pos).all(axis=1).sum()) for t in taught)
    share = sum(int(t.linked.sum()) for t in taught) / solved if solved else 0.0
    record.update(teacher_sigma_h_median_m=_rounded(med), teacher_carrier_share=_rounded(share))
    if share > cfg.max_carrier_share:
        why = (f"carrier phase ties {share:.0%} of the teacher's epochs, above {cfg.max_carrier_share:.0%}: the "
               "checks score pseudoranges, which cannot show where re-weighting them moves a carrier-shaped track")
    elif med < cfg.min_teacher_sigma_m:
        why = (f"the teacher's median horizontal sigma is {med:.2f} m, below {cfg.min_teacher_sigma_m:g} m: a track "
               "that tight cannot show what re-weighting the pseudoranges does to it")
    else:
        return
    record.update(decision="declined", best_epoch=0, reason=f"{record['reason']}; but {why}")


def check_in_graph(out: Path, weights: Path, traces: list[Trace], opts: RunOptions, cfg: AdaptConfig,
                   record: dict, log=None) -> None:
    """The graph check (:mod:`learned.graph_check`) of the adapted checkpoint ``out`` against the base
    ``weights`` on the logs' ``traces`` (no truth); turns ``record`` into a decline when it fails."""
    t0 = time.perf_counter()
    base, adapted = graph_errors(traces, [replace(opts, weights=weights), replace(opts, weights=Path(out))],
                                 cfg.graph_folds, cfg.seed)
    keep, reason = graph_decision(base, adapted, cfg.graph_margin)
    record["graph_check"] = {"base_m": _rounded(base["error_m"]), "adapted_m": _rounded(adapted["error_m"]),
                             "measurements": adapted["measurements"], "folds": cfg.graph_folds,
                             "folds_unsolved": adapted["folds_unsolved"], "margin": cfg.graph_margin,
                             "seconds": round(time.perf_counter() - t0, 1)}
    if log:
        log(f"{reason} ({record['graph_check']['seconds']:.0f} s)")
    if not keep:
        record.update(decision="declined", best_epoch=0, reason=f"{record['reason']}; but {reason}")


#: What ``AdaptConfig.part`` may name, and the parameter-name prefixes each fine-tunes (None: all).
PARTS = {"all": None, "sat": ("sat_head.",)}


def trainable(model: torch.nn.Module, part: str) -> list[torch.nn.Parameter]:
    """The parameters ``part`` fine-tunes (:data:`PARTS`); the others are frozen (``requires_grad`` off)."""
    if part not in PARTS:
        raise DataError(f"part must be one of {', '.join(PARTS)}, got {part!r}")
    keep = []
    for n, p in model.named_parameters():
        p.requires_grad_(PARTS[part] is None or n.startswith(PARTS[part]))
        if p.requires_grad:
            keep.append(p)
    return keep


def scale_anchor(out: dict, ref: dict, mask: torch.Tensor) -> torch.Tensor:
    """Departure from the base's per-satellite answer ``ref`` in what the log cannot check: each epoch's
    mean log-sigma (the leave-one-out residuals fix only the sigmas' ratios, not their common scale
    against the graph's other factors) and the biases in units of the base sigma. Scalar; (B,S) inputs."""
    n = mask.sum(1).clamp_min(1)
    dlog = (torch.log(out["sigma"] / ref["sigma"]) * mask).sum(1) / n
    dbias = (((out["bias"] - ref["bias"]) / ref["sigma"]) ** 2 * mask).sum(1) / n
    return (dlog ** 2 + dbias).mean()


def adapt_epoch(model, opt, inp: dict, tcfg: TrainConfig, cfg: AdaptConfig, order: torch.Tensor,
                base=None) -> float:
    """One pass over the rows ``order``: ``cfg.agree`` x the training losses against the teacher plus
    ``cfg.loo`` x the leave-one-satellite-out consistency at the teacher (:func:`learned.consistency.loo_nll`)
    plus ``cfg.anchor`` x :func:`scale_anchor` against the frozen ``base`` model; the mean loss."""
    model.train()
    total = 0.0
    for a in range(0, order.numel(), tcfg.batch):
        b = take(inp, order[a:a + tcfg.batch])
        out = outputs(model, b, tcfg.features)
        loss = cfg.agree * batch_loss(out, b, tcfg.loss, True) if cfg.agree else 0.0
        if cfg.loo:
            loss = loss + cfg.loo * loo_nll(b["sat_pos"], b["pr"], b["mask"], b["truth"], out["sigma"], out["bias"])
        if cfg.anchor:
            with torch.no_grad():
                ref = outputs(base, b, tcfg.features)
            loss = loss + cfg.anchor * scale_anchor(out, ref, b["mask"])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        total += float(loss.detach()) * b["x"].shape[0]
    return total / max(order.numel(), 1)


def fine_tune(model: torch.nn.Module, samples, tcfg: TrainConfig, cfg: AdaptConfig, held=None,
              progress: bool = False) -> tuple[list[dict], dict | None, dict]:
    """``tcfg.epochs`` passes of :func:`adapt_epoch` over ``samples`` from the model's current weights,
    scoring the held-out samples ``held`` (:func:`learned.selfcheck.criteria`, ``CRITERION``) before and after each.
    Leaves the model at the best epoch, or at its starting weights when that is declined. Returns the
    per-epoch history, the input ranges at the samples' WLS solutions (for the guard) and the decision
    (``decision``, ``reason``, ``best_epoch``, ``heldout``: the criterion per epoch from 0, ``heldout_all``:
    every held-out figure, ``heldout_samples``)."""
    torch.manual_seed(tcfg.seed)
    opt = torch.optim.Adam(trainable(model, cfg.part), lr=tcfg.lr, betas=tcfg.betas)
    tr = sample_tensors(samples, tcfg.features, torch.device("cpu"), tcfg.wls_max_err)
    va = heldout_inputs(sample_tensors(held, tcfg.features, torch.device("cpu")), tcfg.features) \
        if held is not None and len(held) else None
    start = copy.deepcopy(model.state_dict())
    base = copy.deepcopy(model).eval() if cfg.anchor else None
    allc = [criteria(model, va, tcfg.features) if va is not None else None]
    scores = [allc[0][CRITERION] if va is not None else float("nan")]
    states, history = [start], []
    bar = _bar(tcfg.epochs) if progress else None
    for epoch in range(tcfg.epochs):
        t0 = time.perf_counter()
        inp = make_inputs(tr, guesses_for(tr, tcfg, epoch_generator(tcfg.seed, epoch)), tcfg.features)
        order = torch.randperm(len(samples), generator=epoch_generator(tcfg.seed, epoch + 1_000))
        loss = adapt_epoch(model, opt, inp, tcfg, cfg, order, base)
        if not math.isfinite(loss):
            raise DataError(f"adaptation diverged at epoch {epoch + 1} (loss {loss}); try a smaller --lr")
        allc.append(criteria(model, va, tcfg.features) if va is not None else None)
        scores.append(allc[-1][CRITERION] if va is not None else float("nan"))
        states.append(copy.deepcopy(model.state_dict()))
        history.append({"epoch": epoch + 1, "train_loss": loss, "heldout": _rounded(scores[-1]),
                        "samples": len(samples), "time_s": time.perf_counter() - t0})
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.3f}", heldout=f"{scores[-1]:.3f}")
    if bar is not None:
        bar.close()
    best, reason = decide(scores, cfg.margin)
    if va is None:
        reason = (f"nothing held out to validate on: {len(samples)} teacher-trusted epochs fill fewer than two "
                  f"blocks of --block {cfg.block} (the second is held out); a longer log adapts")
    model.load_state_dict(states[best])
    model.eval()
    check = {"decision": "accepted" if best else "declined", "reason": reason, "best_epoch": best,
             "heldout": [_rounded(v) for v in scores],
             "heldout_all": [c and {k: _rounded(v) for k, v in c.items()} for c in allc],
             "heldout_samples": 0 if held is None else len(held), "margin": cfg.margin, "block": cfg.block,
             "every": cfg.every}
    return history, _ranges(tr, tcfg), check


def _rounded(v: float) -> float | None:
    """``v`` to 5 decimals, None when not finite (so that two records compare equal)."""
    return round(v, 5) if math.isfinite(v) else None


def _bar(total: int):
    from tqdm import tqdm
    return tqdm(total=total, desc="adapt", unit="epoch", file=sys.stderr, dynamic_ncols=True)


def _ranges(tr: dict, tcfg: TrainConfig) -> dict | None:
    """The guard's input ranges at the samples' WLS solutions, or None when WLS solved none."""
    rows = torch.nonzero(tr["wls_ok"]).flatten()
    if not rows.numel():
        return None
    at_wls = make_inputs(take(tr, rows), tr["wls"][rows], tcfg.features)
    return input_ranges(at_wls["x"], at_wls["mask"])
