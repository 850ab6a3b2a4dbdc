"""``gnssfuse train``: fit the correction network and its per-satellite head.

Three losses train it (:class:`LossWeights`, :mod:`learned.losses`): the paper's MSE of the NED correction
(plus, after ``warmup`` epochs, a Gaussian NLL on the detached mean for the variance head), the Gaussian NLL
of each pseudorange's error under the per-satellite sigma and bias, and the error of the position the
per-satellite weights give (one weighted least-squares step from the guess): the weights are trained for
what the ``dnn`` and ``fused`` modes use them for; a shrink term keeps the head at the physical sigma model
and zero bias unless the data insist (:func:`head_departure`). Adam(lr 3e-4, betas (0.9, 0.99)).

Every epoch draws new initial guesses (geometry-based augmentation, :mod:`learned.augment`): the paper's box
around the truth and/or each sample's own WLS or no-prior graph solution plus jitter (``--guess-mix``), the
points where inference asks the network. Validation asks at each sample's WLS solution exactly; the best
validation error of the configured output is saved to ``--out``, the last state (with optimizer) to
``<out>.last`` for ``--resume``. Afterwards both outputs' covariances are calibrated on the validation
split (:mod:`learned.calibrate`).

Reproducible on CPU for a given seed (model init, guesses and batch order come from seeded generators; per-
epoch generators derive from (seed, epoch, rank), so a resumed run draws what an uninterrupted one would).
Under ``torchrun`` (:mod:`learned.distributed`) every rank trains on its shard of each epoch's permutation
with its own guess stream, gradients are averaged, and rank 0 alone validates, logs and writes checkpoints.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fusion.errors import CheckpointError, DataError, GnssfuseError
from learned import distributed as dist
from learned.augment import (draw_guesses, draw_mixed_guesses, epoch_generator, parse_guess_mix, satellite_groups,
                             thin_satellites)
from learned.calibrate import calibrate_checkpoint
from learned.checkpoint import read_checkpoint, save_checkpoint
from learned.data import Samples
from learned.features import (CATEGORY_GROUPS, OPTIONAL_GROUPS, FeatureConfig, context_channels, features_torch,
                              target_torch)
from learned.heads import report_sigma
from learned.losses import gaussian_nll, position_loss, sat_nll, weighted_ls_step
from learned.forward import OUTPUTS, outputs, predict_all, take
from learned.ensemble import is_manifest
from learned.guard import input_ranges, widened_ranges
from learned.model import build_model

#: Feature chunk size when regenerating a whole epoch's inputs (bounded memory on any device).
CHUNK = 16384
#: Feature dropout of the shipped recipe (:attr:`TrainConfig.dropout`).
DEFAULT_DROPOUT = {"pr_sigma": 0.5, "cn0": 0.3, "cmd": 0.3, "carrier": 0.3, "system": 0.05, "signal": 0.1,
                   "heading": 0.2}


@dataclass
class LossWeights:
    """Mix of the three losses (0 switches one off)."""

    correction: float = 1.0     # paper's MSE (+ variance NLL after warm-up), out_scale units
    sat: float = 0.1            # per-satellite NLL [log m]
    wls: float = 1.0            # Huber of the learned-weight WLS position error, over ``wls_scale`` [m]
    wls_scale: float = 5.0
    # pull toward the physical sigma model and no bias: the head departs from them only where the
    # data insist (unregularised, its departures lost to the model alone on unseen drives)
    shrink: float = 1.0


@dataclass
class TrainConfig:
    eta: float = 15.0
    epochs: int = 200
    batch: int = 64
    lr: float = 3e-4
    betas: tuple[float, float] = (0.9, 0.99)
    seed: int = 0
    model: str = "set"
    hparams: dict = field(default_factory=dict)
    augment: bool = True
    warmup_epochs: int | None = None      # None: max(1, epochs // 10)
    val_frac: float = 0.1
    device: str = "cpu"
    features: FeatureConfig = field(default_factory=FeatureConfig)
    data: dict = field(default_factory=dict)  # description of the training data (for the checkpoint)
    guess_mix: dict = field(default_factory=lambda: {"box": 1.0, "wls": 0.0})
    wls_jitter: float = 2.0               # [m] per NED axis around WLS / graph guesses
    # Training only: a guess source farther than this from the truth gives that sample a box guess.
    wls_max_err: float = 100.0
    calibrate: bool = True
    signals: tuple[str, ...] = ("GPS_L1",)
    loss: LossWeights = field(default_factory=LossWeights)
    output: str = "wls"                   # what the dnn mode returns (one of OUTPUTS)
    # feature dropout (version 3): per sample, the chance that a file-level group reads as missing
    # (pr_sigma: as in RINEX, which reports none; the physical model then starts from C/N0 or a default);
    # per slot, the chance that the constellation / signal reads as unknown
    dropout: dict = field(default_factory=lambda: dict(DEFAULT_DROPOUT))
    # a checkpoint whose weights start the run (pre-training elsewhere, e.g. on simulated traces); None:
    # weights drawn from the seed. The optimiser starts afresh either way.
    init: str | Path | None = None
    # satellite dropout: per sample and epoch, the chance that it keeps only a few of its satellites
    # (learned.augment.thin_satellites), as a street canyon leaves them; 0: off
    sat_dropout: float = 0.0
    # > 0: the per-satellite losses target each pseudorange's error averaged over this centred window [s] along
    # its arc (Samples.pr_fast taken out), the part a smoother cannot average away; 0: one epoch's error
    slow_target_s: float = 0.0
    # > 0: validate and save an exponential moving average of the weights, updated after every step with this
    # decay (torch.optim.swa_utils; 0.999 averages over about 1,000 steps, two epochs of the recipe): one
    # epoch's weights carry the noise of its last batches. 0: the trained weights themselves
    ema_decay: float = 0.0

    def warmup(self) -> int:
        return max(1, self.epochs // 10) if self.warmup_epochs is None else self.warmup_epochs

    def to_checkpoint_config(self) -> dict:
        hp = dict(self.hparams, d_in=self.features.n_inputs)
        return {
            "model": {"kind": self.model, "hparams": hp}, "features": self.features.to_dict(),
            "eta": self.eta, "augment": self.augment, "seed": self.seed, "epochs": self.epochs,
            "batch": self.batch, "lr": self.lr, "betas": list(self.betas), "warmup_epochs": self.warmup(),
            "val_frac": self.val_frac, "data": self.data, "guess_mix": parse_guess_mix(self.guess_mix),
            "wls_jitter": self.wls_jitter, "wls_max_err": self.wls_max_err, "signals": list(self.signals),
            "loss": vars(self.loss).copy(), "output": self.output,
            **({"dropout": dict(self.dropout)} if self.features.version > 2 else {}),
            **({"init": str(self.init)} if self.init is not None else {}),
            **({"sat_dropout": self.sat_dropout} if self.sat_dropout > 0 else {}),
            **({"slow_target_s": self.slow_target_s} if self.slow_target_s > 0 else {}),
            **({"ema_decay": self.ema_decay} if self.ema_decay > 0 else {}),
        }


# ------------------------------------------------------------------------------------------ tensors
def _guess_source(name: str, pos: np.ndarray, truth: np.ndarray, max_err: float, device) -> dict:
    """``name`` (N,3) positions (NaN rows -> 0), ``name_ok`` (finite) and ``name_use`` (finite and within
    ``max_err`` of the truth: the training-time filter for guesses from this source)."""
    ok = np.isfinite(pos).all(1)
    use = ok & (np.linalg.norm(np.where(ok[:, None], pos - truth, 0.0), axis=1) <= max_err)
    return {name: torch.as_tensor(np.where(ok[:, None], pos, 0.0), dtype=torch.float64, device=device),
            f"{name}_ok": torch.as_tensor(ok, device=device), f"{name}_use": torch.as_tensor(use, device=device)}


def sample_tensors(s: Samples, fcfg: FeatureConfig, device, max_err: float = math.inf) -> dict:
    """Sample arrays on ``device``: measurements, truth, guess sources (``wls``; ``graph`` when carried)
    and the context channels (N,S,C) the feature config asks for."""
    if len(fcfg.inputs) > 2 and s.ctx is None:
        raise DataError(f"features {fcfg.inputs} need per-slot context but the samples carry none")
    f64 = dict(dtype=torch.float64, device=device)
    extra = context_channels(s.ctx, s.mask, fcfg) if s.ctx is not None else np.zeros(s.mask.shape + (0,))
    prs, alt = _physical_sigmas(s, fcfg)
    graph = {} if s.graph is None else _guess_source("graph", s.graph, s.truth, max_err, device)
    return {"sat_pos": torch.as_tensor(s.sat_pos, **f64), "pr": torch.as_tensor(s.pr, **f64),
            "mask": torch.as_tensor(s.mask, device=device), "truth": torch.as_tensor(s.truth, **f64),
            "extra": torch.as_tensor(extra, dtype=torch.float32, device=device),
            "pr_sigma": torch.as_tensor(prs, **f64), "pr_sigma_alt": torch.as_tensor(alt, **f64),
            "real": torch.as_tensor(s.real_or_false(), device=device),
            # the simulator's true clock: only for the paper-leak experiment (FeatureConfig(clock="given"))
            **({} if s.clock is None else {"clock": torch.as_tensor(s.clock, **f64)}),
            # the lasting part of each pseudorange (TrainConfig.slow_target_s): a label, never an input
            **({} if s.pr_fast is None else {"pr_target": torch.as_tensor(s.pr - s.pr_fast, **f64)}),
            **_guess_source("wls", s.wls_or_nan(), s.truth, max_err, device), **graph}


def _physical_sigmas(s: Samples, fcfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """(N,S) the sigma [m] the physical model starts from, and the same without the receiver's report
    (what a file without one gives: feature dropout). Version 2: the trace's pr_sigma, both."""
    if s.ctx is None:
        return np.ones(s.mask.shape), np.ones(s.mask.shape)
    if fcfg.version == 2:
        return s.ctx["pr_sigma"], s.ctx["pr_sigma"]
    c = s.ctx
    return (report_sigma(c["pr_sigma"], c["pr_sigma_ok"], c["cn0"]),
            report_sigma(c["pr_sigma"], np.zeros(s.mask.shape, bool), c["cn0"]))


