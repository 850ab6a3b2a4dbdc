"""Position priors from a *prior provider* (the learned correction, or any other source), made
safe for the graph.

A provider is any callable ``provider(trace, init_pos (E,3), valid (E,)) -> (mean_ecef (E,3),
cov_ecef (E,3,3), valid (E,))``; ``fusion`` knows nothing more about it (``learned`` supplies the
DNN one). :func:`ask_provider` calls it and checks what comes back; :func:`clean_priors` is the one
rule that decides which priors the graph uses and with what covariance.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from fusion.errors import GeometryError
from fusion.trace import Trace

#: ``provider(trace, init_pos (E,3), valid (E,)) -> (mean_ecef (E,3), cov_ecef (E,3,3), valid (E,))``
PriorProvider = Callable[[Trace, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

#: ``slot_noise(trace, init_pos (E,3), valid (E,)) -> (sigma (E,S), bias (E,S))`` [m]: a pseudorange sigma
#: and bias per slot, NaN where the provider has no opinion (the graph keeps its own sigma and no bias).
SlotNoiseProvider = Callable[[Trace, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

#: ``doppler_noise(trace, inp) -> counts``: called by :func:`fusion.estimate.graph.inputs.prepare_inputs` once
#: the graph's Doppler factors and their physical sigmas are chosen (``inp`` an ``EpochInputs``), it scales
#: ``inp.raw.prr_sigma`` in place and returns what it did, for the run's report.
DopplerNoiseProvider = Callable[[Trace, object], dict]

#: smallest eigenvalue [m^2] a provider's covariance needs to be used as a prior
PRIOR_MIN_EIG = 1e-6


@dataclass
class LearnedGraphInputs:
    """What a learned model hands the graph for a whole trace, from one pass (E epochs, S slots).

    prior_mean (E,3) ECEF [m], prior_cov (E,3,3) [m^2], prior_ok (E,) bool: a position prior per epoch
    (None: no prior). pr_sigma, pr_bias (E,S) [m]: each pseudorange's sigma and bias (None: no
    opinion; NaN in a slot: no opinion there, the graph keeps its physical model). doppler_noise: a
    :data:`DopplerNoiseProvider` (None: the physical model). info: counts the model reports (what its guard
    did), passed on to the mode's info.
    """

    prior_mean: np.ndarray | None = None
    prior_cov: np.ndarray | None = None
    prior_ok: np.ndarray | None = None
    pr_sigma: np.ndarray | None = None
    pr_bias: np.ndarray | None = None
    doppler_noise: "DopplerNoiseProvider | None" = None
    info: dict | None = None

    @property
    def has_prior(self) -> bool:
        return self.prior_mean is not None


def learned_from_providers(trace: Trace, provider: "PriorProvider | None", slot_noise: "SlotNoiseProvider | None",
                           at: np.ndarray) -> LearnedGraphInputs | None:
    """The providers' answers at ``at`` (E,3), each asked once, as :class:`LearnedGraphInputs` (None when
    neither is given)."""
    if provider is None and slot_noise is None:
        return None
    out = LearnedGraphInputs()
    if provider is not None:
        out.prior_mean, out.prior_cov, out.prior_ok = ask_provider(provider, trace, at, trace.n_sats >= 1)
    if slot_noise is not None:
        sigma, bias = (np.asarray(a, float) for a in slot_noise(trace, at, np.isfinite(at).all(axis=1)))
        if sigma.shape != trace.mask.shape or bias.shape != trace.mask.shape:
            raise GeometryError(f"{trace.name}: slot noise provider returned shapes {sigma.shape} / "
                                f"{bias.shape}, expected {trace.mask.shape}")
        out.pr_sigma, out.pr_bias = sigma, bias
    return out


@dataclass
class Priors:
    """A provider's output made safe for the graph (see :func:`clean_priors`), E epochs.

    mean (E,3) ECEF (0 where not ok); cov (E,3,3) the covariance used (identity where not ok);
    ok (E,) bool usable; finite (E,) bool mean and covariance finite; spd (E,) bool covariance
    positive definite (smallest eigenvalue > ``PRIOR_MIN_EIG``, identity where not finite).
    """

    mean: np.ndarray
    cov: np.ndarray
    ok: np.ndarray
    finite: np.ndarray
    spd: np.ndarray


def ask_provider(provider: PriorProvider, trace: Trace, at: np.ndarray, valid: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Call ``provider`` at positions ``at`` (E,3) for the epochs in ``valid`` (E,); return its
    (mean (E,3), cov (E,3,3), valid (E,)) as float/bool arrays, or :class:`GeometryError` naming the
    trace when the shapes are not those."""
    E = trace.n_epochs
    mean, cov, ok = provider(trace, at, valid)
    mean, cov, ok = np.asarray(mean, float), np.asarray(cov, float), np.asarray(ok, bool)
    if mean.shape != (E, 3) or cov.shape != (E, 3, 3) or ok.shape != (E,):
        raise GeometryError(f"{trace.name}: prior provider returned shapes {mean.shape}, {cov.shape}, "
                            f"{ok.shape}; expected {(E, 3)}, {(E, 3, 3)}, {(E,)}")
    return mean, cov, ok


def clean_priors(mean: np.ndarray, cov: np.ndarray, valid: np.ndarray, scale: float, floor_m: float,
                 what: str = "cov_scale / sigma_floor_m") -> Priors:
    """The one rule turning a provider's (mean (E,3), cov (E,3,3), valid (E,)) into priors.

    A prior is used where the provider said valid, mean and covariance are finite and the
    symmetrised covariance is positive definite; the covariance used is then
    ``scale * cov + floor_m**2 * I`` (inflation: the network's covariance ignores that its errors
    are correlated from epoch to epoch; floor: see ``experiments/results/graph_tuning.md``).
    ``what`` names the options in the error raised when scale <= 0 or floor_m < 0.
    """
    if not (scale > 0 and floor_m >= 0):
        raise GeometryError(f"{what}: the covariance scale must be > 0 and the sigma floor >= 0, got "
                            f"{scale} and {floor_m}")
    mean, cov, valid = np.asarray(mean, float), np.asarray(cov, float), np.asarray(valid, bool)
    finite = np.isfinite(mean).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    cov_safe = np.where(finite[:, None, None], 0.5 * (cov + cov.transpose(0, 2, 1)), np.eye(3))
    # a singular / indefinite covariance from the provider is a defect: reject it before the
    # floor below would hide it
    spd = np.linalg.eigvalsh(cov_safe)[:, 0] > PRIOR_MIN_EIG
    ok = valid & finite & spd
    used = scale * cov_safe + floor_m ** 2 * np.eye(3)
    return Priors(mean=np.where(ok[:, None], mean, 0.0), cov=np.where(ok[:, None, None], used, np.eye(3)),
                  ok=ok, finite=finite, spd=spd)
