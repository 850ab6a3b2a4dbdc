"""The learned correction as a GTSAM factor you can drop into your own graph.

Example (any graph whose variable at ``key`` is an ECEF ``Point3``)::

    from learned.infer import Corrector
    from learned.factor import learned_prior_factor

    corrector = Corrector.load()                      # shipped weights, or Corrector.load("my.pt")
    factor, mean, cov = learned_prior_factor(corrector, sat_pos, pr, mask, init_pos, gtsam.symbol("x", k))
    graph.add(factor)

For a ``Pose3`` variable use :func:`learned_pose_translation_factor` (a ``PoseTranslationPrior3D``
on the pose's translation, i.e. the pose frame is ECEF). :func:`learned_prior_factors` does a whole
trace in one network pass (much faster than one call per epoch).
``examples/04_learned_factor_in_your_graph.py`` composes it with an odometry chain.
"""
from __future__ import annotations

from typing import Callable

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.graph_build import robust_model
from fusion.trace import Trace, empty_trace

#: ``provider(trace, init_pos (E,3), valid (E,)) -> (mean_ecef (E,3), cov_ecef (E,3,3), valid (E,))``;
#: ``learned.infer.Corrector`` instances are providers.
PriorProvider = Callable[[Trace, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def one_epoch_trace(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, pr_sigma: np.ndarray | None = None,
                    signal: np.ndarray | None = None, t_ms: int = 0, name: str = "epoch") -> Trace:
    """Wrap one epoch's measurements (S satellites) as a 1-epoch :class:`Trace`.

    sat_pos (S,3) transmit-time ECEF [m]; pr (S,) corrected pseudoranges [m]; mask (S,) bool.
    """
    sat_pos, pr, mask = np.asarray(sat_pos, float), np.asarray(pr, float), np.asarray(mask, bool)
    S = pr.shape[0] if pr.ndim == 1 else -1
    if S < 1 or sat_pos.shape != (S, 3) or mask.shape != (S,):
        raise GeometryError(f"{name}: expected sat_pos (S,3), pr (S,), mask (S,) with S >= 1; got "
                            f"{sat_pos.shape}, {pr.shape}, {mask.shape}")
    kw = empty_trace(1, S, name=name)
    # padded slots get finite filler, as the Trace contract requires
    kw.update(t_ms=np.array([t_ms], np.int64), sat_pos=np.where(mask[:, None], sat_pos, 0.0)[None],
              pr=np.where(mask, pr, 0.0)[None], mask=mask[None])
    for label, extra in (("pr_sigma", pr_sigma), ("signal", signal)):
        if extra is not None and np.shape(extra) != (S,):
            raise GeometryError(f"{name}: {label} must have shape ({S},) like pr, got {np.shape(extra)}")
    if pr_sigma is not None:
        kw["pr_sigma"] = np.where(mask, np.asarray(pr_sigma, float), 1.0)[None]
    if signal is not None:
        kw["signal"] = np.asarray(signal, np.int8)[None]
    return Trace(**kw)


def learned_prior(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                  init_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The learned position estimate for one epoch: (mean_ecef (3,), cov_ecef (3,3)).

    Raises :class:`GeometryError` when the corrector declines the epoch (e.g. fewer than 4
    satellites above its elevation mask at ``init_pos``) or returns a non-positive-definite covariance.
    """
    init_pos = np.asarray(init_pos, float)
    if init_pos.shape != (3,) or not np.isfinite(init_pos).all():
        raise GeometryError(f"init_pos must be a finite ECEF (3,) vector, got {init_pos!r}")
    trace = one_epoch_trace(sat_pos, pr, mask)
    mean, cov, valid = corrector(trace, init_pos[None], np.ones(1, bool))
    mean, cov = np.asarray(mean, float)[0], np.asarray(cov, float)[0]
    if not bool(np.asarray(valid)[0]) or not (np.isfinite(mean).all() and np.isfinite(cov).all()):
        raise GeometryError(f"the learned corrector gave no estimate for this epoch ({int(np.sum(mask))} "
                            f"satellites; it needs >= 4 above its elevation mask at the initial position)")
    cov = 0.5 * (cov + cov.T)
    if np.linalg.eigvalsh(cov)[0] <= 0:
        raise GeometryError(f"the learned covariance is not positive definite: {cov.tolist()}")
    return mean, cov


def _noise(cov: np.ndarray, cov_scale: float, sigma_floor_m: float, robust: str, robust_k: float):
    """(covariance used (3,3), noise model): inflated, floored, optionally robust (see GraphConfig)."""
    if not (cov_scale > 0 and sigma_floor_m >= 0):
        raise GeometryError(f"cov_scale must be > 0 and sigma_floor_m >= 0, got {cov_scale} and {sigma_floor_m}")
    used = cov_scale * cov + sigma_floor_m ** 2 * np.eye(3)
    return used, robust_model(robust, robust_k, gtsam.noiseModel.Gaussian.Covariance(used))


def learned_prior_factor(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                         init_pos: np.ndarray, key: int, *, cov_scale: float = 1.0, sigma_floor_m: float = 0.0,
                         robust: str = "none", robust_k: float = 1.0
                         ) -> tuple[gtsam.PriorFactorPoint3, np.ndarray, np.ndarray]:
    """A ``PriorFactorPoint3`` on ``key`` at the DNN-corrected position of one epoch.

    corrector: a trained ``learned.infer.Corrector`` (or any position prior provider callable
        ``(trace, init_pos (E,3), valid (E,)) -> (mean (E,3), cov (E,3,3), valid (E,))``).
    sat_pos:   (S,3) satellite ECEF at transmit time [m] (unrotated; the corrector handles Sagnac).
    pr:        (S,) corrected pseudoranges [m] (satellite clock, iono, tropo removed).
    mask:      (S,) bool, which slots are real.
    init_pos:  (3,) ECEF initial guess [m] (e.g. WLS or the previous estimate; never the truth).
    key:       the GTSAM key of an ECEF ``Point3`` variable.

    cov_scale, sigma_floor_m, robust, robust_k: the covariance used is
        ``cov_scale * cov + sigma_floor_m**2 * I``, wrapped in a robust loss ("huber", "cauchy" or
        "none") on the Mahalanobis distance (``robust_k`` in sigmas). The defaults use the network's
        covariance as is; ``fusion.graph_build.GraphConfig`` documents the safer values our own graph
        uses (16, 2 m, "cauchy", 1), which keep a confidently wrong output from dragging the solution.

    Returns ``(factor, mean_ecef (3,), cov_ecef (3,3))``, ``cov_ecef`` being the covariance in the
    factor's noise model. The receiver clock is estimated inside the corrector from the
    pseudoranges, so the factor involves the position only. Raises :class:`GeometryError` if the
    corrector cannot produce an estimate.
    """
    mean, cov = learned_prior(corrector, sat_pos, pr, mask, init_pos)
    cov, model = _noise(cov, cov_scale, sigma_floor_m, robust, robust_k)
    return gtsam.PriorFactorPoint3(key, mean, model), mean, cov


def learned_pose_translation_factor(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray,
                                    mask: np.ndarray, init_pos: np.ndarray, key: int
                                    ) -> tuple[gtsam.PoseTranslationPrior3D, np.ndarray, np.ndarray]:
    """Like :func:`learned_prior_factor` for a ``Pose3`` variable whose translation is ECEF.

    ``PoseTranslationPrior3D``'s error is ``translation - measured`` in the *world* frame (checked
    in ``tests/test_factor.py``), so the ECEF covariance is used as is, whatever the pose's rotation.
    """
    mean, cov = learned_prior(corrector, sat_pos, pr, mask, init_pos)
    factor = gtsam.PoseTranslationPrior3D(key, mean, gtsam.noiseModel.Gaussian.Covariance(cov))
    return factor, mean, cov


def learned_prior_factors(corrector: PriorProvider, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                          keys: list[int], on_pose: bool = False) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """Learned priors for every epoch of a trace in one batched corrector call.

    init_pos (E,3) ECEF guesses, valid (E,) bool epochs to try, keys: E GTSAM keys.
    on_pose: ``PoseTranslationPrior3D`` on ``Pose3`` keys instead of ``PriorFactorPoint3``.
    Returns ``(factors, mean (E,3), cov (E,3,3), ok (E,))``; ``factors[k]`` is None where
    ``ok[k]`` is False (declined by the corrector, non-finite, or covariance not positive definite).
    """
    E = trace.n_epochs
    init_pos, valid = np.asarray(init_pos, float), np.asarray(valid, bool)
    if init_pos.shape != (E, 3) or valid.shape != (E,) or len(keys) != E:
        raise GeometryError(f"{trace.name}: init_pos must be ({E}, 3), valid ({E},) and {E} keys; got "
                            f"{init_pos.shape}, {valid.shape}, {len(keys)}")
    valid = valid & np.isfinite(init_pos).all(axis=1)
    mean, cov, ok = corrector(trace, np.where(valid[:, None], init_pos, 0.0), valid)
    mean, cov, ok = np.asarray(mean, float), np.asarray(cov, float), np.asarray(ok, bool) & valid
    ok &= np.isfinite(mean).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    cov = np.where(ok[:, None, None], 0.5 * (cov + cov.transpose(0, 2, 1)), np.eye(3))
    ok &= np.linalg.eigvalsh(cov)[:, 0] > 0
    make = gtsam.PoseTranslationPrior3D if on_pose else gtsam.PriorFactorPoint3
    factors = [make(keys[k], mean[k], gtsam.noiseModel.Gaussian.Covariance(cov[k])) if ok[k] else None
               for k in range(E)]
    return factors, mean, cov, ok
