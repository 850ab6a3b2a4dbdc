"""Covariance calibration of both outputs, fitted where the network is asked.

For each output (``correction``: the variance head; ``wls``: the learned-weight least-squares covariance)
and each NED axis, a sigma scale ``s_k = median(|err_k| / sigma_k) / 0.6745`` makes the 1-sigma interval
hold 68.3 % of the errors; a median, not the RMS of z, because a few guess blunders (z of 50+) would
otherwise set the scale for every epoch. Stored in the checkpoint as ``config["calibration"][output]``
and applied by :class:`learned.infer.Corrector`. ``experiments/crossval.py`` refits the scales on unseen
drives (the honest place) and can write them into a checkpoint with :func:`store_calibration`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from learned.checkpoint import load_model, save_checkpoint
from learned.features import FeatureConfig
from learned.forward import predict_all, take

_MAD_TO_SIGMA = 0.6744897501960817
#: Fewest real validation samples to calibrate on them alone (simulated errors are not phone errors).
CALIB_MIN_REAL = 200


def sigma_scale(z: np.ndarray) -> dict:
    """Per-axis scale from |err| / sigma ``z`` (N,3), with the 1/2-sigma coverage before and after."""
    z = np.abs(np.asarray(z, float))
    z = z[np.isfinite(z).all(1)]
    s = np.maximum(np.median(z, axis=0) / _MAD_TO_SIGMA, 1e-3) if len(z) else np.ones(3)

    def cover(zz: np.ndarray, k: float) -> list[float]:
        return [float(v) for v in (zz <= k).mean(0)] if len(zz) else [float("nan")] * 3
    return {"method": "median", "scale_ned": [float(v) for v in s], "n": int(len(z)),
            "within_1sigma_before": cover(z, 1), "within_2sigma_before": cover(z, 2),
            "within_1sigma_after": cover(z / s, 1), "within_2sigma_after": cover(z / s, 2)}


def z_scores(out: dict, inp: dict, fcfg: FeatureConfig) -> dict[str, np.ndarray]:
    """|err| / sigma per NED axis (N,3) of both outputs from :func:`learned.forward.predict_all`."""
    err_c = (out["mean"].double() - inp["y"].double()) * fcfg.out_scale
    sd_c = torch.exp(0.5 * out["logvar"].double()) * fcfg.out_scale
    R = inp["R"]
    err_w = torch.einsum("bij,bj->bi", R, out["pos"] - inp["truth"])
    var_w = torch.einsum("bij,bjk,bik->bi", R, out["cov"], R)
    return {"correction": (err_c / sd_c).abs().cpu().numpy(),
            "wls": (err_w / var_w.clamp_min(1e-12).sqrt()).abs().cpu().numpy()}


def calibrate_checkpoint(path: Path, va: dict, fcfg: FeatureConfig) -> dict:
    """Fit both outputs' scales on validation inputs ``va`` (:func:`learned.train.make_inputs` at the
    guesses inference uses) with the checkpoint at ``path``, on its real samples when there are enough,
    and store them in it."""
    model, blob = load_model(path, map_location=va["x"].device)
    real = va["real"]
    sub = take(va, torch.nonzero(real).flatten()) if int(real.sum()) >= CALIB_MIN_REAL else va
    z = z_scores(predict_all(model, sub, fcfg), sub, fcfg)
    cal = {k: dict(sigma_scale(v), subset="real validation samples" if sub is not va else "all validation samples")
           for k, v in z.items()}
    store_calibration(path, cal)
    return cal


def store_calibration(path: Path, cal: dict) -> None:
    """Write ``cal`` (output name -> :func:`sigma_scale` dict) into the checkpoint's config."""
    model, blob = load_model(path)
    save_checkpoint(path, model, dict(blob["config"], calibration=cal), epoch=blob.get("epoch", 0),
                    history=blob.get("history", []))