def feature_dropout(t: dict, cfg: TrainConfig, generator: torch.Generator) -> dict:
    """Sample tensors with this epoch's feature dropout applied to ``extra`` (and the physical model's
    starting sigma where the report is dropped). Version 2 or no dropout: ``t`` as is."""
    fc, p = cfg.features, cfg.dropout or {}
    if fc.version == 2 or not any(p.values()) or t["extra"].shape[-1] == 0:
        return t
    extra, prs = t["extra"].clone(), t["pr_sigma"]
    N, S = t["mask"].shape
    dev = extra.device

    def draw(rate: float, per_slot: bool) -> torch.Tensor:
        u = torch.rand((N, S) if per_slot else (N, 1), generator=generator, device=dev, dtype=torch.float64)
        return (u < rate).expand(N, S)
    for g, sl in fc.slices().items():
        sl = slice(sl.start - 4, sl.stop - 4)            # extra holds the channels after res and los
        if g in OPTIONAL_GROUPS and p.get(g, 0) > 0:
            d = draw(p[g], False)
            extra[..., sl] = extra[..., sl].masked_fill(d[..., None], 0.0)
            if g == "pr_sigma":
                prs = torch.where(d, t["pr_sigma_alt"], prs)
        elif g in CATEGORY_GROUPS and p.get(g, 0) > 0:
            d = draw(p[g], True) & t["mask"]
            unknown = torch.zeros(sl.stop - sl.start, dtype=extra.dtype, device=dev)
            unknown[-1] = 1.0
            extra[..., sl] = torch.where(d[..., None], unknown, extra[..., sl])
    return dict(t, extra=extra, pr_sigma=prs)


