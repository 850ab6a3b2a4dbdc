"""``gnssfuse train``: fit the correction network (paper Sec. 5.0 settings by default).

Adam(lr 3e-4, betas (0.9, 0.99)), batch 64, MSE on the NED correction; after ``--warmup-epochs`` of pure
MSE the per-axis log-variance head is trained with a Gaussian NLL on the *detached* mean, so the mean is
fitted exactly as in the paper and the variance head only learns how large its errors are.
Every epoch draws new initial guesses (geometry-based augmentation, :mod:`learned.augment`) unless
``--no-augment``, in which case guesses are drawn once and kept (the paper's baseline). ``--guess-mix``
chooses where guesses come from: the paper's box around the truth (``box``) and/or each sample's own WLS
solution plus ``--wls-jitter`` (``wls``: the inference-time distribution; the network learns to undo what
pulls WLS off, e.g. NLOS-biased satellites); ``graph``: each sample's own no-prior factor-graph
solution plus the same jitter (where the fused mode asks the network). After training, the variance
head is calibrated on the validation split from WLS guesses, or from graph guesses when the mix uses
``graph`` (per-NED-axis scale, stored in the checkpoint, applied by
:class:`learned.infer.Corrector`). Validation uses
guesses drawn once, so its loss is comparable across epochs; the best validation MSE is saved to ``--out``
and the last state (with optimizer) to ``<out>.last`` for ``--resume``.

Reproducible on CPU for a given seed (model init, guesses and batch order come from seeded generators;
per-epoch generators are derived from (seed, epoch), so a resumed run draws what an uninterrupted one would).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fusion.errors import CheckpointError, DataError
from fusion.geometry import ecef2geodetic, geodetic2ecef
from learned.augment import draw_guesses, draw_mixed_guesses, epoch_generator, parse_guess_mix
from learned.checkpoint import read_checkpoint, save_checkpoint
from learned.data import (Samples, build_samples, load_real_traces, simulated_traces, split_blocks,
                          split_random)
from learned.features import FeatureConfig, features_torch, target_torch
from learned.model import build_model, count_parameters

#: Feature chunk size when regenerating a whole epoch's inputs (bounded memory on any device).
CHUNK = 16384


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
    wls_jitter: float = 2.0               # [m] per NED axis around the WLS guess
    # Training only: a sample whose WLS (for a wls guess) or no-prior graph solution (for a graph guess)
    # is farther than this from the truth gets a box guess instead (a 200 m blunder would dominate the
    # MSE; the network's output scale is 10 m).
    wls_max_err: float = 100.0
    # after training, fit the variance scale on validation guesses at WLS (at the graph solution when
    # the mix uses graph guesses)
    calibrate: bool = True
    # Signals the training traces were loaded with (real traces: load_real_traces' default; the simulator
    # makes GPS L1); inference uses only these slots of a trace.
    signals: tuple[str, ...] = ("GPS_L1",)

    def warmup(self) -> int:
        return max(1, self.epochs // 10) if self.warmup_epochs is None else self.warmup_epochs

    def to_checkpoint_config(self, reference_ecef: np.ndarray | None) -> dict:
        return {
            "model": {"kind": self.model, "hparams": dict(self.hparams)},
            "features": self.features.to_dict(),
            "eta": self.eta, "augment": self.augment, "seed": self.seed, "epochs": self.epochs,
            "batch": self.batch, "lr": self.lr, "betas": list(self.betas), "warmup_epochs": self.warmup(),
            "val_frac": self.val_frac, "data": self.data,
            "guess_mix": parse_guess_mix(self.guess_mix), "wls_jitter": self.wls_jitter,
            "wls_max_err": self.wls_max_err, "signals": list(self.signals),
            # Direct-position model only: features and targets live at this fixed ECEF reference.
            "reference_ecef": None if reference_ecef is None else [float(v) for v in reference_ecef],
        }


def _guess_source(name: str, pos: np.ndarray, truth: np.ndarray, max_err: float, device: torch.device
                  ) -> dict[str, torch.Tensor]:
    """``name`` (N,3) positions (NaN rows -> 0), ``name_ok`` (finite) and ``name_use`` (finite and within
    ``max_err`` of the truth: the training-time filter for guesses from this source)."""
    ok = np.isfinite(pos).all(1)
    use = ok & (np.linalg.norm(np.where(ok[:, None], pos - truth, 0.0), axis=1) <= max_err)
    return {name: torch.as_tensor(np.where(ok[:, None], pos, 0.0), dtype=torch.float64, device=device),
            f"{name}_ok": torch.as_tensor(ok, device=device), f"{name}_use": torch.as_tensor(use, device=device)}


def _tensors(s: Samples, device: torch.device, wls_max_err: float = math.inf) -> dict[str, torch.Tensor]:
    """Sample arrays on ``device``, with the guess sources of :func:`_guess_source`: ``wls`` always,
    ``graph`` when the samples carry graph positions."""
    f64 = dict(dtype=torch.float64, device=device)
    graph = {} if s.graph is None else _guess_source("graph", s.graph, s.truth, wls_max_err, device)
    return {"sat_pos": torch.as_tensor(s.sat_pos, **f64), "pr": torch.as_tensor(s.pr, **f64),
            "mask": torch.as_tensor(s.mask, device=device), "truth": torch.as_tensor(s.truth, **f64),
            **_guess_source("wls", s.wls_or_nan(), s.truth, wls_max_err, device),
            "real": torch.as_tensor(s.real_or_false(), device=device),
            **({} if s.clock is None else {"clock": torch.as_tensor(s.clock, **f64)}), **graph}


def _require_graph(*ts: dict[str, torch.Tensor]) -> None:
    """DataError unless every sample set carries graph positions (a mix with 'graph' guesses)."""
    if not all("graph" in t for t in ts):
        raise DataError("guess mix uses 'graph' but the samples carry no graph positions "
                        "(build them with with_graph=True)")


def guesses_for(t: dict[str, torch.Tensor], cfg: "TrainConfig", generator: torch.Generator) -> torch.Tensor:
    """Initial guesses (N,3) for one epoch: the paper's box only (bit-identical to earlier versions),
    or the configured box / WLS / graph mix (graph: needs samples built ``with_graph``)."""
    mix = parse_guess_mix(cfg.guess_mix)
    box, gf = mix["box"], mix.get("graph", 0.0)
    if box >= 1.0:
        return draw_guesses(t["truth"], cfg.eta, generator)
    if gf > 0:
        _require_graph(t)
    return draw_mixed_guesses(t["truth"], t["wls"], t["wls_use"], cfg.eta, box, cfg.wls_jitter, generator,
                              t.get("graph"), t.get("graph_use"), gf)[0]


def make_inputs(t: dict[str, torch.Tensor], guess: torch.Tensor, fcfg: FeatureConfig
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (N,S,4) float32 and targets (N,3) float32 at ``guess`` (N,3) or a broadcast (1,3)."""
    xs, ys = [], []
    n = t["pr"].shape[0]
    for a in range(0, n, CHUNK):
        sl = slice(a, min(a + CHUNK, n))
        g = guess[sl] if guess.shape[0] == n else guess.expand(sl.stop - sl.start, 3)
        # The true clock only for the paper-leak experiment (FeatureConfig.clock == "given").
        clk = t["clock"][sl] if fcfg.clock == "given" else None
        x, R = features_torch(t["sat_pos"][sl], t["pr"][sl], t["mask"][sl], g, fcfg, clk)
        xs.append(x)
        ys.append(target_torch(t["truth"][sl], g, R, fcfg))
    return torch.cat(xs), torch.cat(ys)


