"""Inference: the trained network as a position corrector, a position-prior provider and a pipeline mode.

Honest protocol: the initial guess comes from WLS (or any estimate that never saw the truth); the receiver
clock is re-estimated from the measurements at every guess (:mod:`learned.features`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fusion.errors import CheckpointError, GeometryError
from fusion.geometry import ned_rotation
from fusion.trace import SIGNALS, Trace
from learned.checkpoint import load_model
from learned.features import FeatureConfig, compact_slots, elevation_mask, features_torch

#: Weights shipped with the package (see learned/weights/TRAINING.md).
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "gnssfuse_dnn.pt"
#: Training signal set assumed for checkpoints that do not record one (all were GPS L1 only).
DEFAULT_SIGNALS = ("GPS_L1",)
#: Epochs per forward pass at inference (bounded memory; 2,000-epoch traces go in one chunk).
INFER_CHUNK = 4096


@dataclass
class Correction:
    """Network output for every epoch of a trace (NaN rows where ``valid`` is False).

    mean_ecef: (E,3) corrected position [m].  cov_ecef: (E,3,3) its covariance [m^2].
    corr_ned:  (E,3) correction in the NED frame of the initial guess [m].  cov_ned: (E,3,3) [m^2].
    valid:     (E,) bool: initial guess valid and >= 4 satellites above the elevation mask at it.
    n_too_few: epochs with a valid guess but < 4 satellites above the mask.
    """

    mean_ecef: np.ndarray
    cov_ecef: np.ndarray
    corr_ned: np.ndarray
    cov_ned: np.ndarray
    valid: np.ndarray
    n_too_few: int = 0


class Corrector:
    """A loaded checkpoint. ``corrector(trace, init_pos, valid) -> (mean_ecef, cov_ecef, valid)``.

    Variance calibration: when the checkpoint's config holds ``calibration.scale_ned`` (per-NED-axis sigma
    scale fitted on validation guesses at WLS, or at the no-prior graph solution when the training mix used
    graph guesses (``calibration.guess``), by :func:`learned.train.fit_calibration`), predicted variances are
    multiplied by its square (``calibrated=False`` gives the raw head, e.g. to report before/after).
    Checkpoints without it (trained before calibration existed) load with scale 1.

    Signals: the network only ever sees the signals it was trained on (``config["signals"]``, GPS_L1 for
    checkpoints written before the key existed); other slots of a trace are ignored by :meth:`predict`
    (the initial guess may still come from an all-signal WLS).
    """

    def __init__(self, model: torch.nn.Module, config: dict, device: str = "cpu", path: Path | None = None,
                 calibrated: bool = True):
        self.model = model.eval()
        self.config = config
        try:
            self.features = FeatureConfig.from_dict(config["features"])
        except (TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: bad feature config {config['features']!r}: {exc}") from exc
        if self.features.clock != "median":
            # Paper-leak reproduction (true receiver clock as an input): never allowed to run in the product.
            raise CheckpointError(f"{path}: trained with features.clock={self.features.clock!r} (the paper's "
                                  "true-clock leak, experiment only); refusing to use it for inference")
        signals = tuple(config.get("signals") or DEFAULT_SIGNALS)
        unknown = [s for s in signals if s not in SIGNALS]
        if unknown:
            raise CheckpointError(f"{path}: unknown training signal(s) {unknown} (known: {', '.join(SIGNALS)})")
        self.signals = signals
        self._signal_idx = np.array([SIGNALS.index(s) for s in signals], np.int8)
        self.kind = config["model"]["kind"]
        self.device = torch.device(device)
        self.path = path
        ref = config.get("reference_ecef")
        if self.kind == "direct" and ref is None:
            raise CheckpointError(f"{path}: direct-position checkpoint without a reference point")
        self.reference = None if ref is None else np.asarray(ref, float)
        scale = (config.get("calibration") or {}).get("scale_ned")
        if scale is not None:
            scale = np.asarray(scale, float)
            if scale.shape != (3,) or not (np.isfinite(scale).all() and (scale > 0).all()):
                raise CheckpointError(f"{path}: calibration scale_ned must be 3 positive numbers, got {scale.tolist()}")
        self.var_scale = np.ones(3) if (scale is None or not calibrated) else scale ** 2

    @classmethod
    def load(cls, path: str | Path | None = None, device: str = "cpu", calibrated: bool = True) -> "Corrector":
        path = SHIPPED_WEIGHTS if path is None else Path(path)
        if not path.is_file():
            raise CheckpointError(f"{path}: checkpoint not found"
                                  + (" (shipped weights missing from learned/weights/)" if path == SHIPPED_WEIGHTS else ""))
        model, blob = load_model(path, map_location=device)
        return cls(model, blob["config"], device=device, path=path, calibrated=calibrated)

    @torch.no_grad()
    def predict(self, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                elev_mask_deg: float | None = None) -> Correction:
        """Correct ``init_pos`` (E,3) ECEF at epochs where ``valid`` (E,) and >= 4 satellites of the
        checkpoint's signals clear the elevation mask (checkpoint's, unless given) seen from the guess.
        Batched over all epochs."""
        E = trace.n_epochs
        init_pos = np.asarray(init_pos, float)
        if init_pos.shape != (E, 3) or np.shape(valid) != (E,):
            raise GeometryError(f"{trace.name}: init_pos must be ({E}, 3) and valid ({E},), "
                             f"got {init_pos.shape} and {np.shape(valid)}")
        elev = self.features.elev_mask_deg if elev_mask_deg is None else elev_mask_deg
        ok = np.asarray(valid, bool) & np.isfinite(init_pos).all(1)
        idx = np.flatnonzero(ok)
        guess = init_pos[idx]
        # Only the signals the network was trained on (a GPS-L1 network fed GLONASS/Galileo/BeiDou slots
        # would see their inter-system clock offsets as residuals it has never met).
        own = trace.mask[idx] & np.isin(trace.signal[idx], self._signal_idx)
        mask = elevation_mask(trace.sat_pos[idx], own, guess, elev)
        enough = mask.sum(1) >= 4
        n_too_few = int((~enough).sum())
        idx, guess, mask = idx[enough], guess[enough], mask[enough]

        mean = np.full((E, 3), np.nan)
        cov = np.full((E, 3, 3), np.nan)
        corr = np.full((E, 3), np.nan)
        cov_n = np.full((E, 3, 3), np.nan)
        if len(idx):
            at = guess if self.reference is None else np.broadcast_to(self.reference, guess.shape)
            out, var = self._forward(trace.sat_pos[idx], trace.pr[idx], mask, at)
            R_at = ned_rotation(at)                               # (N,3,3) ECEF -> NED at feature point
            m_ecef = at + np.einsum("nji,nj->ni", R_at, out)
            c_ecef = np.einsum("nji,nj,njk->nik", R_at, var, R_at)
            # a correcting (non-direct) model is evaluated at the guess itself: same rotation
            R_g = R_at if self.reference is None else ned_rotation(guess)
            mean[idx], cov[idx] = m_ecef, c_ecef
            corr[idx] = np.einsum("nij,nj->ni", R_g, m_ecef - guess)
            cov_n[idx] = np.einsum("nij,njk,nlk->nil", R_g, c_ecef, R_g)
        v = np.zeros(E, bool)
        v[idx] = True
        return Correction(mean, cov, corr, cov_n, v, n_too_few)

    @torch.no_grad()
    def _forward(self, sat_pos, pr, mask, at) -> tuple[np.ndarray, np.ndarray]:
        """Network output (N,3) [m] and per-axis variance (N,3) [m^2] in the NED frame at ``at``."""
        f64 = dict(dtype=torch.float64, device=self.device)
        sat_pos, pr, mask = compact_slots(sat_pos, pr, mask)
        outs, vars_ = [], []
        for a in range(0, len(pr), INFER_CHUNK):
            sl = slice(a, a + INFER_CHUNK)
            m = torch.as_tensor(mask[sl], device=self.device)
            x, _ = features_torch(torch.as_tensor(sat_pos[sl], **f64), torch.as_tensor(pr[sl], **f64), m,
                                  torch.as_tensor(np.ascontiguousarray(at[sl]), **f64), self.features)
            mu, logvar = self.model(x, m)
            outs.append(mu.double().cpu().numpy())
            vars_.append(torch.exp(logvar).double().cpu().numpy())
        s = self.features.out_scale
        return np.concatenate(outs) * s, np.concatenate(vars_) * (s * s) * self.var_scale

    def __call__(self, trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
        return self.provider()(trace, init_pos, valid)

    def provider(self, elev_mask_deg: float | None = None):
        """This corrector as a graph prior provider ``(trace, init_pos, valid) -> (mean_ecef, cov_ecef,
        valid)`` with the elevation mask fixed (None: the checkpoint's), so that the ``fused`` mode
        feeds the network what ``dnn`` does under the same ``--elev-mask``."""
        def ask(trace: Trace, init_pos: np.ndarray, valid: np.ndarray):
            c = self.predict(trace, init_pos, valid, elev_mask_deg=elev_mask_deg)
            return c.mean_ecef, c.cov_ecef, c.valid
        return ask


def calibration(err_ned: np.ndarray, cov_ned: np.ndarray) -> dict:
    """Fraction of |error| within 1 and 2 predicted sigma per NED axis (ideal Gaussian: 0.683 / 0.954).

    err_ned (N,3) [m], cov_ned (N,3,3) [m^2]; rows with NaN are ignored.
    """
    ok = np.isfinite(err_ned).all(1) & np.isfinite(cov_ned).all((1, 2))
    sig = np.sqrt(np.diagonal(cov_ned[ok], axis1=1, axis2=2))
    z = np.abs(err_ned[ok]) / sig
    return {"n": int(ok.sum()), "within_1sigma": (z <= 1).mean(0).tolist() if ok.any() else [np.nan] * 3,
            "within_2sigma": (z <= 2).mean(0).tolist() if ok.any() else [np.nan] * 3}