def satellite_dropout(t: dict, cfg: TrainConfig, generator: torch.Generator, samples: dict) -> dict:
    """Sample tensors ``t`` with this epoch's satellite dropout applied to ``mask`` (:func:`thin_satellites`);
    the satellite of each slot (``sat_group`` (N,S)) is found once and kept in ``samples``, the run's own
    sample tensors. Off: ``t`` as is."""
    if cfg.sat_dropout <= 0:
        return t
    if "sat_group" not in samples:
        samples["sat_group"] = satellite_groups(samples["sat_pos"], samples["mask"])
    return dict(t, mask=thin_satellites(t["mask"], samples["sat_group"], cfg.sat_dropout, generator))


def guesses_for(t: dict, cfg: TrainConfig, generator: torch.Generator) -> torch.Tensor:
    """Initial guesses (N,3) for one epoch: the paper's box, or the configured box / WLS / graph mix."""
    mix = parse_guess_mix(cfg.guess_mix)
    if mix["box"] >= 1.0:
        return draw_guesses(t["truth"], cfg.eta, generator)
    if mix.get("graph", 0.0) > 0 and "graph" not in t:
        raise DataError("guess mix uses 'graph' but the samples carry no graph positions (with_graph=True)")
    return draw_mixed_guesses(t["truth"], t["wls"], t["wls_use"], cfg.eta, mix["box"], cfg.wls_jitter,
                              generator, t.get("graph"), t.get("graph_use"), mix.get("graph", 0.0))[0]


