"""``gnssfuse train``: fit the correction network (paper Sec. 5.0 settings by default).

Adam(lr 3e-4, betas (0.9, 0.99)), batch 64, MSE on the NED correction; after ``--warmup-epochs`` of pure
MSE the per-axis log-variance head is trained with a Gaussian NLL on the *detached* mean, so the mean is
fitted exactly as in the paper and the variance head only learns how large its errors are.
Every epoch draws new initial guesses (geometry-based augmentation, :mod:`learned.augment`) unless
``--no-augment``, in which case guesses are drawn once and kept (the paper's baseline). Validation uses
guesses drawn once, so its loss is comparable across epochs; the best validation MSE is saved to ``--out``
and the last state (with optimizer) to ``<out>.last`` for ``--resume``.

Reproducible on CPU for a given seed (model init, guesses and batch order come from seeded generators;
per-epoch generators are derived from (seed, epoch), so a resumed run draws what an uninterrupted one would).
"""
from __future__ import annotations

import argparse
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
from learned.augment import draw_guesses, epoch_generator
from learned.checkpoint import read_checkpoint, save_checkpoint
from learned.data import Samples, build_samples, load_real_traces, simulated_traces, split_random
from learned.features import FeatureConfig, features_torch, ned_rotation_torch, target_torch
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

    def warmup(self) -> int:
        return max(1, self.epochs // 10) if self.warmup_epochs is None else self.warmup_epochs

    def to_checkpoint_config(self, reference_ecef: np.ndarray | None) -> dict:
        return {
            "model": {"kind": self.model, "hparams": dict(self.hparams)},
            "features": self.features.to_dict(),
            "eta": self.eta, "augment": self.augment, "seed": self.seed, "epochs": self.epochs,
            "batch": self.batch, "lr": self.lr, "betas": list(self.betas), "warmup_epochs": self.warmup(),
            "val_frac": self.val_frac, "data": self.data,
            # Direct-position model only: features and targets live at this fixed ECEF reference.
            "reference_ecef": None if reference_ecef is None else [float(v) for v in reference_ecef],
        }


def _tensors(s: Samples, device: torch.device) -> dict[str, torch.Tensor]:
    f64 = dict(dtype=torch.float64, device=device)
    return {"sat_pos": torch.as_tensor(s.sat_pos, **f64), "pr": torch.as_tensor(s.pr, **f64),
            "mask": torch.as_tensor(s.mask, device=device), "truth": torch.as_tensor(s.truth, **f64)}


def make_inputs(t: dict[str, torch.Tensor], guess: torch.Tensor, fcfg: FeatureConfig
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (N,S,4) float32 and targets (N,3) float32 at ``guess`` (N,3) or a broadcast (1,3)."""
    xs, ys = [], []
    n = t["pr"].shape[0]
    for a in range(0, n, CHUNK):
        sl = slice(a, min(a + CHUNK, n))
        g = guess[sl] if guess.shape[0] == n else guess.expand(sl.stop - sl.start, 3)
        x, R = features_torch(t["sat_pos"][sl], t["pr"][sl], t["mask"][sl], g, fcfg)
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
    direct = cfg.model == "direct"
    ref = reference_point(train_s.truth) if direct else None
    if direct and cfg.features.out_scale < 100:
        # Residuals and targets at a fixed reference are km-sized: scale them to O(1) like the others.
        cfg.features = FeatureConfig(res_scale=1000.0, out_scale=1000.0, elev_mask_deg=cfg.features.elev_mask_deg)
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
        for key in ("model", "eta", "augment", "seed", "features", "data"):
            if blob["config"].get(key) != ckpt_cfg.get(key):
                raise CheckpointError(f"{last}: cannot resume, {key!r} differs "
                                      f"({blob['config'].get(key)!r} in checkpoint vs {ckpt_cfg.get(key)!r} now)")
        model.load_state_dict(blob["model_state"])
        opt.load_state_dict(blob["optimizer_state"])
        start, history = blob["epoch"], list(blob["history"])
    best = min((h["val_mse"] for h in history), default=math.inf)

    tr, va = _tensors(train_s, device), _tensors(val_s, device)
    ref_t = None if ref is None else torch.as_tensor(ref, dtype=torch.float64, device=device)[None]
    # Validation (and no-augmentation training) guesses: drawn once, from generators independent of epochs.
    if direct:
        xv, yv = make_inputs(va, ref_t, fcfg) if len(val_s) else (None, None)
        fixed_train = make_inputs(tr, ref_t, fcfg)
    else:
        gv = draw_guesses(va["truth"], cfg.eta, epoch_generator(cfg.seed, -2, device))
        xv, yv = make_inputs(va, gv, fcfg) if len(val_s) else (None, None)
        fixed_train = None if cfg.augment else make_inputs(
            tr, draw_guesses(tr["truth"], cfg.eta, epoch_generator(cfg.seed, -1, device)), fcfg)

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
            x, y = make_inputs(tr, draw_guesses(tr["truth"], cfg.eta, gen), fcfg)
        perm = torch.randperm(n, generator=gen, device=device)
        t_feat = time.perf_counter() - t0
        use_nll = epoch >= cfg.warmup()
        model.train()
        sums = torch.zeros(2, dtype=torch.float64)
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
            sums += torch.tensor([mse.item() * len(idx), loss.item() * len(idx)], dtype=torch.float64)
        rec = {"epoch": epoch + 1, "train_mse": float(sums[0] / n), "train_loss": float(sums[1] / n),
               "nll": use_nll, "time_s": time.perf_counter() - t0, "feature_s": t_feat, "model_s": t_model,
               "samples": n}
        rec.update(evaluate_arrays(model, xv, yv, va["mask"], fcfg) if xv is not None else
                   {"val_mse": rec["train_mse"]})
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
    return history


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
                   help="'sim' (fusion.simulate), 'toy' (learned.toy), and/or trace folders / Kaggle roots "
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
    p.add_argument("--sim-bias", action="store_true", help="simulate with the Gaussian + bias scenario")
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
                       elev_mask_deg: float) -> tuple[Samples, dict]:
    traces, desc = [], {"sources": sources}
    for src in sources:
        if src in ("sim", "toy"):
            traces += simulated_traces(sim_traces, sim_epochs, seed=seed, bias=sim_bias, toy=src == "toy")
            desc[src] = {"traces": sim_traces, "epochs_per_trace": sim_epochs, "bias": sim_bias, "seed": seed}
        else:
            traces += load_real_traces([src])
    samples = build_samples(traces, elev_mask_deg)
    desc.update(traces=samples.names, n_samples=len(samples), skipped=samples.skipped)
    return samples, desc


def main(argv: list[str], prog: str = "gnssfuse train") -> int:
    args = _parser(prog).parse_args(argv)
    if args.epochs < 1 or args.batch < 1 or not (0 <= args.val_frac < 1) or args.eta <= 0:
        raise DataError("need --epochs >= 1, --batch >= 1, 0 <= --val-frac < 1, --eta > 0")
    if args.threads:
        torch.set_num_threads(args.threads)
    sources = [s for item in args.data for s in item.split(",") if s]
    samples, desc = load_training_data(sources, sim_traces=args.sim_traces, sim_epochs=args.sim_epochs,
                                       sim_bias=args.sim_bias, seed=args.seed, elev_mask_deg=args.elev_mask)
    train_s, val_s = split_random(samples, args.val_frac, np.random.default_rng(args.seed))
    desc.update(n_train=len(train_s), n_val=len(val_s))
    cfg = TrainConfig(eta=args.eta, epochs=args.epochs, batch=args.batch, lr=args.lr, seed=args.seed,
                      model=args.model, augment=not args.no_augment, warmup_epochs=args.warmup_epochs,
                      val_frac=args.val_frac, device=args.device,
                      features=FeatureConfig(elev_mask_deg=args.elev_mask), data=desc)
    model_params = count_parameters(build_model(args.model))
    print(f"{prog}: {len(train_s)} training / {len(val_s)} validation samples from {len(samples.names)} traces; "
          f"model {args.model} ({model_params} parameters); skipped {samples.skipped}", file=sys.stderr)
    hist = train(train_s, val_s, cfg, args.out, resume=args.resume, progress=not args.quiet)
    if hist:
        h = min(hist, key=lambda r: r["val_mse"])
        print(f"best epoch {h['epoch']}: val MAE N/E/D [m] = "
              + "/".join(f"{v:.2f}" for v in h.get("val_mae_ned_m", [float('nan')] * 3)) + f" -> {args.out}")
    return 0