def reference_point(truth: np.ndarray) -> np.ndarray:
    """Direct model's fixed reference: the training truths' mean, put on the ellipsoid (h = 0)."""
    llh = ecef2geodetic(truth.mean(0))
    return geodetic2ecef(np.array([llh[0], llh[1], 0.0]))


def gaussian_nll(mean: torch.Tensor, logvar: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return 0.5 * (logvar + (y - mean) ** 2 * torch.exp(-logvar)).mean()


def train(train_s: Samples, val_s: Samples, cfg: TrainConfig, out: str | Path, *, resume: bool = False,
          progress: bool = True) -> list[dict]:
    """Train and checkpoint; returns the per-epoch history (losses, MAE [m], timings [s])."""
    out = Path(out)
    last = out.with_name(out.name + ".last")
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise DataError("--device cuda requested but CUDA is not available")
    if len(train_s) == 0:
        raise DataError("no training samples after filtering (truth present, >= 4 satellites)")
    if cfg.features.clock == "given" and (train_s.clock is None or (len(val_s) and val_s.clock is None)):
        raise DataError("FeatureConfig(clock='given') (paper-leak experiment) needs samples with a true clock "
                        "(learned.data.simulated_samples_with_clock)")
    direct = cfg.model == "direct"
    ref = reference_point(train_s.truth) if direct else None
    if direct and cfg.features.out_scale < 100:
        # Residuals and targets at a fixed reference are km-sized: scale them to O(1) like the others.
        cfg.features = dataclasses.replace(cfg.features, res_scale=1000.0, out_scale=1000.0)
    ckpt_cfg = cfg.to_checkpoint_config(ref)
    fcfg = cfg.features

    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model, **cfg.hparams).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=cfg.betas)
    history: list[dict] = []
    start = 0
    if resume:
        if not last.is_file():
            raise CheckpointError(f"{last}: no checkpoint to resume from")
        blob = read_checkpoint(last, map_location=device)
        for key in ("model", "eta", "augment", "seed", "features", "data", "guess_mix", "wls_jitter"):
            if blob["config"].get(key) != ckpt_cfg.get(key):
                raise CheckpointError(f"{last}: cannot resume, {key!r} differs "
                                      f"({blob['config'].get(key)!r} in checkpoint vs {ckpt_cfg.get(key)!r} now)")
        model.load_state_dict(blob["model_state"])
        opt.load_state_dict(blob["optimizer_state"])
        start, history = blob["epoch"], list(blob["history"])
    best = min((h["val_mse"] for h in history), default=math.inf)

    tr, va = _tensors(train_s, device, cfg.wls_max_err), _tensors(val_s, device, cfg.wls_max_err)
    # Honest validation: guess = the sample's WLS position exactly (what inference sees), every WLS-valid sample.
    vw = torch.nonzero(va["wls_ok"]).flatten()
    xw, yw = (make_inputs({k: v[vw] for k, v in va.items()}, va["wls"][vw], fcfg) if len(vw) and not direct
              else (None, None))
    # With a graph source: also validate (and calibrate) at each sample's no-prior graph solution exactly,
    # the point where the fused mode asks the network.
    use_graph = parse_guess_mix(cfg.guess_mix).get("graph", 0.0) > 0 and not direct
    if use_graph:
        _require_graph(tr, va)
    vg = torch.nonzero(va["graph_ok"]).flatten() if use_graph else torch.zeros(0, dtype=torch.long)
    xg, yg = (make_inputs({k: v[vg] for k, v in va.items()}, va["graph"][vg], fcfg) if len(vg)
              else (None, None))
    ref_t = None if ref is None else torch.as_tensor(ref, dtype=torch.float64, device=device)[None]
    # Validation (and no-augmentation training) guesses: drawn once, from generators independent of epochs.
    if direct:
        xv, yv = make_inputs(va, ref_t, fcfg) if len(val_s) else (None, None)
        fixed_train = make_inputs(tr, ref_t, fcfg)
    else:
        gv = guesses_for(va, cfg, epoch_generator(cfg.seed, -2, device))
        xv, yv = make_inputs(va, gv, fcfg) if len(val_s) else (None, None)
        fixed_train = None if cfg.augment else make_inputs(
            tr, guesses_for(tr, cfg, epoch_generator(cfg.seed, -1, device)), fcfg)

    n = len(train_s)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.epochs, initial=start, desc="train", unit="epoch", file=sys.stderr, dynamic_ncols=True)
    for epoch in range(start, cfg.epochs):
        gen = epoch_generator(cfg.seed, epoch, device)
        t0 = time.perf_counter()
        if fixed_train is not None:
            x, y = fixed_train
        else:
            x, y = make_inputs(tr, guesses_for(tr, cfg, gen), fcfg)
        perm = torch.randperm(n, generator=gen, device=device)
        t_feat = time.perf_counter() - t0
        use_nll = epoch >= cfg.warmup()
        model.train()
        # summed on the device and read once per epoch: an .item() per batch would sync the GPU every step
        sums = torch.zeros(2, dtype=torch.float64, device=device)
        t_model = 0.0
        for a in range(0, n, cfg.batch):
            idx = perm[a:a + cfg.batch]
            xb, yb, mb = x[idx], y[idx], tr["mask"][idx]
            tm = time.perf_counter()
            mean, logvar = model(xb, mb)
            mse = F.mse_loss(mean, yb)
            loss = mse + gaussian_nll(mean.detach(), logvar, yb) if use_nll else mse
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            t_model += time.perf_counter() - tm
            sums += torch.stack([mse.detach(), loss.detach()]).double() * len(idx)
        sums = sums.cpu()
        rec = {"epoch": epoch + 1, "train_mse": float(sums[0] / n), "train_loss": float(sums[1] / n),
               "nll": use_nll, "time_s": time.perf_counter() - t0, "feature_s": t_feat, "model_s": t_model,
               "samples": n}
        rec.update(evaluate_arrays(model, xv, yv, va["mask"], fcfg) if xv is not None else
                   {"val_mse": rec["train_mse"]})
        if xw is not None:
            rec.update({"val_wls_" + k[4:]: v for k, v in
                        evaluate_arrays(model, xw, yw, va["mask"][vw], fcfg).items()})
        if xg is not None:
            rec.update({"val_graph_" + k[4:]: v for k, v in
                        evaluate_arrays(model, xg, yg, va["mask"][vg], fcfg).items()})
        history.append(rec)
        if rec["val_mse"] < best:
            best = rec["val_mse"]
            save_checkpoint(out, model, ckpt_cfg, epoch=epoch + 1, history=history)
        save_checkpoint(last, model, ckpt_cfg, optimizer_state=opt.state_dict(), epoch=epoch + 1, history=history)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(train=f"{rec['train_mse']:.4f}", val=f"{rec['val_mse']:.4f}",
                            mae=f"{rec.get('val_mae_m', float('nan')):.2f}m")
    if bar is not None:
        bar.close()
    if not out.is_file():  # zero epochs left to run (e.g. resume of a finished run) still leaves a model
        save_checkpoint(out, model, ckpt_cfg, epoch=start, history=history)
    # Calibrate where the network will be asked: graph guesses when the mix uses them, else WLS guesses.
    cx, cy, ci, at = (xg, yg, vg, "graph") if xg is not None else (xw, yw, vw, "wls")
    if cfg.calibrate and cx is not None:
        blob = read_checkpoint(out, map_location=device)
        model.load_state_dict(blob["model_state"])
        real = va["real"][ci]
        # Calibrate for phones when there are enough phone samples: simulated errors are not phone errors.
        sub = real if int(real.sum()) >= CALIB_MIN_REAL else torch.ones_like(real)
        cal = fit_calibration(model, cx[sub], cy[sub], va["mask"][ci][sub], fcfg)
        cal["subset"] = "real validation samples" if sub is real else "all validation samples"
        if at == "graph":     # key only for the new source: older checkpoints (WLS guesses) stay as they were
            cal["guess"] = "graph"
        save_checkpoint(out, model, dict(blob["config"], calibration=cal), epoch=blob["epoch"],
                        history=blob["history"])
    return history