def make_inputs(t: dict, guess: torch.Tensor, fcfg: FeatureConfig) -> dict:
    """Network inputs at ``guess`` (N,3): ``x`` (N,S,F) float32, target ``y`` (N,3), NED rotation ``R``
    (N,3,3) and the guess, beside the sample tensors."""
    xs, ys, Rs = [], [], []
    for a in range(0, guess.shape[0], CHUNK):
        sl = slice(a, a + CHUNK)
        clock = t["clock"][sl] if fcfg.clock == "given" else None
        x, R = features_torch(t["sat_pos"][sl], t["pr"][sl], t["mask"][sl], guess[sl], fcfg, clock,
                              extra=t["extra"][sl])
        xs.append(x)
        Rs.append(R)
        ys.append(target_torch(t["truth"][sl], guess[sl], R, fcfg))
    return dict(t, x=torch.cat(xs), y=torch.cat(ys), R=torch.cat(Rs), guess=guess)


# ---------------------------------------------------------------------------------------- the step
def batch_loss(out: dict, b: dict, w: LossWeights, use_nll: bool) -> torch.Tensor:
    """The weighted sum of the three losses and the shrink term on one batch. Where the batch carries
    ``pr_target`` (the pseudoranges' lasting part), the per-satellite NLL and the learned-weight position are
    scored on it instead of the measured pseudoranges, which the network still reads."""
    loss = w.correction * F.mse_loss(out["mean"], b["y"])
    if use_nll:
        loss = loss + w.correction * gaussian_nll(out["mean"].detach(), out["logvar"], b["y"])
    pr = b.get("pr_target", b["pr"])
    if w.sat:
        loss = loss + w.sat * sat_nll(b["sat_pos"], pr, b["mask"], b["truth"], out["sigma"], out["bias"])
    if w.wls:
        pos = out["pos"] if pr is b["pr"] else weighted_ls_step(b["sat_pos"], pr, b["mask"], b["guess"],
                                                                out["sigma"], out["bias"])[0]
        loss = loss + w.wls * position_loss(pos, b["truth"], b["R"], w.wls_scale)
    if w.shrink:
        loss = loss + w.shrink * head_departure(out, b["mask"])
    return loss


