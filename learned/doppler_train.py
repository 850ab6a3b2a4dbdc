"""Training the Doppler head (:mod:`learned.doppler_head`) on traces with Doppler and ground truth.

The target of each Doppler measurement is its error at the truth: ``rhs - grad . v_true - drift``, with the
receiver velocity from central differences of the truth track and the epoch's clock drift the median of the
epoch's ``rhs - grad . v_true`` (truth gives no clock). The features are those of inference, computed the same
way (the graph's inputs without anything learned and without the Doppler consistency check, so that the
physical sigmas are the head's base). The loss is the negative log-likelihood of the inlier / outlier mixture
the head's sigma stands for, plus ``shrink * m^2`` (the head keeps the physical model where the data do not
insist), with C/N0 dropped at ``cn0_dropout`` per measurement so that logs without C/N0 (GSDC 2021 files)
read as missing, not as out of range. CPU, seeded, full passes over the data in fixed-size batches.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import nn

from fusion.errors import DataError
from fusion.estimate.graph.consistency import row_medians
from fusion.estimate.graph.raw_inputs import doppler_rows_at
from fusion.estimate.graph.inputs import prepare_inputs
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.trace import Trace
from learned.doppler_head import (FEATURES, FORMAT_VERSION, GUARDED, M_BOUND, OUTLIER_RATIO, SYSTEMS,
                                  doppler_features)

#: epochs need this many Doppler measurements for the median drift to be a target
MIN_EPOCH_DOPPLER = 6
#: a system enters the head's guard as seen with at least this many training measurements
MIN_SYSTEM_ROWS = 200


@dataclass
class HeadConfig:
    """The head's recipe: hidden width, passes over the rows, batch size, Adam's learning rate, the weight of the
    pull of ``m`` to 0, the share of rows whose C/N0 is dropped, the seed."""

    hidden: int = 32
    epochs: int = 20
    batch: int = 4096
    lr: float = 1e-3
    shrink: float = 0.01
    cn0_dropout: float = 0.3
    seed: int = 0


def truth_velocity(trace: Trace, max_step_s: float = 1.5) -> np.ndarray:
    """(E,3) ECEF [m/s]: central differences of the truth track, NaN where a neighbour is missing or more
    than ``max_step_s`` away."""
    E = trace.n_epochs
    v = np.full((E, 3), np.nan)
    if trace.truth is None or E < 3:
        return v
    t = trace.t_ms / 1000.0
    span = t[2:] - t[:-2]
    ok = (span > 0) & (span <= 2 * max_step_s)
    v[1:-1] = np.where(ok[:, None], (trace.truth[2:] - trace.truth[:-2]) / np.where(ok, span, 1.0)[:, None], np.nan)
    return v


def truth_errors(trace: Trace, inp, ks: np.ndarray, ss: np.ndarray) -> np.ndarray:
    """(N,) each Doppler measurement's error at the truth [m/s] (module docstring), NaN where the truth
    velocity is missing or the epoch has fewer than MIN_EPOCH_DOPPLER measurements."""
    vel = truth_velocity(trace)
    grad, rhs = doppler_rows_at(trace, inp.raw, inp.init_pos, ks, ss)
    d = rhs - np.einsum("ij,ij->i", grad, vel[ks])
    pad = np.full(trace.mask.shape, np.nan)
    pad[ks, ss] = d
    n = np.isfinite(pad).sum(axis=1)
    drift = np.where(n >= MIN_EPOCH_DOPPLER, row_medians(pad), np.nan)
    return d - drift[ks]


def trace_rows(trace: Trace, opts: RunOptions) -> dict[str, np.ndarray]:
    """The head's training rows of one trace: x (N,F), err (N,) [m/s], sigma (N,) the physical sigma [m/s]
    (rows without a target dropped)."""
    if not trace.has_doppler or not trace.has_truth:
        raise DataError(f"{trace.name}: the Doppler head needs Doppler and ground truth; this trace lacks "
                        + ("Doppler" if not trace.has_doppler else "ground truth"))
    cfg = replace(opts.graph, use_doppler=True, use_carrier=False, doppler_check_window_s=0.0)
    inp = prepare_inputs(trace, solve_initial(trace, opts), cfg, opts.elev_mask_deg)
    if inp.raw is None:
        raise DataError(f"{trace.name}: no Doppler measurement survives the graph's selection")
    x, ks, ss = doppler_features(trace, inp)
    err = truth_errors(trace, inp, ks, ss)
    keep = np.isfinite(err)
    return {"x": x[keep], "err": err[keep], "sigma": inp.raw.prr_sigma[ks, ss][keep]}


class HeadNet(nn.Module):
    """F -> hidden -> hidden -> 2 (raw log multiplier, outlier logit), ReLU."""

    def __init__(self, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(len(FEATURES), hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 2))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(x)
        return M_BOUND * torch.tanh(out[:, 0] / M_BOUND), out[:, 1]


def mixture_nll(m: torch.Tensor, logit: torch.Tensor, err: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """(N,) negative log-likelihood of err under (1-p) N(0, s^2) + p N(0, (K s)^2), s = sigma e^m."""
    s = sigma * torch.exp(m)
    log_in = -0.5 * (err / s) ** 2 - torch.log(s) + nn.functional.logsigmoid(-logit)
    log_out = -0.5 * (err / (OUTLIER_RATIO * s)) ** 2 - torch.log(OUTLIER_RATIO * s) + nn.functional.logsigmoid(logit)
    return -torch.logaddexp(log_in, log_out) + 0.5 * math.log(2 * math.pi)


def drop_cn0(x: torch.Tensor, rate: float, gen: torch.Generator) -> torch.Tensor:
    """x with C/N0 made missing (flag and value 0) on a random ``rate`` of rows."""
    if rate <= 0:
        return x
    drop = torch.rand(x.shape[0], generator=gen) < rate
    x = x.clone()
    for name in ("cn0_present", "cn0"):
        x[drop, FEATURES.index(name)] = 0.0
    return x


def fit(rows: dict[str, np.ndarray], cfg: HeadConfig, progress=None) -> tuple[HeadNet, list[float]]:
    """Train a HeadNet on rows (:func:`trace_rows`, concatenated); returns it and the mean loss per epoch."""
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    net = HeadNet(cfg.hidden)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    x, err, sig = (torch.as_tensor(rows[k], dtype=torch.float32) for k in ("x", "err", "sigma"))
    hist = []
    for _ in range(cfg.epochs):
        order, total = torch.randperm(len(err), generator=gen), 0.0
        for i in range(0, len(err), cfg.batch):
            b = order[i:i + cfg.batch]
            m, logit = net(drop_cn0(x[b], cfg.cn0_dropout, gen))
            loss = mixture_nll(m, logit, err[b], sig[b]).mean() + cfg.shrink * (m ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(b)
        hist.append(total / len(err))
        if progress is not None:
            progress(hist[-1])
    return net, hist


def head_dict(net: HeadNet, rows: dict[str, np.ndarray], cfg: HeadConfig, names: list[str]) -> dict:
    """The trained head as the checkpoint config's ``doppler_head`` (plain lists: JSON in the .npz)."""
    x = rows["x"]
    lin = [m for m in net.net if isinstance(m, nn.Linear)]
    rng = []
    for g in GUARDED:
        col = x[:, FEATURES.index(g)]
        if g == "cn0":
            col = col[x[:, FEATURES.index("cn0_present")] > 0.5]
        rng.append([float(col.min()), float(col.max())] if len(col) else [0.0, 0.0])
    counts = {s: int(x[:, FEATURES.index(f"sys_{s}")].sum()) for s in SYSTEMS}
    return {"version": FORMAT_VERSION, "features": list(FEATURES),
            "layers": [[m.weight.detach().numpy().tolist(), m.bias.detach().numpy().tolist()] for m in lin],
            "range": rng, "systems": [s for s, n in counts.items() if n >= MIN_SYSTEM_ROWS],
            "trained_on": names, "rows": int(len(x)), "system_rows": counts,
            "recipe": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__}}