#: Fewest real validation samples (at the calibration guesses: WLS, or graph) to calibrate on them alone.
CALIB_MIN_REAL = 200


@torch.no_grad()
def fit_calibration(model, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, fcfg: FeatureConfig) -> dict:
    """Per-NED-axis scale ``s`` for the predicted sigma (variance *= s^2) from features ``x`` built at
    the guesses the network will be asked at (each sample's WLS, or its no-prior graph solution).

    ``s_k = median(|err_k| / sigma_k) / 0.6745``: makes the 1-sigma interval hold 68.3 % of the errors;
    a median, not the RMS of z, because a few guess blunders (z of 50+) would otherwise set the scale for
    all epochs. Both are stored (``scale_rms`` for information); coverages before/after on the same set.
    """
    model.eval()
    mean, logvar = model(x, mask)
    z = ((mean - y) * torch.exp(-0.5 * logvar)).double().abs()
    s = (z.median(dim=0).values / 0.6744897501960817).clamp_min(1e-3)
    rms = torch.sqrt((z ** 2).mean(0))

    def cover(zz: torch.Tensor, k: float) -> list[float]:
        return [float(v) for v in (zz <= k).double().mean(0)]

    return {"method": "median", "scale_ned": [float(v) for v in s], "scale_rms": [float(v) for v in rms],
            "n": int(x.shape[0]), "within_1sigma_before": cover(z, 1), "within_2sigma_before": cover(z, 2),
            "within_1sigma_after": cover(z / s, 1), "within_2sigma_after": cover(z / s, 2)}