def head_departure(out: dict, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared log-multiplier of the per-satellite sigma plus squared bias in units of the sigma,
    over real slots (B,S): zero when the head keeps the physical model."""
    dep = out["log_mult"] ** 2 + (out["bias"] / out["sigma"]) ** 2
    return (dep * mask).sum() / mask.sum().clamp_min(1)


def train_epoch(model, opt, inp: dict, cfg: TrainConfig, epoch: int, order: torch.Tensor, average=None) -> float:
    """One pass over the rows ``order`` in batches (``average``: a weight average updated after each step, or
    None); returns the mean loss."""
    model.train()
    total = torch.zeros((), dtype=torch.float64, device=order.device)
    for a in range(0, order.numel(), cfg.batch):
        b = take(inp, order[a:a + cfg.batch])
        loss = batch_loss(outputs(model, b, cfg.features), b, cfg.loss, epoch >= cfg.warmup())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        dist.average_gradients(model)
        opt.step()
        if average is not None:
            average.update_parameters(model)
        total += loss.detach().double() * b["x"].shape[0]  # read once per epoch: no GPU sync per step
    return float(total) / max(order.numel(), 1)


def estimate_loss(model, inp: dict, cfg: TrainConfig) -> dict:
    """Validation at the samples' WLS solutions: MAE N/E/D [m] of both outputs and the selection score
    (mean horizontal error of ``cfg.output`` [m])."""
    out = predict_all(model, inp, cfg.features)
    err_c = (out["mean"].double() - inp["y"]) * cfg.features.out_scale
    err_w = torch.einsum("bij,bj->bi", inp["R"], out["pos"] - inp["truth"])
    chosen = err_w if cfg.output == "wls" else err_c
    return {"val_score_m": float(chosen[:, :2].norm(dim=1).mean()),
            "val_mae_ned_m": [float(v) for v in err_c.abs().mean(0)],
            "val_wls_mae_ned_m": [float(v) for v in err_w.abs().mean(0)]}


# ------------------------------------------------------------------------------------- the loop
def weight_average(model, cfg: TrainConfig):
    """The exponential moving average of ``model``'s weights that :attr:`TrainConfig.ema_decay` asks for, or None."""
    if cfg.ema_decay <= 0:
        return None
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema_decay), use_buffers=True)


def resume_state(average) -> dict:
    """What a resumed run needs beside the weights and the optimizer: the global generator's state (the layers'
    dropout draws from it) and the weight average's, where there is one."""
    state = {"rng_state": torch.get_rng_state()}
    if average is not None:
        state["average_state"] = average.state_dict()
    return state


def setup(cfg: TrainConfig, last: Path, resume: bool, device) -> tuple:
    """Model, optimizer, weight average (or None), start epoch and history (from ``last`` when resuming)."""
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model, **cfg.to_checkpoint_config()["model"]["hparams"]).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=cfg.betas)
    if not resume:
        if cfg.init is not None:
            model.load_state_dict(pretrained_state(Path(cfg.init), cfg, device))
        return model, opt, weight_average(model, cfg), 0, []
    if not last.is_file():
        raise CheckpointError(f"{last}: no checkpoint to resume from")
    blob = read_checkpoint(last, map_location=device)
    if cfg.warmup_epochs is None:
        # the default warm-up follows the epoch count, which a resumed run may raise: keep the run's own
        cfg.warmup_epochs = blob["config"].get("warmup_epochs")
    now = cfg.to_checkpoint_config()
    # everything but the epoch count shapes the run: a resumed run must draw what an uninterrupted one would
    for key in ("model", "eta", "augment", "seed", "features", "data", "guess_mix", "wls_jitter", "loss", "batch",
                "lr", "betas", "warmup_epochs", "val_frac", "wls_max_err", "signals", "output", "dropout",
                "sat_dropout", "ema_decay"):
        if _resume_view(blob["config"], key) != _resume_view(now, key):
            raise CheckpointError(f"{last}: cannot resume, {key!r} differs "
                                  f"({blob['config'].get(key)!r} in checkpoint vs {now.get(key)!r} now)")
    model.load_state_dict(blob["model_state"])
    opt.load_state_dict(blob["optimizer_state"])
    if "rng_state" in blob:                     # the layers' dropout draws from it (hparams "dropout")
        torch.set_rng_state(blob["rng_state"])
    average = weight_average(model, cfg)
    if average is not None:
        average.load_state_dict(blob["average_state"])
    return model, opt, average, int(blob["epoch"]), list(blob["history"])


