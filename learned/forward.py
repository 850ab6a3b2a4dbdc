"""One forward pass of the network and what its heads mean in metres, shared by training, calibration and
inference: the correction (``mean``, ``logvar``, in out_scale units), the per-satellite sigma and bias [m],
and the position the per-satellite weights give (one weighted least-squares step from the guess) with its
covariance."""
from __future__ import annotations

import torch

from learned.features import FeatureConfig
from learned.heads import OUTPUTS  # noqa: F401  (re-exported: training imports it from here)
from learned.losses import weighted_ls_step
from learned.model import base_sigma, sat_sigma_bias


def take(t: dict, idx: torch.Tensor) -> dict:
    """The rows ``idx`` of every tensor of a sample dict."""
    return {k: v[idx] for k, v in t.items()}


def outputs(model, b: dict, fcfg: FeatureConfig) -> dict:
    """Forward pass on batch ``b`` (``x`` (B,S,F), ``mask`` (B,S), ``sat_pos`` (B,S,3), ``pr`` (B,S),
    ``pr_sigma`` (B,S) reported sigma [m], ``guess`` (B,3); :func:`learned.train.make_inputs`): the correction
    (``mean``, ``logvar``, out_scale units), per-slot ``sigma``/``bias`` [m] and the learned-weight position
    ``pos`` (B,3) with its covariance ``cov`` (B,3,3)."""
    mean, logvar, sat = model(b["x"], b["mask"])
    # x[..., 3] is the line of sight's down component at the guess: -sin(elevation)
    base = base_sigma(b["pr_sigma"], -b["x"][..., 3])
    sigma, bias = sat_sigma_bias(sat, fcfg.res_scale, base)
    pos, cov = weighted_ls_step(b["sat_pos"], b["pr"], b["mask"], b["guess"], sigma, bias)
    return {"mean": mean, "logvar": logvar, "sigma": sigma, "bias": bias, "pos": pos, "cov": cov,
            "log_mult": torch.log(sigma / base)}


@torch.no_grad()
def predict_all(model, inp: dict, fcfg: FeatureConfig, batch: int = 4096) -> dict:
    """:func:`outputs` over every row of ``inp`` in chunks, concatenated."""
    model.eval()
    parts = [outputs(model, take(inp, torch.arange(a, min(a + batch, inp["x"].shape[0]), device=inp["x"].device)),
                     fcfg) for a in range(0, inp["x"].shape[0], batch)]
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