@torch.no_grad()
def evaluate_arrays(model, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, fcfg: FeatureConfig,
                    batch: int = 4096) -> dict:
    """Validation MSE (normalised units), MAE per axis [m] and 1/2-sigma coverage of the variance head."""
    model.eval()
    means, logvars = [], []
    for a in range(0, x.shape[0], batch):
        m, lv = model(x[a:a + batch], mask[a:a + batch])
        means.append(m)
        logvars.append(lv)
    mean, logvar = torch.cat(means), torch.cat(logvars)
    err = (mean - y) * fcfg.out_scale
    sigma = torch.exp(0.5 * logvar) * fcfg.out_scale
    mae = err.abs().mean(0)
    return {"val_mse": float(F.mse_loss(mean, y)), "val_mae_m": float(mae.mean()),
            "val_mae_ned_m": [float(v) for v in mae],
            "val_within_1sigma": [float(v) for v in (err.abs() <= sigma).float().mean(0)],
            "val_within_2sigma": [float(v) for v in (err.abs() <= 2 * sigma).float().mean(0)]}


# ------------------------------------------------------------------------------------------------- CLI
def _parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    p.add_argument("--data", nargs="+", required=True,
                   help="'sim' (fusion.sim.simulate), 'toy' (learned.toy), and/or trace folders / Kaggle roots "
                        "(comma-separated also accepted)")
    p.add_argument("--eta", type=float, default=15.0, help="augmentation half-width per NED axis [m]")
    p.add_argument("--epochs", type=int, default=200)
    p.add_argument("--out", type=Path, required=True, help="best checkpoint path (last state: <out>.last)")
    p.add_argument("--resume", action="store_true", help="continue from <out>.last")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--model", default="set", choices=("set", "deepsets", "direct"))
    p.add_argument("--no-augment", action="store_true", help="draw guesses once and keep them (paper's baseline)")
    p.add_argument("--sim-traces", type=int, default=50)
    p.add_argument("--sim-epochs", type=int, default=200, help="epochs per simulated trace")
    p.add_argument("--sim-bias", action="store_true",
                   help="simulate 'sim' with the Gaussian + bias scenario ('sim-bias' in --data adds such traces "
                        "next to Gaussian ones)")
    p.add_argument("--sim-bias-traces", type=int, default=None, help="traces for 'sim-bias' (default --sim-traces)")
    p.add_argument("--guess-mix", default="box=1",
                   help="initial-guess sources and fractions, e.g. box=0.5,wls=0.5 (box: truth + U(+-eta) per NED "
                        "axis, the paper's; wls: the sample's own WLS solution + U(+-wls-jitter); graph: the "
                        "sample's own no-prior factor-graph (fused-nodnn) solution + U(+-wls-jitter))")
    p.add_argument("--wls-jitter", type=float, default=2.0, help="[m] per NED axis around WLS guesses")
    p.add_argument("--wls-max-err", type=float, default=100.0,
                   help="[m] a training sample whose WLS (wls guesses) or graph solution (graph guesses) is "
                        "farther from the truth gets a box guess instead")
    p.add_argument("--val-split", default="random", choices=("random", "blocks"),
                   help="validation = random epochs, or random blocks of 60 consecutive epochs")
    p.add_argument("--no-calibrate", action="store_true", help="do not fit the variance scale after training")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--warmup-epochs", type=int, default=None, help="MSE-only epochs before the NLL term")
    p.add_argument("--val-frac", type=float, default=0.1)
    p.add_argument("--elev-mask", type=float, default=10.0, help="elevation mask [deg], at the truth")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (1 is fastest on a busy machine: small batches do not parallelise)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def load_training_data(sources: list[str], *, sim_traces: int, sim_epochs: int, sim_bias: bool, seed: int,
                       elev_mask_deg: float, sim_bias_traces: int | None = None, with_graph: bool = False
                       ) -> tuple[Samples, dict]:
    """``sim`` / ``toy``: simulated (Gaussian, or bias with ``sim_bias``); ``sim-bias`` / ``toy-bias``: the
    Gaussian + NLOS-bias scenario (seed + 1, so not the same drives as ``sim``); anything else: real traces."""
    traces, real, desc = [], [], {"sources": sources}
    for src in sources:
        if src in ("sim", "toy", "sim-bias", "toy-bias"):
            extra = src.endswith("-bias")
            n = (sim_bias_traces if sim_bias_traces is not None else sim_traces) if extra else sim_traces
            sd = seed + 1 if extra else seed
            new = simulated_traces(n, sim_epochs, seed=sd, bias=extra or sim_bias, toy=src.startswith("toy"))
            desc[src] = {"traces": n, "epochs_per_trace": sim_epochs, "bias": extra or sim_bias, "seed": sd}
            real += [False] * len(new)
        else:
            new = load_real_traces([src])
            real += [True] * len(new)
        traces += new
    samples = build_samples(traces, elev_mask_deg, real=real, with_graph=with_graph)
    desc.update(traces=samples.names, n_samples=len(samples), skipped=samples.skipped)
    return samples, desc