def pretrained_state(path: Path, cfg: TrainConfig, device) -> dict:
    """The weights of checkpoint ``path`` (a state dict on ``device``): the start of a run that fine-tunes a
    pre-trained network. Its network and inputs must be this run's (:class:`CheckpointError` naming the file
    and what differs otherwise)."""
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to start from")
    if is_manifest(path):
        raise CheckpointError(f"{path}: an ensemble manifest; a run starts from one network (one of its members)")
    blob = read_checkpoint(path, map_location=device)
    now = cfg.to_checkpoint_config()
    for key in ("model", "features"):
        if blob["config"].get(key) != now[key]:
            raise CheckpointError(f"{path}: cannot start from it, its {key!r} differs "
                                  f"({blob['config'].get(key)!r} in checkpoint vs {now[key]!r} now)")
    return blob["model_state"]


def _resume_view(config: dict, key: str):
    """What of a run config's ``key`` a resumed run must match: the dropout rates only of the groups the run
    reads (a checkpoint written before a new input group existed has no rate for it, and needs none)."""
    value = config.get(key)
    if key != "dropout" or not isinstance(value, dict):
        return value
    used = set((config.get("features") or {}).get("inputs") or ())
    return {g: r for g, r in value.items() if g in used}


def validation_inputs(va: dict, fcfg: FeatureConfig) -> dict | None:
    """Validation inputs at each sample's WLS solution exactly (what inference sees), or None."""
    rows = torch.nonzero(va["wls_ok"]).flatten()
    return make_inputs(take(va, rows), va["wls"][rows], fcfg) if rows.numel() else None


def check_inputs(train_s: Samples, val_s: Samples, cfg: TrainConfig, device) -> None:
    if cfg.features.clock == "given" and (train_s.clock is None or (len(val_s) and val_s.clock is None)):
        raise DataError("FeatureConfig(clock='given') (paper-leak experiment) needs samples with a true clock "
                        "(learned.data.simulated_samples_with_clock)")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise DataError("--device cuda requested but CUDA is not available")
    if len(train_s) == 0:
        raise DataError("no training samples after filtering (truth present, >= 4 satellites)")
    if cfg.output not in OUTPUTS:
        raise DataError(f"output must be one of {OUTPUTS}, got {cfg.output!r}")
    if (cfg.slow_target_s > 0) != (train_s.pr_fast is not None):
        raise DataError(f"slow_target_s {cfg.slow_target_s} needs training samples built with the same window "
                        "(learned.data.samples_from_trace(slow_window_s=...)), and 0 samples without it")