def main(argv: list[str], prog: str = "gnssfuse train") -> int:
    args = _parser(prog).parse_args(argv)
    if args.epochs < 1 or args.batch < 1 or not (0 <= args.val_frac < 1) or args.eta <= 0:
        raise DataError("need --epochs >= 1, --batch >= 1, 0 <= --val-frac < 1, --eta > 0")
    if args.wls_jitter < 0 or args.wls_max_err <= 0:
        raise DataError("need --wls-jitter >= 0 and --wls-max-err > 0")
    try:
        mix = parse_guess_mix(args.guess_mix)
    except ValueError as exc:
        raise DataError(f"--guess-mix: {exc}") from None
    if args.threads:
        torch.set_num_threads(args.threads)
    sources = [s for item in args.data for s in item.split(",") if s]
    samples, desc = load_training_data(sources, sim_traces=args.sim_traces, sim_epochs=args.sim_epochs,
                                       sim_bias=args.sim_bias, seed=args.seed, elev_mask_deg=args.elev_mask,
                                       sim_bias_traces=args.sim_bias_traces,
                                       with_graph=mix.get("graph", 0.0) > 0)
    split = split_blocks if args.val_split == "blocks" else split_random
    train_s, val_s = split(samples, args.val_frac, np.random.default_rng(args.seed))
    desc.update(n_train=len(train_s), n_val=len(val_s), val_split=args.val_split)
    cfg = TrainConfig(eta=args.eta, epochs=args.epochs, batch=args.batch, lr=args.lr, seed=args.seed,
                      model=args.model, augment=not args.no_augment, warmup_epochs=args.warmup_epochs,
                      val_frac=args.val_frac, device=args.device,
                      features=FeatureConfig(elev_mask_deg=args.elev_mask), data=desc, guess_mix=mix,
                      wls_jitter=args.wls_jitter, wls_max_err=args.wls_max_err, calibrate=not args.no_calibrate)
    model_params = count_parameters(build_model(args.model))
    print(f"{prog}: {len(train_s)} training / {len(val_s)} validation samples from {len(samples.names)} traces; "
          f"model {args.model} ({model_params} parameters); skipped {samples.skipped}", file=sys.stderr)
    hist = train(train_s, val_s, cfg, args.out, resume=args.resume, progress=not args.quiet)
    if hist:
        h = min(hist, key=lambda r: r["val_mse"])
        print(f"best epoch {h['epoch']}: val MAE N/E/D [m] = "
              + "/".join(f"{v:.2f}" for v in h.get("val_mae_ned_m", [float('nan')] * 3))
              + ("" if "val_wls_mae_ned_m" not in h else " (guess = WLS: "
                 + "/".join(f"{v:.2f}" for v in h["val_wls_mae_ned_m"]) + ")")
              + ("" if "val_graph_mae_ned_m" not in h else " (guess = graph: "
                 + "/".join(f"{v:.2f}" for v in h["val_graph_mae_ned_m"]) + ")") + f" -> {args.out}")
        cal = read_checkpoint(args.out)["config"].get("calibration")
        if cal:
            print(f"variance scale N/E/D {'/'.join(f'{v:.2f}' for v in cal['scale_ned'])} ({cal['subset']}, "
                  f"n={cal['n']}): within 1 sigma {'/'.join(f'{v:.2f}' for v in cal['within_1sigma_before'])}"
                  f" -> {'/'.join(f'{v:.2f}' for v in cal['within_1sigma_after'])}")
    return 0