def train(train_s: Samples, val_s: Samples, cfg: TrainConfig, out: str | Path, *, resume: bool = False,
          progress: bool = True) -> list[dict]:
    """Train and checkpoint; returns the per-epoch history (losses, validation errors [m], timings [s])."""
    out, device = Path(out), dist.device_for(cfg.device)
    last = out.with_name(out.name + ".last")
    check_inputs(train_s, val_s, cfg, device)
    model, opt, average, start, history = setup(cfg, last, resume, device)
    kept = model if average is None else average.module     # what is validated and saved
    dist.broadcast_parameters(model)
    tr = sample_tensors(train_s, cfg.features, device, cfg.wls_max_err)
    va = validation_inputs(sample_tensors(val_s, cfg.features, device, cfg.wls_max_err), cfg.features) \
        if len(val_s) else None
    best = min((h["val_score_m"] for h in history), default=math.inf)
    ckpt_cfg = dict(cfg.to_checkpoint_config(), world_size=dist.world_size())
    at_wls = validation_inputs(tr, cfg.features)       # the training inputs where dnn asks: the OOD guard's ranges
    ckpt_cfg["input_ranges"] = input_ranges(at_wls["x"], at_wls["mask"]) if at_wls is not None else None
    if cfg.init is not None:
        # the network has seen its pre-training's inputs too: the guard must not hand those to the physical model
        ckpt_cfg["input_ranges"] = widened_ranges(read_checkpoint(cfg.init)["config"].get("input_ranges"),
                                                  ckpt_cfg["input_ranges"])
    bar = progress_bar(cfg, start) if progress and dist.is_main() else None
    for epoch in range(start, cfg.epochs):
        rec = run_epoch(model, opt, tr, va, cfg, epoch, average)
        history.append(rec)
        if not (math.isfinite(rec["train_loss"]) and math.isfinite(rec["val_score_m"])):
            raise GnssfuseError(f"training diverged in epoch {epoch + 1}: its loss is not finite (a lower --lr?); "
                                f"{out} is left as it was")
        if dist.is_main():
            if rec["val_score_m"] < best:
                best = rec["val_score_m"]
                save_checkpoint(out, kept, ckpt_cfg, epoch=epoch + 1, history=history)
            save_checkpoint(last, model, ckpt_cfg, optimizer_state=opt.state_dict(), epoch=epoch + 1,
                            history=history, extra=resume_state(average))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{rec['train_loss']:.3f}", val=f"{rec['val_score_m']:.2f}m")
    if dist.is_main():
        finish(kept, out, ckpt_cfg, history, start, va, val_s, cfg)
    dist.barrier()
    return history


def run_epoch(model, opt, tr: dict, va: dict | None, cfg: TrainConfig, epoch: int, average=None) -> dict:
    """Fresh guesses, one training pass over this rank's shard, validation (of the weight average where there
    is one); the epoch's history record (with the time spent making inputs and in the forward/backward/step
    loop, for the benchmarks)."""
    t0 = time.perf_counter()
    gen = epoch_generator(cfg.seed, epoch, tr["truth"].device, rank=dist.rank())
    fixed = epoch_generator(cfg.seed, -1, tr["truth"].device)       # --no-augment: the same guesses every epoch
    guess = guesses_for(tr, cfg, gen if cfg.augment else fixed)
    inp = make_inputs(satellite_dropout(feature_dropout(tr, cfg, gen), cfg, gen, tr), guess, cfg.features)
    # one permutation shared by every rank (same seed), each rank taking its own shard of it
    order = dist.shard(torch.randperm(tr["truth"].shape[0], generator=epoch_generator(cfg.seed, epoch)))
    t1 = time.perf_counter()
    loss = train_epoch(model, opt, inp, cfg, epoch, order.to(tr["truth"].device), average)
    rec = {"epoch": epoch + 1, "train_loss": loss, "samples": int(order.numel()), "world_size": dist.world_size(),
           "nll": epoch >= cfg.warmup(), "feature_s": t1 - t0, "model_s": time.perf_counter() - t1}
    kept = model if average is None else average.module
    rec.update(estimate_loss(kept, va, cfg) if va is not None and dist.is_main() else {"val_score_m": loss})
    rec["time_s"] = time.perf_counter() - t0
    return rec


def finish(model, out: Path, ckpt_cfg: dict, history: list, start: int, va: dict | None,
           val_s: Samples, cfg: TrainConfig) -> None:
    """Leave a model at ``out`` even when no epoch ran, then calibrate it on the validation split."""
    if not out.is_file():
        save_checkpoint(out, model, ckpt_cfg, epoch=start, history=history)
    if cfg.calibrate and va is not None:
        calibrate_checkpoint(out, va, cfg.features)


def progress_bar(cfg: TrainConfig, start: int):
    from tqdm import tqdm
    return tqdm(total=cfg.epochs, initial=start, desc="train", unit="epoch", file=sys.stderr, dynamic_ncols=True)
